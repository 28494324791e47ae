"""Polhodes and the separatrix of the torque-free body, for plotting and classification."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._free_body import _check, torque_free_omega, torque_free_period
from ._validation import ParameterError, format_value, is_concrete


def separatrix_condition(
    inertia: Float[ArrayLike, "3"], omega: Float[ArrayLike, "... 3"]
) -> Float[Array, "..."]:
    """`H^2 - 2 T I_2`, with `I_2` the intermediate principal moment.

    Zero on the separatrix, positive for rotation about the major axis, negative about the minor
    axis. Computed as `sum_i I_i (I_i - I_2) w_i^2`, so that it is accurate close to zero.
    """
    inertia, _ = _check(inertia, jnp.zeros(3))
    return _separatrix_condition(inertia, omega)


@jax.jit
def _separatrix_condition(inertia, omega):
    omega = jnp.asarray(omega, inertia.dtype)
    i2 = jnp.sort(inertia)[1]
    return jnp.sum(inertia * (inertia - i2) * omega**2, axis=-1)


def polhode(
    inertia: Float[ArrayLike, "3"], omega0: Float[ArrayLike, "3"], num: int = 200
) -> Float[Array, "num 3"]:
    """One closed polhode: body rates over one period of the closed-form solution.

    Multiply by the moments (`inertia * omega`) for the curve on the momentum sphere. On the
    separatrix, where the period is infinite, returns the homoclinic orbit over `[-T, T]` with
    `T` long enough to come within `1e-6` of the saddles.
    """
    if not isinstance(num, int) or num < 2:
        raise ParameterError(f"num={num!r}: must be an integer >= 2")
    return _polhode(*_check(inertia, omega0), num)


@functools.partial(jax.jit, static_argnames="num")
def _polhode(inertia, omega0, num):
    period = torque_free_period(inertia, omega0)
    finite = jnp.isfinite(period)
    # On the separatrix: from about -20/lam to 20/lam (sech(20) ~ 4e-9).
    lam_scale = jnp.sqrt(jnp.sum(jnp.asarray(omega0, inertia.dtype) ** 2))
    span = jnp.where(finite, period, 40.0 / jnp.where(lam_scale > 0, lam_scale, 1.0))
    start = jnp.where(finite, 0.0, -0.5 * span)
    t = start + span * jnp.linspace(0.0, 1.0, num, dtype=inertia.dtype)
    return torque_free_omega(inertia, omega0, t)


def separatrix_curves(
    inertia: Float[ArrayLike, "3"], momentum: float = 1.0, num: int = 101
) -> Float[Array, "4 num 3"]:
    """The separatrix on the momentum sphere `|h| = momentum`: four arcs joining the two saddles
    on the intermediate axis, `h1^2 (I2/I1 - 1) + h3^2 (I2/I3 - 1) = 0` (axes as given).

    Requires three distinct moments: with two equal moments there is no intermediate axis, and
    a [`jaxdyn.ParameterError`][] says so.
    """
    inertia, _ = _check(inertia, jnp.zeros(3))
    if not isinstance(num, int) or num < 2:
        raise ParameterError(f"num={num!r}: must be an integer >= 2")
    if is_concrete(inertia):
        moments = np.sort(np.asarray(inertia))
        if moments[0] == moments[1] or moments[1] == moments[2]:
            raise ParameterError(
                f"inertia={format_value(inertia)}: two equal principal moments, so there is no "
                "intermediate axis and no separatrix (every polhode circles the symmetry axis)"
            )
    return _separatrix_curves(inertia, momentum, num)


@functools.partial(jax.jit, static_argnames="num")
def _separatrix_curves(inertia, momentum, num):
    perm = jnp.argsort(inertia)
    i1, i2, i3 = inertia[perm]
    k = jnp.sqrt((i2 / i1 - 1) / (1 - i2 / i3))
    psi = jnp.linspace(0.0, jnp.pi, num, dtype=inertia.dtype)
    arcs = []
    for a, b in ((1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)):
        n = jnp.stack([a * jnp.ones_like(k), jnp.zeros_like(k), b * k]) / jnp.sqrt(1 + k**2)
        e2 = jnp.array([0.0, 1.0, 0.0], inertia.dtype)
        h_sorted = momentum * (jnp.cos(psi)[:, None] * e2 + jnp.sin(psi)[:, None] * n)
        arcs.append(jnp.zeros_like(h_sorted).at[:, perm].set(h_sorted))
    return jnp.stack(arcs)
