"""Tests for `jaxdyn._elliptic`.

References: `scipy.special` (`ellipk`, `ellipkm1`, `ellipj`, `ellipkinc`, `ellipe`,
`elliprf`, `elliprc`, `elliprj`, `elliprd`) where it is accurate, and otherwise
independent routes: exact special values (DLMF 22.5), identities, `scipy.integrate.quad`,
closed-form derivatives, and central finite differences.

Where scipy is itself inaccurate this is said next to the test:
- `scipy.special.ellipj` replaces the AGM by a first-order expansion in `1 - m` for
  `m >= 1 - 1e-10` (wrong once `u` is a fair fraction of `K`), and loses ~1e-11 near
  `m = 1 - 1e-6`. Near `m = 1` we therefore check `sn, cn, dn` at `u = F(phi | m)` from
  `scipy.special.ellipkinc` (which is accurate there) against `sin phi`, `cos phi`,
  `sqrt(1 - m sin^2 phi)`: that is the definition of the amplitude, and it is well
  conditioned (where F is ill conditioned, near `phi = pi/2`, the functions are flat).
  (Integrating the ODEs `sn' = cn dn`, ... is not a usable reference there: near the
  separatrix an error of one ulp in the invariant `dn^2 + m sn^2` changes `1 - m` by 100%.)
- `scipy.special.elliprj` loses up to ~1e-11 when `p` is much smaller than `x, y, z`
  (its `1 + e_m` cancels); that regime is checked against closed forms instead.
- `scipy.special.elliprf` returns NaN for some arguments below ~1e-200.
- `scipy.special.ellipkinc(phi, 1)` is `+inf` also for `phi <= -pi/2`; `F` is odd.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special as sp
from helpers import FINITE_DIFF, ROUNDOFF, central_difference, tol
from scipy.integrate import quad

from jaxdyn._elliptic import (
    carlson_rc,
    carlson_rf,
    carlson_rj,
    ellipf,
    ellipj,
    ellipk,
    ellippi,
)

# Absolute error allowed for sn, cn, dn, per unit of max(1, |u| / K) (the reduction modulo
# the period costs about an ulp of |u|), plus a few ulp of |u| itself: rounding u (or K)
# moves the functions by that much, which shows when K is large (m -> 1). Measured against
# mpmath: at most 5 ulp * max(1, |u|).
ELLIPJ_ATOL = 1e-14
ELLIPJ_ULPS_OF_U = 8

# scipy.special.ellipj itself is only good to ~1.4e-11 at m = 1 - 1e-6 (measured against
# mpmath), so the comparison there is at this absolute tolerance.
SCIPY_ELLIPJ_NEAR_ONE_ATOL = 1e-10

# sn^2 + cn^2 = 1 and dn^2 + m sn^2 = 1 hold to a couple of ulp of one.
IDENTITY_ATOL = 4 * np.finfo(float).eps

# Absolute noise of a central difference of an O(1) function with step 1e-6: ~eps / 1e-6.
FD_NOISE = 1e-9

# The public functions are jitted; these wrappers too. Inputs are vectorised by
# broadcasting, and shapes are reused across tests to keep compilations few. Gradients are
# taken in reverse mode.
_ellipj = jax.jit(lambda u, m, m1: jnp.stack(ellipj(u, m, m1)))
_ellipj_implicit = jax.jit(lambda u, m: jnp.stack(ellipj(u, m)))
# Jacobian of (sn, cn, dn) with respect to v = (u, m).
_ellipj_jac = jax.jit(jax.jacrev(lambda v: jnp.stack(ellipj(v[0], v[1]))))
# ... and with respect to v = (u, x), at m1 = 1e-8 x, m = 1 - m1 (so that a finite
# difference step in x is relative to m1).
_ellipj_near_one = jax.jit(lambda v: jnp.stack(ellipj(v[0], 1.0 - 1e-8 * v[1], 1e-8 * v[1])))
_ellipj_jac_near_one = jax.jit(jax.jacrev(_ellipj_near_one))
_ellipk_grad = jax.jit(jax.vmap(jax.grad(ellipk)))
_ellipk_grad_m1 = jax.jit(jax.vmap(jax.grad(lambda m1: ellipk(1.0 - m1, m1))))
_ellipf_grad = jax.jit(jax.grad(ellipf, argnums=(0, 1)))
_ellippi_grad = jax.jit(jax.grad(ellippi, argnums=(0, 1)))


def _ellipj_atol(u, k):
    u = np.abs(u)
    return ELLIPJ_ATOL * np.maximum(1.0, u / k) + ELLIPJ_ULPS_OF_U * np.finfo(float).eps * u


def _scipy_ellipj(u, m):
    return np.stack(sp.ellipj(u, m)[:3])


def _periods(m, n_periods=50, num=401):
    k = sp.ellipk(m)
    u = np.linspace(-4 * n_periods * k, 4 * n_periods * k, num)
    return np.concatenate([u, [0.0, 1e-3, k / 2, k, 2 * k, 3 * k, -k, -4 * k]]), k


# ----------------------------------------------------------------------------------------
# K(m)
# ----------------------------------------------------------------------------------------


def test_ellipk_vs_scipy():
    m = np.concatenate([np.linspace(-5.0, 0.99, 60), 1 - np.logspace(-2, -8, 7), [1.0]])
    k = ellipk(m)
    assert k.dtype == jnp.float64
    np.testing.assert_allclose(k, sp.ellipk(m), rtol=tol(ROUNDOFF))  # (inf at m = 1)


def test_ellipk_near_one_with_m1():
    m1 = np.array([1e-300, 1e-200, 1e-100, 1e-20, 1e-16, 1e-10, 1e-6, 1e-3, 0.0])
    k = ellipk(1.0 - m1, m1)
    np.testing.assert_allclose(k, sp.ellipkm1(m1), rtol=tol(ROUNDOFF))  # (inf at m1 = 0)
    # Gradient: finite away from m1 == 0, and no NaN at m1 == 0.
    grad = _ellipk_grad_m1(np.array([1e-300, 0.0]))
    np.testing.assert_allclose(grad[0], -0.5 / 1e-300, rtol=tol(ROUNDOFF))
    assert not np.isnan(grad[1])


def test_ellipk_gradient_closed_form():
    # dK/dm = (E - m1 K) / (2 m m1) (DLMF 19.4.1, in terms of m = k^2).
    def exact(m, m1):
        return (sp.ellipe(m) - m1 * sp.ellipkm1(m1)) / (2 * m * m1)

    m = np.array([0.1, 0.5, 0.9, 0.999999, 0.0])
    grad = _ellipk_grad(m)
    np.testing.assert_allclose(grad[:-1], exact(m[:-1], 1 - m[:-1]), rtol=tol(ROUNDOFF))
    assert grad[-1] == pytest.approx(math.pi / 8, rel=tol(ROUNDOFF))
    m1 = np.array([1e-12, 1e-100])
    grad = _ellipk_grad_m1(m1)
    np.testing.assert_allclose(grad, -exact(1 - m1, m1), rtol=tol(ROUNDOFF))


# ----------------------------------------------------------------------------------------
# sn, cn, dn
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("m", [0.0, 1e-300, 0.5, 0.99])
def test_ellipj_vs_scipy(m):
    u, k = _periods(m)
    got = _ellipj_implicit(u, m)
    assert got.dtype == jnp.float64
    assert np.all(np.abs(got - _scipy_ellipj(u, m)) <= _ellipj_atol(u, k))


def test_ellipj_vs_scipy_close_to_one():
    # m = 1 - 1e-6: scipy is only good to ~1e-11 here (see SCIPY_ELLIPJ_NEAR_ONE_ATOL).
    m = 1 - 1e-6
    u, k = _periods(m, n_periods=5)
    atol = SCIPY_ELLIPJ_NEAR_ONE_ATOL * np.maximum(1.0, np.abs(u) / k)
    assert np.all(np.abs(_ellipj_implicit(u, m) - _scipy_ellipj(u, m)) <= atol)
    # m = 1 - 1e-10: scipy's expansion in 1 - m is accurate (to (1 - m)^2 e^(4u)) for
    # |u| <= 3 only.
    m = 1 - 1e-10
    u = np.linspace(-3, 3, 409)
    assert np.all(np.abs(_ellipj_implicit(u, m) - _scipy_ellipj(u, m)) <= ELLIPJ_ATOL)


@pytest.mark.parametrize("m1_approx", [1e-6, 1e-10, 1e-14, 1e-16])
def test_ellipj_near_one_via_amplitude(m1_approx):
    # sn(F(phi|m)) = sin(phi), cn = cos(phi), dn = sqrt(1 - m sin^2 phi) for all real phi.
    m = 1.0 - m1_approx
    m1 = 1.0 - m  # exact, so that scipy (which only sees m) and we use the same m1
    offsets = np.array([-1e-3, -1e-6, -1e-9, 0.0, 1e-9, 1e-6, 1e-3])
    phi = np.concatenate(
        [np.linspace(-2.9 * np.pi, 2.9 * np.pi, 121), np.pi / 2 + offsets, 1.5 * np.pi + offsets]
    )
    u = sp.ellipkinc(phi, m)
    expected = np.stack([np.sin(phi), np.cos(phi), np.sqrt(m1 + m * np.cos(phi) ** 2)])
    got = _ellipj(u, m, m1)
    assert np.all(np.abs(got - expected) <= _ellipj_atol(u, sp.ellipkm1(m1)))


def _special_values(m1):
    """u and (sn, cn, dn)(u) at multiples of K/2 (DLMF Tables 22.5.1-2), k' = sqrt(m1)."""
    k = sp.ellipkm1(m1)
    kc = math.sqrt(m1)
    s, c, d = 1 / math.sqrt(1 + kc), math.sqrt(kc / (1 + kc)), math.sqrt(kc)
    table = [  # u / K, sn, cn, dn
        (0.5, s, c, d),
        (1, 1, 0, kc),
        (1.5, s, -c, d),
        (2, 0, -1, 1),
        (3, -1, 0, kc),
        (4, 0, 1, 1),
        (-1, -1, 0, kc),
        (-2.5, s, -c, d),
    ]
    u, *expected = np.array(table).T
    return u * k, np.array(expected), k


@pytest.mark.parametrize("m1", [0.5, 1e-10, 1e-20, 1e-100, 1e-300])
def test_ellipj_special_values(m1):
    u, expected, k = _special_values(m1)
    got = np.asarray(_ellipj(u, 1.0 - m1, m1))
    assert np.all(np.abs(got - expected) <= _ellipj_atol(u, k))
    # Relative accuracy near u = K, also for k' = 1e-150: dn(K) = k'.
    at_k = np.abs(u / k) % 2 == 1  # u = +-K, 3K
    np.testing.assert_allclose(got[2, at_k], math.sqrt(m1), rtol=tol(ROUNDOFF))


def test_ellipj_m1_argument_beats_one_minus_m():
    # 1 - 1e-20 rounds to 1: without m1 the functions collapse to tanh and sech.
    u, expected, k = _special_values(1e-20)
    assert np.all(np.abs(_ellipj(u, 1.0, 1e-20) - expected) <= _ellipj_atol(u, k))
    assert np.max(np.abs(_ellipj_implicit(u, 1.0) - expected)) > 0.5


def test_ellipj_identities():
    u = np.linspace(-30, 30, 135)
    for m in [0.0, 0.3, 0.9, 1 - 1e-6, 1 - 1e-10, 1 - 1e-16]:
        m1 = 1.0 - m  # exact
        sn, cn, dn = _ellipj(u, m, m1)
        np.testing.assert_allclose(sn**2 + cn**2, 1.0, rtol=0, atol=IDENTITY_ATOL)
        np.testing.assert_allclose(dn**2 + m * sn**2, 1.0, rtol=0, atol=IDENTITY_ATOL)
        # d/du (sn, cn, dn) = (cn dn, -sn dn, -m sn cn), DLMF 22.13.1-3, in forward mode.
        _, (dsn, dcn, ddn) = jax.jvp(lambda u: ellipj(u, m, m1), (u,), (np.ones_like(u),))
        atol = _ellipj_atol(u, 1.0)
        assert np.all(np.abs(dsn - cn * dn) <= atol)
        assert np.all(np.abs(dcn + sn * dn) <= atol)
        assert np.all(np.abs(ddn + m * sn * cn) <= atol)


def test_ellipj_limits():
    u = np.array([-800.0, -30.0, -1.0, 0.0, 0.5, 3.0, 30.0, 800.0])
    sech = 2 * np.exp(-np.abs(u)) / (1 + np.exp(-2 * np.abs(u)))
    expected = np.stack([np.tanh(u), sech, sech])
    for got in (_ellipj_implicit(u, 1.0), _ellipj(u, 1.0, 0.0)):
        np.testing.assert_allclose(got, expected, rtol=tol(ROUNDOFF), atol=1e-300)
    expected = np.stack([np.sin(u), np.cos(u), np.ones_like(u)])
    np.testing.assert_allclose(_ellipj_implicit(u, 0.0), expected, rtol=0, atol=4e-13)


def test_ellipj_negative_m():
    # DLMF 22.17 (imaginary modulus): for m < 0, with mu = -m / (1 - m), v = u sqrt(1 - m),
    # sn(u|m) = sd(v|mu) / sqrt(1 - m), cn(u|m) = cd(v|mu), dn(u|m) = nd(v|mu).
    u = np.linspace(-10, 10, 409)
    for m in [-0.5, -3.0]:
        sn, cn, dn = _scipy_ellipj(u * math.sqrt(1 - m), -m / (1 - m))
        expected = np.stack([sn / dn / math.sqrt(1 - m), cn / dn, 1 / dn])
        np.testing.assert_allclose(_ellipj_implicit(u, m), expected, rtol=0, atol=1e-13)


# ----------------------------------------------------------------------------------------
# Gradients of sn, cn, dn
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("m", [0.3, 0.8])
@pytest.mark.parametrize("u", [0.4, 2.5, -7.0, 13.0])
def test_ellipj_gradients_vs_finite_differences(m, u):
    v = np.array([u, m])
    jac = _ellipj_jac(v)
    for i in range(3):
        fd = central_difference(lambda v: _ellipj_implicit(v[0], v[1])[i], v)
        np.testing.assert_allclose(jac[i], fd, rtol=tol(FINITE_DIFF), atol=FD_NOISE)


@pytest.mark.parametrize("u", [0.7, 3.0, 8.0, 11.0, -13.0, 25.0])
def test_ellipj_gradients_near_one(u):
    # m = 1 - 1e-8: K ~ 10.6, so u = 11 is just past the quarter period.
    v = np.array([u, 1.0])
    jac = _ellipj_jac_near_one(v)
    for i in range(3):
        fd = central_difference(lambda v: _ellipj_near_one(v)[i], v)
        np.testing.assert_allclose(jac[i], fd, rtol=tol(FINITE_DIFF), atol=FD_NOISE)


def test_ellipj_parameter_derivative_at_the_ends():
    # First-order expansions in m (A&S 16.13.1-3) and in m1 = 1 - m (A&S 16.15.1-3):
    # d sn/dm at m = 0 is -(u - sin u cos u) cos u / 4, and at m = 1 (and to O(m1) at
    # m1 = 1e-8) d sn/dm1 is (tanh u - u sech^2 u) / 4.
    for u in [-1.5, 0.3, 0.7, 1.5]:
        s, c = math.sin(u), math.cos(u)
        q = (u - s * c) / 4
        d_dm = _ellipj_jac(np.array([u, 0.0]))[:, 1]
        np.testing.assert_allclose(d_dm, [-q * c, q * s, -(s**2) / 2], rtol=0, atol=1e-15)
        t, h, sinh = math.tanh(u), 1 / math.cosh(u), math.sinh(u)
        expected = np.array([t - u * h**2, -t * (sinh - u * h), t * (sinh + u * h)]) / 4
        # (x = m1 / 1e-8)
        d_dm1 = _ellipj_jac_near_one(np.array([u, 0.0]))[:, 1] / 1e-8
        np.testing.assert_allclose(d_dm1, expected, rtol=tol(ROUNDOFF))
        d_dm1 = _ellipj_jac_near_one(np.array([u, 1.0]))[:, 1] / 1e-8
        np.testing.assert_allclose(d_dm1, expected, rtol=1e-6)
        # Without m1 the derivative at m = 1 is the same, with the sign of dm = -dm1.
        d_dm = _ellipj_jac(np.array([u, 1.0]))[:, 1]
        np.testing.assert_allclose(d_dm, -expected, rtol=tol(ROUNDOFF))


def test_gradients_finite_at_the_ends():
    for m in [0.0, 1.0]:
        for u in [0.0, 0.5, -30.0, 800.0]:
            assert np.all(np.isfinite(_ellipj_jac(np.array([u, m]))))
    for x in [0.0, 1e-292]:  # m1 = 0 and 1e-300
        for u in [0.0, 0.5, -30.0, 800.0]:
            assert np.all(np.isfinite(_ellipj_jac_near_one(np.array([u, x]))))
    # At u = 0, d sn/du = 1 exactly (no halving at the boundary of the reduction).
    assert _ellipj_jac(np.array([0.0, 0.5]))[0, 0] == 1.0
    assert np.all(np.isfinite(_ellipk_grad(np.array([0.0, 1.0, 0.5, 1.0 - 1e-16, 1.0]))))
    assert np.all(np.isfinite(np.array(_ellipf_grad(math.pi / 2, 1.0))))
    assert np.all(np.isfinite(np.array(_ellippi_grad(0.0, 0.0))))


# ----------------------------------------------------------------------------------------
# Carlson's integrals
# ----------------------------------------------------------------------------------------

_CARLSON_VALUES = [0.0, 1e-16, 1e-8, 0.3, 1.0, 2.5, 1e8, 1e16]


def test_carlson_rf_vs_scipy():
    grid = np.array(np.meshgrid(*[_CARLSON_VALUES] * 3)).reshape(3, -1)
    # Extreme ratios (scipy returns NaN for the last): R_F(0, m1, 1) = K(1 - m1),
    # R_F(0, a, a) = pi / (2 sqrt a).
    extreme = np.array([[0.0, 0.0, 0.0], [1e-300, 1e-200, 1e-300], [1.0, 1.0, 1e-300]])
    got = carlson_rf(*np.concatenate([grid, extreme], axis=1))
    got, got_extreme = got[: grid.shape[1]], got[grid.shape[1] :]
    expected = [sp.ellipkm1(1e-300), sp.ellipkm1(1e-200), math.pi / 2 * 1e150]
    np.testing.assert_allclose(got_extreme, expected, rtol=tol(ROUNDOFF))
    x, y, z = grid
    two_zeros = (x == 0).astype(int) + (y == 0) + (z == 0) >= 2
    assert np.all(got[two_zeros] == np.inf)
    np.testing.assert_allclose(got[~two_zeros], sp.elliprf(x, y, z)[~two_zeros], rtol=1e-14)


def test_carlson_rc_vs_scipy():
    x, y = np.array(np.meshgrid(_CARLSON_VALUES, _CARLSON_VALUES)).reshape(2, -1)
    got = carlson_rc(x, y)
    np.testing.assert_allclose(got[y > 0], sp.elliprc(x, y)[y > 0], rtol=1e-14)
    assert np.all(got[y == 0] == np.inf)


def test_carlson_rj_vs_scipy():
    xyz = [0.0, 1e-8, 0.3, 1.0, 2.5]
    grid = np.array(np.meshgrid(xyz, xyz, xyz, [0.01, 0.5, 1.0, 3.0, 1e3, 1e8, 1e30]))
    # p << x, y, z, where scipy loses digits: R_J(x, x, x, p) = 3 (R_C(x, p) - 1/sqrt x) /
    # (x - p) (DLMF 19.21.12 with y = z = x, an identity used only for p > 4 max(x, y, z)).
    x1, p1 = (v.ravel() for v in np.meshgrid([0.3, 1.0, 7.0], [1e-300, 1e-30, 1e-8]))
    x, y, z, p = np.concatenate([grid.reshape(4, -1), [x1, x1, x1, p1]], axis=1)
    got, rd = carlson_rj(x, y, z, p), carlson_rj(x, y, z, z)  # (the same compilation)
    expected = 3 * (sp.elliprc(x1, p1) - 1 / np.sqrt(x1)) / (x1 - p1)
    np.testing.assert_allclose(got[-x1.size :], expected, rtol=1e-14)
    two_zeros = (x == 0).astype(int) + (y == 0) + (z == 0) >= 2
    assert np.all(got[two_zeros] == np.inf)
    ok = ~two_zeros
    ok[-x1.size :] = False
    np.testing.assert_allclose(got[ok], sp.elliprj(x, y, z, p)[ok], rtol=1e-13)
    # R_J(x, y, z, z) = R_D(x, y, z), DLMF 19.16.5.
    np.testing.assert_allclose(rd[ok], sp.elliprd(x, y, z)[ok], rtol=1e-13)


# ----------------------------------------------------------------------------------------
# F(phi | m) and Pi(n | m)
# ----------------------------------------------------------------------------------------


_N_PHI = 241


@pytest.mark.parametrize("m", [0.0, 1e-300, 0.3, 0.9, 1 - 1e-6, 1 - 1e-10, -2.0])
def test_ellipf_vs_scipy(m):
    phi = np.linspace(-3 * np.pi, 3 * np.pi, _N_PHI)
    got = ellipf(phi, m, 1.0 - m)
    np.testing.assert_allclose(got, sp.ellipkinc(phi, m), rtol=tol(ROUNDOFF), atol=1e-300)


def test_ellipf_m_one():
    # F(phi | 1) = atanh(sin phi), which diverges at |phi| = pi/2; beyond, F is +-inf (F is
    # odd; scipy returns +inf on both sides).
    finite = np.linspace(-1.5, 1.5, _N_PHI - 5)
    phi = np.concatenate([finite, [np.pi / 2, 2.0, 3 * np.pi, -np.pi / 2, -2.0]])
    expected = np.concatenate([np.arctanh(np.sin(finite)), [np.inf] * 3 + [-np.inf] * 2])
    np.testing.assert_allclose(ellipf(phi, 1.0, 0.0), expected, rtol=tol(ROUNDOFF))


def test_ellipf_gradient():
    # dF/dphi = 1 / dn and dF/dm = (E - m1 F) / (2 m m1) - sin cos / (2 m1 dn), with
    # dn = sqrt(1 - m sin^2 phi) (DLMF 19.4(i), in terms of m = k^2).
    for phi, m in [(2.3, 0.7), (-4.0, 0.9), (0.5, 0.3)]:
        g_phi, g_m = _ellipf_grad(phi, m)
        s, c, m1 = math.sin(phi), math.cos(phi), 1 - m
        dn = math.sqrt(1 - m * s**2)
        e, f = sp.ellipeinc(phi, m), sp.ellipkinc(phi, m)
        assert g_phi == pytest.approx(1 / dn, rel=tol(ROUNDOFF))
        assert g_m == pytest.approx((e - m1 * f) / (2 * m * m1) - s * c / (2 * m1 * dn), rel=1e-12)


_PI_N = np.array([0.0, 0.3, 0.9, 0.999, 1.0, -0.5, -10.0, -1e6])[:, None]
_PI_M1 = np.array([1.0, 0.7, 0.5, 0.1, 1e-10, 1e-300, 0.0])[None, :]


def test_ellippi_vs_carlson_formula():
    # DLMF 19.25.2 evaluated with scipy's Carlson integrals (no cancellation for n >= 0).
    got = ellippi(_PI_N, 1.0 - _PI_M1, _PI_M1)
    n, m1 = _PI_N[:4], _PI_M1[:, :-1]
    expected = sp.elliprf(0, m1, 1) + n / 3 * sp.elliprj(0, m1, 1, 1 - n)
    np.testing.assert_allclose(got[:4, :-1], expected, rtol=tol(ROUNDOFF))
    # Pi(1 | m) and Pi(n | 1) diverge.
    assert np.all(got[4] == np.inf) and np.all(got[:, -1] == np.inf)


def test_ellippi_vs_quadrature():
    # For n << 0 the formula above cancels; integrate the definition instead.
    got = ellippi(_PI_N, 1.0 - _PI_M1, _PI_M1)
    for i, n in enumerate(_PI_N[:, 0]):
        for j, m in enumerate(1 - _PI_M1[0, :4]):
            if n == 1.0:
                continue

            def integrand(t):
                return 1 / ((1 - n * np.sin(t) ** 2) * np.sqrt(1 - m * np.sin(t) ** 2))

            expected, _ = quad(integrand, 0, np.pi / 2, epsabs=0, epsrel=1e-13, limit=200)
            assert got[i, j] == pytest.approx(expected, rel=tol(ROUNDOFF))


def test_ellippi_gradient():
    # DLMF 19.4(i), in terms of m = k^2:
    # dPi/dn = (E + (m - n) K / n + (n^2 - m) Pi / n) / (2 (m - n) (n - 1)),
    # dPi/dm = (E / (m - 1) + Pi) / (2 (n - m)).
    for n, m in [(-3.0, 0.5), (0.3, 0.5), (0.8, 0.2), (-1e3, 0.9)]:
        g_n, g_m = _ellippi_grad(n, m)
        k, e = sp.ellipk(m), sp.ellipe(m)
        pi = sp.elliprf(0, 1 - m, 1) + n / 3 * sp.elliprj(0, 1 - m, 1, 1 - n)
        d_n = (e + (m - n) * k / n + (n * n - m) * pi / n) / (2 * (m - n) * (n - 1))
        assert g_n == pytest.approx(d_n, rel=1e-11)
        assert g_m == pytest.approx((e / (m - 1) + pi) / (2 * (n - m)), rel=1e-11)


# ----------------------------------------------------------------------------------------
# dtypes, jit, vmap
# ----------------------------------------------------------------------------------------


def test_float32():
    f32 = np.float32
    rtol = tol(ROUNDOFF, jnp.float32)
    m = f32(0.7)
    m64 = np.float64(m)  # scipy sees the same (rounded) parameter
    u = np.linspace(-12, 12, 49, dtype=f32)
    got = ellipj(u, m)
    assert all(g.dtype == jnp.float32 for g in got)
    atol = rtol * np.maximum(1, np.abs(u) / sp.ellipk(m64))
    assert np.all(np.abs(np.stack(got) - _scipy_ellipj(u.astype(np.float64), m64)) <= atol)
    mm = np.linspace(0, 0.95, 20, dtype=f32)
    assert ellipk(mm).dtype == jnp.float32
    np.testing.assert_allclose(ellipk(mm), sp.ellipk(mm.astype(np.float64)), rtol=rtol)
    assert ellipk(f32(1.0), f32(1e-30)) == pytest.approx(sp.ellipkm1(np.float64(f32(1e-30))))
    phi = np.linspace(-7, 7, 29, dtype=f32)
    assert ellipf(phi, m).dtype == jnp.float32
    np.testing.assert_allclose(ellipf(phi, m), sp.ellipkinc(phi.astype(np.float64), m64), rtol)
    x, y, z, p = (np.array(v, dtype=f32) for v in ([0.0, 0.5, 2.0], 1.0, 3.0, [0.5, 50.0, 1.0]))
    for ours, theirs, args in [
        (carlson_rf, sp.elliprf, (x, y, z)),
        (carlson_rc, sp.elliprc, (x, 3.0)),  # a Python scalar does not upcast
        (carlson_rj, sp.elliprj, (x, y, z, p)),
    ]:
        assert ours(*args).dtype == jnp.float32
        expected = theirs(*(np.float64(a) for a in args))
        np.testing.assert_allclose(ours(*args), expected, rtol=rtol)
    n = np.array([-5.0, 0.0, 0.5], dtype=f32)
    assert ellippi(n, m).dtype == jnp.float32
    expected = sp.elliprf(0, 1 - m64, 1) + n / 3 * sp.elliprj(0, 1 - m64, 1, 1 - n)
    np.testing.assert_allclose(ellippi(n, m), expected, rtol=rtol)


def test_vmap_jit_broadcasting():
    rtol = 4 * np.finfo(float).eps  # (the order of floating-point operations may differ)
    u = np.linspace(-5, 5, 7)
    m = np.array([0.1, 0.5, 0.9, 0.999, 0.0])
    mapped = np.stack(jax.jit(jax.vmap(jax.vmap(ellipj, (None, 0)), (0, None)))(u, m))
    assert mapped.shape == (3, 7, 5)
    expected = _scipy_ellipj(u[:, None], m[None, :])
    np.testing.assert_allclose(mapped, expected, rtol=0, atol=ELLIPJ_ATOL * 4)
    np.testing.assert_allclose(jax.vmap(ellipk)(m), ellipk(m), rtol=rtol)
