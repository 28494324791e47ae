"""jaxdyn: differentiable rigid-body dynamics in pure JAX."""

from ._body import AbstractBody as AbstractBody
from ._effect import AbstractEffect as AbstractEffect
from ._effects import (
    ExternalTorque as ExternalTorque,
    GravityGradient as GravityGradient,
    Rotor as Rotor,
)
from ._inertia import inertia_tensor as inertia_tensor, principal_axes as principal_axes
from ._rigid_body import RigidBody as RigidBody
from ._rod import FallingRod as FallingRod
from ._scene import Scene as Scene
from ._simulate import Trajectory as Trajectory, simulate as simulate
from ._validation import ParameterError as ParameterError


__version__ = "0.1.0"
