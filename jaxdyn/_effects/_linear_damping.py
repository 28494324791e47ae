"""Linear rate damping: a torque opposing the body rates, an energy sink."""

from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._effect import AbstractEffect
from .._inputs import Input
from .._validation import Check, ParameterError, as_float_array, nonnegative_check


class LinearDamping(AbstractEffect):
    r"""A torque opposing the body rates about each body axis, `tau_i = -c_i w_i`: eddy-current
    dampers, or a body spinning in a viscous medium. It removes kinetic energy at the rate
    `sum c_i w_i^2` (kept in the state as `dissipated`, so that energy plus dissipation is a
    checkable invariant) and changes the angular momentum.

    With coefficients proportional to the principal moments, `c_i = k I_i`, the motion is the
    torque-free motion slowed down: `w(t) = exp(-k t) w_free(s)`, `s = (1 - exp(-k t)) / k`.

    **Arguments:**

    - `coefficients`: `c_i` about the body axes (N m s), three values or one for all.

    State: `dissipated` (the energy removed, J).
    """

    coefficients: Float[Array, "3"]

    kind: ClassVar[str] = "linear-damping"
    inputs: ClassVar[tuple[Input, ...]] = (
        Input("coefficients", "damping coefficient c_i about each body axis (torque "
              "-c_i w_i)", "N m s", shapes=((3,), ()), bound="nonnegative"),
    )
    state_kinds: ClassVar[dict[str, str]] = {"dissipated": "energy"}

    def __init__(self, coefficients: Float[ArrayLike, "3"] | float):
        c = as_float_array("linear-damping.coefficients", coefficients)
        if c.shape not in ((), (3,)):
            raise ParameterError(f"linear-damping.coefficients has shape {c.shape}: expected "
                                 "(3,) or one number")
        self.coefficients = jnp.broadcast_to(c, (3,))

    def checks(self) -> list[Check]:
        c = self.coefficients
        return [nonnegative_check("linear-damping.coefficients", c)]

    def initial_state(self, body_state, **values):
        if values:
            raise ParameterError(f"linear-damping: unexpected initial values {sorted(values)}; "
                                 "its only state, dissipated, starts at 0")
        return {"dissipated": jnp.zeros((), body_state["omega"].dtype)}

    def state_derivative(self, t, y, own, body):
        w = y["omega"]
        return {"dissipated": jnp.sum(self.coefficients.astype(w.dtype) * w**2)}

    def torque(self, t, y, own, body) -> Array:
        w = y["omega"]
        return -self.coefficients.astype(w.dtype) * w
