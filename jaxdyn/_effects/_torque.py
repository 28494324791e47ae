from collections.abc import Callable
from typing import ClassVar, Literal

import equinox as eqx
from jaxtyping import Array, ArrayLike, Float

from .._effect import AbstractEffect
from .._inputs import Input
from .._rotations import quat_conjugate, quat_rotate
from .._validation import Check, ParameterError, as_float_array, finite_check


class ExternalTorque(AbstractEffect):
    """An external torque, constant or a function of time, in the body or the inertial frame.

    **Arguments:**

    - `torque`: three components (N m), or a function `t -> torque` (an `eqx.Module` if its
      parameters should be differentiable), or with `feedback=True` a function
      `(t, y) -> torque` of the time and the state dict (a control law).
    - `frame`: `"body"` (components in the body frame) or `"inertial"` (components in the
      inertial frame; the scene then integrates attitude).
    - `feedback`: whether a callable `torque` also takes the state.
    """

    torque_value: Float[Array, "3"] | Callable
    frame: Literal["body", "inertial"] = eqx.field(static=True)
    feedback: bool = eqx.field(static=True)

    kind: ClassVar[str] = "torque"
    inputs: ClassVar[tuple[Input, ...]] = (
        Input("torque", "a constant external torque", "N m", shapes=((3,),)),
        Input("frame", "the frame of its components ('inertial' makes the scene integrate "
              "the attitude)", "", type="text", choices=("body", "inertial")),
    )

    def __init__(self, torque: Float[ArrayLike, "3"] | Callable, frame: str = "body",
                 feedback: bool = False):
        if frame not in ("body", "inertial"):
            raise ParameterError(f"torque.frame={frame!r}: allowed are 'body', 'inertial'")
        if feedback and not callable(torque):
            raise ParameterError("torque.feedback=True: needs a function (t, y) -> torque")
        self.frame = frame  # type: ignore[assignment]
        self.feedback = feedback
        self.torque_value = torque if callable(torque) else as_float_array(
            "torque.torque", torque, (3,)
        )

    @property
    def needs_attitude(self) -> bool:  # type: ignore[override]
        return self.frame == "inertial"

    def constructor_args(self):
        return {"torque": self.torque_value, "frame": self.frame, "feedback": self.feedback}

    def checks(self) -> list[Check]:
        if callable(self.torque_value):
            return []
        return [finite_check("torque.torque", self.torque_value)]

    def torque(self, t, y, own, body) -> Array:
        dtype = y["omega"].dtype
        if self.feedback:
            tau = self.torque_value(t, y)
        elif callable(self.torque_value):
            tau = self.torque_value(t)
        else:
            tau = self.torque_value
        tau = tau.astype(dtype)
        if self.frame == "inertial":
            tau = quat_rotate(quat_conjugate(y["quaternion"]), tau)
        return tau
