"""jaxdyn: differentiable rigid-body dynamics in pure JAX."""

from . import accuracy as accuracy
from ._body import AbstractBody as AbstractBody
from ._cache import enable_compilation_cache as enable_compilation_cache
from ._distributions import (
    AbstractDistribution as AbstractDistribution,
    Fixed as Fixed,
    LogNormal as LogNormal,
    Normal as Normal,
    Uniform as Uniform,
    parse_distribution as parse_distribution,
)
from ._effect import AbstractEffect as AbstractEffect
from ._effects import (
    AttitudeTracking as AttitudeTracking,
    ExternalTorque as ExternalTorque,
    GravityGradient as GravityGradient,
    LinearDamping as LinearDamping,
    RateDamping as RateDamping,
    RingDamper as RingDamper,
    Rotor as Rotor,
    Wheels as Wheels,
)
from ._elliptic import (
    carlson_rc as carlson_rc,
    carlson_rf as carlson_rf,
    carlson_rj as carlson_rj,
    ellipf as ellipf,
    ellipj as ellipj,
    ellipk as ellipk,
    ellippi as ellippi,
)
from ._ensemble import Ensemble as Ensemble, ensemble as ensemble, final_state as final_state
from ._free_body import (
    elliptic_parameter as elliptic_parameter,
    torque_free_omega as torque_free_omega,
    torque_free_period as torque_free_period,
)
from ._free_body_attitude import torque_free_attitude as torque_free_attitude
from ._identify import (
    AbstractParameterisation as AbstractParameterisation,
    FitResult as FitResult,
    Positive as Positive,
    Unconstrained as Unconstrained,
    UnitQuaternion as UnitQuaternion,
    ValidInertia as ValidInertia,
    fit as fit,
)
from ._inertia import inertia_tensor as inertia_tensor, principal_axes as principal_axes
from ._inputs import Input as Input
from ._outcome import Outcome as Outcome, SimulationError as SimulationError
from ._polhode import (
    polhode as polhode,
    separatrix_condition as separatrix_condition,
    separatrix_curves as separatrix_curves,
)
from ._rigid_body import RigidBody as RigidBody
from ._rod import FallingRod as FallingRod
from ._rotations import (
    dcm_to_euler321 as dcm_to_euler321,
    dcm_to_mrp as dcm_to_mrp,
    dcm_to_quat as dcm_to_quat,
    euler321_to_dcm as euler321_to_dcm,
    euler321_to_quat as euler321_to_quat,
    mrp_derivative as mrp_derivative,
    mrp_from_quat as mrp_from_quat,
    mrp_shadow as mrp_shadow,
    mrp_switch as mrp_switch,
    mrp_to_dcm as mrp_to_dcm,
    quat_conjugate as quat_conjugate,
    quat_derivative as quat_derivative,
    quat_from_axis_angle as quat_from_axis_angle,
    quat_from_mrp as quat_from_mrp,
    quat_multiply as quat_multiply,
    quat_normalize as quat_normalize,
    quat_rotate as quat_rotate,
    quat_to_axis_angle as quat_to_axis_angle,
    quat_to_dcm as quat_to_dcm,
    quat_to_euler321 as quat_to_euler321,
    safe_norm as safe_norm,
    skew as skew,
)
from ._rough_rod import RoughFloorRod as RoughFloorRod
from ._scene import Scene as Scene
from ._scenefile import (
    SceneSpec as SceneSpec,
    builtin_scenes as builtin_scenes,
    load_scene as load_scene,
)
from ._separatrix import (
    Equilibria as Equilibria,
    Separatrices as Separatrices,
    critical_rotor_momenta as critical_rotor_momenta,
    find_equilibria as find_equilibria,
    trace_separatrices as trace_separatrices,
)
from ._simulate import Trajectory as Trajectory, simulate as simulate
from ._solvers import RK4 as RK4, RotationSplitting as RotationSplitting
from ._validation import ParameterError as ParameterError

__version__ = "0.1.0"
