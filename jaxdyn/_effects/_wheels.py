r"""Momentum wheels: reaction wheels, a dual spinner's rotor, a viscous ring damper.

Each wheel `i` spins about a fixed unit axis `g_i` in the body, with axial moment `J_i`. Its state
is its absolute axial angular momentum `h_i = J_i (Omega_i + g_i . w)`, where `Omega_i` is its spin
relative to the body; an axisymmetric wheel's `h_i` changes only by the torque `u_i` applied to it
about its axis (the motor torque, minus viscous friction). With `I` the body's inertia including
every wheel's transverse inertia but NOT its axial inertia `J_i`, the body obeys

$$I \dot w = (I w + \textstyle\sum_i h_i g_i) \times w - \sum_i u_i g_i + \tau_{ext},
\qquad \dot h_i = u_i,$$

the total angular momentum `I w + sum h_i g_i` is conserved under internal torques, and the kinetic
energy `w.I w / 2 + sum h_i^2 / (2 J_i)` changes at the rate `sum u_i Omega_i` (motor power minus
viscous loss). Reference: Schaub & Junkins, *Analytical Mechanics of Space Systems*, ch. 4.
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
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
    on_host,
    positive_check,
)


class Wheels(AbstractEffect):
    """Momentum wheels with optional motors, limits and viscous damping.

    **Arguments:**

    - `axes`: `(N, 3)` spin axes in the body frame (normalised here).
    - `inertia`: `(N,)` axial moments of inertia `J_i` (kg m^2). The body's inertia must exclude
      them (it includes the wheels' transverse inertia).
    - `motor`: motor torques on the wheels (N m): `None` (free wheels), `(N,)` constants, or a
      control law `(t, y, wheels) -> (N,)` (an `eqx.Module` such as [`jaxdyn.RateDamping`][] or
      [`jaxdyn.AttitudeTracking`][] to keep its gains differentiable).
    - `max_torque`: `(N,)` motor torque limits (commands are clipped), or `None`.
    - `max_speed`: `(N,)` relative spin limits (rad/s): a motor at its limit cannot drive the wheel
      faster (it may still slow it; the cut-off fades in over the last 1%), or `None`.
    - `damping`: `(N,)` viscous coefficients `c_i` (N m s) between wheel and body, or `None`. A
      wheel with damping and no motor is a viscous ring damper, an energy sink.

    State: `momentum` (`h_i`), and `work` (the motor work) when there are motors, `dissipated`
    (the viscous loss) when there is damping. Initial values: `speed` (relative spins `Omega_i`,
    default 0).
    """

    axes: Float[Array, "N 3"]
    inertia: Float[Array, " N"]
    motor: Any
    max_torque: Float[Array, " N"] | None
    max_speed: Float[Array, " N"] | None
    damping: Float[Array, " N"] | None

    kind = "wheels"
    inputs = (
        Input("axes", "spin axes in the body frame (normalised), one row per wheel", "1",
              shapes=(("N", 3), (3,))),
        Input("inertia", "axial moments J_i (the body's inertia then excludes them)",
              "kg m^2", shapes=(("N",), ()), bound="positive"),
        Input("motor", "constant motor torques (or a control law: see control)", "N m",
              shapes=(("N",), ()), columns=("wheel{i}_torque",)),
        Input("max_torque", "motor torque limits (commands are clipped)", "N m",
              shapes=(("N",), ()), bound="positive"),
        Input("max_speed", "relative spin limits", "rad/s", shapes=(("N",), ()),
              bound="positive"),
        Input("damping", "viscous coefficients between wheel and body", "N m s",
              shapes=(("N",), ()), bound="nonnegative"),
        Input("control", "control law driving the motors: 'rate-damping' (gain) or "
              "'attitude-tracking' (target, kp, kd)", "", type="text",
              choices=("none", "rate-damping", "attitude-tracking")),
        Input("gain", "rate-damping gain: body torque -gain w", "N m s", bound="nonnegative"),
        Input("target", "attitude-tracking target quaternion, scalar first", shapes=((4,),)),
        Input("kp", "attitude-tracking proportional gain", "N m", bound="nonnegative"),
        Input("kd", "attitude-tracking rate gain", "N m s", bound="nonnegative"),
        Input("speed", "initial spins relative to the body", "rad/s", shapes=(("N",), ()),
              role="initial", state="speed", fit="free", columns=("wheel{i}_speed",),
              measured_optionally=True, fits="momentum"),
    )
    parameter_names = ("axes", "inertia", "max_torque", "max_speed", "damping")
    state_kinds = {"momentum": "momentum", "work": "energy", "dissipated": "energy"}

    def __init__(
        self,
        axes: Float[ArrayLike, "N 3"],
        inertia: Float[ArrayLike, " N"],
        motor: Float[ArrayLike, " N"] | Callable | None = None,
        max_torque: Float[ArrayLike, " N"] | None = None,
        max_speed: Float[ArrayLike, " N"] | None = None,
        damping: Float[ArrayLike, " N"] | None = None,
    ):
        axes = as_rows("wheels.axes", axes)
        n = axes.shape[0]
        dtype = axes.dtype
        self.axes = nonzero_unit("wheels.axes", axes, axis=1)

        def vector(name, value):
            return None if value is None else as_per_row(f"wheels.{name}", value, n, dtype)

        self.inertia = vector("inertia", inertia)
        self.motor = motor if (motor is None or callable(motor)) else vector("motor", motor)
        self.max_torque = vector("max_torque", max_torque)
        self.max_speed = vector("max_speed", max_speed)
        self.damping = vector("damping", damping)

    @classmethod
    def from_inputs(cls, control: str = "none", gain=None, target=None, kp=None, kd=None,
                    **values: Any) -> "Wheels":
        """Wheels from scene-file values: `control` names a law whose gains are given by name
        (`gain` for rate damping; `target`, `kp`, `kd` for attitude tracking)."""
        given = {"gain": gain, "target": target, "kp": kp, "kd": kd}
        gains = {k: v for k, v in given.items() if v is not None}
        law, uses = _LAWS[control]
        stray = sorted(set(gains) - set(uses))
        if stray:
            needs = next(name for name, (_, u) in _LAWS.items() if stray[0] in u)
            raise ParameterError(
                f"wheels.{stray[0]} given, but wheels.control={control!r} does not use it: "
                f"set wheels.control to {needs!r} or remove it")
        missing = [k for k in uses if k not in gains]
        if missing:
            raise ParameterError(f"wheels.{missing[0]} is required with wheels.control="
                                 f"{control!r}")
        if law is not None:
            if "motor" in values:
                raise ParameterError("wheels.motor: give constant motor torques or a control "
                                     "law, not both")
            values["motor"] = law(**gains)
        return cls(**values)

    @property
    def size(self) -> int:
        return self.axes.shape[0]

    @property
    def conserves(self) -> frozenset[str]:  # type: ignore[override]
        if self.motor is None and self.damping is None:
            return frozenset({"energy", "momentum"})
        return frozenset({"momentum"})

    def constructor_args(self) -> dict[str, Any]:
        return {"axes": self.axes, "inertia": self.inertia, "motor": self.motor,
                "max_torque": self.max_torque, "max_speed": self.max_speed,
                "damping": self.damping}

    def parameters(self) -> dict[str, Any]:
        return {k: v for k, v in self.constructor_args().items()
                if k in self.parameter_names and v is not None}

    def checks(self) -> list[Check]:
        checks = [finite_check("wheels.axes", self.axes),
                  positive_check("wheels.inertia", self.inertia)]
        for name in ("max_torque", "max_speed"):
            value = getattr(self, name)
            if value is not None:
                checks.append(positive_check(f"wheels.{name}", value))
        if self.damping is not None:
            checks.append(nonnegative_check("wheels.damping", self.damping))
        if self.motor is not None and not callable(self.motor):
            checks.append(finite_check("wheels.motor", self.motor))
        return checks

    # -- state ----------------------------------------------------------------------------------

    def initial_state(self, body_state, speed: Any = 0.0, **unknown: Any):
        if unknown:
            raise ParameterError(
                f"unknown initial values {sorted(unknown)} for wheels: allowed is speed"
            )
        omega = body_state["omega"]
        speed = as_float_array("wheels.speed", speed, None, omega.dtype, host=True)
        # (NumPy on the host where the values are concrete, then put on the device: eager
        # `jnp` compiled a program for each operation.)
        xp, inertia, axes, omega_, speed = on_host(self.inertia, self.axes, omega, speed)
        put = jax.device_put if xp is np else (lambda x: x)
        if speed.ndim == 0:
            speed = xp.broadcast_to(speed, (self.size,))
        if speed.shape != (self.size,):
            raise ParameterError(f"wheels.speed has shape {speed.shape}: expected ({self.size},)")
        y = {"momentum": put(inertia * (speed + axes @ omega_))}
        if self.motor is not None:
            y["work"] = put(xp.zeros((), omega.dtype))
        if self.damping is not None:
            y["dissipated"] = put(xp.zeros((), omega.dtype))
        return y

    def jump_times(self):
        jumps = getattr(self.motor, "jump_times", None)
        return None if jumps is None else jumps()

    def speed(self, y, own) -> Float[Array, " N"]:
        """Wheel spins relative to the body, `Omega_i = h_i / J_i - g_i . w`."""
        return own["momentum"] / self.inertia - self.axes @ y["omega"]

    def motor_torque(self, t, y, own) -> Float[Array, " N"] | None:
        """Motor torques after the torque and speed limits (`None` without motors)."""
        if self.motor is None:
            return None
        u = self.motor(t, y, self) if callable(self.motor) else self.motor
        u = jnp.asarray(u, y["omega"].dtype)
        if self.max_torque is not None:
            u = jnp.clip(u, -self.max_torque, self.max_torque)
        if self.max_speed is not None:
            # Within 1% of the limit, torque that would speed the wheel up fades linearly to
            # zero: a continuous limiter, so adaptive steps do not chatter at the limit.
            speed = self.speed(y, own)
            room = jnp.clip((self.max_speed - jnp.abs(speed)) / (0.01 * self.max_speed), 0, 1)
            u = jnp.where(u * speed > 0, u * room, u)
        return u

    def _axial_torque(self, t, y, own) -> Float[Array, " N"]:
        u = self.motor_torque(t, y, own)
        total = jnp.zeros_like(own["momentum"]) if u is None else u
        if self.damping is not None:
            total = total - self.damping * self.speed(y, own)
        return total

    def state_derivative(self, t, y, own, body):
        dy = {"momentum": self._axial_torque(t, y, own)}
        if self.motor is not None:
            dy["work"] = jnp.dot(self.motor_torque(t, y, own), self.speed(y, own))
        if self.damping is not None:
            dy["dissipated"] = jnp.dot(self.damping, self.speed(y, own) ** 2)
        return dy

    def momentum(self, t, y, own, body) -> Array:
        return own["momentum"] @ self.axes

    def outputs(self, t, y, own, body) -> dict[str, Array]:
        """The wheels' tachometers: `speed`, each wheel's spin relative to the body (rad/s)."""
        return {"speed": self.speed(y, own)}

    def momentum_rate(self, t, y, own, body) -> Array | None:
        if self.motor is None and self.damping is None:
            return None
        return self._axial_torque(t, y, own) @ self.axes

    def split_momentum(self, y, own) -> Array | None:
        if self.motor is None and self.damping is None:  # free wheels keep h constant
            return own["momentum"] @ self.axes
        return None

    def energy(self, t, y, own, body) -> Array:
        return 0.5 * jnp.sum(own["momentum"] ** 2 / self.inertia)


class CommandedTorques(eqx.Module):
    """Motor torques for [`jaxdyn.Wheels`][] as commanded in telemetry: `torques[k]` held from
    `times[k]` until the next command (zero-order hold; before the first command, none).
    A command equal to the one before it is dropped (it changes nothing): the integrator
    steps to each change of the torques (`jump_times`), not across it.
    Known inputs when identifying a body from its wheels' telemetry: the torques, in
    absolute units, fix the scale of the inertia.

    **Arguments:**

    - `times`: `(K,)` increasing command times (s).
    - `torques`: `(K, N)` motor torques (N m), one column per wheel.
    """

    times: Float[Array, " K"]
    torques: Float[Array, "K N"]

    def __init__(self, times: Float[ArrayLike, " K"], torques: Float[ArrayLike, "K N"]):
        times = as_float_array("commanded_torques.times", times)
        torques = as_float_array("commanded_torques.torques", torques, None, times.dtype)
        if times.ndim != 1 or times.size == 0:
            raise ParameterError(f"commanded_torques.times has shape {times.shape}: "
                                 "expected a non-empty 1-D array")
        torques = torques[:, None] if torques.ndim == 1 else torques
        if torques.ndim != 2 or torques.shape[0] != times.size:
            raise ParameterError(f"commanded_torques.torques has shape {torques.shape}: "
                                 f"expected ({times.size}, N), one row per command time")
        if not isinstance(times, jax.core.Tracer) and not isinstance(torques, jax.core.Tracer):
            # A command that repeats the previous one is no jump: dropped, so that the
            # integrator stops at the changes only (telemetry holds a command over many rows).
            # (Only valid times: invalid ones are refused by `__check_init__`, whole.)
            u, t = np.asarray(torques), np.asarray(times)
            keep = np.ones(u.shape[0], bool)
            keep[1:] = np.any(u[1:] != u[:-1], axis=1)
            if not keep.all() and np.all(np.isfinite(t)) and np.all(np.diff(t) > 0):
                times, torques = times[keep], torques[keep]
        self.times, self.torques = times, torques

    def __check_init__(self):
        from .._validation import raise_if_violated

        raise_if_violated([
            finite_check("commanded_torques.torques", self.torques),
            ("commanded_torques.times", self.times,
             ~jnp.all(jnp.isfinite(self.times)) | jnp.any(jnp.diff(self.times) <= 0),
             "must be finite and strictly increasing"),
        ])

    def jump_times(self) -> Float[Array, " K"]:
        """The command times: the torques jump there."""
        return self.times

    def __call__(self, t, y, wheels) -> Array:
        k = jnp.searchsorted(self.times, t, side="right", method="scan_unrolled") - 1
        held = self.torques[jnp.clip(k, 0, self.times.size - 1)]
        return jnp.where(k >= 0, held, 0.0).astype(y["omega"].dtype)


class RateDamping(eqx.Module):
    """Control law for [`jaxdyn.Wheels`][]: the wheels apply the body torque `-gain w`
    (least-squares allocation over the wheel axes). Detumbles a body."""

    gain: Float[Array, ""]

    def __init__(self, gain: ArrayLike):
        self.gain = as_float_array("rate_damping.gain", gain, ())

    def __check_init__(self):
        _gain_checks({"rate_damping.gain": self.gain})

    def __call__(self, t, y, wheels: Wheels) -> Array:
        wanted = -self.gain.astype(y["omega"].dtype) * y["omega"]
        return _allocate(wheels, wanted)


class AttitudeTracking(eqx.Module):
    """Control law for [`jaxdyn.Wheels`][]: quaternion feedback towards a fixed target attitude,
    body torque `-kp sign(dq0) dq_vec - kd w` with `dq = target^* (x) q` (needs attitude).

    Reference: Wie, Weiss & Arapostathis (1989), "Quaternion feedback regulator for spacecraft
    eigenaxis rotations".
    """

    target: Float[Array, "4"]
    kp: Float[Array, ""]
    kd: Float[Array, ""]

    def __init__(self, target: Float[ArrayLike, "4"], kp: ArrayLike, kd: ArrayLike):
        target = as_float_array("attitude_tracking.target", target, (4,))
        self.target = nonzero_unit("attitude_tracking.target", target)
        self.kp = as_float_array("attitude_tracking.kp", kp, (), target.dtype)
        self.kd = as_float_array("attitude_tracking.kd", kd, (), target.dtype)

    def __check_init__(self):
        _gain_checks({"attitude_tracking.kp": self.kp, "attitude_tracking.kd": self.kd})

    def __call__(self, t, y, wheels: Wheels) -> Array:
        from .._rotations import quat_conjugate, quat_multiply

        if "quaternion" not in y:
            raise ParameterError(
                "attitude tracking needs the attitude: use Scene(..., attitude=True)"
            )
        dtype = y["omega"].dtype
        dq = quat_multiply(quat_conjugate(self.target.astype(dtype)), y["quaternion"])
        sign = jnp.where(dq[0] >= 0, 1.0, -1.0).astype(dtype)
        wanted = -self.kp.astype(dtype) * sign * dq[1:] - self.kd.astype(dtype) * y["omega"]
        return _allocate(wheels, wanted)


_LAWS = {  # scene-file control laws: the class and the gains it takes, by name
    "none": (None, ()),
    "rate-damping": (RateDamping, ("gain",)),
    "attitude-tracking": (AttitudeTracking, ("target", "kp", "kd")),
}


def _gain_checks(gains: dict) -> None:
    """Control-law gains: finite and non-negative (a NaN gain would only show up as an
    exhausted step budget; a negative one pumps energy in)."""
    from .._validation import raise_if_violated

    raise_if_violated([nonnegative_check(name, g) for name, g in gains.items()])


def _allocate(wheels: Wheels, body_torque) -> Array:
    """Wheel torques `u` whose reaction `-sum u_i g_i` best matches `body_torque`."""
    axes = wheels.axes.astype(body_torque.dtype)  # (N, 3)
    return -jnp.linalg.pinv(axes.T) @ body_torque
