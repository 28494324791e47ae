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


def test_block_solve_matches_a_dense_solve():
    """The Levenberg-Marquardt step of the lifted problem, solved segment by segment (block
    Thomas recursion and a Schur complement), equals the dense solve of the same normal
    equations assembled from the same blocks; a fixed component does not move."""
    rng = np.random.default_rng(6001)
    S, n_p, n_s, m, c = 5, 3, 2, 7, 2
    A = rng.normal(size=(S, m, n_p + n_s))
    blocks = {"N": np.einsum("kij,kil->kjl", A, A), "g": rng.normal(size=(S, n_p + n_s)),
              "P": rng.normal(size=(S, c, n_p)), "G": rng.normal(size=(S, c, n_s)),
              "E": rng.normal(size=(S, c, n_s)), "d": rng.normal(size=(S, c))}
    for k in ("P", "G", "E", "d"):
        blocks[k][-1] = 0.0  # the last segment has no successor
    p_free, s0_free = np.array([True, False, True]), np.array([True, False])
    # Dense: the Jacobian of the lifted residuals, row by row.
    n = n_p + S * n_s
    H, g = np.zeros((n, n)), np.zeros(n)
    for k in range(S):
        rows = np.zeros((m, n))
        rows[:, :n_p] = A[k, :, :n_p]
        rows[:, n_p + k * n_s:n_p + (k + 1) * n_s] = A[k, :, n_p:]
        H += rows.T @ rows
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
    H = np.where(free[:, None] & free[None, :], H, 0.0) + np.diag(~free)
    g = np.where(free, g, 0.0)
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


def test_lifted_optimum_where_the_defects_cannot_close(monkeypatch):
    """On a record so long that the condensed steps lose their precision (propagated over
    hundreds of segments, issue 20's 1e5-sample wheel record), the fit keeps the lifted
    optimum with tight continuity weights and the lifted problem's normal matrix. Here the
    condensed steps are refused outright on a short record, where single shooting gives the
    reference: the same estimate to a small fraction of its interval, the same intervals to
    0.1 % (here 0.02 %; the lifted problem's own normal matrix, without the tighter continuity
    weights, gives 0.4 % here and up to 33 % on the 1e4-sample wheel record)."""
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
        assert np.all(np.abs(a - b) <= 0.05 * sa), (name, (a - b) / sa)
        assert np.allclose(sa, sb, rtol=1e-3), (name, sb / sa)
