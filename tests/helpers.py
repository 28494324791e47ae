"""Tolerances and comparison helpers, in one place for the whole test suite."""

import contextlib
import os

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


def host_devices_env(count: int) -> dict:
    """The environment of a child process that sees `count` host devices: the suite's own
    `XLA_FLAGS` (the faster-compiling emitters, `tests/conftest.py`, which also key the shared
    compilation cache) with the device count added, not replaced."""
    flags = os.environ.get("XLA_FLAGS", "")
    return {**os.environ,
            "XLA_FLAGS": f"{flags} --xla_force_host_platform_device_count={count}".strip()}


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
    """Central finite differences of a function of a 1-D float64 array: the gradient of a
    scalar function, or the Jacobian of an array-valued one (`d f / d x_i` along the last
    axis)."""
    x = np.asarray(x, dtype=np.float64)
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = eps * max(1.0, abs(x[i]))
        cols.append((np.asarray(f(jnp.asarray(x + e)), np.float64)
                     - np.asarray(f(jnp.asarray(x - e)), np.float64)) / (2 * e[i]))
    return np.stack(cols, axis=-1)


def expm_longdouble(a):
    """`expm(a)` by the Taylor series scaled and squared in NumPy's long double (a 64-bit
    mantissa on x86; only float64 where long double is float64, as on some ARM machines),
    rounded to float64: a reference for closed forms of matrix exponentials."""
    a = np.asarray(a, np.longdouble)
    squarings = max(0, int(np.ceil(np.log2(max(np.abs(a).sum(0).max(), 1e-300)))) + 6)
    b = a / np.longdouble(2.0) ** squarings
    out = term = np.eye(a.shape[0], dtype=np.longdouble)
    for k in range(1, 25):
        term = term @ b / k
        out = out + term
    for _ in range(squarings):
        out = out @ out
    return out.astype(np.float64)


# The default relative tolerance of `jd.simulate`, and how far (as a multiple of it) a
# well-conditioned result may lie from an exact reference at the defaults (issue 17).
DEFAULT_RTOL = 1e-8
WITHIN_RTOL = 10


# -- compiled programs -----------------------------------------------------------------------

# A program new to the process is either lowered by JAX (then compiled by XLA or found in its
# persistent cache) or loaded compiled from jaxdyn's program store (`_programs`), which skips
# the lowering: both are counted, so a check holds whether or not an earlier run stored it.
_NEW_PROGRAM = ("/jax/core/compile/jaxpr_to_mlir_module_duration",
                "/jaxdyn/programs/load_duration")


@contextlib.contextmanager
def new_programs():
    """Count the programs a process takes on inside the block: one per program JAX lowers
    (whether XLA then compiles it or a persistent cache holds it) and one per compiled program
    loaded from jaxdyn's program store. Yields a list that grows by one per program."""
    seen = []

    def listener(name, *args, **kwargs):
        if name in _NEW_PROGRAM:
            seen.append(name)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield seen
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def compiled_flops(fn, *args) -> float:
    """XLA's count of floating-point operations in the compiled `fn(*args)`."""
    cost = jax.jit(fn).lower(*args).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, list | tuple) else cost
    return float(cost["flops"])


# Two compiled programs that do the same arithmetic cost the same to within this fraction
# (XLA's fusion and counting of bookkeeping operations may differ by a little from one version
# to the next; an extra term in a vector field costs several times more).
COST_MARGIN = 0.02


# -- independent references ------------------------------------------------------------------

def scipy_euler(inertia, omega0, t1, ts=None, *, rtol=1e-13, atol=1e-14):
    """Euler's equations integrated by scipy's DOP853 (an independent reference): `inertia` is
    the principal moments or a full inertia tensor. The rates at `ts` (default: the solver's
    own steps), one row each."""
    from scipy.integrate import solve_ivp

    tensor = np.diag(inertia) if np.ndim(inertia) == 1 else np.asarray(inertia)
    inv = np.linalg.inv(tensor)
    sol = solve_ivp(lambda t, w: inv @ np.cross(tensor @ w, w), (0, t1), omega0,
                    t_eval=ts, rtol=rtol, atol=atol, method="DOP853")
    return sol.y.T
