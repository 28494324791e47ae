"""The classic fourth-order Runge-Kutta method (fixed steps), for accuracy studies."""

from collections.abc import Callable
from typing import ClassVar

import diffrax as dfx
import numpy as np

_RK4_TABLEAU = dfx.ButcherTableau(
    c=np.array([0.5, 0.5, 1.0]),
    b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
    b_error=np.zeros(4),
    a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
)


class RK4(dfx.AbstractERK):
    """Kutta's classic fourth-order method: four stages, no error estimate, so use it with fixed
    steps (`dt0`, `diffrax.ConstantStepSize()`). Third-order Hermite dense output."""

    tableau: ClassVar[dfx.ButcherTableau] = _RK4_TABLEAU
    interpolation_cls: ClassVar[Callable[..., dfx.ThirdOrderHermitePolynomialInterpolation]] = (
        dfx.ThirdOrderHermitePolynomialInterpolation.from_k
    )

    def order(self, terms):
        return 4
