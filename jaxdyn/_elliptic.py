"""Elliptic integrals and Jacobi elliptic functions in pure JAX.

JAX has no elliptic functions, and the torque-free rigid body needs them: its angular
velocity is given by Jacobi's `sn`, `cn`, `dn`, its period by `K(m)` and its attitude by
incomplete integrals of the first and third kinds. Everything here is written in
`jax.numpy` with fixed iteration counts, so it is jit-able, vmap-able, differentiable in
forward and reverse mode, and preserves the floating-point dtype of its inputs. The
public functions are wrapped in `jax.jit`, so calling them outside of `jit` is cheap too.

The parameter convention is that of `scipy.special` (and DLMF/Abramowitz & Stegun): `m` is
the *parameter*, `m = k^2` with `k` the modulus. Most functions accept an optional `m1`,
the complementary parameter `1 - m`. When `m` is close to one, `1 - m` loses all its
digits to cancellation; a caller who knows `m1` more accurately (for example from
differences of moments of inertia) should pass it, and it is then used in place of
`1 - m` everywhere. Functions of `m` near one then depend on `m1` only, so when
differentiating with respect to the parameter make `m` and `m1` functions of the same
traced quantity (the derivative is the total derivative along `m + m1 = 1`).
"""

import math

import jax
import jax.lax as lax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = ["carlson_rc", "carlson_rf", "carlson_rj", "ellipf", "ellipj", "ellipk", "ellippi"]

# Levels of the arithmetic-geometric mean. The AGM of (1, sqrt(m1)) has converged to
# double precision after 13 levels for m1 = 1e-300 (fewer for larger m1). Levels after
# convergence are harmless: c_n underflows to zero and the angle just halves exactly.
_AGM_LEVELS = 16

# Duplication steps of Carlson's algorithms. Double precision is reached after 13 steps
# even when the arguments differ in ratio by 1e300 (one of them may be zero), and for R_J
# with p <= 4 max(x, y, z) (larger p is transformed away); extra steps only refine.
_CARLSON_STEPS = 16


def _float_dtype(*xs):
    dtype = jnp.result_type(*xs)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    return dtype


def _as_float(*xs):
    dtype = _float_dtype(*xs)
    return tuple(jnp.asarray(x, dtype) for x in xs)


def _parameters(m, m1, *others):
    """Cast to a common float dtype and fill in `m1 = 1 - m` if it was not given."""
    if m1 is None:
        *others, m = _as_float(*others, m)
        m1 = 1.0 - m
    else:
        *others, m, m1 = _as_float(*others, m, m1)
    return (*others, m, m1)


def _agm(b):
    """AGM(1, b) with `_AGM_LEVELS` fixed levels."""

    def level(_, ab):
        a, b = ab
        return 0.5 * (a + b), jnp.sqrt(a * b)

    a, _ = lax.fori_loop(0, _AGM_LEVELS, level, (jnp.ones_like(b), b))
    return a


@jax.jit
def ellipk(
    m: Float[ArrayLike, "..."], m1: Float[ArrayLike, "..."] | None = None
) -> Float[Array, "..."]:
    r"""Complete elliptic integral of the first kind,

    $K(m) = \int_0^{\pi/2} \frac{d\theta}{\sqrt{1 - m \sin^2\theta}} = \frac{\pi}{2\,
    \mathrm{AGM}(1, \sqrt{1 - m})}$

    (DLMF 19.8.5), evaluated with a fixed number of AGM levels. Same convention as
    `scipy.special.ellipk`.

    **Arguments:**

    - `m`: the parameter, `m <= 1` (negative `m` is allowed).
    - `m1`: optional complementary parameter `1 - m`. If given it is used instead of
        `1 - m` (and `m` is then only used for its shape and dtype), which keeps full
        relative accuracy as `m -> 1`: `m1` may be as small as the smallest normal
        number (`1e-308` in float64; XLA flushes subnormal numbers to zero).

    **Returns:**

    `K(m)`, with the dtype of the inputs. It is `+inf` at `m1 == 0`; the gradient there is
    reported as zero (it is infinite), and it is finite everywhere else.
    """
    m, m1 = _parameters(m, m1)
    shape = jnp.broadcast_shapes(m.shape, m1.shape)
    zero = m1 == 0
    m1_safe = jnp.where(zero, 1.0, m1)
    k = jnp.where(zero, jnp.inf, (0.5 * math.pi) / _agm(jnp.sqrt(m1_safe)))
    return jnp.broadcast_to(k, shape)


def _gauss_levels(m, m1):
    """The AGM scale of Abramowitz & Stegun 16.4 / DLMF 22.20(ii), `_AGM_LEVELS` levels.

    Returns `a_N` and the ratios `k_n = c_n / a_n`, `beta_n = b_n / a_n` (n = 1..N). As in
    Cephes `ellpj`, except that `c_n` is computed as `c_{n-1}^2 / (4 a_n)`, without
    cancellation, from `c_0^2 = m` and `b_0 = sqrt(m1)` (so `m` and `m1` are used
    independently).
    """

    def level(carry, _):
        a, b, c2 = carry
        a_next = 0.5 * (a + b)
        c = c2 / (4.0 * a_next)
        b = jnp.sqrt(a * b)
        return (a_next, b, c * c), (c / a_next, b / a_next)

    carry = (jnp.ones_like(m1), jnp.sqrt(m1), m)
    (a, _, _), ratios = lax.scan(level, carry, length=_AGM_LEVELS)
    return a, ratios


def _descending_gauss(w, a, ratios, m1):
    """sn, cn, dn of `w` in [0, K/2] by the descending Gauss transformation.

    The backward recurrence `phi_{n-1} = (phi_n + asin(k_n sin phi_n)) / 2` from
    `phi_N = 2^N a_N w` (DLMF 22.20(ii)), with the `asin` computed as an `atan2` using
    `1 - k_n^2 sin^2 phi_n = cos^2 phi_n + beta_n^2 sin^2 phi_n`: this stays well
    conditioned when `k_n sin phi_n` is close to one (m close to one).
    """

    def level(phi, ratio):
        k, beta = ratio
        sin, cos = jnp.sin(phi), jnp.cos(phi)
        psi = jnp.arctan2(k * sin, jnp.sqrt(cos * cos + (beta * sin) ** 2))
        return 0.5 * (phi + psi), None

    phi, _ = lax.scan(level, (2.0**_AGM_LEVELS) * a * w, ratios, reverse=True)
    sn, cn = jnp.sin(phi), jnp.cos(phi)
    dn = jnp.sqrt(cn * cn + m1 * sn * sn)  # = sqrt(1 - m sn^2), without cancellation
    return sn, cn, dn


def _ellipj_reduced(u, m, m1):
    """Reduce `u` modulo the period and evaluate; requires `0 < m1`."""
    m, m1 = jnp.broadcast_arrays(m, m1)
    a, ratios = _gauss_levels(m, m1)
    k = (0.5 * math.pi) / a
    negative = u < 0
    x = jnp.where(negative, -u, u)
    # x = 2K n + r with 0 <= r <= 2K; sn and cn change sign over a half period 2K.
    n = lax.stop_gradient(jnp.floor(x / (2.0 * k)))
    r = x - n * (2.0 * k)
    r = jnp.where(r < 0.0, 0.0, jnp.where(r > 2.0 * k, 2.0 * k, r))  # (clip halves gradients)
    odd = jnp.mod(n, 2.0) == 1
    # sn(2K - r) = sn r, cn(2K - r) = -cn r, dn(2K - r) = dn r.
    second_quarter = r > k
    r = jnp.where(second_quarter, 2.0 * k - r, r)
    # For r in [K/2, K] use v = K - r and the complement identities, which keep relative
    # accuracy near r = K even when m is close to one.
    upper = r > 0.5 * k
    w = jnp.where(upper, k - r, r)
    sn_w, cn_w, dn_w = _descending_gauss(w, a, ratios, m1)
    sqrt_m1 = jnp.sqrt(m1)
    sn = jnp.where(upper, cn_w / dn_w, sn_w)
    cn = jnp.where(upper, sqrt_m1 * sn_w / dn_w, cn_w)
    dn = jnp.where(upper, sqrt_m1 / dn_w, dn_w)
    sn = jnp.where(negative != odd, -sn, sn)
    cn = jnp.where(odd != second_quarter, -cn, cn)
    return sn, cn, dn


def _ellipj_m_is_one(u, m1):
    """sn, cn, dn at m = 1 (tanh, sech, sech), with first-order terms in `m1`.

    The first-order terms (Abramowitz & Stegun 16.15, as in Cephes `ellpj`) vanish since
    `m1 == 0` where this is used, but make the derivative with respect to `m1` correct.
    """
    negative = u < 0
    x = jnp.where(negative, -u, u)
    e = jnp.exp(-x)
    sech = 2.0 * e / (1.0 + e * e)  # no overflow, and a finite gradient, at large |u|
    tanh = jnp.tanh(u)
    big = 0.5 * math.log(jnp.finfo(u.dtype).max)
    sinh = jnp.sinh(jnp.clip(u, -big, big))
    q = 0.25 * m1
    sn = tanh + q * (tanh - u * sech * sech)
    cn = sech - q * tanh * (sinh - u * sech)
    dn = sech + q * tanh * (sinh + u * sech)
    return sn, cn, dn


@jax.jit
def ellipj(
    u: Float[ArrayLike, "..."],
    m: Float[ArrayLike, "..."],
    m1: Float[ArrayLike, "..."] | None = None,
) -> tuple[Float[Array, "..."], Float[Array, "..."], Float[Array, "..."]]:
    """Jacobi elliptic functions `sn(u|m)`, `cn(u|m)`, `dn(u|m)`.

    Same convention as `scipy.special.ellipj` (which also returns the amplitude; this does
    not). The argument is first reduced modulo the period using the quarter period `K(m)`;
    on `[0, K/2]` the functions are evaluated by the AGM / descending Gauss transformation
    (Abramowitz & Stegun 16.4, DLMF 22.20(ii)) with a fixed number of levels, and on
    `[K/2, K]` through the complement identities `sn(K - v) = cn v / dn v`,
    `cn(K - v) = sqrt(m1) sn v / dn v`, `dn(K - v) = sqrt(m1) / dn v` (DLMF Table 22.4.3), so
    that the results keep their relative accuracy near `u = K` as `m -> 1`. In float64 the
    absolute error is a few units of roundoff times `max(1, |u|)` for `0 <= m <= 1`,
    including `m` within `1e-300` of one (pass `m1`). Negative `m` is allowed too.

    At `m == 1` (`m1 == 0`) the limits `tanh u`, `sech u`, `sech u` are returned, with
    finite gradients (including the derivative with respect to the parameter).

    **Arguments:**

    - `u`: the argument.
    - `m`: the parameter, `m <= 1`.
    - `m1`: optional complementary parameter `1 - m`, used instead of `1 - m` when given
        (see the module docstring); `m1 == 0` is `m == 1`.

    **Returns:**

    A tuple `(sn, cn, dn)`, broadcast together and with the dtype of the inputs.
    """
    u, m, m1 = _parameters(m, m1, u)
    one = m1 == 0
    m_safe = jnp.where(one, 0.0, m)
    m1_safe = jnp.where(one, 1.0, m1)
    reduced = _ellipj_reduced(u, m_safe, m1_safe)
    limit = _ellipj_m_is_one(u, m1)
    return tuple(jnp.where(one, lim, red) for lim, red in zip(limit, reduced))


# ----------------------------------------------------------------------------------------
# Carlson's symmetric integrals, by duplication (Carlson 1995). The arguments are first
# scaled by a power of two (the integrals are homogeneous), which keeps the duplication
# steps clear of overflow and of underflow to (flushed) subnormal numbers.
# ----------------------------------------------------------------------------------------


def _sqrt(x):
    """sqrt, with no inf or NaN in its derivative at 0 (which it takes to be 0).

    This only loses the (infinite) derivative with respect to a Carlson argument that is
    exactly zero; derivatives with respect to the other arguments stay correct.
    """
    zero = x == 0
    return jnp.where(zero, 0.0, jnp.sqrt(jnp.where(zero, 1.0, x)))


def _int_type(dtype):
    return {2: jnp.int16, 4: jnp.int32, 8: jnp.int64}[jnp.dtype(dtype).itemsize]


def _pow2(k, dtype):
    """2^k, exactly, for integers k in the normal exponent range of `dtype`."""
    info = jnp.finfo(dtype)
    biased = (k + (info.maxexp - 1)).astype(_int_type(dtype))
    return lax.bitcast_convert_type(biased << info.nmant, dtype)


def _normalise(*xs):
    """Scale nonnegative arguments by a power of two 4^h so that the largest is near
    `2^(maxexp / 8)`; flag when two or more are zero.

    The Carlson integrals are homogeneous, so the result is rescaled exactly by `2^h`
    (R_F, R_C) or `8^h` (R_J). This keeps the duplication steps clear of overflow and of
    underflow to (flushed) subnormal numbers while preserving the ratios of the arguments:
    arguments down to `2^(minexp - maxexp / 8)` times the largest are resolved. The
    target is moderate so that derivatives (powers up to about -4 of the arguments) do
    not underflow either.
    """
    biggest = xs[0]
    for v in xs[1:]:
        biggest = jnp.maximum(biggest, v)
    biggest = lax.stop_gradient(biggest)
    info = jnp.finfo(biggest.dtype)
    bits = lax.bitcast_convert_type(biggest, _int_type(biggest.dtype))
    exponent = (bits >> info.nmant) - (info.maxexp - 1)  # floor(log2) (sign bit is 0)
    h = (info.maxexp // 8 - exponent) // 2
    scale = _pow2(h, biggest.dtype)  # applied twice: 4^h itself may not be representable
    xs = tuple(v * scale * scale for v in xs)
    bad = sum((v == 0).astype(jnp.int32) for v in xs) >= 2
    return tuple(jnp.where(bad, 1.0, v) for v in xs), scale, bad


def _rf(x, y, z):
    a0 = (x + y + z) / 3.0

    def step(_, carry):
        x, y, z, a, scale = carry
        sx, sy, sz = _sqrt(x), _sqrt(y), _sqrt(z)
        lam = sx * sy + sx * sz + sy * sz
        x, y, z, a = (0.25 * (v + lam) for v in (x, y, z, a))
        return x, y, z, a, 0.25 * scale

    carry = (x, y, z, a0, jnp.ones_like(a0))
    _, _, _, a, scale = lax.fori_loop(0, _CARLSON_STEPS, step, carry)
    xx = (a0 - x) * scale / a
    yy = (a0 - y) * scale / a
    zz = -xx - yy
    e2 = xx * yy - zz * zz
    e3 = xx * yy * zz
    series = 1.0 - e2 / 10.0 + e3 / 14.0 + e2 * e2 / 24.0 - 3.0 * e2 * e3 / 44.0
    return series / jnp.sqrt(a)


@jax.jit
def carlson_rf(
    x: Float[ArrayLike, "..."], y: Float[ArrayLike, "..."], z: Float[ArrayLike, "..."]
) -> Float[Array, "..."]:
    r"""Carlson's symmetric elliptic integral of the first kind,

    $R_F(x, y, z) = \frac12 \int_0^\infty \frac{dt}{\sqrt{(t + x)(t + y)(t + z)}}$,

    by the duplication algorithm of Carlson 1995, "Numerical computation of real or
    complex elliptic integrals", Numer. Algorithms 10, with a fixed number of steps (DLMF
    19.36(i)). Same convention as `scipy.special.elliprf`.

    **Arguments:**

    - `x`, `y`, `z`: nonnegative, at most one of them zero.

    **Returns:**

    `R_F(x, y, z)`, with the dtype of the inputs; `+inf` if two arguments are zero. The
    derivative with respect to an argument that is exactly zero is infinite and is not
    returned correctly (it comes out finite); the other derivatives are correct.
    """
    (x, y, z), scale, bad = _normalise(*_as_float(x, y, z))
    return jnp.where(bad, jnp.inf, _rf(x, y, z) * scale)


def _rc(x, y):
    a0 = (x + 2.0 * y) / 3.0

    def step(_, carry):
        x, y, a, scale = carry
        lam = 2.0 * _sqrt(x) * _sqrt(y) + y
        x, y, a = (0.25 * (v + lam) for v in (x, y, a))
        return x, y, a, 0.25 * scale

    _, _, a, scale = lax.fori_loop(0, _CARLSON_STEPS, step, (x, y, a0, jnp.ones_like(a0)))
    s = (y - a0) * scale / a
    series = 1.0 + s * s * (
        3.0 / 10.0
        + s * (1.0 / 7.0 + s * (3.0 / 8.0 + s * (9.0 / 22.0 + s * (159.0 / 208.0 + s * 9.0 / 8.0))))
    )
    return series / jnp.sqrt(a)


@jax.jit
def carlson_rc(x: Float[ArrayLike, "..."], y: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    r"""Carlson's degenerate integral $R_C(x, y) = R_F(x, y, y)$ (DLMF 19.2.17),

    by the duplication algorithm of Carlson 1995 with a fixed number of steps. Same
    convention as `scipy.special.elliprc`.

    **Arguments:**

    - `x`: nonnegative.
    - `y`: positive (the Cauchy principal value for `y < 0` is not supported).

    **Returns:**

    `R_C(x, y)`, with the dtype of the inputs; `+inf` if `y == 0`.
    """
    x, y = _as_float(x, y)
    bad = y == 0
    (x, y), scale, _ = _normalise(x, jnp.where(bad, 1.0, y))
    return jnp.where(bad, jnp.inf, _rc(x, y) * scale)


def _rc1p(e, one_plus_e):
    """R_C(1, 1 + e) for -1 < e <= 1, given also 1 + e (DLMF 19.2.18-19)."""
    small = jnp.abs(e) < 0.1
    # sum_k (-e)^k / (2k + 1), to k = 16 (relative error below 1e-18 for |e| < 0.1)
    t = -jnp.where(small, e, 0.0)
    series = jnp.zeros_like(t)
    for k in range(16, -1, -1):
        series = series * t + 1.0 / (2 * k + 1)
    # e < 0: atanh(s) / s = log((1 + s) / sqrt(1 + e)) / s with s = sqrt(-e).
    negative = e < 0
    s_neg = jnp.sqrt(jnp.where(small | ~negative, 0.5, -e))
    rc_neg = jnp.log((1.0 + s_neg) / jnp.sqrt(jnp.where(small | ~negative, 0.5, one_plus_e)))
    # e > 0: atan(s) / s with s = sqrt(e).
    s_pos = jnp.sqrt(jnp.where(small | negative, 0.5, e))
    rc_pos = jnp.arctan(s_pos)
    return jnp.where(small, series, jnp.where(negative, rc_neg / s_neg, rc_pos / s_pos))


def _rf_rj(x, y, z, p):
    """R_F(x, y, z) and R_J(x, y, z, p) by one duplication (Carlson 1995, Algorithms 1 and
    4); R_J converges only slowly when p >> max(x, y, z)."""
    x, y, z, p = jnp.broadcast_arrays(x, y, z, p)
    a0_rf = (x + y + z) / 3.0
    a0 = (x + y + z + 2.0 * p) / 5.0

    def step(_, carry):
        x, y, z, p, a_rf, a, scale, total, dx, dy, dz = carry
        sx, sy, sz, sp = _sqrt(x), _sqrt(y), _sqrt(z), _sqrt(p)
        lam = sx * sy + sx * sz + sy * sz
        d = (sp + sx) * (sp + sy) * (sp + sz)
        # Carlson's e_m = delta_m / d_m^2 written as a product of factors in (-1, 1]
        # (no overflow), with d_x = p_m - x_m = (p - x) / 4^m etc. The sum d_m^2 + delta_m
        # also expands to 2 sqrt(p_m) (p_m + lambda_m) d_m, free of cancellation.
        e = (dx / (sp + sx) ** 2) * (dy / (sp + sy) ** 2) * (dz / (sp + sz) ** 2)
        one_plus_e = 2.0 * sp * (p + lam) / d
        total = total + scale * _rc1p(e, one_plus_e) / d
        x, y, z, p, a_rf, a = (0.25 * (v + lam) for v in (x, y, z, p, a_rf, a))
        return x, y, z, p, a_rf, a, 0.25 * scale, total, 0.25 * dx, 0.25 * dy, 0.25 * dz

    one, zero = jnp.ones_like(a0), jnp.zeros_like(a0)
    carry = (x, y, z, p, a0_rf, a0, one, zero, p - x, p - y, p - z)
    _, _, _, _, a_rf, a, scale, total, _, _, _ = lax.fori_loop(0, _CARLSON_STEPS, step, carry)
    # R_F
    xx = (a0_rf - x) * scale / a_rf
    yy = (a0_rf - y) * scale / a_rf
    zz = -xx - yy
    e2 = xx * yy - zz * zz
    e3 = xx * yy * zz
    series = 1.0 - e2 / 10.0 + e3 / 14.0 + e2 * e2 / 24.0 - 3.0 * e2 * e3 / 44.0
    rf = series / jnp.sqrt(a_rf)
    # R_J
    xx = (a0 - x) * scale / a
    yy = (a0 - y) * scale / a
    zz = (a0 - z) * scale / a
    pp = -0.5 * (xx + yy + zz)
    xyz = xx * yy * zz
    e2 = xx * yy + xx * zz + yy * zz - 3.0 * pp * pp
    e3 = xyz + 2.0 * e2 * pp + 4.0 * pp**3
    e4 = (2.0 * xyz + e2 * pp + 3.0 * pp**3) * pp
    e5 = xyz * pp * pp
    series = (
        1.0
        - 3.0 * e2 / 14.0
        + e3 / 6.0
        + 9.0 * e2 * e2 / 88.0
        - 3.0 * e4 / 22.0
        - 9.0 * e2 * e3 / 52.0
        + 3.0 * e5 / 26.0
    )
    return rf, scale * series / (a * jnp.sqrt(a)) + 6.0 * total


@jax.jit
def carlson_rj(
    x: Float[ArrayLike, "..."],
    y: Float[ArrayLike, "..."],
    z: Float[ArrayLike, "..."],
    p: Float[ArrayLike, "..."],
) -> Float[Array, "..."]:
    r"""Carlson's symmetric elliptic integral of the third kind,

    $R_J(x, y, z, p) = \frac32 \int_0^\infty \frac{dt}{(t + p)\sqrt{(t + x)(t + y)(t + z)}}$,

    by the duplication algorithm of Carlson 1995 with a fixed number of steps (DLMF
    19.36(i)). Same convention as `scipy.special.elliprj`.

    Duplication converges only by a factor of 4 a step in `p / max(x, y, z)`, so for
    `p > 4 max(x, y, z)` the integral is instead obtained from one with a smaller `p`, by
    DLMF 19.21.12 (there with `R_C(yz/x, pq/x) = sqrt(x) R_C(yz, pq)`), `x = min(x, y, z)`:
    `(p - x) R_J(x, y, z, p) + (q - x) R_J(x, y, z, q) = 3 R_F(x, y, z) - 3 sqrt(x) R_C(yz, pq)`
    where `(p - x)(q - x) = (y - x)(z - x)`, so that `x <= q <= min(y, z)`.

    **Arguments:**

    - `x`, `y`, `z`: nonnegative, at most one of them zero.
    - `p`: positive (the Cauchy principal value for `p < 0` is not supported).

    **Returns:**

    `R_J(x, y, z, p)`, with the dtype of the inputs; `+inf` if two of `x, y, z` or `p`
    are zero. The derivative with respect to an argument that is exactly zero is infinite
    and is not returned correctly (it comes out finite); the other derivatives are correct.
    """
    return _carlson_rj(*_as_float(x, y, z, p), transform=True)[1]


def _carlson_rj(x, y, z, p, transform):
    """R_J, and R_F(x, y, z) as a by-product, of arguments of one float dtype."""
    (x, y, z, p), scale, bad = _normalise(x, y, z, p)
    bad = bad | (p == 0)
    x, y, z, p = (jnp.where(bad, 1.0, v) for v in (x, y, z, p))
    if transform:
        rf, rj = _rf_rj_large_p(x, y, z, p)
    else:  # the caller knows that p <= max(x, y, z)
        rf, rj = _rf_rj(x, y, z, p)
    rf = jnp.where(bad, jnp.inf, rf * scale)
    return rf, jnp.where(bad, jnp.inf, rj * scale * scale * scale)  # (scale^3 may overflow)


def _rf_rj_large_p(x, y, z, p):
    """R_F and R_J of normalised arguments, using DLMF 19.21.12 where p > 4 max(x, y, z)."""
    # lo = min(x, y, z), and (y1, z1) the other two.
    x_min = (x <= y) & (x <= z)
    y_min = ~x_min & (y <= z)
    lo = jnp.where(x_min, x, jnp.where(y_min, y, z))
    y1, z1 = jnp.where(x_min, y, x), jnp.where(x_min | y_min, z, y)
    large = p > 4.0 * jnp.maximum(y1, z1)
    # Harmless stand-ins where the transformation is not used.
    lo, y1, z1 = (jnp.where(large, v, c * p) for v, c in ((lo, 0.25), (y1, 0.5), (z1, 0.5)))
    # The transformed integrals are rescaled by 4^h2 to keep q clear of underflow (the
    # products below cannot overflow: p > 4 z1 and max(x, y, z, p) < 2^(maxexp / 8 + 2)).
    (lo2, y2, z2), scale2, _ = _normalise(lo, y1, z1)
    q2 = lo2 + (y2 - lo2) * (z1 - lo) / (p - lo)
    q2 = jnp.maximum(q2, jnp.finfo(q2.dtype).tiny)
    args = (jnp.where(large, a, b) for a, b in zip((lo2, y2, z2, q2), (x, y, z, p)))
    rf, rj = _rf_rj(*args)
    # sqrt(x) R_C(yz, pq) = sqrt(x / p) R_C(y z / p, q) in the rescaled units.
    rc = carlson_rc(y2 * z1 / p, q2)
    rest = 3.0 * rf - 3.0 * (_sqrt(lo) / jnp.sqrt(p)) * rc - (q2 - lo2) * rj
    rf = jnp.where(large, rf * scale2, rf)
    return rf, jnp.where(large, rest * scale2 / (p - lo), rj)


@jax.jit
def ellipf(
    phi: Float[ArrayLike, "..."],
    m: Float[ArrayLike, "..."],
    m1: Float[ArrayLike, "..."] | None = None,
) -> Float[Array, "..."]:
    r"""Incomplete elliptic integral of the first kind,

    $F(\phi | m) = \int_0^\phi \frac{d\theta}{\sqrt{1 - m \sin^2\theta}}$.

    Same convention as `scipy.special.ellipkinc`. For `|phi| <= pi/2` it is evaluated as
    `sin(phi) R_F(cos^2 phi, m1 + m cos^2 phi, 1)` (DLMF 19.25.5, with
    `1 - m sin^2 phi` written without cancellation), and extended to all real `phi` by
    `F(phi + j pi | m) = F(phi | m) + 2 j K(m)` (DLMF 19.2(ii)).

    **Arguments:**

    - `phi`: the amplitude, any real number.
    - `m`: the parameter, `m <= 1`.
    - `m1`: optional complementary parameter `1 - m`, used instead of `1 - m` when given.

    **Returns:**

    `F(phi | m)`, with the dtype of the inputs. At `m == 1` it is `atanh(sin phi)`, which
    diverges at `|phi| = pi/2`: `+-inf` is returned for `|phi| >= pi/2`.
    """
    phi, m, m1 = _parameters(m, m1, phi)
    j = lax.stop_gradient(jnp.round(phi / math.pi))
    r = phi - j * math.pi
    s, c = jnp.sin(r), jnp.cos(r)
    c2 = c * c
    f = s * carlson_rf(c2, m1 + m * c2, 1.0)
    # At m == 1, K == inf; keep inf * 0 out of the values and gradients.
    one = m1 == 0
    k = ellipk(jnp.where(one, 0.0, m), jnp.where(one, 1.0, m1))
    f = f + jnp.where(j == 0, 0.0, 2.0 * j * k)
    diverges = one & ((j != 0) | (jnp.abs(r) >= 0.5 * math.pi))
    return jnp.where(diverges, jnp.where(phi < 0, -jnp.inf, jnp.inf), f)


@jax.jit
def ellippi(
    n: Float[ArrayLike, "..."],
    m: Float[ArrayLike, "..."],
    m1: Float[ArrayLike, "..."] | None = None,
) -> Float[Array, "..."]:
    r"""Complete elliptic integral of the third kind,

    $\Pi(n | m) = \int_0^{\pi/2} \frac{d\theta}{(1 - n \sin^2\theta)
    \sqrt{1 - m \sin^2\theta}} = R_F(0, 1 - m, 1) + \frac{n}{3} R_J(0, 1 - m, 1, 1 - n)$

    (DLMF 19.25.2), with the characteristic `n` in the sign convention of Abramowitz &
    Stegun 17.7 / DLMF 19.2.7 (as in Mathematica's `EllipticPi[n, m]`).

    **Arguments:**

    - `n`: the characteristic, `n < 1` (the Cauchy principal value for `n > 1` is not
        supported).
    - `m`: the parameter, `m <= 1`.
    - `m1`: optional complementary parameter `1 - m`, used instead of `1 - m` when given.

    **Returns:**

    `Pi(n | m)`, with the dtype of the inputs; `+inf` at `m == 1` or `n == 1`.
    """
    n, m, m1 = _parameters(m, m1, n)
    bad = (m1 == 0) | (n == 1)
    n = jnp.where(bad, 0.0, n)
    m1 = jnp.where(bad, 1.0, m1)
    # For n < 0 the two terms of DLMF 19.25.2 would cancel (badly as n -> -inf); instead use
    # p R_J(0, y, z, p) + q R_J(0, y, z, q) = 3 R_F(0, y, z) with pq = yz (DLMF 19.21.12),
    # which gives two positive terms, and R_J(0, m1, 1, q) = m1^(-3/2) R_J(0, 1, 1/m1, q/m1)
    # (R_F and R_J are homogeneous; this form keeps q/m1 = 1/(1 - n) clear of underflow).
    negative = n < 0
    y, z = jnp.where(negative, 1.0, m1), jnp.where(negative, 1.0 / m1, 1.0)
    p = jnp.where(negative, 1.0 / (1.0 - n), 1.0 - n)
    zero = jnp.zeros_like(p)
    rf, rj = _carlson_rj(*jnp.broadcast_arrays(zero, y, z, p), transform=False)  # p <= z
    sqrt_m1 = jnp.sqrt(m1)
    pi_negative = (rf - n / (3.0 * (1.0 - n)) * rj) / (sqrt_m1 * (1.0 - n))
    pi = jnp.where(negative, pi_negative, rf + (n / 3.0) * rj)
    return jnp.where(bad, jnp.inf, pi)
