r"""Attitude thrusters: body-fixed jets fired on and off by a sampled controller.

Thruster `i` sits at `r_i` (m, body frame, from the centre of mass) and pushes along the unit
vector `d_i` with thrust `F_i` (N) while it fires, giving the body the torque
`a_i = r_i x F_i d_i` (its force moves the centre of mass, which attitude dynamics ignores). It
burns propellant at `F_i / v_e` (kg/s, `v_e` the effective exhaust velocity, `g0 Isp`).

Control law `"rate-damping"`, pulse-width modulated: every `period` `T` the controller reads the
rates `w` and asks for the torque `tau = -k w`, each axis left alone while its rate is within
the dead band (`|w_j| <= deadband`). Thruster `i` then fires for
`t_i = T max(0, a_i . tau) / |a_i|^2` (its share of the angular impulse `T tau`, exact where
each thruster's torque lies along one body axis and no two point the same way), at least the
minimum on-time `MIB_i / F_i` of its minimum impulse bit once asked to fire, and at most `T`.
A pulse starts at the sample and ends `t_i` later.

Each switch (a sample, a pulse's end) is an event located by root finding (see
`jaxdyn._hybrid`): the scene runs as segments between switches, so a pulse delivers its impulse
`a_i t_i` exactly instead of being smeared over an integration step. State: `propellant` (the
mass used, kg), `on_time` (each thruster's total firing time, s), and the controller's own
memory (`firing`, `pulse_end`, `next_sample`), constant between switches.

With the dead band, rate damping ends in one of two ways. If the smallest velocity change a
pulse can make, `dw_min = MIB |a_i| / (F_i I)` about a principal axis, is below twice the
dead band, the rate settles inside the band. Otherwise no pulse can land it there: the rate
jumps across the band and back at every sample, a limit cycle of peak-to-peak amplitude
`dw_min` (Sidi, *Spacecraft Dynamics and Control*, 1997, sec. 9.4; Wie, *Space Vehicle
Dynamics and Control*, sec. 7.3).
"""

from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._effect import AbstractEffect
from .._inputs import Input
from .._validation import (
    Check,
    ParameterError,
    as_float_array,
    as_per_row,
    as_rows,
    finite_check,
    nonnegative_check,
    nonzero_unit,
    positive_check,
)

LAWS = ("rate-damping", "none")
_IDLE = 1e6  # the pulse-end event of a controller with no thruster firing: never reached


class Thrusters(AbstractEffect):
    """Attitude thrusters fired by a pulse-width-modulated rate-damping controller with a dead
    band; each switch located as an event, the propellant used as state (see the module's
    notes).

    **Arguments:**

    - `positions`: `(N, 3)` thruster positions from the centre of mass, body frame (m).
    - `directions`: `(N, 3)` thrust directions, body frame (normalised here).
    - `thrust`: `(N,)` thrusts while firing (N), or one value for all.
    - `exhaust_velocity`: effective exhaust velocity `g0 Isp` (m/s).
    - `min_impulse`: `(N,)` minimum impulse bits (N s), or one value; 0: no minimum.
    - `control`: `"rate-damping"` or `"none"` (never fires).
    - `gain`: the rate-damping gain `k` (N m s): torque asked `-k w`.
    - `deadband`: rates within it (each body axis, rad/s) are left alone.
    - `period`: the controller's sample period `T` (s), also the longest pulse.
    - `max_switches`: the most switches (samples and pulse ends) one run may take; a run
      needing more fails with a message saying so.

    State: `propellant` (kg used), `on_time` (`(N,)`, s), and the controller's `firing`,
    `pulse_end`, `next_sample`.
    """

    positions: Float[Array, "N 3"]
    directions: Float[Array, "N 3"]
    thrust: Float[Array, " N"]
    exhaust_velocity: Float[Array, ""]
    min_impulse: Float[Array, " N"]
    gain: Float[Array, ""]
    deadband: Float[Array, ""]
    period: Float[Array, ""]
    control: str = eqx.field(static=True)
    max_switches: int = eqx.field(static=True)  # type: ignore[misc]

    kind: ClassVar[str] = "thrusters"
    inputs: ClassVar[tuple[Input, ...]] = (
        Input("positions", "thruster positions from the centre of mass, body frame", "m",
              shapes=(("N", 3), (3,))),
        Input("directions", "thrust directions, body frame (normalised)", "1",
              shapes=(("N", 3), (3,))),
        Input("thrust", "thrust of each thruster while firing", "N", shapes=(("N",), ()),
              bound="positive"),
        Input("exhaust_velocity", "effective exhaust velocity g0 Isp", "m/s", bound="positive"),
        Input("min_impulse", "minimum impulse bit of each thruster", "N s",
              shapes=(("N",), ()), bound="nonnegative"),
        Input("control", "firing law: 'rate-damping' (PWM of the torque -gain w) or 'none'",
              "", type="text", choices=LAWS),
        Input("gain", "rate-damping gain k (torque asked -k w)", "N m s", bound="nonnegative"),
        Input("deadband", "rates left alone, each body axis", "rad/s", bound="nonnegative"),
        Input("period", "controller sample period (the longest pulse)", "s", bound="positive"),
        Input("max_switches", "the most switches (samples and pulse ends) one run may take",
              "1", bound="positive"),
    )
    parameter_names: ClassVar[tuple[str, ...]] = (
        "positions", "directions", "thrust", "exhaust_velocity", "min_impulse", "gain",
        "deadband", "period")
    state_kinds: ClassVar[dict[str, str]] = {"on_time": "time", "pulse_end": "time",
                                             "next_sample": "time"}

    def __init__(self, positions: Float[ArrayLike, "N 3"], directions: Float[ArrayLike, "N 3"],
                 thrust: Float[ArrayLike, " N"], exhaust_velocity: ArrayLike = 2200.0,
                 min_impulse: Float[ArrayLike, " N"] = 0.0, control: str = "rate-damping",
                 gain: ArrayLike = 0.0, deadband: ArrayLike = 0.0, period: ArrayLike = 1.0,
                 max_switches: int = 4000):
        if control not in LAWS:
            raise ParameterError(f"thrusters.control={control!r}: allowed are {LAWS}")
        self.control = control
        positions = as_rows("thrusters.positions", positions)
        n, dtype = positions.shape[0], positions.dtype
        directions = as_rows("thrusters.directions", directions, dtype)
        if directions.shape != (n, 3):
            raise ParameterError(f"thrusters.directions has shape {directions.shape}: "
                                 f"expected ({n}, 3), one row per thruster")
        self.positions = positions
        self.directions = nonzero_unit("thrusters.directions", directions, axis=1)

        self.thrust = as_per_row("thrusters.thrust", thrust, n, dtype)
        self.min_impulse = as_per_row("thrusters.min_impulse", min_impulse, n, dtype)
        for name, value in (("exhaust_velocity", exhaust_velocity), ("gain", gain),
                            ("deadband", deadband), ("period", period)):
            setattr(self, name, as_float_array(f"thrusters.{name}", value, (), dtype))
        if (isinstance(max_switches, bool) or not float(max_switches).is_integer()
                or not 1 <= max_switches <= 10**7):
            raise ParameterError(f"thrusters.max_switches={max_switches!r}: expected a whole "
                                 "number from 1 to 10000000")
        self.max_switches = int(max_switches)

    def constructor_args(self) -> dict[str, Any]:
        return {**{k: getattr(self, k) for k in self.parameter_names},
                "control": self.control, "max_switches": self.max_switches}

    def checks(self) -> list[Check]:
        return [finite_check("thrusters.positions", self.positions),
                positive_check("thrusters.thrust", self.thrust),
                positive_check("thrusters.exhaust_velocity", self.exhaust_velocity),
                positive_check("thrusters.period", self.period),
                nonnegative_check("thrusters.min_impulse", self.min_impulse),
                nonnegative_check("thrusters.gain", self.gain),
                nonnegative_check("thrusters.deadband", self.deadband)]

    @property
    def size(self) -> int:
        return self.positions.shape[0]

    @property
    def arms(self) -> Float[Array, "N 3"]:
        """The torque of each thruster while it fires, `r_i x F_i d_i` (N m, body frame)."""
        return jnp.cross(self.positions, self.thrust[:, None] * self.directions)

    # -- state and switches ----------------------------------------------------------------------

    def initial_state(self, body_state, **values: Any):
        if values:
            raise ParameterError(f"thrusters has no initial values: unexpected {sorted(values)}")
        dtype = body_state["omega"].dtype
        zeros = jnp.zeros(self.size, dtype)
        return {"propellant": jnp.zeros((), dtype), "on_time": zeros, "firing": zeros,
                "pulse_end": zeros, "next_sample": jnp.zeros((), dtype)}

    def on_times(self, w: Float[Array, "3"]) -> Float[Array, " N"]:
        """Each thruster's pulse length (s) commanded at a sample where the rates are `w`."""
        dtype = w.dtype
        if self.control == "none":
            return jnp.zeros(self.size, dtype)
        period = self.period.astype(dtype)
        wanted = -self.gain.astype(dtype) * jnp.where(jnp.abs(w) > self.deadband.astype(dtype),
                                                      w, 0)
        arms = self.arms.astype(dtype)
        share = period * jnp.maximum(arms @ wanted, 0) / jnp.sum(arms**2, axis=1)
        shortest = (self.min_impulse / self.thrust).astype(dtype)
        return jnp.minimum(jnp.where(share > 0, jnp.maximum(share, shortest), 0), period)

    def _sample(self, t, y, own):
        on = self.on_times(y["omega"])
        return {**own, "firing": (on > 0).astype(on.dtype), "pulse_end": t + on,
                "next_sample": t + self.period.astype(on.dtype)}

    def start_mode(self, t0, y, own):
        return self._sample(t0, y, own)

    def events(self):
        return {"sample": self._until_sample, "pulse_end": self._until_pulse_end}

    def _until_sample(self, t, y, own):
        return (own["next_sample"] - t) / self.period.astype(t.dtype)

    def _until_pulse_end(self, t, y, own):
        left = (own["pulse_end"] - t) / self.period.astype(t.dtype)
        return jnp.min(jnp.where(own["firing"] > 0, left, _IDLE))

    def switch_mode(self, t, y, own, fired):
        # The pulses ending here (all within round-off of the earliest), then a new command if
        # a sample is due (a pulse as long as the period ends at the next sample).
        tol = (1e-8 if own["pulse_end"].dtype == jnp.float64 else 1e-3) * self.period
        left = jnp.where(own["firing"] > 0, own["pulse_end"] - t, jnp.inf)
        ending = fired["pulse_end"] & (left <= jnp.min(left) + tol)
        own = {**own, "firing": jnp.where(ending, 0, own["firing"]).astype(left.dtype)}
        sampled = self._sample(t, y, own)
        return {k: jnp.where(fired["sample"], sampled[k], v) for k, v in own.items()}

    # -- physics ----------------------------------------------------------------------------------

    def torque(self, t, y, own, body) -> Array:
        return own["firing"] @ self.arms.astype(own["firing"].dtype)

    def state_derivative(self, t, y, own, body):
        firing = own["firing"]
        dtype = firing.dtype
        zero = jnp.zeros_like
        return {"propellant": jnp.dot(firing, self.thrust.astype(dtype))
                / self.exhaust_velocity.astype(dtype),
                "on_time": firing, "firing": zero(firing), "pulse_end": zero(firing),
                "next_sample": zero(own["next_sample"])}
