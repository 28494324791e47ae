"""jaxdyn: differentiable rigid-body dynamics in pure JAX.

Public names are imported on first use (PEP 562), so `import jaxdyn` costs little and a
program pays only for the parts it touches (diffrax, optimistix, ...).
"""

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

_LAZY = {  # public name -> (module, name in it)
    "accuracy": (".accuracy", ""),
    "AbstractBody": ("._body", "AbstractBody"),
    "animate": ("._animate", "animate"),
    "enable_compilation_cache": ("._cache", "enable_compilation_cache"),
    "prefer_fast_programs": ("._xla", "prefer_fast_programs"),
    "AbstractDistribution": ("._distributions", "AbstractDistribution"),
    "Fixed": ("._distributions", "Fixed"),
    "LogNormal": ("._distributions", "LogNormal"),
    "Normal": ("._distributions", "Normal"),
    "Uniform": ("._distributions", "Uniform"),
    "parse_distribution": ("._distributions", "parse_distribution"),
    "AbstractEffect": ("._effect", "AbstractEffect"),
    "AttitudeTracking": ("._effects", "AttitudeTracking"),
    "ExternalTorque": ("._effects", "ExternalTorque"),
    "GravityGradient": ("._effects", "GravityGradient"),
    "LinearDamping": ("._effects", "LinearDamping"),
    "MagneticTorquers": ("._effects", "MagneticTorquers"),
    "Thrusters": ("._effects", "Thrusters"),
    "RateDamping": ("._effects", "RateDamping"),
    "CommandedTorques": ("._effects", "CommandedTorques"),
    "RingDamper": ("._effects", "RingDamper"),
    "Rotor": ("._effects", "Rotor"),
    "Wheels": ("._effects", "Wheels"),
    "carlson_rc": ("._elliptic", "carlson_rc"),
    "carlson_rf": ("._elliptic", "carlson_rf"),
    "carlson_rj": ("._elliptic", "carlson_rj"),
    "ellipf": ("._elliptic", "ellipf"),
    "ellipj": ("._elliptic", "ellipj"),
    "ellipk": ("._elliptic", "ellipk"),
    "ellippi": ("._elliptic", "ellippi"),
    "Ensemble": ("._ensemble", "Ensemble"),
    "ensemble": ("._ensemble", "ensemble"),
    "final_state": ("._ensemble", "final_state"),
    "elliptic_parameter": ("._free_body", "elliptic_parameter"),
    "torque_free_omega": ("._free_body", "torque_free_omega"),
    "torque_free_period": ("._free_body", "torque_free_period"),
    "torque_free_attitude": ("._free_body_attitude", "torque_free_attitude"),
    "AbstractParameterisation": ("._identify", "AbstractParameterisation"),
    "FitResult": ("._identify", "FitResult"),
    "Positive": ("._identify", "Positive"),
    "Unconstrained": ("._identify", "Unconstrained"),
    "UnitQuaternion": ("._identify", "UnitQuaternion"),
    "ValidInertia": ("._identify", "ValidInertia"),
    "fit": ("._identify", "fit"),
    "inertia_tensor": ("._inertia", "inertia_tensor"),
    "principal_axes": ("._inertia", "principal_axes"),
    "Input": ("._inputs", "Input"),
    "Outcome": ("._outcome", "Outcome"),
    "SimulationError": ("._outcome", "SimulationError"),
    "polhode": ("._polhode", "polhode"),
    "separatrix_condition": ("._polhode", "separatrix_condition"),
    "separatrix_curves": ("._polhode", "separatrix_curves"),
    "RigidBody": ("._rigid_body", "RigidBody"),
    "FallingRod": ("._rod", "FallingRod"),
    "dcm_to_euler321": ("._rotations", "dcm_to_euler321"),
    "dcm_to_mrp": ("._rotations", "dcm_to_mrp"),
    "dcm_to_quat": ("._rotations", "dcm_to_quat"),
    "euler321_to_dcm": ("._rotations", "euler321_to_dcm"),
    "euler321_to_quat": ("._rotations", "euler321_to_quat"),
    "mrp_derivative": ("._rotations", "mrp_derivative"),
    "mrp_from_quat": ("._rotations", "mrp_from_quat"),
    "mrp_shadow": ("._rotations", "mrp_shadow"),
    "mrp_switch": ("._rotations", "mrp_switch"),
    "mrp_to_dcm": ("._rotations", "mrp_to_dcm"),
    "quat_conjugate": ("._rotations", "quat_conjugate"),
    "quat_derivative": ("._rotations", "quat_derivative"),
    "quat_from_axis_angle": ("._rotations", "quat_from_axis_angle"),
    "quat_from_mrp": ("._rotations", "quat_from_mrp"),
    "quat_multiply": ("._rotations", "quat_multiply"),
    "quat_normalize": ("._rotations", "quat_normalize"),
    "quat_rotate": ("._rotations", "quat_rotate"),
    "quat_to_axis_angle": ("._rotations", "quat_to_axis_angle"),
    "quat_to_dcm": ("._rotations", "quat_to_dcm"),
    "quat_to_euler321": ("._rotations", "quat_to_euler321"),
    "safe_norm": ("._rotations", "safe_norm"),
    "skew": ("._rotations", "skew"),
    "RoughFloorRod": ("._rough_rod", "RoughFloorRod"),
    "Scene": ("._scene", "Scene"),
    "SceneSpec": ("._scenefile", "SceneSpec"),
    "builtin_scenes": ("._scenefile", "builtin_scenes"),
    "load_scene": ("._scenefile", "load_scene"),
    "Equilibria": ("._separatrix", "Equilibria"),
    "Separatrices": ("._separatrix", "Separatrices"),
    "critical_rotor_momenta": ("._separatrix", "critical_rotor_momenta"),
    "find_equilibria": ("._separatrix", "find_equilibria"),
    "trace_separatrices": ("._separatrix", "trace_separatrices"),
    "Trajectory": ("._solution", "Trajectory"),
    "simulate": ("._simulate", "simulate"),
    "RK4": ("._solvers", "RK4"),
    "RotationSplitting": ("._solvers", "RotationSplitting"),
    "ParameterError": ("._validation", "ParameterError"),
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    try:
        module, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'jaxdyn' has no attribute {name!r}") from None
    value = importlib.import_module(module, __name__)
    value = value if attr == "" else getattr(value, attr)
    globals()[name] = value  # later lookups skip __getattr__
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


if TYPE_CHECKING:  # the same names, for type checkers and editors
    from . import accuracy as accuracy
    from ._animate import animate as animate
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
        CommandedTorques as CommandedTorques,
        ExternalTorque as ExternalTorque,
        GravityGradient as GravityGradient,
        LinearDamping as LinearDamping,
        MagneticTorquers as MagneticTorquers,
        RateDamping as RateDamping,
        RingDamper as RingDamper,
        Rotor as Rotor,
        Thrusters as Thrusters,
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
    from ._simulate import simulate as simulate
    from ._solution import Trajectory as Trajectory
    from ._solvers import RK4 as RK4, RotationSplitting as RotationSplitting
    from ._validation import ParameterError as ParameterError
    from ._xla import prefer_fast_programs as prefer_fast_programs
