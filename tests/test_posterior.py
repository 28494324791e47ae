"""The posterior sampled by NUTS (blackjax) through the fit's residuals.

Where the Gauss-Newton approximation holds (a well-determined body, small noise), the
posterior is nearly Gaussian with the Gauss-Newton mean and covariance (the Laplace
approximation, an independent route): the draws' mean and spread agree with the fit's
estimate and intervals. Coverage over seeds on a nearly axisymmetric body, where the two
differ, takes minutes: `python benchmarks/identify.py --coverage 20`.
"""

import jax.numpy as jnp
import numpy as np
import pytest
from test_identify import FIT_BODY, SAMPLES, euler_rates

import jaxdyn as jd

pytest.importorskip("blackjax")


def test_posterior_agrees_with_gauss_newton_where_it_holds():
    moments = np.array([0.6, 0.8, 1.0])
    w0 = np.array([0.7, 0.2, 0.6])
    ts = np.linspace(0.0, 8.0, SAMPLES)
    noise = 1e-3
    data = euler_rates(np.diag(moments), w0, ts)
    data = data + noise * np.random.default_rng(7001).normal(size=data.shape)
    res = jd.fit(jd.Scene(jd.RigidBody(moments)), ts, {"omega": data}, **FIT_BODY,
                 restarts=1, horizons=(1.0,), y0={"omega": jnp.asarray(w0)}, posterior=200,
                 warmup=150, key=3)
    draws = res.posterior["inertia.principal_moments"][:, :2]
    value = np.asarray(res.values["inertia.principal_moments"])[:2]
    std = np.asarray(res.std["inertia.principal_moments"])[:2]
    assert draws.shape == (200, 2) and np.all(np.isfinite(draws))
    assert 0.5 < res.posterior_acceptance < 1.0
    # With the Gauss-Newton covariance as its mass matrix, NUTS takes a few leapfrog steps
    # per draw on a nearly Gaussian posterior (about 7; Stan-style adaptation of a dense mass
    # matrix over 150 warm-up steps took about 290 here).
    assert res.posterior_leapfrogs < 20, res.posterior_leapfrogs
    # Mean within 0.5 sigma: the Monte Carlo standard error of 200 correlated draws (an
    # effective sample size of 50 or more) is at most 0.14 sigma. Spread within 30 %.
    assert np.all(np.abs(draws.mean(0) - value) < 0.5 * std), (draws.mean(0), value, std)
    assert np.allclose(draws.std(0), std, rtol=0.3), (draws.std(0), std)
