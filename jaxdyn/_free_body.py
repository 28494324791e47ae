"""Closed-form motion of the torque-free rigid body (Jacobi elliptic functions).

With principal moments ordered so that the body spins about axis 3 (the axis whose rate never
changes sign), `physics.md` section 2 gives

    w1 = s1 A1 cn(u | m),   w2 = sigma s1 s3 A2 sn(u | m),   w3 = s3 A3 dn(u | m),   u = lam t + u0

with `sigma = sign(I3 - I1)`, `s1`, `s3` the signs of the initial rates, and `u0` from the
initial condition through the incomplete integral `F(phi0 | m)`. Every difference of invariants is
written as `D_k = H^2 - 2 T I_k = sum_i I_i (I_i - I_k) w_i^2`, which avoids the cancellation of
computing `H^2` and `2 T I_k` separately; in particular the complementary parameter
`1 - m = (I3 - I1) D_2 / ((I3 - I2) D_1)` is exact near the separatrix, where `m -> 1`.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._elliptic import carlson_rf, ellipj, ellipk
from ._padded import over_padded_times


class _Setup(NamedTuple):
    moments: Array  # as used (axis 3 = spin axis)
    omega0: Array  # in the frame used
    perm: Array  # original index of each used axis
    sign: Array  # +-1: used = sign * original[perm]
    amp: Array  # A1, A2, A3
    signs: Array  # s1, sigma s1 s3, s3
    m: Array
    m1: Array
    lam: Array
    u0: Array
    at_saddle: Array


def _d(moments, omega, k):
    """`D_k = H^2 - 2 T I_k`, without cancellation."""
    return jnp.sum(moments * (moments - moments[k]) * omega**2)


def _safe_div(a, b):
    ok = b != 0
    return jnp.where(ok, a / jnp.where(ok, b, 1.0), 0.0)


def _sorted(inertia, omega0):
    """Moments in ascending order and the rates in that frame, by a proper rotation (an odd
    permutation of axes also flips every rate's sign, which keeps Euler's equations)."""
    inertia = jnp.asarray(inertia)
    dtype = inertia.dtype
    omega0 = jnp.asarray(omega0, dtype)
    perm = jnp.argsort(inertia)
    # The permutation's sign, exactly: prod_{i<j} (p_j - p_i) is +-2 for a permutation of 0..2.
    parity = ((perm[1] - perm[0]) * (perm[2] - perm[0]) * (perm[2] - perm[1]) // 2).astype(dtype)
    return inertia[perm], parity * omega0[perm], perm, parity


def _setup(moments, omega, perm, parity) -> _Setup:
    """Parameters of the elliptic solution, from ascending moments (three distinct)."""
    dtype = moments.dtype
    # Below the separatrix (H^2 < 2 T I2) the body spins about the minor axis: reverse the order
    # (an odd permutation again, so negate) so that the spin axis is axis 3.
    reverse = _d(moments, omega, 1) < 0
    moments = jnp.where(reverse, moments[::-1], moments)
    omega = jnp.where(reverse, -omega[::-1], omega)
    perm = jnp.where(reverse, perm[::-1], perm)
    sign = jnp.where(reverse, -parity, parity)

    i1, i2, i3 = moments
    w1, w2, w3 = omega
    d1, d2, d3 = _d(moments, omega, 0), _d(moments, omega, 1), _d(moments, omega, 2)
    a1 = jnp.sqrt(jnp.maximum(_safe_div(-d3, i1 * (i3 - i1)), 0.0))
    a2 = jnp.sqrt(jnp.maximum(_safe_div(-d3, i2 * (i3 - i2)), 0.0))
    a3 = jnp.sqrt(jnp.maximum(_safe_div(d1, i3 * (i3 - i1)), 0.0))
    m = jnp.clip(_safe_div((i2 - i1) * (-d3), (i3 - i2) * d1), 0.0, 1.0)
    m1 = jnp.clip(_safe_div((i3 - i1) * d2, (i3 - i2) * d1), 0.0, 1.0)
    lam = jnp.sqrt(jnp.maximum(_safe_div((i3 - i2) * d1, i1 * i2 * i3), 0.0))

    s1 = jnp.where(w1 >= 0, 1.0, -1.0).astype(dtype)
    s3 = jnp.where(w3 >= 0, 1.0, -1.0).astype(dtype)
    sigma = jnp.sign(i3 - i1)
    # Initial phase: cn(u0) = |w1| / A1 >= 0, sn(u0) = sigma s1 s3 w2 / A2, so
    # u0 = F(phi0 | m) = sin(phi0) R_F(cos^2 phi0, m1 + m cos^2 phi0, 1) with |phi0| <= pi/2.
    x = _safe_div(s1 * w1, a1)  # |w1|, with derivative +1 at w1 = 0 (where s1 = +1)
    y = _safe_div(sigma * s1 * s3 * w2, a2)
    r = jnp.sqrt(x**2 + y**2)
    moving = r > 0
    r = jnp.where(moving, r, 1.0)
    c, s = x / r, y / r
    at_saddle = (m1 == 0) & (c == 0)  # exactly at the intermediate-axis equilibrium
    rf = carlson_rf(c**2, jnp.where(at_saddle, 1.0, m1 + m * c**2), jnp.ones_like(c))
    # Near the quarter period (|cos phi0| < |sin phi0|) use F(phi) = K - F(psi) with the
    # complementary amplitude (sn(K - u) = cd(u)): F(psi) = C R_F(m1 S^2, m1, m1 + m C^2), whose
    # derivative stays finite at C = 0 (R_F's derivative in an argument that is exactly zero is
    # infinite). Not on the separatrix, where K is infinite.
    near_quarter = (jnp.abs(c) < jnp.abs(s)) & (m1 > 0)
    m1_safe = jnp.where(m1 > 0, m1, 1.0)
    k = ellipk(m, m1_safe)
    rf_c = carlson_rf(m1_safe * s**2, m1_safe, m1_safe + m * c**2)
    u0 = jnp.where(near_quarter, jnp.sign(s) * (k - c * rf_c), s * rf)
    u0 = jnp.where(moving & ~at_saddle, u0, 0.0)
    return _Setup(
        moments, omega, perm, sign, jnp.stack([a1, a2, a3]),
        jnp.stack([s1, sigma * s1 * s3, s3]), m, m1, lam, u0, at_saddle,
    )


def _axisymmetric(moments, omega, t):
    """Two equal moments (ascending frame): the rate about the symmetry axis `a` is constant
    and the transverse rates rotate at `Omega = (I_a - I_t) / I_t w_a` (a sphere: constant)."""
    a = jnp.where(moments[0] == moments[1], 2, 0)
    b, c = (a + 1) % 3, (a + 2) % 3
    i_t = moments[b]
    angle = (moments[a] - i_t) / i_t * omega[a] * t
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    wb = omega[b] * cos - omega[c] * sin
    wc = omega[b] * sin + omega[c] * cos
    w = jnp.zeros(t.shape + (3,), moments.dtype)
    return w.at[..., a].set(omega[a] * jnp.ones_like(t)).at[..., b].set(wb).at[..., c].set(wc)


def _sinhc(x):
    """`sinh(sqrt(x)) / sqrt(x)` for `x >= 0` and `sin(sqrt(-x)) / sqrt(-x)` for `x < 0`: the
    entire function `sum_k x^k / (2k + 1)!`, smooth through 0 (its series where `|x| < 1`)."""
    small = jnp.abs(x) < 1
    r = jnp.sqrt(jnp.where(small, 1.0, jnp.abs(x)))
    grows = x > 0  # (each branch gets its argument only where it is used: a sinh that
    # overflowed where sin is taken would make the discarded cotangent 0 * inf = NaN)
    wide = jnp.where(grows, jnp.sinh(jnp.where(grows, r, 0.0)),
                     jnp.sin(jnp.where(grows, 0.0, r))) / r
    xs = jnp.where(small, x, 0.0)
    series = jnp.ones_like(xs)
    for k in range(12, 0, -1):  # Horner; the first term left out is below 1 / 25!
        series = 1.0 + xs * series / ((2 * k) * (2 * k + 1))
    return jnp.where(small, series, wide)


def spin_flow(jac, t):
    """`expm(jac t)` for each `t`, where `jac` is Euler's equations' Jacobian at a spin about a
    principal axis (or at rest): its trace and determinant are zero, so `jac^3 = mu^2 jac`
    with `mu^2 = tr(jac^2) / 2` (Cayley-Hamilton) and

        expm(jac t) = I + t S(mu^2 t^2) jac + t^2 G(mu^2 t^2) jac^2,

    `S(x) = sinh(sqrt x) / sqrt x` (growing about the intermediate axis, `mu^2 > 0`; turning,
    `sin`, about the others), `G(x) = S(x / 4)^2 / 2 = (cosh(sqrt x) - 1) / x`. A few dozen
    operations where `jax.scipy.linalg.expm` under `vmap` compiles five Pade approximants and
    a linear solve (checked against it in the tests)."""
    mu2 = 0.5 * jnp.sum(jac * jac.T)
    x = mu2 * t * t
    s = (t * _sinhc(x))[..., None, None]
    g = (0.5 * t * t * _sinhc(0.25 * x) ** 2)[..., None, None]
    return jnp.eye(3, dtype=jac.dtype) + s * jac + g * (jac @ jac)


def euler_jacobian(moments, omega):
    """The Jacobian of Euler's torque-free equations `w' = ((I w) x w) / I` at `omega`."""
    return jax.jacfwd(lambda w: jnp.cross(moments * w, w) / moments)(omega)


def _equilibrium(moments, omega, t):
    """A spin about a principal axis (or rest): constant in value; the derivative with respect
    to the initial rates is the linearised flow `expm(J t)` (growing for the intermediate axis)."""
    flow = spin_flow(euler_jacobian(moments, omega), t.reshape(-1))
    delta = omega - jax.lax.stop_gradient(omega)  # zero in value, carries the tangent
    w = jax.lax.stop_gradient(omega) + flow @ delta
    return w.reshape(t.shape + (3,))


_NO_TIMES = object()  # (`_check` of the functions that take no times; `t=None` is refused)


def _check(inertia, omega0, t=_NO_TIMES):
    """Eager checks of the closed-form functions' inputs (skipped for traced values)."""
    from ._inertia import moments_checks
    from ._validation import ParameterError, as_float_array, finite_check, raise_if_violated

    # (Values given on the host stay there: the compiled program's call transfers them.)
    inertia = as_float_array("inertia", inertia, host=True)
    if inertia.shape != (3,):
        raise ParameterError(f"inertia has shape {inertia.shape}: expected 3 principal moments")
    raise_if_violated(moments_checks("inertia", inertia))
    omega0 = as_float_array("omega0", omega0, (3,), inertia.dtype, host=True)
    raise_if_violated([finite_check("omega0", omega0)])  # (NumPy on the host: no program)
    if t is _NO_TIMES:
        return inertia, omega0
    t = as_float_array("t", t, None, inertia.dtype, host=True)
    raise_if_violated([finite_check("t", t)])
    return inertia, omega0, t


def torque_free_omega(
    inertia: Float[ArrayLike, "3"], omega0: Float[ArrayLike, "3"], t: Float[ArrayLike, "*times"]
) -> Float[Array, "*times 3"]:
    """Body rates of a torque-free rigid body in closed form.

    Valid on both sides of the separatrix and on it (`m = 1`, where `sn = tanh` and
    `cn = dn = sech`: the homoclinic orbit), for principal moments in any order, with signs and
    phase following the initial condition. Differentiable with respect to every argument.

    **Arguments:**

    - `inertia`: the three principal moments (any order).
    - `omega0`: body rates at `t = 0` in the same principal frame (rad/s).
    - `t`: times (any shape).

    **Returns:**

    Body rates with shape `t.shape + (3,)`. The compiled closed form is reused for any number
    of times within one of a few padded lengths (four per octave), so a new number of times
    (a slider over the time span) costs a call, not a compilation.

    Reference: Landau & Lifshitz, *Mechanics*, section 37.
    """
    inertia, omega0, t = _check(inertia, omega0, t)
    return over_padded_times(lambda t: _torque_free_omega(inertia, omega0, t), t, inertia,
                             omega0)


@jax.jit
def _torque_free_omega(inertia, omega0, t):
    moments, omega, perm, parity = _sorted(inertia, omega0)
    dtype = moments.dtype
    t = jnp.asarray(t, dtype)
    equilibrium = jnp.sum(omega != 0) <= 1
    axisymmetric = (moments[0] == moments[1]) | (moments[1] == moments[2])
    p = _setup(*_safe_general(moments, omega, equilibrium | axisymmetric), perm, parity)
    u = p.lam * t + p.u0
    sn, cn, dn = ellipj(u, p.m, p.m1)
    w = jnp.stack([cn, sn, dn], axis=-1) * (p.signs * p.amp)
    w = jnp.where(p.at_saddle, p.omega0, w)
    general = jnp.zeros_like(w).at[..., p.perm].set(p.sign * w)  # original[perm] = sign * used
    # (At rest where it is not used: the flow is then the identity, which neither overflows
    # nor poisons the reverse-mode derivative through `jnp.where` with `inf * 0`.)
    sorted_frame = jnp.where(
        equilibrium, _equilibrium(moments, jnp.where(equilibrium, omega, 0.0), t),
        _axisymmetric(moments, omega, t)
    )
    sorted_frame = jnp.zeros_like(sorted_frame).at[..., perm].set(parity * sorted_frame)
    return jnp.where(equilibrium | axisymmetric, sorted_frame, general)


def _safe_general(moments, omega, degenerate):
    """Inputs for the general branch: where it is not used, a harmless non-degenerate body, so
    that its square roots and divisions cannot poison gradients through `jnp.where`."""
    dtype = moments.dtype
    moments = jnp.where(degenerate, jnp.array([1.0, 2.0, 3.0], dtype), moments)
    omega = jnp.where(degenerate, jnp.array([0.3, 0.2, 1.0], dtype), omega)
    return moments, omega


def torque_free_period(
    inertia: Float[ArrayLike, "3"], omega0: Float[ArrayLike, "3"]
) -> Float[Array, ""]:
    """Period of the body rates, `4 K(m) / lam` (infinite on the separatrix)."""
    return _torque_free_period(*_check(inertia, omega0))


@jax.jit
def _torque_free_period(inertia, omega0):
    p = _setup(*_sorted(inertia, omega0))
    return 4 * ellipk(p.m, p.m1) / p.lam


def elliptic_parameter(
    inertia: Float[ArrayLike, "3"], omega0: Float[ArrayLike, "3"]
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """The parameter `m` of the elliptic solution and its complement `1 - m` (exact near 1)."""
    return _elliptic_parameter(*_check(inertia, omega0))


@jax.jit
def _elliptic_parameter(inertia, omega0):
    p = _setup(*_sorted(inertia, omega0))
    return p.m, p.m1
