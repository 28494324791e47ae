r"""The rod on a rough floor: a slender rod whose lower tip touches a floor with Coulomb friction.

Same conventions as the frictionless [`jaxdyn.FallingRod`][] (`physics.md`, section 1): `theta`
from the vertical, the top moves to `+x` for `theta > 0`, length `L`, mass `m`,
`I_c = m L^2 / 12`, tip on the floor at `y = 0`. The floor pushes on the tip with a normal force
`N >= 0` and a friction force `F` (along `x`). Three modes:

- **stick** (`mode = 0`): the tip is fixed and the rod pivots about it,
  $I_\text{tip}\ddot\theta = m g \tfrac{L}{2}\sin\theta$ with $I_\text{tip} = m L^2/3$. The contact
  forces follow from $\mathbf{F} = m\mathbf{a}_c$ with the pivot kinematics
  $\mathbf{a}_c = \tfrac{L}{2}(\ddot\theta\cos\theta - \dot\theta^2\sin\theta,
  \; -\ddot\theta\sin\theta - \dot\theta^2\cos\theta)$:
  $F = m a_{cx}$, $N = m g + m a_{cy}$. It lasts while $|F| \le \mu_s N$.
- **slip** (`mode = 1`): the tip slides with velocity of sign $\sigma$ (`slip_sign`), and kinetic
  friction opposes it, $F = -\sigma\mu_k N$. With $\dot H_c = L_c$,
  $I_c\ddot\theta = \tfrac{L}{2}\sin\theta\,N - \tfrac{L}{2}\cos\theta\,F
  = \tfrac{L}{2} k N$ with $k = \sin\theta + \sigma\mu_k\cos\theta$, the super-particle theorem
  $m\ddot x_c = F$, $m\ddot y_c = N - m g$ and the constraint $y_c = \tfrac{L}{2}\cos\theta$:

  $$\ddot\theta = \frac{3 k (2 g - L\dot\theta^2\cos\theta)}{L(1 + 3 k \sin\theta)},\qquad
  N = \frac{m (g - \tfrac{L}{2}\dot\theta^2\cos\theta)}{1 + 3 k\sin\theta},$$

  which is the frictionless rod for $\mu_k = 0$. It lasts until the tip comes to rest
  ($\sigma v_\text{tip} = 0$) or $N = 0$.
- **flight** (`mode = 2`): $N = F = 0$; the CM falls freely and the rod turns at a constant rate.

Switches, each an event located by root finding (see `jaxdyn._hybrid`):

- stick -> slip where $|F| = \mu_s N$, the tip sliding the way the forces push it,
  $\sigma = -\operatorname{sign} F$ (the friction needed points against the tendency to slide);
- slip -> stick or slip where the tip comes to rest: it sticks if $|F| \le \mu_s N$ for the
  pivoting rod there, and otherwise slides on, $\sigma = -\operatorname{sign} F$;
- slip -> flight (lift-off) where $N = 0$, that is $L\dot\theta^2\cos\theta = 2 g$ (whatever the
  friction). At $N = 0$, $\ddot\theta = 0$ and $\tfrac{d}{dt}(L\dot\theta^2\cos\theta) =
  -L\dot\theta^3\sin\theta$, so a rod falling away from upright never lifts off: lift-off needs a
  rod turning towards upright fast enough, or a start with $L\dot\theta_0^2\cos\theta_0 > 2 g$
  (which lifts off at once). A pivoting rod loses contact only through slipping first: at
  $N = 0$ any friction would exceed $\mu_s N$.
- The run ends when the rod lies flat ($\theta = \pm\pi/2$, event `"flat"`, as for the
  frictionless rod) or, after a lift-off, when the rod comes back down onto the floor (event
  `"touchdown"`, where the lower end reaches the floor; the impact would need a collision law,
  which this model does not have).

The energy balance is checked through the invariant `energy`: mechanical energy plus the work
done against kinetic friction (`friction_work`, integrated as a state variable,
$\dot W = \mu_k N |v_\text{tip}|$), which every mode conserves.

Painlevé's paradox (no consistent sliding solution where $1 + 3 k\sin\theta \le 0$) needs
$\mu_k > 4/3$ and a tip sliding away from the side the rod leans. From a tip at rest, sliding that
way needs $|F| > \mu_s N$ with $F$ pointing to the lean, and for the pivoting rod that ratio is at
most $3\sin\theta\cos\theta / (1 + 3\cos^2\theta) \le 3/4$ (its maximum at $\tan\theta = 2$,
whatever the rate), so with $\mu_k \le \mu_s$ the paradox cannot be reached.

References: the slip regimes of a toppling rod (sticking, then sliding backward or forward
depending on the friction coefficient): R. Cross, "The fall and bounce of pencils and other
elongated objects", Am. J. Phys. 74 (2006); Painlevé's paradox: P. Painlevé, *Leçons sur le
frottement* (1895), and F. Génot and B. Brogliato, "New results on Painlevé paradoxes",
Eur. J. Mech. A/Solids 18 (1999).
"""

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._body import AbstractBody
from ._custom_types import Scalar, State
from ._inputs import Input
from ._rod import ROD_INPUTS, ROD_UNITS, check_angle_rate, rod_scales, rod_start
from ._validation import Check, as_float_array, on_host, positive_check

STICK, SLIP, FLIGHT = 0.0, 1.0, 2.0
# Value of an event that does not apply to the current mode.
_INACTIVE = 1e3
_RECORDS = ("slip_theta", "slip_direction", "liftoff")


def _sign(x, fallback):
    return jnp.where(x > 0, 1.0, jnp.where(x < 0, -1.0, fallback)).astype(x.dtype)


class RoughFloorRod(AbstractBody):
    r"""A slender rod on a floor with Coulomb friction (static `mu_s`, kinetic `mu_k`): it pivots
    about its tip while friction holds, slides when the friction needed exceeds `mu_s N`, sticks
    again when the tip comes to rest, and leaves the floor when `N` reaches zero.

    A hybrid body: [`jaxdyn.simulate`][] runs it as segments in one mode each, switched at events
    located by root finding (module docstring for the physics; `jaxdyn._hybrid` for the loop).
    With `mu_s = mu_k = 0` it is the frictionless [`jaxdyn.FallingRod`][].

    **Arguments:**

    - `length`: rod length `L` (m).
    - `mass`: rod mass `m` (kg).
    - `g`: gravitational acceleration (m/s^2).
    - `mu_s`: static friction coefficient, `>= 0`.
    - `mu_k`: kinetic friction coefficient, `0 <= mu_k <= mu_s`.

    State (from `scene.state(theta=..., theta_dot=...)`): `theta`, `theta_dot`; the tip's
    position and velocity `tip_x`, `tip_vx`, `tip_y`, `tip_vy` (the tip starts at rest on the
    floor at `x = 0`); `friction_work` (work done against kinetic friction); the mode (`mode`: 0
    stick, 1 slip, 2 flight; `slip_sign`: the sign of the tip's velocity while it slides); and
    records of the run: `slip_theta` and `slip_direction` (the angle at the first slip onset and
    +1 if the tip first slid forward, towards the side the rod leans, -1 backward, 0 if it has
    not slid) and `liftoff` (1 once the rod has left the floor). `scene.state` starts in the
    stick mode; `simulate` settles the mode at the start (flight if the floor would have to
    pull, else stick if friction holds, else slip).
    """

    length: Float[Array, ""]
    mass: Float[Array, ""]
    g: Float[Array, ""]
    mu_s: Float[Array, ""]
    mu_k: Float[Array, ""]

    kind: ClassVar[str] = "rough-floor-rod"
    inputs: ClassVar[tuple[Input, ...]] = (
        *(dataclasses.replace(i, fit=None, columns=()) for i in ROD_INPUTS),
        Input("mu_s", "static friction coefficient", bound="nonnegative"),
        Input("mu_k", "kinetic friction coefficient, at most mu_s", bound="nonnegative"),
    )
    output_units: ClassVar[Mapping[str, str]] = ROD_UNITS
    invariant_names: ClassVar[tuple[str, ...]] = ("energy",)
    max_switches: ClassVar[int] = 16
    report_labels: ClassVar[Mapping[str, Mapping[float, str]]] = {
        "slip_direction": {1.0: "forward", -1.0: "backward"},
    }

    def __init__(self, length: ArrayLike = 1.0, mass: ArrayLike = 1.0, g: ArrayLike = 9.81,
                 mu_s: ArrayLike = 0.5, mu_k: ArrayLike = 0.4):
        self.length = as_float_array("length", length, ())
        dtype = self.length.dtype
        self.mass = as_float_array("mass", mass, (), dtype)
        self.g = as_float_array("g", g, (), dtype)
        self.mu_s = as_float_array("mu_s", mu_s, (), dtype)
        self.mu_k = as_float_array("mu_k", mu_k, (), dtype)

    def checks(self) -> list[Check]:
        xp, mu_s, mu_k = on_host(self.mu_s, self.mu_k)
        return [
            positive_check("length", self.length),
            positive_check("mass", self.mass),
            positive_check("g", self.g),
            ("mu_s", self.mu_s, ~((mu_s >= 0) & xp.isfinite(mu_s)), "must be finite and >= 0"),
            ("mu_k", self.mu_k, ~((mu_k >= 0) & (mu_k <= mu_s) & xp.isfinite(mu_k)),
             "must be finite and within [0, mu_s] (kinetic friction cannot exceed static)"),
        ]

    # -- state ----------------------------------------------------------------------------------

    def initial_state(
        self, attitude: bool, theta: Any = None, theta_dot: Any = 0.0, **unknown: Any
    ) -> State:
        dtype = self.length.dtype
        theta, theta_dot = rod_start("a rough-floor rod", dtype, attitude, theta, theta_dot,
                                     unknown)
        zero = jnp.zeros((), dtype)
        y = {"theta": theta, "theta_dot": theta_dot}
        for name in ("tip_x", "tip_vx", "tip_y", "tip_vy", "friction_work", "mode", "slip_sign",
                     *_RECORDS):
            y[name] = zero
        return y

    def natural_scales(self, t0, t1, y0, effects, attitude):
        """As the frictionless rod's (`rod_scales`), with the tip's position against `L A` and
        its velocity against `L w A`; the mode flags and records against 1."""
        w, angle = rod_scales(self.length, self.g, y0["theta"], y0["theta_dot"])
        energy = self.mass * self.g * self.length
        one = jnp.ones_like(angle)
        scales = {name: one for name in y0}
        scales.update(theta=angle, theta_dot=w * angle, tip_x=self.length * angle,
                      tip_y=self.length * angle, tip_vx=self.length * w * angle,
                      tip_vy=self.length * w * angle, friction_work=energy * angle)
        return scales, {"time": 1 / w, "momentum": energy / w, "energy": energy}

    # -- dynamics of each mode ------------------------------------------------------------------

    def _stick(self, theta, theta_dot):
        """Pivoting about the tip: `theta_ddot`, friction `F` and normal force `N`."""
        m, L, g = self.mass, self.length, self.g
        s, c = jnp.sin(theta), jnp.cos(theta)
        theta_ddot = 1.5 * g / L * s
        friction = m * L / 2 * (theta_ddot * c - theta_dot**2 * s)
        normal = m * g - m * L / 2 * (theta_ddot * s + theta_dot**2 * c)
        return theta_ddot, friction, normal

    def _slip(self, theta, theta_dot, sigma):
        """Sliding with velocity sign `sigma`: `theta_ddot`, `F`, `N` and the tip's
        acceleration."""
        m, L, g = self.mass, self.length, self.g
        s, c = jnp.sin(theta), jnp.cos(theta)
        k = s + sigma * self.mu_k * c
        denom = 1 + 3 * k * s
        theta_ddot = 3 * k * (2 * g - L * theta_dot**2 * c) / (L * denom)
        normal = m * (g - L / 2 * theta_dot**2 * c) / denom
        friction = -sigma * self.mu_k * normal
        tip_ax = friction / m - L / 2 * (theta_ddot * c - theta_dot**2 * s)
        return theta_ddot, friction, normal, tip_ax

    def _modes(self, y):
        mode = y["mode"]
        return mode == STICK, mode == SLIP, mode == FLIGHT

    def _forces(self, y):
        """`theta_ddot`, friction, normal force, tip accelerations in the current mode."""
        theta, theta_dot = y["theta"], y["theta_dot"]
        stick, slip, _ = self._modes(y)
        L, g = self.length, self.g
        s, c = jnp.sin(theta), jnp.cos(theta)
        a_st, f_st, n_st = self._stick(theta, theta_dot)
        a_sl, f_sl, n_sl, ax_sl = self._slip(theta, theta_dot, y["slip_sign"])
        zero = jnp.zeros_like(theta)
        theta_ddot = jnp.where(stick, a_st, jnp.where(slip, a_sl, zero))
        friction = jnp.where(stick, f_st, jnp.where(slip, f_sl, zero))
        normal = jnp.where(stick, n_st, jnp.where(slip, n_sl, zero))
        tip_ax = jnp.where(stick, zero, jnp.where(slip, ax_sl, L / 2 * s * theta_dot**2))
        tip_ay = jnp.where(stick | slip, zero, -g + L / 2 * c * theta_dot**2)
        return theta_ddot, friction, normal, tip_ax, tip_ay

    def derivative(self, t: Scalar, y: State, effects: tuple, attitude: bool) -> State:
        theta_ddot, _, normal, tip_ax, tip_ay = self._forces(y)
        stick, slip, flight = self._modes(y)
        zero = jnp.zeros_like(theta_ddot)
        dy = {name: zero for name in y}
        dy["theta"] = y["theta_dot"]
        dy["theta_dot"] = theta_ddot
        dy["tip_x"] = jnp.where(stick, zero, y["tip_vx"])
        dy["tip_vx"] = tip_ax
        dy["tip_y"] = jnp.where(flight, y["tip_vy"], zero)
        dy["tip_vy"] = tip_ay
        # Power dissipated by kinetic friction, -F v = mu_k N |v| (sigma v >= 0 while sliding).
        dy["friction_work"] = jnp.where(
            slip, self.mu_k * normal * y["slip_sign"] * y["tip_vx"], zero
        )
        return dy

    # -- outputs and invariants -----------------------------------------------------------------

    def _energies(self, y):
        m, L, g = self.mass, self.length, self.g
        theta, theta_dot = y["theta"], y["theta_dot"]
        s, c = jnp.sin(theta), jnp.cos(theta)
        vx = y["tip_vx"] + L / 2 * c * theta_dot
        vy = y["tip_vy"] - L / 2 * s * theta_dot
        kinetic = 0.5 * m * (vx**2 + vy**2) + m * L**2 / 24 * theta_dot**2
        potential = m * g * (y["tip_y"] + L / 2 * c)
        return kinetic, potential

    def invariants(self, t: Scalar, y: State, effects: tuple, attitude: bool) -> dict[str, Array]:
        kinetic, potential = self._energies(y)
        return {"energy": kinetic + potential + y["friction_work"]}

    def outputs(self, t: Scalar, y: State, effects: tuple, attitude: bool) -> dict[str, Array]:
        m, L, g = self.mass, self.length, self.g
        theta, theta_dot = y["theta"], y["theta_dot"]
        s, c = jnp.sin(theta), jnp.cos(theta)
        theta_ddot, friction, normal, _, _ = self._forces(y)
        kinetic, potential = self._energies(y)
        return {
            "theta": theta,
            "theta_dot": theta_dot,
            "theta_ddot": theta_ddot,
            "mode": y["mode"],
            "normal_force": normal,
            "friction_force": friction,
            "normal_force_over_weight": normal / (m * g),
            "friction_force_over_weight": friction / (m * g),
            "cm_x": y["tip_x"] + L / 2 * s,
            "cm_height": y["tip_y"] + L / 2 * c,
            "tip_x": y["tip_x"],
            "tip_height": y["tip_y"],
            "tip_velocity": y["tip_vx"],
            "top_x": y["tip_x"] + L * s,
            "top_height": y["tip_y"] + L * c,
            "kinetic_energy": kinetic,
            "potential_energy": potential,
            "mechanical_energy": kinetic + potential,
            "friction_work": y["friction_work"],
        }

    def invariant_scale(self, name, value):
        # The energy of the rod standing upright, m g L / 2 (as for the frictionless rod).
        return self.mass * self.g * self.length / 2

    # -- hybrid protocol ------------------------------------------------------------------------

    def events(self):
        """Each positive while the current mode lasts, scaled to order one; `_INACTIVE` where
        it does not apply to the mode."""
        L, g = self.length, self.g

        def flat(t, y):
            # Exactly zero for a rod that starts flat (cos(pi/2) would round to 6e-17).
            stick, slip, _ = self._modes(y)
            return jnp.where(stick | slip, jnp.pi / 2 - jnp.abs(y["theta"]), _INACTIVE)

        def slip_onset(t, y):
            stick, _, _ = self._modes(y)
            _, friction, normal = self._stick(y["theta"], y["theta_dot"])
            value = (self.mu_s * normal - jnp.abs(friction)) / (self.mass * g)
            return jnp.where(stick, value, _INACTIVE)

        def restick(t, y):
            _, slip, _ = self._modes(y)
            return jnp.where(slip, y["slip_sign"] * y["tip_vx"] / jnp.sqrt(g * L), _INACTIVE)

        def liftoff(t, y):
            # N of the sliding rod is m (g - L theta_dot^2 cos(theta) / 2) / (1 + 3 k sin(theta)).
            _, slip, _ = self._modes(y)
            value = 1 - L * y["theta_dot"] ** 2 * jnp.cos(y["theta"]) / (2 * g)
            return jnp.where(slip, value, _INACTIVE)

        def touchdown(t, y):
            # The lower end of the rod (the tip, or the top once the rod is past horizontal).
            _, _, flight = self._modes(y)
            low = y["tip_y"] + jnp.minimum(0.0, L * jnp.cos(y["theta"]))
            return jnp.where(flight, low / L, _INACTIVE)

        return {"flat": flat, "slip": slip_onset, "restick": restick, "liftoff": liftoff,
                "touchdown": touchdown}

    def _enter_slip(self, y, sigma):
        """`y` switched to sliding with sign `sigma`, recording the first slip onset."""
        first = y["slip_direction"] == 0
        lean = _sign(y["theta"], _sign(y["theta_dot"], jnp.ones_like(sigma)))
        return {
            **y,
            "mode": jnp.full_like(y["mode"], SLIP),
            "slip_sign": sigma,
            "slip_theta": jnp.where(first, y["theta"], y["slip_theta"]),
            "slip_direction": jnp.where(first, sigma * lean, y["slip_direction"]),
        }

    def _enter_flight(self, y):
        one = jnp.ones_like(y["mode"])
        return {**y, "mode": 2 * one, "slip_sign": 0 * one, "liftoff": one}

    def _settle(self, y):
        """The mode of a rod whose tip is at rest on the floor: flight if the floor would have to
        pull, stick if friction holds, else slip the way the forces push the tip."""
        theta, theta_dot = y["theta"], y["theta_dot"]
        L, g = self.length, self.g
        y = {**y, "tip_vx": jnp.zeros_like(y["tip_vx"])}
        _, friction, normal = self._stick(theta, theta_dot)
        lifts = L * theta_dot**2 * jnp.cos(theta) >= 2 * g
        holds = (normal >= 0) & (jnp.abs(friction) <= self.mu_s * normal)
        sigma = -_sign(friction, _sign(theta, jnp.ones_like(theta)))
        stuck = {**y, "mode": jnp.zeros_like(y["mode"]), "slip_sign": jnp.zeros_like(sigma)}
        return _select(lifts, self._enter_flight(y), _select(holds, stuck,
                                                             self._enter_slip(y, sigma)))

    def state_checks(self, y):
        tip = jnp.stack([y["tip_vx"], y["tip_y"], y["tip_vy"]])
        return [("y0 tip (tip_vx, tip_y, tip_vy)", tip, jnp.any(tip != 0),
                 "the tip of a rough-floor rod must start at rest on the floor (build y0 "
                 "with scene.state)")]

    def start_mode(self, t0, y0):
        # The tip starts at rest on the floor (as `initial_state` builds it); the records start
        # empty; the rod lying flat ends the run at once.
        zero = jnp.zeros_like(y0["theta"])
        y = {**y0, **{name: zero for name in _RECORDS}}
        flat = jnp.abs(y0["theta"]) >= jnp.pi / 2
        return _select(flat, y, self._settle(y)), flat

    def switch_mode(self, t, y, fired):
        stick, slip, flight = self._modes(y)
        theta, theta_dot = y["theta"], y["theta_dot"]
        _, friction, _ = self._stick(theta, theta_dot)
        lifts = self.length * theta_dot**2 * jnp.cos(theta) >= 2 * self.g
        # Stick -> slip is forced at its event (the boundary |F| = mu_s N would otherwise be
        # decided by rounding); the direction is where the forces push the tip.
        sigma = -_sign(friction, _sign(theta, jnp.ones_like(theta)))
        slipped = _select(lifts, self._enter_flight(y), self._enter_slip(y, sigma))
        new = _select(stick & fired["slip"], slipped, y)
        new = _select(slip & fired["restick"], self._settle(y), new)
        new = _select(slip & fired["liftoff"], self._enter_flight(y), new)
        stop = ((stick | slip) & fired["flat"]) | (flight & fired["touchdown"])
        return new, stop

    # -- reporting ------------------------------------------------------------------------------

    def summary(self, ts, ys, valid, t_final, y_final, event, effects=(),
                attitude=False) -> dict[str, Any]:
        flat = event.get("flat", jnp.asarray(False))
        n_over_w = self.outputs(ts, ys, (), False)["normal_force_over_weight"]
        nan = jnp.asarray(jnp.nan, t_final.dtype)
        slipped = y_final["slip_direction"] != 0
        return {
            "impact_time": jnp.where(flat, t_final, nan),
            "impact_rate": jnp.where(flat, y_final["theta_dot"], nan),
            "min_normal_force_over_weight": jnp.min(jnp.where(valid, n_over_w, jnp.inf)),
            "slip_angle": jnp.where(slipped, y_final["slip_theta"], nan),
            "slip_direction": jnp.where(slipped, y_final["slip_direction"], nan),
            "liftoff": y_final["liftoff"] > 0,
        }

    # -- analytic companion ---------------------------------------------------------------------

    def pivot_forces(self, theta: ArrayLike, theta0: ArrayLike,
                     theta_dot0: ArrayLike = 0.0) -> dict[str, Array]:
        r"""Contact forces of the rod pivoting about its fixed tip, as functions of the angle, from
        the pivot's energy integral (no integration):

        $$\dot\theta^2 = \dot\theta_0^2 + \frac{6 g}{L}\sin\frac{\theta - \theta_0}{2}
        \sin\frac{\theta + \theta_0}{2}, \qquad \ddot\theta = \frac{3 g}{2 L}\sin\theta$$

        (the product form of `(3 g / L)(cos(theta0) - cos(theta))`), then `F = m a_cx` and
        `N = m g + m a_cy`. From rest near upright, `N = m g (3 cos(theta) - 1)^2 / 4` and
        `F = 3 m g sin(theta) (3 cos(theta) - 2) / 4`.

        **Arguments:**

        - `theta`: angles (rad) reached by the pivoting rod.
        - `theta0`, `theta_dot0`: where it started pivoting.

        **Returns:**

        A dict with `theta_dot` (rad/s, with the sign of `theta_dot0`, or of the fall where it
        starts at rest), `normal_force` and `friction_force` (N, the friction the floor must
        supply to keep the tip fixed: positive along `+x`).
        """
        dtype = self.length.dtype
        theta = as_float_array("theta", theta, None, dtype)
        theta0, theta_dot0 = check_angle_rate(dtype, theta0, theta_dot0,
                                              ("theta0", "theta_dot0"), None)
        return self._pivot_forces(theta, theta0, theta_dot0)

    @eqx.filter_jit
    def _pivot_forces(self, theta, theta0, theta_dot0):
        L, g = self.length, self.g
        rate2 = theta_dot0**2 + 6 * g / L * jnp.sin(0.5 * (theta - theta0)) * jnp.sin(
            0.5 * (theta + theta0)
        )
        rate2 = jnp.maximum(rate2, 0.0)
        direction = _sign(theta_dot0, _sign(theta0, jnp.ones_like(theta0)))
        theta_dot = direction * jnp.sqrt(rate2)
        _, friction, normal = self._stick(theta, theta_dot)
        return {"theta_dot": theta_dot, "normal_force": normal, "friction_force": friction}


def _select(pred, a: State, b: State) -> State:
    return {k: jnp.where(pred, a[k], b[k]) for k in a}
