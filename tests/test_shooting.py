"""Multiple shooting (long records): the structured solver against a dense solve, and the
estimate against single shooting's on the same data. (A long noise-free record recovered from
the default start by multiple shooting: test_identify.py's
`test_long_noise_free_record_converges_from_the_default_start`.) Reference data from SciPy's
DOP853 (see test_identify.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_identify import (
    _attitude_record,
    _star_tracker,
)

import jaxdyn as jd
from jaxdyn._identify import _shooting


def _random_blocks(seed):
    """Random lifted blocks (`A`: each segment's data Jacobian) and a fixed component of `p`
    and of `s_0`."""
    rng = np.random.default_rng(seed)
    S, n_p, n_s, m, c = 5, 3, 2, 7, 2
    A = rng.normal(size=(S, m, n_p + n_s))
    blocks = {"N": np.einsum("kij,kil->kjl", A, A), "g": rng.normal(size=(S, n_p + n_s)),
              "P": rng.normal(size=(S, c, n_p)), "G": rng.normal(size=(S, c, n_s)),
              "E": rng.normal(size=(S, c, n_s)), "d": rng.normal(size=(S, c))}
    for k in ("P", "G", "E", "d"):
        blocks[k][-1] = 0.0  # the last segment has no successor
    return blocks, A, np.array([True, False, True]), np.array([True, False])


def _dense(blocks, A, p_free, s0_free):
    """The lifted normal matrix `H`, its data part `H_data` and gradient `g`, assembled row by
    row from the Jacobian of the lifted residuals; fixed components with zero rows and
    columns (and a unit diagonal in `H`), and the mask of free components."""
    S, m, _ = A.shape
    n_p, n_s, c = p_free.size, s0_free.size, blocks["P"].shape[1]
    n = n_p + S * n_s
    H, H_data, g = np.zeros((n, n)), np.zeros((n, n)), np.zeros(n)
    for k in range(S):
        rows = np.zeros((m, n))
        rows[:, :n_p] = A[k, :, :n_p]
        rows[:, n_p + k * n_s:n_p + (k + 1) * n_s] = A[k, :, n_p:]
        H_data += rows.T @ rows
        sel = np.r_[np.arange(n_p), n_p + k * n_s + np.arange(n_s)]
        g[sel] += blocks["g"][k]
        if k < S - 1:
            crow = np.zeros((c, n))
            crow[:, :n_p] = blocks["P"][k]
            crow[:, n_p + k * n_s:n_p + (k + 1) * n_s] = blocks["G"][k]
            crow[:, n_p + (k + 1) * n_s:n_p + (k + 2) * n_s] = blocks["E"][k]
            H += crow.T @ crow
            g += crow.T @ blocks["d"][k]
    free = np.r_[p_free, s0_free, np.ones((S - 1) * n_s, bool)]
    mask = free[:, None] & free[None, :]
    H = np.where(mask, H + H_data, 0.0) + np.diag(~free)
    return H, np.where(mask, H_data, 0.0), np.where(free, g, 0.0), free


def test_block_solve_matches_a_dense_solve():
    """The Levenberg-Marquardt step of the lifted problem, solved segment by segment (block
    Thomas recursion and a Schur complement), equals the dense solve of the same normal
    equations assembled from the same blocks; a fixed component does not move."""
    blocks, A, p_free, s0_free = _random_blocks(6001)
    n_p = p_free.size
    H, _, g, free = _dense(blocks, A, p_free, s0_free)
    lam = 0.3
    damping = lam * np.diag(H)
    x = -np.linalg.solve(H + np.diag(damping), g)
    dp, ds, predicted = _shooting.lm_step(jax.tree.map(jnp.asarray, blocks), lam,
                                          jnp.asarray(p_free), jnp.asarray(s0_free))
    got = np.r_[np.asarray(dp), np.ravel(ds)]
    assert np.allclose(got, x, rtol=1e-10, atol=1e-12 * np.max(np.abs(x)))
    assert got[1] == 0.0 and got[n_p + 1] == 0.0
    # The predicted reduction is that of the quadratic model.
    assert float(predicted) == pytest.approx(-(g @ x + 0.5 * x @ (H - np.diag(~free)) @ x),
                                             rel=1e-10)


def test_lifted_covariance_is_the_sandwich_of_a_dense_solve():
    """The lifted estimator's covariance of `z = (p, s_0)` over the residual variance,
    computed segment by segment, equals `H^-1 H_data H^-1` from the dense lifted normal
    matrix (only the data rows carry noise), zero on the fixed components; positive definite,
    and below `H^-1` (which counts the continuity rows as observations)."""
    blocks, A, p_free, s0_free = _random_blocks(6002)
    n_p, n_s = p_free.size, s0_free.size
    H, H_data, _, free = _dense(blocks, A, p_free, s0_free)
    Hinv = np.linalg.inv(H)
    sandwich = (Hinv @ H_data @ Hinv)[:n_p + n_s, :n_p + n_s]
    got = np.asarray(_shooting.lifted_covariance(jax.tree.map(jnp.asarray, blocks),
                                                 jnp.asarray(p_free), jnp.asarray(s0_free)))
    assert np.allclose(got, sandwich, rtol=1e-9, atol=1e-12 * np.max(np.abs(sandwich)))
    z_free = free[:n_p + n_s]
    assert np.all(got[~z_free] == 0.0) and np.all(got[:, ~z_free] == 0.0)
    # Positive semidefinite, and below the "posterior" H^-1 (H_data <= H).
    ev = np.linalg.eigvalsh(got[np.ix_(z_free, z_free)])
    assert ev.min() > 0
    gap = (Hinv[:n_p + n_s, :n_p + n_s] - got)[np.ix_(z_free, z_free)]
    assert np.linalg.eigvalsh(gap).min() > -1e-12 * ev.max()


def test_identifiable_where_the_dynamics_amplify_a_perturbation():
    """A component seen directly by every segment's data (a gyro bias: `p_0`) or not
    amplified by the dynamics (an attitude: `s_0[1]`) is identifiable beside components
    whose condensed columns an unstable state amplifies 1e3-fold per segment (`p_1` feeds
    it, `s_0[0]` is it); a component that neither the data nor the dynamics see (`p_2`) is
    not. Condensed columns alone, against the largest, held `p_0` and `s_0[1]` fixed."""
    rng = np.random.default_rng(7)
    S, m, n_p, n_s = 8, 12, 3, 2
    A = rng.normal(size=(S, m, n_p + n_s))
    A[:, :, 0] = 1.0  # the bias adds to every sample
    A[:, :, 2] = 0.0  # seen by nothing
    P = np.zeros((S, n_s, n_p))
    P[:, 0, 1] = 1.0  # p_1 drives the unstable state
    G = np.broadcast_to(np.diag([1e3, 1.0]), (S, n_s, n_s)).copy()
    E = np.broadcast_to(-np.eye(n_s), (S, n_s, n_s)).copy()
    blocks = {"N": np.einsum("kij,kil->kjl", A, A), "g": np.zeros((S, n_p + n_s)),
              "P": P, "G": G, "E": E, "d": np.zeros((S, n_s))}
    for k in ("P", "G", "E"):
        blocks[k][-1] = 0.0
    blocks = jax.tree.map(jnp.asarray, blocks)
    s0_free = jnp.asarray([True, True])
    got = _shooting.identifiable(blocks, s0_free, 1e-6)
    assert got.tolist() == [True, True, False, True, True]
    H, *_ = _shooting.condense(blocks, jnp.ones(n_p, bool), s0_free)
    condensed = np.sqrt(np.diag(np.asarray(H)))
    assert (condensed > 1e-6 * condensed.max()).tolist() == [False, True, False, True, False]


def _same_estimate(single, multiple, names):
    for name in names:
        a, b = np.asarray(single.values[name]), np.asarray(multiple.values[name])
        sa, sb = np.asarray(single.std[name]), np.asarray(multiple.std[name])
        # The same least-squares estimate: apart by a tiny fraction of its interval.
        assert np.all(np.abs(a - b) <= 1e-3 * sa + 1e-12), (name, a, b, sa)
        assert np.allclose(sa, sb, rtol=1e-3, atol=1e-15), (name, sa, sb)


def test_multiple_shooting_gives_the_single_shooting_estimate_and_intervals():
    """Gyro (biased, noisy) and star-tracker (random signs) data over 64 samples: a fit cut
    into 4 segments lands on the single-shooting optimum, with the same intervals (the
    defects closed exactly, the condensed normal matrix that of single shooting)."""
    rng = np.random.default_rng(6101)
    ts = np.linspace(0.0, 16.0, 64)
    moments, w, q, w0, q0 = _attitude_record(ts)
    bias, s_gyro, s_star = np.array([2e-3, -1e-3, 5e-4]), 1e-3, 1e-3
    data = {"omega": w + bias + s_gyro * rng.normal(size=w.shape),
            "quaternion": _star_tracker(q, s_star, rng)}
    scene = jd.Scene(jd.RigidBody(moments), attitude=True)
    kwargs = dict(parameters={"inertia": jd.ValidInertia()},
                  initial={"omega": jd.Unconstrained(), "quaternion": jd.UnitQuaternion()},
                  bias=["omega"], sigma={"omega": s_gyro, "quaternion": s_star}, restarts=1,
                  y0=scene.state(omega=w0, quaternion=q0))
    single = jd.fit(scene, ts, data, segments=1, horizons=(1.0,), **kwargs)
    multiple = jd.fit(scene, ts, data, segments=4, **kwargs)
    assert single.segments == 1 and multiple.segments == 4
    assert single.converged and multiple.converged
    _same_estimate(single, multiple, ["inertia.principal_moments", "bias.omega", "omega"])
    assert multiple.loss == pytest.approx(single.loss, rel=1e-6)
    assert multiple.residual_rms_by_output == pytest.approx(single.residual_rms_by_output,
                                                            rel=1e-6)
    # The residuals over the record, reassembled from the segments, are single shooting's.
    for name, rho in single.residual_autocorrelation.items():
        assert np.allclose(multiple.residual_autocorrelation[name], rho, atol=1e-6)
    assert single.systematic == multiple.systematic == ()

    # Between its compiled programs, the lifted Levenberg--Marquardt loop works on the host in
    # NumPy: an eager `jax.numpy` operation is a program of its own, lowered and compiled on its
    # first call in every process (a first multiple-shooting fit compiled about 140 of them,
    # 2-3 s of 11 s). With JAX's caches emptied, the same fit again lowers only the loop's
    # named programs (jaxdyn's stored programs are kept by jaxdyn: they are not lowered again).
    jax.clear_caches()
    again, lowered = _lowering(lambda: jd.fit(scene, ts, data, segments=4, **kwargs))
    assert again.loss == multiple.loss
    eager = [name for name in lowered if name not in _LOOP_PROGRAMS]
    assert lowered and not eager, lowered


# The programs of multiple shooting's loop that are plain `jax.jit`s (lowered again once JAX's
# caches are emptied); anything else lowered is an eager operation.
_LOOP_PROGRAMS = {"lm_step", "condense", "condensed_step", "lifted_covariance", "_weighted",
                  "bind_segments"}


def _lowering(fn):
    """`fn()` and the names of the programs JAX lowered meanwhile (from its compile log)."""
    import logging
    import re

    names = []

    class Names(logging.Handler):
        def emit(self, record):
            found = re.match(r"Finished jaxpr to MLIR module conversion jit\((.*?)\)",
                             record.getMessage())
            if found:
                names.append(found.group(1))

    handler, logger = Names(), logging.getLogger("jax")
    logger.addHandler(handler)
    try:
        with jax.log_compiles(True):
            out = fn()
    finally:
        logger.removeHandler(handler)
    return out, names


def test_lifted_optimum_where_the_defects_cannot_close(monkeypatch):
    """On a record so long that the condensed steps lose their precision (propagated over
    hundreds of segments, issue 20's 1e5-sample wheel record), the fit keeps the lifted
    optimum with the lifted estimator's own covariance. Here the condensed steps are refused
    outright on a short record, where single shooting gives the reference: the same estimate
    to a small fraction of its interval; intervals no narrower than single shooting's (the
    constrained estimator is the efficient one; the lifted residual variance is a little
    smaller) and not much wider (on a record this short, equal to 2e-4)."""
    rng = np.random.default_rng(6103)
    ts = np.linspace(0.0, 16.0, 64)
    moments, w, q, w0, q0 = _attitude_record(ts)
    s_gyro, s_star = 1e-3, 1e-3
    data = {"omega": w + s_gyro * rng.normal(size=w.shape),
            "quaternion": _star_tracker(q, s_star, rng)}
    scene = jd.Scene(jd.RigidBody(moments), attitude=True)
    kwargs = dict(parameters={"inertia": jd.ValidInertia()},
                  initial={"omega": jd.Unconstrained(), "quaternion": jd.UnitQuaternion()},
                  sigma={"omega": s_gyro, "quaternion": s_star}, restarts=1,
                  y0=scene.state(omega=w0, quaternion=q0))
    single = jd.fit(scene, ts, data, segments=1, horizons=(1.0,), **kwargs)
    step = _shooting.condensed_step

    def imprecise(*args):
        dp, ds, _ = step(*args)
        return dp, ds, jnp.inf  # (a step length that does not shrink)

    monkeypatch.setattr(_shooting, "condensed_step", imprecise)
    lifted = jd.fit(scene, ts, data, segments=4, **kwargs)
    assert lifted.segments == 4 and lifted.converged
    for name in ["inertia.principal_moments", "omega"]:
        a, b = np.asarray(single.values[name]), np.asarray(lifted.values[name])
        sa, sb = np.asarray(single.std[name]), np.asarray(lifted.std[name])
        # (The largest normalised moment is 1 by definition: no interval to compare, and the
        # two estimates agree to round-off.)
        assert np.all(np.abs(a - b) <= 0.05 * sa + 1e-14 * np.abs(a)), (name, (a - b) / sa)
        determined = sa > 1e-9 * np.abs(a)
        ratio = sb[determined] / sa[determined]
        assert np.all((ratio >= 1 - 1e-3) & (ratio <= 2)), (name, ratio)
    # A closing step that lands at a wrong point (a linearisation without precision that
    # claims to have converged) is refused: the data explain it far worse than the lifted
    # optimum, and the fit is the lifted one.

    def wrong(*args):
        dp, ds, _ = step(*args)
        return dp + 1e-2, ds, jnp.zeros(())  # (an insignificant step, it says)

    monkeypatch.setattr(_shooting, "condensed_step", wrong)
    refused = jd.fit(scene, ts, data, segments=4, **kwargs)
    for name in ["inertia.principal_moments", "omega"]:
        a, b = np.asarray(lifted.values[name]), np.asarray(refused.values[name])
        assert np.allclose(a, b, rtol=1e-9, atol=1e-12), (name, a, b)
        assert np.allclose(lifted.std[name], refused.std[name], rtol=1e-9, atol=0)


def test_a_segment_that_cannot_be_integrated_is_named(monkeypatch):
    """A segment whose integration fails from its starting state (here: a step budget of 3
    steps per segment) stops the fit with an error naming the segment, its times and the
    remedies, instead of a failed decomposition of non-finite blocks."""
    ts = np.linspace(0.0, 16.0, 64)
    moments, w, _, w0, _ = _attitude_record(ts)
    scene = jd.Scene(jd.RigidBody(moments))
    monkeypatch.setattr(_shooting, "_SEGMENT_STEPS", 3)
    named = r"segment 1 of 4 \(t = 0 to .*\) and 3 other segments failed .*budget \(3 steps"
    with pytest.raises(RuntimeError, match=named):
        jd.fit(scene, ts, {"omega": w}, parameters={"inertia": jd.ValidInertia()},
               initial=["omega"], segments=4, restarts=1, y0={"omega": jnp.asarray(w0)})
