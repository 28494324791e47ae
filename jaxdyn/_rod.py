r"""The falling rod: a slender rod standing on frictionless ice slides and falls.

With no horizontal force the centre of mass (CM) moves only vertically. Angular momentum about the
CM (`H_dot = L_c`), the super-particle theorem (`F = m a_c`) and the constraint
`y_c = (L/2) cos(theta)` give (see `physics.md`, section 1)

$$\ddot\theta = \frac{3 \sin\theta\,(2 g - L \dot\theta^2 \cos\theta)}{L (1 + 3\sin^2\theta)},
\qquad N = m g - m \tfrac{L}{2}(\dot\theta^2\cos\theta + \ddot\theta \sin\theta).$$
"""

from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._body import AbstractBody
from ._custom_types import Scalar, State
from ._inputs import Input
from ._validation import (
    Check,
    ParameterError,
    as_float_array,
    finite_check,
    on_host,
    positive_check,
)

# Gauss-Legendre nodes for the fall-time quadrature (three panels of 32 nodes; see `fall_time`).
_GL_X, _GL_W = np.polynomial.legendre.leggauss(32)


def _gauss_legendre(f, a, b):
    """The integrals of `f` over the intervals `[a[i], b[i]]` (arrays of one shape), by one
    32-point Gauss-Legendre rule each, with `f` evaluated once on every node of every interval
    (one copy of `f` in the program, whatever the number of intervals)."""
    x = jnp.asarray(_GL_X, a.dtype)
    w = jnp.asarray(_GL_W, a.dtype)
    half = 0.5 * (b - a)
    nodes = (0.5 * (a + b))[..., None] + half[..., None] * x
    return half * jnp.sum(w * f(nodes), axis=-1)


def check_angle_rate(dtype, theta, theta_dot, names=("theta", "theta_dot"), shape=()):
    """An angle within [-pi/2, pi/2] (a rod cannot start below the floor) and a finite rate, as
    arrays of `dtype`; the error names the fields as `names`."""
    from ._validation import raise_if_violated

    theta = as_float_array(names[0], theta, shape, dtype)
    theta_dot = as_float_array(names[1], theta_dot, shape, dtype)
    xp, th = on_host(theta)
    raise_if_violated([
        (names[0], theta, ~(xp.abs(th) <= np.pi / 2),
         "must be finite and within [-pi/2, pi/2] (the rod cannot start below the floor)"),
        finite_check(names[1], theta_dot),
    ])
    return theta, theta_dot


ROD_UNITS = {
    "theta": "rad", "theta_dot": "rad/s", "theta_ddot": "rad/s^2", "normal_force": "N",
    "cm_height": "m", "cm_x": "m", "tip_x": "m", "top_x": "m", "top_height": "m",
    "tip_height": "m", "tip_velocity": "m/s", "energy": "J", "kinetic_energy": "J",
    "potential_energy": "J", "mechanical_energy": "J", "friction_force": "N",
    "friction_work": "J",
}
"""Units of the rods' derived outputs."""

ROD_INPUTS = (
    Input("length", "rod length L", "m", bound="positive", fit="positive"),
    Input("mass", "rod mass (enters the normal force and the energies only)", "kg",
          bound="positive", fit="positive"),
    Input("g", "gravitational acceleration", "m/s^2", bound="positive"),
    Input("theta0", "initial angle from the vertical (the top moves to +x for theta > 0)",
          "rad", role="initial", state="theta", required=True, fit="free", columns=("theta",)),
    Input("theta_dot0", "initial angular rate", "rad/s", role="initial", state="theta_dot",
          fit="free"),
)
"""The inputs of the rods (the rough-floor rod adds its friction coefficients)."""


def rod_start(name: str, dtype, attitude: bool, theta, theta_dot, unknown):
    """Checked initial angle and rate of a rod standing on a floor (shared by the rod bodies)."""
    if unknown:
        raise ParameterError(
            f"unknown state variables {sorted(unknown)} for {name}: allowed are theta, theta_dot"
        )
    if attitude:
        raise ParameterError(f"attitude=True: {name} has no 3-D attitude (its state starts "
                             "with theta, theta_dot)")
    if theta is None:
        raise ParameterError("theta is required: the angle from the vertical in rad")
    return check_angle_rate(dtype, theta, theta_dot)


def rod_scales(length, g, theta, theta_dot):
    """Natural scales of a rod's motion from `(theta, theta_dot)`: the rate `w = sqrt(g / L)`
    and the angle `A = max(|theta|, |theta_dot| / w)` (1 for a rod upright at rest, which
    stays there). A rod released at `theta0 = 1e-12` is so resolved relative to `1e-12`
    while it starts to fall, whatever the units of `L` and `g`."""
    w = jnp.sqrt(g / length)
    angle = jnp.maximum(jnp.abs(theta), jnp.abs(theta_dot) / w)
    angle = jnp.where(jnp.isfinite(angle) & (angle > 0), angle, 1.0)
    return w, angle


class FallingRod(AbstractBody):
    """A slender rod on a frictionless floor, its lower tip on the floor.

    **Arguments:**

    - `length`: rod length `L` (m).
    - `mass`: rod mass `m` (kg). Enters only the normal force and the energies.
    - `g`: gravitational acceleration (m/s^2).

    State: `theta` (angle from the vertical, rad; the top moves towards `+x` for `theta > 0`) and
    `theta_dot` (rad/s). The run ends at the event `"flat"` (the CM reaches the floor,
    `theta = +-pi/2`), located by root finding.
    """

    length: Float[Array, ""]
    mass: Float[Array, ""]
    g: Float[Array, ""]

    kind: ClassVar[str] = "falling-rod"
    inputs: ClassVar[tuple[Input, ...]] = ROD_INPUTS
    plain_scene: ClassVar[str | None] = "falling-rod"
    output_units: ClassVar[Mapping[str, str]] = ROD_UNITS
    identifiability: ClassVar[Mapping[str, str]] = {
        "mass": "the mass cancels from the rod's equation of motion (theta(t) depends on "
        "g/L only); with g known the length is determined, the mass is not",
    }
    invariant_names: ClassVar[tuple[str, ...]] = ("energy",)

    def __init__(self, length: ArrayLike = 1.0, mass: ArrayLike = 1.0, g: ArrayLike = 9.81):
        self.length = as_float_array("length", length, ())
        dtype = self.length.dtype
        self.mass = as_float_array("mass", mass, (), dtype)
        self.g = as_float_array("g", g, (), dtype)

    def checks(self) -> list[Check]:
        return [
            positive_check("length", self.length),
            positive_check("mass", self.mass),
            positive_check("g", self.g),
        ]

    # -- protocol -------------------------------------------------------------------------------

    def initial_state(
        self, attitude: bool, theta: Any = None, theta_dot: Any = 0.0, **unknown: Any
    ) -> State:
        theta, theta_dot = rod_start("a falling rod", self.length.dtype, attitude, theta,
                                     theta_dot, unknown)
        return {"theta": theta, "theta_dot": theta_dot}

    def natural_scales(self, t0, t1, y0, effects, attitude):
        """`theta` against the angle `A`, `theta_dot` against `w A` (see `rod_scales`); the
        time scale is `1 / w`."""
        w, angle = rod_scales(self.length, self.g, y0["theta"], y0["theta_dot"])
        energy = self.mass * self.g * self.length
        return ({"theta": angle, "theta_dot": w * angle},
                {"time": 1 / w, "momentum": energy / w, "energy": energy})

    def angular_acceleration(self, theta, theta_dot):
        """`theta_ddot` from the equation of motion."""
        s, c = jnp.sin(theta), jnp.cos(theta)
        L, g = self.length, self.g
        return 3 * s * (2 * g - L * theta_dot**2 * c) / (L * (1 + 3 * s**2))

    def derivative(self, t: Scalar, y: State, effects: tuple, attitude: bool) -> State:
        theta, theta_dot = y["theta"], y["theta_dot"]
        return {"theta": theta_dot, "theta_dot": self.angular_acceleration(theta, theta_dot)}

    def _energies(self, theta, theta_dot):
        m, L, g = self.mass, self.length, self.g
        kinetic = m * L**2 / 24 * (1 + 3 * jnp.sin(theta) ** 2) * theta_dot**2
        potential = m * g * L / 2 * jnp.cos(theta)
        return kinetic, potential

    def invariants(self, t: Scalar, y: State, effects: tuple, attitude: bool) -> dict[str, Array]:
        kinetic, potential = self._energies(y["theta"], y["theta_dot"])
        return {"energy": kinetic + potential}

    def outputs(self, t: Scalar, y: State, effects: tuple, attitude: bool) -> dict[str, Array]:
        theta, theta_dot = y["theta"], y["theta_dot"]
        m, L, g = self.mass, self.length, self.g
        s, c = jnp.sin(theta), jnp.cos(theta)
        theta_ddot = self.angular_acceleration(theta, theta_dot)
        normal = m * g - m * L / 2 * (theta_dot**2 * c + theta_ddot * s)
        kinetic, potential = self._energies(theta, theta_dot)
        return {
            "theta": theta,
            "theta_dot": theta_dot,
            "theta_ddot": theta_ddot,
            "normal_force": normal,
            "normal_force_over_weight": normal / (m * g),
            "cm_height": L / 2 * c,
            "cm_x": jnp.zeros_like(theta),
            "tip_x": -L / 2 * s,
            "top_x": L / 2 * s,
            "top_height": L * c,
            "kinetic_energy": kinetic,
            "potential_energy": potential,
        }

    def exact_final(self, y0, t1, effects, attitude):
        """The impact (time, flat angle, rate) from the quadrature and the energy integral."""
        theta0, theta_dot0 = y0["theta"], y0["theta_dot"]
        t_fall = self.fall_time(theta0, theta_dot0)
        if not bool(t_fall <= t1):
            return None
        # The side it lands on: its own, unless it rises with the energy to pass over the top.
        side = jnp.where(theta0 == 0, jnp.sign(theta_dot0), jnp.sign(theta0))
        rising = side * theta_dot0 < 0
        s0 = jnp.sin(0.5 * theta0)
        kinetic = theta_dot0**2 * (1 + 3 * jnp.sin(theta0) ** 2) * self.length / (24 * self.g)
        side = jnp.where(rising & (kinetic > s0**2), -side, side)
        flat = jnp.pi / 2 * side
        rate = self.rate(jnp.pi / 2, theta0, theta_dot0)
        return t_fall, {"theta": flat, "theta_dot": jnp.sign(flat) * rate}

    def invariant_scale(self, name, value):
        # The energy of the rod standing upright, m g L / 2: the energy of a rod starting flat is
        # zero, so its own magnitude is no scale.
        return self.mass * self.g * self.length / 2

    def events(self):
        # Changes sign as the rod lies flat on either side, and is exactly zero for a rod that
        # starts flat (cos(pi/2) would round to 6e-17 instead), so that the run ends at once.
        return {"flat": lambda t, y: jnp.pi / 2 - jnp.abs(y["theta"])}

    def summary(self, ts, ys, valid, t_final, y_final, event, effects=(),
                attitude=False) -> dict[str, Any]:
        flat = event.get("flat", jnp.asarray(False))
        n_over_w = self.outputs(ts, ys, (), False)["normal_force_over_weight"]
        theta0, theta_dot0 = ys["theta"][0], ys["theta_dot"][0]
        nan = jnp.asarray(jnp.nan, t_final.dtype)
        fall = self._fall_time(theta0, theta_dot0)
        return {
            "impact_time": jnp.where(flat, t_final, nan),
            "impact_rate": jnp.where(flat, y_final["theta_dot"], nan),
            "min_normal_force_over_weight": jnp.min(jnp.where(valid, n_over_w, jnp.inf)),
            "reference": {
                "impact_time": fall,
                # (none where the rod never lands: upright at rest, it stays there)
                "impact_rate": jnp.where(
                    jnp.isfinite(fall),
                    jnp.sign(y_final["theta"]) * self._rate(jnp.pi / 2, theta0, theta_dot0), nan),
            },
        }

    # -- analytic companions --------------------------------------------------------------------

    def _check_start(self, theta0, theta_dot0):
        return check_angle_rate(self.length.dtype, theta0, theta_dot0,
                                ("theta0", "theta_dot0"), None)

    def rate(self, theta: ArrayLike, theta0: ArrayLike, theta_dot0: ArrayLike = 0.0) -> Array:
        r"""`|theta_dot|` at angle `theta` from the energy integral, starting at
        `(theta0, theta_dot0)`.

        $$\dot\theta^2 (1 + 3\sin^2\theta) = \dot\theta_0^2 (1 + 3\sin^2\theta_0)
        + \frac{24 g}{L} \sin\frac{\theta - \theta_0}{2} \sin\frac{\theta + \theta_0}{2},$$

        the product form of `12 (cos(theta0) - cos(theta)) / 2`, which keeps every digit when
        `theta0` is tiny. Returns 0 where the energy does not reach `theta`.
        """
        theta0, theta_dot0 = self._check_start(theta0, theta_dot0)
        return self._rate(theta, theta0, theta_dot0)

    @eqx.filter_jit
    def _rate(self, theta, theta0, theta_dot0):
        dtype = self.length.dtype
        theta, theta0, theta_dot0 = (jnp.asarray(x, dtype) for x in (theta, theta0, theta_dot0))
        L, g = self.length, self.g
        num = theta_dot0**2 * (1 + 3 * jnp.sin(theta0) ** 2) + 24 * g / L * jnp.sin(
            0.5 * (theta - theta0)
        ) * jnp.sin(0.5 * (theta + theta0))
        num = jnp.maximum(num, 0.0)
        safe = jnp.where(num > 0, num, 1.0)
        return jnp.where(num > 0, jnp.sqrt(safe / (1 + 3 * jnp.sin(theta) ** 2)), 0.0)

    def fall_time(self, theta0: ArrayLike, theta_dot0: ArrayLike = 0.0) -> Array:
        """Time for the rod to lie flat, by quadrature of the energy integral.

        With `s = sin(theta/2)` the energy integral reads
        `theta_dot^2 = (24 g / L) (s^2 - s_*^2) / (1 + 3 sin^2 theta)` with a constant `s_*^2`
        (positive: the rod turns back before upright; negative: it passes over the top). The
        substitution `v = log(s + sqrt(s^2 - s_*^2))` removes the `1/sqrt` singularity at a turning
        point and the `log(1/theta0)` growth near upright, leaving the smooth integrand
        `dt/dv = sqrt((1 + 3 sin^2 theta) L / (6 g)) / cos(theta/2)`, integrated by composite
        Gauss-Legendre. Returns `inf` when the rod never falls (at rest exactly upright, or with
        exactly the energy to come to rest upright).

        A negative `theta_dot0` (towards upright) is handled: the rod rises, turns back or passes
        over, and falls on the side its energy dictates.
        """
        return self._fall_time(*self._check_start(theta0, theta_dot0))

    @eqx.filter_jit
    def _fall_time(self, theta0, theta_dot0):
        dtype = self.length.dtype
        theta0, theta_dot0 = (jnp.asarray(x, dtype) for x in (theta0, theta_dot0))
        L, g = self.length, self.g
        # Mirror so that theta0 >= 0; then `rising` means moving towards upright.
        sign = jnp.where(theta0 < 0, -1.0, 1.0).astype(dtype)
        theta0, theta_dot0 = sign * theta0, sign * theta_dot0
        rising = theta_dot0 < 0
        s0 = jnp.sin(0.5 * theta0)
        sb = jnp.sin(jnp.asarray(jnp.pi / 4, dtype))
        c = jnp.abs(theta_dot0) * jnp.sqrt((1 + 3 * jnp.sin(theta0) ** 2) * L / (24 * g))
        s_star2 = s0**2 - c**2  # may be negative
        r_b = jnp.sqrt(jnp.sin(0.5 * (jnp.pi / 2 - theta0)) * jnp.sin(0.5 * (jnp.pi / 2 + theta0))
                       + c**2)
        start = s0 + c
        never = start <= 0  # at rest exactly upright
        v0 = jnp.log(jnp.where(never, 1.0, start))
        vb = jnp.log(sb + r_b)
        low_ok = s_star2 != 0
        v_low = 0.5 * jnp.log(jnp.where(low_ok, jnp.abs(s_star2), 1.0))

        def integrand(v):
            s = 0.5 * (jnp.exp(v) + s_star2 * jnp.exp(-v))
            sin_theta = 2 * s * jnp.sqrt(1 - s**2)
            return jnp.sqrt((1 + 3 * sin_theta**2) * L / (6 * g)) / jnp.sqrt(1 - s**2)

        # Three integrals (the fall from v0, and the rise to the turning point and the fall from
        # it), each in three panels split near its upper end, where the integrand varies (the
        # long lower part, small angles, is nearly constant): nine panels in one rule.
        a = jnp.stack([v0, v_low, v_low])
        b = jnp.stack([vb, v0, vb])
        p1 = jnp.clip(b - 6.0, a, b)
        p2 = jnp.clip(b - 1.5, a, b)
        panels = _gauss_legendre(integrand, jnp.stack([a, p1, p2]), jnp.stack([p1, p2, b]))
        falling, up, down = panels[0] + panels[1] + panels[2]
        back = jnp.where(rising & low_ok, up + down, 0.0)
        total = jnp.where(rising, back, falling)
        # At rest exactly upright the fall time is infinite and grows like log(1/theta0) nearby:
        # return that branch so the gradient is -inf (what it is), not a silent 0.
        k = jnp.sqrt(6 * g / L)
        upright = -jnp.log(jnp.abs(theta0)) / k
        total = jnp.where(never, upright, total)
        return jnp.where(rising & ~low_ok, jnp.inf, total)

    def normal_force_energy(self, theta: ArrayLike, theta0: ArrayLike,
                            theta_dot0: ArrayLike = 0.0) -> Array:
        """Normal force along the fall as a function of the angle, from the energy integral."""
        theta0, theta_dot0 = self._check_start(theta0, theta_dot0)
        return self._normal_force_energy(theta, theta0, theta_dot0)

    @eqx.filter_jit
    def _normal_force_energy(self, theta, theta0, theta_dot0):
        theta = jnp.asarray(theta, self.length.dtype)
        theta_dot = self._rate(theta, theta0, theta_dot0)
        out = self.outputs(None, {"theta": theta, "theta_dot": theta_dot}, (), False)
        return out["normal_force"]

