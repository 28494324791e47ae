"""A rigid body: Euler's equations with optional attitude (quaternion) kinematics."""

from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._body import AbstractBody
from ._custom_types import Scalar, State
from ._inertia import invert3, moments_checks, principal_axes, tensor_checks
from ._inputs import Input
from ._rotations import (
    mrp_from_quat,
    quat_derivative,
    quat_multiply,
    quat_rotate,
    quat_to_dcm,
    quat_to_euler321,
    safe_norm,
)
from ._validation import Check, ParameterError, as_float_array, nonzero_unit


def _sum(terms: list) -> Array | None:
    terms = [x for x in terms if x is not None]
    if not terms:
        return None
    total = terms[0]
    for x in terms[1:]:
        total = total + x
    return total


class RigidBody(AbstractBody):
    """A rigid body described by its inertia about the centre of mass.

    **Arguments:**

    - `inertia`: either three principal moments (the body frame is then the principal frame, and
      Euler's equations take their cheapest form), or a full symmetric 3x3 tensor with products of
      inertia in the body frame (principal axes are found by `principal_axes`). Each principal
      moment must be positive and no larger than the sum of the other two.

    State: `omega` (body rates in the body frame, rad/s) and, when the scene integrates attitude,
    `quaternion` (scalar first, mapping body to inertial components). The quaternion kinematics
    `q_dot = q (x) (0, w) / 2` carry the stabilising term `|w| (1 - |q|^2) q / 2`, zero on the unit
    sphere, so that the norm stays at 1 to round-off over long horizons.
    """

    inertia: Float[Array, "3"] | Float[Array, "3 3"]

    kind: ClassVar[str] = "rigid-body"
    residual_kinds: ClassVar[dict[str, str]] = {"quaternion": "rotation"}
    inputs: ClassVar[tuple[Input, ...]] = (
        Input("inertia", "3 principal moments, or the tensor (9 entries row by row) with "
              "products of inertia in the body frame; each principal moment at most the sum "
              "of the other two", "kg m^2", shapes=((3,), (9,), (3, 3)),
              fit="inertia"),
        Input("omega0", "initial body rates in the body frame", "rad/s", shapes=((3,),),
              role="initial", state="omega", required=True, fit="free",
              columns=("wx", "wy", "wz")),
        Input("quaternion0", "initial attitude, scalar first, body to inertial (default: "
              "identity; normalised)", shapes=((4,),), role="initial", state="quaternion",
              needs_attitude=True, fit="unit", columns=("q0", "q1", "q2", "q3"),
              measured_optionally=True),
        Input("attitude", "integrate the attitude quaternion even if no effect needs it",
              "", type="bool", role="scene"),
    )
    accepts_effects: ClassVar[bool] = True
    plain_scene: ClassVar[str | None] = "torque-free"
    output_units: ClassVar[Mapping[str, str]] = {
        "omega": "rad/s", "energy": "J", "kinetic_energy": "J", "momentum": "kg m^2/s",
        "angular_momentum": "kg m^2/s", "momentum_inertial": "kg m^2/s", "euler321": "rad",
    }
    identifiability: ClassVar[Mapping[str, str]] = {
        "inertia.scale": "the rates of a torque-free body do not change when its inertia "
        "is multiplied by a constant, so only the normalised tensor is fitted (principal "
        "moments scaled so that the largest is 1); a known torque or rotor momentum in "
        "the scene would fix the scale",
    }
    invariant_names: ClassVar[tuple[str, ...]] = ("energy", "momentum")

    def __init__(self, inertia: Float[ArrayLike, "3"] | Float[ArrayLike, "3 3"]):
        arr = as_float_array("inertia", inertia)
        if arr.shape not in ((3,), (3, 3)):
            raise ParameterError(
                f"inertia has shape {arr.shape}: expected 3 principal moments or a 3x3 tensor"
            )
        self.inertia = arr

    @classmethod
    def from_inputs(cls, inertia, **values) -> "RigidBody":
        flat = np.asarray(inertia)
        return cls(inertia=flat.reshape(3, 3) if flat.shape == (9,) else inertia, **values)

    # -- mass properties ------------------------------------------------------------------------

    @property
    def is_principal(self) -> bool:
        """Whether `inertia` holds principal moments (the body frame is a principal frame)."""
        return self.inertia.ndim == 1

    @property
    def tensor(self) -> Float[Array, "3 3"]:
        return jnp.diag(self.inertia) if self.is_principal else self.inertia

    @property
    def principal_moments(self) -> Float[Array, "3"]:
        """Principal moments; as given for principal inertia, ascending for a full tensor."""
        return self.inertia if self.is_principal else principal_axes(self.inertia)[0]

    @property
    def principal_axes(self) -> Float[Array, "3 3"]:
        """Columns are the principal axes in the body frame (identity for principal inertia)."""
        if self.is_principal:
            return jnp.eye(3, dtype=self.inertia.dtype)
        return principal_axes(self.inertia)[1]

    def checks(self) -> list[Check]:
        if self.is_principal:
            return moments_checks("inertia", self.inertia)
        return tensor_checks("inertia", self.inertia)

    def body_momentum(self, omega: Float[Array, "3"]) -> Float[Array, "3"]:
        """`I omega`, the body's own angular momentum in the body frame."""
        return self.inertia * omega if self.is_principal else self.inertia @ omega

    def _solve(self, rhs: Float[Array, "3"]) -> Float[Array, "3"]:
        return rhs / self.inertia if self.is_principal else invert3(self.inertia) @ rhs

    # -- protocol -------------------------------------------------------------------------------

    def initial_state(
        self, attitude: bool, omega: Any = None, quaternion: Any = None, **unknown: Any
    ) -> State:
        if unknown:
            raise ParameterError(
                f"unknown state variables {sorted(unknown)} for a rigid body: "
                "allowed are omega, quaternion"
            )
        if omega is None:
            raise ParameterError("omega is required: three body rates in rad/s")
        dtype = self.inertia.dtype
        y = {"omega": as_float_array("omega", omega, (3,), dtype)}
        if attitude:
            q = jnp.array([1.0, 0.0, 0.0, 0.0], dtype) if quaternion is None else quaternion
            q = as_float_array("quaternion", q, (4,), dtype)
            y["quaternion"] = nonzero_unit("quaternion", q)
        elif quaternion is not None:
            raise ParameterError(
                "quaternion given, but the scene does not integrate attitude: "
                "use Scene(..., attitude=True) or an effect that needs attitude"
            )
        return y

    def _internal(self, t, y, effects) -> tuple[Array | None, Array | None, Array | None]:
        h = _sum([e.momentum(t, y, own, self) for e, own in effects])
        hdot = _sum([e.momentum_rate(t, y, own, self) for e, own in effects])
        tau = _sum([e.torque(t, y, own, self, stored=h) if e.uses_stored_momentum
                    else e.torque(t, y, own, self) for e, own in effects])
        return h, hdot, tau

    def derivative(self, t: Scalar, y: State, effects: tuple, attitude: bool) -> State:
        omega = y["omega"]
        h_internal, h_rate, torque = self._internal(t, y, effects)
        if self.is_principal:
            # Written component by component: batched over many trajectories (ensembles), each
            # component is then one contiguous row and XLA fuses a whole stage into one pass.
            # dw_i/dt = (I_j - I_k)/I_i w_j w_k + (h_j w_k - h_k w_j + tau_i - dh_i/dt)/I_i for
            # (i, j, k) cyclic, h the internal momentum: the coefficients are per body, not per
            # step, and an axisymmetric body's I_j - I_k is exactly zero.
            w = [omega[i] for i in range(3)]
            inertia = self.inertia
            inv = [1 / inertia[i] for i in range(3)]
            cyc = ((0, 1, 2), (1, 2, 0), (2, 0, 1))
            rhs = [(inertia[j] - inertia[k]) * inv[i] * (w[j] * w[k]) for i, j, k in cyc]
            extra = [None, None, None]
            if h_internal is not None:
                extra = [h_internal[j] * w[k] - h_internal[k] * w[j] for _, j, k in cyc]
            if torque is not None:
                extra = [torque[i] if e is None else e + torque[i] for i, e in enumerate(extra)]
            if h_rate is not None:
                extra = [-h_rate[i] if e is None else e - h_rate[i] for i, e in enumerate(extra)]
            rhs = [r if e is None else r + e * inv[i] for i, (r, e) in enumerate(zip(rhs, extra))]
            dy = {"omega": jnp.stack(rhs)}
        else:
            h = self.body_momentum(omega)
            if h_internal is not None:
                h = h + h_internal
            rhs = jnp.cross(h, omega)
            if torque is not None:
                rhs = rhs + torque
            if h_rate is not None:
                rhs = rhs - h_rate
            dy = {"omega": self._solve(rhs)}
        if attitude:
            q = y["quaternion"]
            # Constraint stabilisation: the term vanishes on |q| = 1 (the exact solution is
            # unchanged) and pulls round-off drift of the norm back at the rotation rate.
            gain = 0.5 * safe_norm(omega) * (1 - jnp.dot(q, q))
            dy["quaternion"] = quat_derivative(q, omega) + gain * q
        return dy

    def natural_scales(self, t0, t1, y0, effects, attitude):
        """The rates are measured against the largest initial rate `W` (one scale for the three
        components, which exchange magnitude as the body turns); the quaternion against 1.
        A body starting at rest uses the rate its initial acceleration reaches over the run.
        References for effects' state: momentum `I_max W` (or the internal momentum, if
        larger), energy `I_max W^2`, time `1 / W`."""
        omega = y0["omega"]
        rate = jnp.max(jnp.abs(omega))
        accel = jnp.max(jnp.abs(self.derivative(t0, y0, effects, attitude)["omega"]))
        rate = jnp.where(rate > 0, rate, accel * jnp.abs(t1 - t0))
        rate = jnp.where(jnp.isfinite(rate) & (rate > 0), rate, 1.0)
        big = jnp.max(jnp.abs(self.inertia))
        h = _sum([e.momentum(t0, y0, own, self) for e, own in effects])
        momentum = big * rate
        if h is not None:
            momentum = jnp.maximum(momentum, jnp.max(jnp.abs(h)))
        scales = {"omega": rate}
        if attitude:
            scales["quaternion"] = jnp.ones_like(rate)
        return scales, {"time": 1 / rate, "momentum": momentum, "energy": momentum * rate}

    def _momentum_vector(self, t, y, effects) -> Float[Array, "3"]:
        h = self.body_momentum(y["omega"])
        h_internal = _sum([e.momentum(t, y, own, self) for e, own in effects])
        return h if h_internal is None else h + h_internal

    def kinetic_energy(self, omega: Float[Array, "3"]) -> Scalar:
        return 0.5 * jnp.dot(omega, self.body_momentum(omega))

    def invariants(self, t: Scalar, y: State, effects: tuple, attitude: bool) -> dict[str, Array]:
        energy = _sum(
            [self.kinetic_energy(y["omega"])] + [e.energy(t, y, own, self) for e, own in effects]
        )
        h = self._momentum_vector(t, y, effects)
        out = {"energy": energy, "momentum": safe_norm(h)}
        if attitude:
            out["momentum_inertial"] = quat_rotate(y["quaternion"], h)
        return out

    def outputs(self, t: Scalar, y: State, effects: tuple, attitude: bool) -> dict[str, Array]:
        out = {
            "omega": y["omega"],
            "angular_momentum": self._momentum_vector(t, y, effects),
            "kinetic_energy": self.kinetic_energy(y["omega"]),
        }
        if attitude:
            q = y["quaternion"]
            out["quaternion"] = q
            out["quaternion_norm"] = safe_norm(q)
            unit = q / out["quaternion_norm"]
            out["dcm"] = quat_to_dcm(unit)
            out["mrp"] = mrp_from_quat(unit)  # the set with |sigma| <= 1 (shadow switched)
            out["euler321"] = quat_to_euler321(unit)
        return out

    def summary(self, ts, ys, valid, t_final, y_final, event, effects=(),
                attitude=False) -> dict[str, Any]:
        out = {"omega_final": y_final["omega"]}
        if not effects:  # torque-free: the Jacobi-elliptic closed form is the reference
            omega0 = jax.tree.map(lambda a: a[0], ys)["omega"]
            out["reference"] = {"omega_final": self.exact_omega(omega0, t_final - ts[0])}
        return out

    def split_flow(self, axis: int, dt, y: State, effects: tuple, attitude: bool) -> State:
        """Exact flow over `dt` of the kinetic-energy term `(h_k - r_k)^2 / (2 I_k)` alone, for
        `k = axis` (principal inertia; `r` the constant internal momentum): the body momentum
        `h = I w + r` turns about body axis `k` by the angle `-w_k dt`, `w_k` staying constant,
        and the attitude turns by `+w_k dt` about the same axis, so `|h|` and the inertial `H` are
        preserved to round-off. Building block of [`jaxdyn.RotationSplitting`][]."""
        if not self.is_principal:
            raise ParameterError(
                "splitting integrators need principal inertia: build the body from "
                "body.principal_moments and rotate the rates by body.principal_axes"
            )
        r = _sum([e.split_momentum(y, own) for e, own in effects])
        omega = y["omega"]
        h = self.inertia * omega if r is None else self.inertia * omega + r
        i, j = (axis + 1) % 3, (axis + 2) % 3
        angle = omega[axis] * dt
        c, s = jnp.cos(angle), jnp.sin(angle)
        h = h.at[i].set(c * h[i] + s * h[j]).at[j].set(-s * h[i] + c * h[j])
        out = dict(y)
        out["omega"] = (h if r is None else h - r) / self.inertia
        if attitude:
            half = 0.5 * angle
            turn = jnp.zeros(4, omega.dtype).at[0].set(jnp.cos(half)).at[axis + 1].set(
                jnp.sin(half))
            out["quaternion"] = quat_multiply(y["quaternion"], turn)
        return out

    def exact_final(self, y0, t1, effects, attitude):
        if effects or not self.is_principal:
            return None
        out = {"omega": self.exact_omega(y0["omega"], t1)}
        if attitude:
            from ._free_body_attitude import torque_free_attitude

            out["quaternion"] = torque_free_attitude(self.inertia, y0["omega"],
                                                     y0["quaternion"], t1)
        return t1, out

    # -- analytic companion ---------------------------------------------------------------------

    @eqx.filter_jit
    def exact_omega(self, omega0: Float[ArrayLike, "3"], t: Float[ArrayLike, "..."]):
        """Body rates of the torque-free body at times `t`, from the Jacobi-elliptic solution.

        Works for a full tensor too: the rates are moved to the principal frame, propagated in
        closed form, and moved back. See [`jaxdyn.torque_free_omega`][].
        """
        from ._free_body import torque_free_omega

        omega0 = jnp.asarray(omega0, self.inertia.dtype)
        if self.is_principal:
            return torque_free_omega(self.inertia, omega0, t)
        moments, axes = principal_axes(self.inertia)
        w = torque_free_omega(moments, axes.T @ omega0, t)
        return w @ axes.T
