from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._effect import AbstractEffect
from .._inputs import Input
from .._orbit import orbit_direction
from .._rotations import quat_conjugate, quat_rotate
from .._validation import Check, as_float_array, finite_check, positive_check


class GravityGradient(AbstractEffect):
    """Gravity-gradient torque on a body in a circular orbit.

    `L = 3 n^2 (o x I o)`, with `o` the unit vector from the orbited body to the spacecraft in the
    body frame. The orbit lies in the inertial x-y plane: `o_N(t) = (cos(n t + u0), sin(n t + u0),
    0)`. The torque needs the attitude, so a scene with this effect integrates it.

    **Arguments:**

    - `orbit_rate`: orbital mean motion `n` (rad/s).
    - `phase`: argument of latitude `u0` at `t = 0` (rad).
    """

    orbit_rate: Float[Array, ""]
    phase: Float[Array, ""]

    kind: ClassVar[str] = "gravity-gradient"
    inputs: ClassVar[tuple[Input, ...]] = (
        Input("orbit_rate", "orbital mean motion n of the circular orbit", "rad/s",
              bound="positive"),
        Input("phase", "argument of latitude at t = 0", "rad"),
    )
    needs_attitude: ClassVar[bool] = True

    def __init__(self, orbit_rate: ArrayLike, phase: ArrayLike = 0.0):
        self.orbit_rate = as_float_array("gravity-gradient.orbit_rate", orbit_rate, ())
        self.phase = as_float_array("gravity-gradient.phase", phase, (), self.orbit_rate.dtype)

    def checks(self) -> list[Check]:
        return [
            positive_check("gravity-gradient.orbit_rate", self.orbit_rate),
            finite_check("gravity-gradient.phase", self.phase),
        ]

    def direction(self, t, quaternion) -> Float[Array, "3"]:
        """The unit vector `o` to the spacecraft, in the body frame."""
        o_n = orbit_direction(t, self.orbit_rate, self.phase)  # the orbit in the x-y plane
        return quat_rotate(quat_conjugate(quaternion), o_n.astype(quaternion.dtype))

    def torque(self, t, y, own, body) -> Array:
        o = self.direction(t, y["quaternion"])
        n = self.orbit_rate.astype(o.dtype)
        return 3 * n**2 * jnp.cross(o, body.body_momentum(o))
