"""A viscous ring damper: one wheel without a motor, coupled to the body by viscous friction."""

from typing import Any, ClassVar

from jaxtyping import ArrayLike, Float

from .._inputs import Input
from ._wheels import Wheels


class RingDamper(Wheels):
    """A viscous ring damper: a ring of fluid (one wheel without a motor) spinning about a
    body-fixed axis, coupled to the body by viscous friction; an energy sink that leaves the
    angular momentum unchanged (Explorer 1's whip antennas, nutation dampers).

    **Arguments:**

    - `axis`: the ring's axis in the body frame (normalised here).
    - `inertia`: the ring's axial moment of inertia (kg m^2); the body's inertia excludes it.
    - `damping`: the viscous coefficient between ring and body (N m s).

    State as [`jaxdyn.Wheels`][] with one wheel: `momentum` and `dissipated`; initial value
    `speed` (the ring's spin relative to the body, default 0).
    """

    kind: ClassVar[str] = "ring-damper"
    inputs: ClassVar[tuple[Input, ...]] = (
        Input("axis", "the ring's axis in the body frame (normalised)", shapes=((3,),)),
        Input("inertia", "the ring's axial moment of inertia (the body's inertia excludes it)",
              "kg m^2", bound="positive"),
        Input("damping", "viscous coefficient between ring and body", "N m s",
              bound="nonnegative"),
        Input("speed", "initial spin relative to the body", "rad/s", role="initial",
              state="speed"),
    )
    parameter_names: ClassVar[tuple[str, ...]] = ("axis", "inertia", "damping")

    def __init__(self, axis: Float[ArrayLike, "3"], inertia: ArrayLike, damping: ArrayLike):
        super().__init__(axes=[axis], inertia=[inertia], damping=[damping])

    def constructor_args(self) -> dict[str, Any]:
        return {"axis": self.axes[0], "inertia": self.inertia[0], "damping": self.damping[0]}

    def parameters(self) -> dict[str, Any]:
        return self.constructor_args()
