"""`sincos` (the batch engine's vectorised sine and cosine) against NumPy, the engine's rewrite
of vector fields with it, and the engine's vectorised step-size root against `x ** (-1 / p)`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdyn._batch_solve import _inv_root
from jaxdyn._fastmath import sincos, with_vectorised_trig


def _ulps(got, ref):
    """Largest error in units in the last place of `ref`'s type."""
    tiny = np.finfo(ref.dtype).tiny
    ulp = np.spacing(np.maximum(np.abs(ref), tiny)).astype(np.float64)
    return np.max(np.abs(np.asarray(got, np.float64) - ref.astype(np.float64)) / ulp)


@pytest.mark.parametrize("limit", [1.0, 10.0, 1e3, 1.6e6])
def test_sincos_float64_within_two_ulps(limit):
    x = np.random.default_rng(0).uniform(-limit, limit, 100_000)
    s, c = sincos(jnp.asarray(x))
    assert _ulps(s, np.sin(x)) <= 2 and _ulps(c, np.cos(x)) <= 2


def test_sincos_near_multiples_of_half_pi_and_special_values():
    k = np.arange(-3000, 3000) * (np.pi / 2)
    x = np.concatenate([k, np.nextafter(k, np.inf), np.nextafter(k, -np.inf)])
    s, c = sincos(jnp.asarray(x))
    # Absolute error at the zeros, where relative error is meaningless.
    assert np.max(np.abs(np.asarray(s) - np.sin(x))) < 1e-30
    assert np.max(np.abs(np.asarray(c) - np.cos(x))) < 1e-30
    s, c = sincos(jnp.array([0.0, 1e-300, np.inf, -np.inf, np.nan]))
    np.testing.assert_array_equal(np.asarray(s[:2]), [0.0, 1e-300])
    np.testing.assert_array_equal(np.asarray(c[:2]), [1.0, 1.0])
    assert np.all(np.isnan(np.asarray(s[2:]))) and np.all(np.isnan(np.asarray(c[2:])))


def test_sincos_float32_and_derivatives():
    x = np.random.default_rng(1).uniform(-100, 100, 100_000).astype(np.float32)
    s, c = sincos(jnp.asarray(x))
    assert s.dtype == jnp.float32
    assert _ulps(s, np.sin(x.astype(np.float64)).astype(np.float32)) <= 2
    assert _ulps(c, np.cos(x.astype(np.float64)).astype(np.float32)) <= 2
    # First and second derivatives, against the closed forms.
    x0 = 0.7
    assert np.isclose(jax.grad(lambda x: sincos(x)[0])(x0), np.cos(x0), rtol=1e-15)
    assert np.isclose(jax.grad(lambda x: sincos(x)[1])(x0), -np.sin(x0), rtol=1e-15)
    assert np.isclose(jax.grad(jax.grad(lambda x: sincos(x)[0]))(x0), -np.sin(x0), rtol=1e-15)
    jac = jax.jacfwd(lambda x: sincos(x)[1])(jnp.array([0.1, 2.0]))
    np.testing.assert_allclose(np.diag(jac), -np.sin([0.1, 2.0]), rtol=1e-15)


@pytest.mark.parametrize("p", [2, 3, 5, 8])
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_inverse_root_of_the_step_size_controller(p, dtype):
    x = jnp.logspace(-12, 12, 20001, dtype=dtype)
    got = _inv_root(x, p)
    want = np.asarray(x, np.float64) ** (-1.0 / p)
    rel = np.max(np.abs(np.asarray(got, np.float64) / want - 1))
    # A step-size factor needs a few digits (it is multiplied by a safety factor of 0.9)
    assert rel < 1e-4


def test_the_engine_rewrite_computes_every_sine_and_cosine_by_sincos():
    """`with_vectorised_trig` (the batch engine's rewrite of a vector field): the same values,
    and no call of the C library's sine or cosine left, nested calls included."""
    @jax.jit
    def inner(x):
        return jnp.cos(2 * x) * x

    def field(x, y):
        return {"a": jnp.sin(x) * inner(y), "b": jnp.tan(x) + jnp.cos(y) ** 2}

    x = jnp.linspace(-3.0, 3.0, 101)
    y = jnp.linspace(0.5, 7.0, 101)
    rewritten = with_vectorised_trig(field)
    got, want = rewritten(x, y), field(x, y)
    for k in want:
        np.testing.assert_allclose(np.asarray(got[k]), np.asarray(want[k]), rtol=1e-14,
                                   atol=1e-15)
    def primitives(jaxpr):
        for eqn in jaxpr.eqns:
            yield eqn.primitive.name
            for v in eqn.params.values():
                if hasattr(v, "jaxpr"):
                    yield from primitives(v.jaxpr)

    assert {"sin", "cos"} <= set(primitives(jax.make_jaxpr(field)(x, y).jaxpr))  # control
    used = set(primitives(jax.make_jaxpr(rewritten)(x, y).jaxpr))
    assert not {"sin", "cos"} & used and "tan" in used  # (tan is not rewritten)


def test_the_rewrite_shares_one_sincos_between_the_sine_and_cosine_of_an_angle():
    """A vector field takes `sin(theta)` and `cos(theta)` of the same angle, often in several
    places: the rewrite reduces each angle once (one `round` of the argument reduction per
    distinct angle), which keeps the engine's programs smaller to trace and lower."""
    def field(x, y):
        s, c = jnp.sin(x), jnp.cos(x)
        return s * c + jnp.sin(x) ** 2 + jnp.cos(y) * jnp.sin(2.0)

    def count(jaxpr):  # the argument reductions, nested calls included
        return sum((e.primitive.name == "round")
                   + sum(count(v.jaxpr) for v in e.params.values() if hasattr(v, "jaxpr"))
                   for e in jaxpr.eqns)

    def rounds(fn):
        return count(jax.make_jaxpr(fn)(1.0, 2.0).jaxpr)

    x, y = jnp.float64(0.7), jnp.float64(-2.1)
    np.testing.assert_allclose(with_vectorised_trig(field)(x, y), field(x, y), rtol=1e-15)
    # x, y and the constant 2.0: three reductions (six sines and cosines in the field)
    assert rounds(with_vectorised_trig(field)) == 3 and rounds(field) == 0
