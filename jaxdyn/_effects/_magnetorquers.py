r"""Magnetic torque rods: body-fixed dipoles acting on the geomagnetic field along the orbit.

Three rods along the body axes command a dipole `m` (A m^2); the field `b` (T, body frame) of
the IGRF-13 tilted dipole along a circular orbit (see `jaxdyn._orbit`) turns it into the torque
`tau = m x b`, which has no component along `b`. A residual dipole of the spacecraft adds to the
command as a disturbance.

Control law `"bdot"`, in the form analysed by Avanzini & Giulietti (2012, "Magnetic Detumbling
of a Rigid Spacecraft", J. Guidance, Control, and Dynamics 35(4)): `m = (k / |b|) w x b_hat`,
the rods driven by the rate of change of the field direction that the body's rotation causes
(`d b_hat / dt = -w x b_hat` in the body frame, the dominant term while the body tumbles much
faster than the orbit turns). Then `tau = -k (w - (w . b_hat) b_hat)`: the rate across the
field is damped and the kinetic energy never increases,
`dT/dt = w . tau = -k |w x b_hat|^2 <= 0`, also when each rod saturates at its limit. As the
field turns along the orbit every component is damped in turn, down to about the orbit rate.
Avanzini and Giulietti's gain for the fastest detumbling is
`k* = 2 n (1 + sin xi_m) J_min` (`n` the orbit rate, `xi_m` the orbit's inclination to the
geomagnetic equator, `J_min` the smallest principal moment).

Control law `"dump"`, the cross-product law of momentum management (Sidi, *Spacecraft
Dynamics and Control*, 1997, sec. 7.5; Camillo & Markley 1980): with `h` the momentum stored
in the scene's wheels and rotors (body frame), `m = k_d (h x b) / |b|^2`, so that
`tau = m x b = -k_d (h - (h . b_hat) b_hat)`: an external torque against the stored momentum
across the field. Wheels that hold the attitude absorb it, and their momentum drains at the
rate `k_d` across the field; along the field nothing can be dumped at that instant, but the
field turns along the orbit. Every change of the total (body plus wheels) inertial momentum is
the rods' angular impulse.
"""

from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._effect import AbstractEffect
from .._inputs import Input
from .._orbit import EARTH_RADIUS, dipole_field, orbit_direction, orbit_rate
from .._rotations import quat_conjugate, quat_rotate, safe_norm
from .._validation import (
    Check,
    ParameterError,
    as_float_array,
    finite_check,
    nonnegative_check,
    positive_check,
)

LAWS = ("bdot", "dump", "none")


class MagneticTorquers(AbstractEffect):
    """Magnetic torque rods along the body axes, on a circular orbit through the IGRF-13
    dipole field (the scene integrates the attitude).

    **Arguments:**

    - `altitude`: the circular orbit's altitude above the equatorial radius (m).
    - `inclination`, `node`, `phase`: its inclination, right ascension of the ascending node,
      and argument of latitude at `t = 0` (rad).
    - `earth_angle`: the Greenwich angle at `t = 0` (rad): where the Earth-fixed dipole is.
    - `control`: `"bdot"` (detumbling), `"dump"` (momentum dumping for the scene's wheels;
      see the module's notes) or `"none"` (residual dipole only).
    - `gain`: the B-dot gain `k` (N m s).
    - `dump_gain`: the dumping gain `k_d` (1/s).
    - `max_dipole`: each rod's dipole limit (A m^2), one value or three; `None`: no limit.
    - `residual_dipole`: the spacecraft's residual dipole (A m^2), three values.
    """

    altitude: Float[Array, ""]
    inclination: Float[Array, ""]
    node: Float[Array, ""]
    phase: Float[Array, ""]
    earth_angle: Float[Array, ""]
    gain: Float[Array, ""]
    dump_gain: Float[Array, ""]
    max_dipole: Float[Array, "3"] | None
    residual_dipole: Float[Array, "3"]
    control: str = eqx.field(static=True)

    kind: ClassVar[str] = "magnetorquers"
    needs_attitude: ClassVar[bool] = True
    uses_stored_momentum: ClassVar[bool] = True
    inputs: ClassVar[tuple[Input, ...]] = (
        Input("altitude", "circular orbit altitude above the equatorial radius", "m",
              bound="positive"),
        Input("inclination", "orbit inclination", "rad"),
        Input("node", "right ascension of the ascending node", "rad"),
        Input("phase", "argument of latitude at t = 0", "rad"),
        Input("earth_angle", "Greenwich angle at t = 0 (where the dipole is)", "rad"),
        Input("control", "rod control law: 'bdot' (m = k w x b_hat / |b|), 'dump' "
              "(m = k_d h x b / |b|^2, h the wheels' momentum) or 'none'", "",
              type="text", choices=LAWS),
        Input("gain", "B-dot gain k", "N m s", bound="nonnegative"),
        Input("dump_gain", "momentum-dumping gain k_d", "1/s", bound="nonnegative"),
        Input("max_dipole", "dipole limit of each rod", "A m^2", shapes=((3,), ()),
              bound="positive"),
        Input("residual_dipole", "the spacecraft's residual dipole (a disturbance)", "A m^2",
              shapes=((3,),)),
    )
    parameter_names: ClassVar[tuple[str, ...]] = (
        "altitude", "inclination", "node", "phase", "earth_angle", "gain", "dump_gain",
        "residual_dipole")

    def __init__(self, altitude: ArrayLike, inclination: ArrayLike = 0.9,
                 node: ArrayLike = 0.0, phase: ArrayLike = 0.0, earth_angle: ArrayLike = 0.0,
                 control: str = "bdot", gain: ArrayLike = 0.0, dump_gain: ArrayLike = 0.0,
                 max_dipole: ArrayLike | None = None,
                 residual_dipole: Float[ArrayLike, "3"] = (0.0, 0.0, 0.0)):
        if control not in LAWS:
            raise ParameterError(f"magnetorquers.control={control!r}: allowed are {LAWS}")
        self.control = control
        self.altitude = as_float_array("magnetorquers.altitude", altitude, ())
        dtype = self.altitude.dtype
        for name, value in (("inclination", inclination), ("node", node), ("phase", phase),
                            ("earth_angle", earth_angle), ("gain", gain),
                            ("dump_gain", dump_gain)):
            setattr(self, name, as_float_array(f"magnetorquers.{name}", value, (), dtype))
        if max_dipole is None:
            self.max_dipole = None
        else:
            limit = as_float_array("magnetorquers.max_dipole", max_dipole, None, dtype)
            if limit.shape not in ((), (3,)):
                raise ParameterError(f"magnetorquers.max_dipole has shape {limit.shape}: "
                                     "expected one value or three")
            self.max_dipole = jnp.broadcast_to(limit, (3,))
        self.residual_dipole = as_float_array("magnetorquers.residual_dipole",
                                              residual_dipole, (3,), dtype)

    def constructor_args(self) -> dict[str, Any]:
        return {"altitude": self.altitude, "inclination": self.inclination, "node": self.node,
                "phase": self.phase, "earth_angle": self.earth_angle, "control": self.control,
                "gain": self.gain, "dump_gain": self.dump_gain, "max_dipole": self.max_dipole,
                "residual_dipole": self.residual_dipole}

    def parameters(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.parameter_names}

    def checks(self) -> list[Check]:
        checks = [positive_check("magnetorquers.altitude", self.altitude),
                  finite_check("magnetorquers.residual_dipole", self.residual_dipole),
                  nonnegative_check("magnetorquers.gain", self.gain),
                  nonnegative_check("magnetorquers.dump_gain", self.dump_gain)]
        for name in ("inclination", "node", "phase", "earth_angle"):
            checks.append(finite_check(f"magnetorquers.{name}", getattr(self, name)))
        if self.max_dipole is not None:
            checks.append(positive_check("magnetorquers.max_dipole", self.max_dipole))
        return checks

    # -- physics --------------------------------------------------------------------------------

    @property
    def orbit_rate(self) -> Array:
        return orbit_rate(self.altitude)

    def field_inertial(self, t) -> Float[Array, "3"]:
        """The geomagnetic field at the spacecraft (T), inertial frame."""
        r_hat = orbit_direction(t, self.orbit_rate, self.phase, self.inclination, self.node)
        return dipole_field(t, r_hat, EARTH_RADIUS + self.altitude, self.earth_angle)

    def field(self, t, y) -> Float[Array, "3"]:
        """The geomagnetic field in the body frame (T)."""
        q = y["quaternion"]
        return quat_rotate(quat_conjugate(q), self.field_inertial(t).astype(q.dtype))

    def dipole(self, t, y, b=None, stored=None) -> Float[Array, "3"]:
        """The rods' commanded dipole after their limits, plus the residual dipole (A m^2),
        in the body-frame field `b` (computed here if not given); `stored` is the momentum
        the dumping law drains (the scene's wheels and rotors; none: nothing to dump)."""
        b = self.field(t, y) if b is None else b
        w = y["omega"]
        dtype = w.dtype
        if self.control == "bdot":
            norm = safe_norm(b)
            command = self.gain.astype(dtype) * jnp.cross(w, b / norm) / norm
        elif self.control == "dump" and stored is not None:
            command = self.dump_gain.astype(dtype) * jnp.cross(stored, b) / jnp.dot(b, b)
        else:
            command = jnp.zeros_like(w)
        if self.max_dipole is not None:
            limit = self.max_dipole.astype(dtype)
            command = jnp.clip(command, -limit, limit)
        return command + self.residual_dipole.astype(dtype)

    def torque(self, t, y, own, body, stored=None) -> Array:
        b = self.field(t, y)  # once per evaluation: the command and the torque share it
        return jnp.cross(self.dipole(t, y, b, stored), b)
