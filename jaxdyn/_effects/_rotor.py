from typing import ClassVar

from jaxtyping import Array, ArrayLike, Float

from .._effect import AbstractEffect
from .._inputs import Input
from .._validation import Check, as_float_array, finite_check


class Rotor(AbstractEffect):
    """A rotor spinning at constant speed relative to the body (a gyrostat).

    It stores a constant angular momentum `h_r` in the body frame, so Euler's equations become
    `I w_dot = (I w + h_r) x w`. Both `|I w + h_r|` and the kinetic energy `w . I w / 2` stay
    conserved. A rotor can stabilise a spin about the intermediate axis.

    **Arguments:**

    - `momentum`: the rotor's relative angular momentum `h_r` in the body frame (kg m^2/s).
    """

    momentum_vector: Float[Array, "3"]

    kind: ClassVar[str] = "rotor"
    inputs: ClassVar[tuple[Input, ...]] = (
        Input("momentum", "the rotor's angular momentum relative to the body, body frame",
              "kg m^2/s", shapes=((3,),), measures="momentum"),
    )
    conserves: ClassVar[frozenset[str]] = frozenset({"energy", "momentum"})

    def __init__(self, momentum: Float[ArrayLike, "3"]):
        self.momentum_vector = as_float_array("rotor.momentum", momentum, (3,))

    def constructor_args(self):
        return {"momentum": self.momentum_vector}

    def checks(self) -> list[Check]:
        return [finite_check("rotor.momentum", self.momentum_vector)]

    def momentum(self, t, y, own, body) -> Array:
        return self.momentum_vector.astype(y["omega"].dtype)

    def split_momentum(self, y, own) -> Array:
        return self.momentum_vector.astype(y["omega"].dtype)
