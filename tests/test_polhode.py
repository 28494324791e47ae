"""Polhodes, the separatrix and the period of the free body."""

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ROUNDOFF, tol
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

import jaxdyn as jd


@pytest.mark.parametrize("inertia", [[1.0, 2.0, 3.0], [3.0, 1.0, 2.5], [2.0, 2.6, 1.1]])
def test_separatrix_curves_lie_on_the_separatrix(inertia):
    i1, i2, i3 = np.sort(inertia)
    order = np.argsort(inertia)
    arcs = np.asarray(jd.separatrix_curves(jnp.asarray(inertia), momentum=2.0, num=51))
    assert arcs.shape == (4, 51, 3)
    h = arcs.reshape(-1, 3)[:, order]  # components in ascending-moment order
    assert np.allclose(np.linalg.norm(h, axis=1), 2.0, rtol=tol(ROUNDOFF))
    assert np.allclose(h[:, 0] ** 2 * (i2 / i1 - 1) + h[:, 2] ** 2 * (i2 / i3 - 1), 0.0,
                       atol=1e-12)
    # Each arc joins the two saddles on the intermediate axis.
    assert np.allclose(np.abs(arcs[:, [0, -1]][..., order[1]]), 2.0)
    # A state on the separatrix has zero separatrix condition.
    omega = arcs[0, 20] / np.asarray(inertia)
    assert abs(float(jd.separatrix_condition(jnp.asarray(inertia), omega))) < 1e-12


def test_separatrix_condition_keeps_digits_near_zero():
    inertia = jnp.array([1.0, 2.0, 3.0])
    eps = 1e-9
    value = jd.separatrix_condition(inertia, jnp.array([eps, 2.0, 2 * eps]))
    # sum_i I_i (I_i - I_2) w_i^2, evaluated by hand: the naive H^2 - 2 T I_2 cancels 18 digits.
    expected = 1 * (1 - 2) * eps**2 + 3 * (3 - 2) * (2 * eps) ** 2
    assert np.isclose(value, expected, rtol=1e-14)


@pytest.mark.parametrize("omega0", [[0.3, 0.2, 1.0], [1.0, 0.5, 0.1], [0.01, 2.0, 0.02]])
def test_polhode_is_closed_and_keeps_both_invariants(omega0):
    inertia = np.array([1.0, 2.0, 3.0])
    omega0 = np.array(omega0)
    curve = np.asarray(jd.polhode(jnp.asarray(inertia), jnp.asarray(omega0), num=301))
    energy = np.sum(inertia * curve**2, axis=1)
    momentum = np.sum((inertia * curve) ** 2, axis=1)
    assert np.allclose(energy, np.sum(inertia * omega0**2), rtol=1e-12)
    assert np.allclose(momentum, np.sum((inertia * omega0) ** 2), rtol=1e-12)
    assert np.allclose(curve[0], curve[-1], atol=1e-9)


def test_period_against_scipy_integration():
    inertia = np.array([1.0, 2.0, 3.0])
    for omega0 in ([0.3, 0.2, 1.0], [1.0, 0.5, 0.1]):
        period = float(jd.torque_free_period(jnp.asarray(inertia), jnp.asarray(omega0)))
        sol = solve_ivp(lambda t, w: np.cross(inertia * w, w) / inertia, (0, period), omega0,
                        rtol=1e-13, atol=1e-14, method="DOP853")
        assert np.allclose(sol.y[:, -1], omega0, atol=1e-9)


def test_period_diverges_logarithmically_at_the_separatrix():
    inertia = jnp.array([1.0, 2.0, 3.0])
    periods = [float(jd.torque_free_period(inertia, jnp.array([e, 2.0, e])))
               for e in (1e-4, 1e-6, 1e-8)]
    steps = np.diff(periods)
    # 4 K(m) / lam with K ~ log(4 / sqrt(1 - m)) / ... : equal steps per decade of distance.
    assert np.allclose(steps[0], steps[1], rtol=1e-3) and steps[0] > 0
    # Two saddles per period, each passed in sigma^-1 ln(1/eps) on the way in and as long on the
    # way out: P ~ (4 / sigma) ln(1/eps), sigma = W sqrt((I2 - I1)(I3 - I2) / (I1 I3)), W = 2.
    sigma = 2.0 * np.sqrt((2 - 1) * (3 - 2) / (1 * 3))
    assert np.isclose(steps[1], 4 / sigma * np.log(100), rtol=1e-8)
    assert np.isinf(jd.torque_free_period(inertia, jnp.array([0.0, 2.0, 0.0])))


@pytest.mark.parametrize("w1, w3", [(1e-1, 1e-1), (1e-3, 1e-3), (1e-5, 1e-5), (3e-3, 1e-3)])
def test_simulated_period_near_the_separatrix(w1, w3):
    # Near the separatrix (circling the major axis, or with w1 = 3 w3 the minor one) the period
    # of a simulation, from the zero crossings of omega_2 on its dense output, against the
    # closed form 4 K(m) / lambda. The period depends on H^2 - 2 T I_2 ~ eps^2, a small
    # difference of two invariants that the integrator keeps only to its tolerance: at
    # eps = 1e-5 the two agree to about 1e-6 (relative), at eps = 1e-3 to about 1e-10.
    inertia = jnp.array([1.0, 2.0, 3.0])
    omega0 = jnp.array([w1, 2.0, w3])
    period = float(jd.torque_free_period(inertia, omega0))
    scene = jd.Scene(jd.RigidBody(inertia))
    t1 = 1.3 * period  # three crossings
    traj = jd.simulate(scene, scene.state(omega=omega0), t1, rtol=1e-12, atol=1e-14,
                       dense=True, max_steps=100_000)

    def w2(t):
        return float(traj.evaluate(jnp.array([t]))["omega"][0, 1])

    grid = np.linspace(0.0, t1, 2001)
    values = np.asarray(traj.evaluate(jnp.asarray(grid))["omega"][:, 1])
    i = np.flatnonzero(np.sign(values[1:]) != np.sign(values[:-1]))
    assert len(i) >= 3
    first, third = (brentq(w2, grid[k], grid[k + 1], xtol=1e-14, rtol=1e-15) for k in i[[0, 2]])
    assert np.isclose(third - first, period, rtol=1e-5)
