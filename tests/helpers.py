"""Tolerances and comparison helpers, in one place for the whole test suite."""

import jax
import jax.numpy as jnp
import numpy as np

# Relative tolerances keyed by dtype, for results that should be exact up to round-off
# accumulated over a short computation (closed forms, special functions, identities).
ROUNDOFF = {jnp.dtype("float64"): 1e-12, jnp.dtype("float32"): 1e-5}

# Tolerance for comparing a tight integration (rtol=1e-12) against an exact reference.
INTEGRATION = {jnp.dtype("float64"): 1e-9, jnp.dtype("float32"): 1e-4}

# Relative tolerance for gradients checked against central finite differences.
FINITE_DIFF = {jnp.dtype("float64"): 1e-6, jnp.dtype("float32"): 1e-2}


def tol(table, dtype=jnp.float64):
    return table[jnp.dtype(dtype)]


def tree_allclose(x, y, *, rtol, atol=0.0):
    leaves_x, tree_x = jax.tree_util.tree_flatten(x)
    leaves_y, tree_y = jax.tree_util.tree_flatten(y)
    if tree_x != tree_y:
        return False
    return all(
        np.allclose(np.asarray(a), np.asarray(b), rtol=rtol, atol=atol)
        for a, b in zip(leaves_x, leaves_y)
    )


def central_difference(f, x, eps=1e-6):
    """Central finite-difference gradient of a scalar function of a 1-D float64 array."""
    x = np.asarray(x, dtype=np.float64)
    g = np.zeros_like(x)
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = eps * max(1.0, abs(x[i]))
        g[i] = (float(f(jnp.asarray(x + e))) - float(f(jnp.asarray(x - e)))) / (2 * e[i])
    return g

# The default relative tolerance of `jd.simulate`, and how far (as a multiple of it) a
# well-conditioned result may lie from an exact reference at the defaults (issue 17).
DEFAULT_RTOL = 1e-8
WITHIN_RTOL = 10
