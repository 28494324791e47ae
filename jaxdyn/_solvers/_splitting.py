r"""Splitting integrators for free rigid bodies and gyrostats.

The kinetic energy $T = \sum_k (h_k - r_k)^2 / 2 I_k$ splits into three terms whose flows are
exact rotations about one body axis each (`Scene.split_flow`). Composing them gives Lie-Poisson
integrators that preserve $|h|$ and the inertial angular momentum to round-off and keep the energy
error bounded for all time.

References: McLachlan (1993), "Explicit Lie-Poisson integration and the Euler equations",
Phys. Rev. Lett. 71; Touma & Wisdom (1994), "Lie-Poisson integrators for rigid body dynamics in
the solar system", Astron. J. 107; Yoshida (1990), "Construction of higher order symplectic
integrators", Phys. Lett. A 150.
"""

from collections.abc import Callable
from typing import ClassVar

import diffrax as dfx
import equinox as eqx

from .._validation import ParameterError

# Symmetric (Strang) composition of the three axis flows: second order.
_STRANG = ((0, 0.5), (1, 0.5), (2, 1.0), (1, 0.5), (0, 0.5))
# Yoshida's triple jump of the Strang step: fourth order.
_G1 = 1 / (2 - 2 ** (1 / 3))
_TRIPLE_JUMP = (_G1, 1 - 2 * _G1, _G1)


class RotationSplitting(dfx.AbstractSolver):
    """Splitting integrator for torque-free rigid bodies (with constant-speed rotors or free
    wheels), as a diffrax solver. Fixed steps: pass `dt0` to [`jaxdyn.simulate`][].

    **Arguments:**

    - `order`: 2 (Strang splitting, 5 axis rotations per step) or 4 (Yoshida's triple jump of
      the Strang step).

    Works on body rates alone and with attitude; `|h|` and the inertial angular momentum are
    preserved to round-off and the energy error stays bounded. Needs principal inertia.
    """

    order_: int = eqx.field(static=True, default=2)

    term_structure: ClassVar = dfx.AbstractTerm
    interpolation_cls: ClassVar[Callable[..., dfx.LocalLinearInterpolation]] = (
        dfx.LocalLinearInterpolation
    )

    def __check_init__(self):
        if self.order_ not in (2, 4):
            raise ParameterError(f"RotationSplitting order={self.order_}: allowed are 2, 4")

    def order(self, terms):
        return self.order_

    def init(self, terms, t0, t1, y0, args):
        return None

    def _strang(self, scene, y, dt):
        for axis, fraction in _STRANG:
            y = scene.split_flow(axis, fraction * dt, y)
        return y

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        from .._scene import Scene

        if not isinstance(args, Scene):
            raise ParameterError("RotationSplitting runs through jaxdyn.simulate (it needs the "
                                 "scene)")
        dt = t1 - t0
        if self.order_ == 2:
            y1 = self._strang(args, y0, dt)
        else:
            y1 = y0
            for gamma in _TRIPLE_JUMP:
                y1 = self._strang(args, y1, gamma * dt)
        return y1, None, dict(y0=y0, y1=y1), None, dfx.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


RotationSplitting.__init__.__doc__ = None
