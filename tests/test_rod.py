"""The falling rod, checked through independent routes: a Lagrangian through `jax.grad`, the
rotational equation alone for the normal force, scipy quadrature for the fall time, and
closed-form scaling laws for gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import FINITE_DIFF, INTEGRATION, ROUNDOFF, central_difference, tol
from scipy.integrate import quad

import jaxdyn as jd

ROD = jd.FallingRod(length=1.3, mass=2.0, g=9.81)
SCENE = jd.Scene(ROD)
TIGHT = dict(rtol=1e-12, atol=1e-12)


def _lagrangian_acceleration(rod, theta, theta_dot):
    """theta_ddot from the Euler-Lagrange equation of L = T - V, differentiated by JAX."""
    m, L, g = rod.mass, rod.length, rod.g

    def lagrangian(q, qd):
        y_c_dot = -L / 2 * jnp.sin(q) * qd  # the CM moves only vertically
        return 0.5 * m * y_c_dot**2 + 0.5 * (m * L**2 / 12) * qd**2 - m * g * L / 2 * jnp.cos(q)

    dl_dq = jax.grad(lagrangian, 0)(theta, theta_dot)
    mass = jax.grad(jax.grad(lagrangian, 1), 1)(theta, theta_dot)
    mixed = jax.grad(jax.grad(lagrangian, 1), 0)(theta, theta_dot)
    return (dl_dq - mixed * theta_dot) / mass


def test_equation_of_motion_matches_lagrangian():
    rng = np.random.default_rng(0)
    thetas = rng.uniform(-np.pi / 2, np.pi / 2, 50)
    rates = rng.normal(0, 5, 50)
    for theta, rate in zip(thetas, rates):
        y = {"theta": jnp.asarray(theta), "theta_dot": jnp.asarray(rate)}
        got = SCENE.vector_field(0.0, y)["theta_dot"]
        want = _lagrangian_acceleration(ROD, jnp.asarray(theta), jnp.asarray(rate))
        assert np.isclose(got, want, rtol=tol(ROUNDOFF), atol=1e-12)


def test_normal_force_from_rotation_equation_alone():
    # H_dot = L about the CM: I_c theta_ddot = N (L/2) sin(theta), independent of F = m a_c.
    rng = np.random.default_rng(1)
    for theta, rate in zip(rng.uniform(0.1, 1.5, 20), rng.normal(0, 3, 20)):
        y = {"theta": jnp.asarray(theta), "theta_dot": jnp.asarray(rate)}
        out = SCENE.outputs(0.0, y)
        i_c = ROD.mass * ROD.length**2 / 12
        n_rot = i_c * out["theta_ddot"] / (ROD.length / 2 * jnp.sin(theta))
        assert np.isclose(out["normal_force"], n_rot, rtol=tol(ROUNDOFF))


def _quad_fall_time(rod, theta0):
    """Fall time from rest by scipy quadrature, theta = theta0 + (pi/2 - theta0) s^2."""
    L, g = float(rod.length), float(rod.g)
    a = np.pi / 2 - theta0

    def integrand(s):
        theta = theta0 + a * s**2
        rate2 = 12 * g * (np.cos(theta0) - np.cos(theta)) / (L * (1 + 3 * np.sin(theta) ** 2))
        return 2 * a * s / np.sqrt(rate2) if s > 0 else 2 * np.sqrt(a) / np.sqrt(
            12 * g * np.sin(theta0) / (L * (1 + 3 * np.sin(theta0) ** 2)))

    return quad(integrand, 0, 1, epsabs=0, epsrel=1e-12, limit=200)[0]


@pytest.mark.parametrize("theta0", [0.05, 0.3, 1.0])
def test_fall_time_quadrature_against_scipy(theta0):
    assert np.isclose(ROD.fall_time(theta0), _quad_fall_time(ROD, theta0), rtol=1e-11)


def _impact(theta0, theta_dot0=0.0, rod=ROD, **kw):
    scene = jd.Scene(rod)
    traj = jd.simulate(scene, scene.state(theta=theta0, theta_dot=theta_dot0), 20.0,
                       **{**TIGHT, **kw})
    return traj


@pytest.mark.parametrize(
    "theta0, theta_dot0",
    [(0.05, 0.0), (0.4, 0.0), (1e-4, 0.0), (0.2, 1.0), (0.2, -0.5), (0.2, -3.0), (-0.3, 0.2),
     (1.5, 0.0)],
)
def test_impact_time_and_rate_match_energy_integral(theta0, theta_dot0):
    # Cases: from rest (also nearly upright, where the slow start dominates the fall time; closer
    # still in test_hard_cases.py, with a pure relative tolerance); with a rate away from
    # upright; towards upright, turning back; towards upright with enough energy to pass over
    # and fall on the other side; falling to -x.
    traj = _impact(theta0, theta_dot0)
    assert bool(traj.event["flat"])
    expected = ROD.fall_time(theta0, theta_dot0)
    assert np.isclose(traj.t_final, expected, rtol=tol(INTEGRATION))
    rate = ROD.rate(np.pi / 2, theta0, theta_dot0)
    assert np.isclose(abs(float(traj.y_final["theta_dot"])), rate, rtol=tol(INTEGRATION))
    assert np.isclose(abs(float(traj.y_final["theta"])), np.pi / 2, rtol=1e-10)


def test_rate_along_trajectory_matches_energy_integral():
    ts = jnp.linspace(0.0, 0.5, 51)
    traj = _impact(0.3, 0.0, ts=ts)
    ok = np.asarray(traj.valid)
    theta = np.asarray(traj.ys["theta"])[ok]
    rate = np.asarray(traj.ys["theta_dot"])[ok]
    assert np.allclose(rate, ROD.rate(theta, 0.3), rtol=tol(INTEGRATION), atol=1e-9)
    energy = np.asarray(traj.energy)[ok]
    assert np.max(np.abs(energy / energy[0] - 1)) < tol(INTEGRATION)
    n_energy = ROD.normal_force_energy(theta, 0.3)
    assert np.allclose(np.asarray(traj.normal_force)[ok], n_energy, rtol=1e-7)


def _normal_force_over_weight(rod, theta, theta0):
    """N / (m g) of the rod falling from rest at theta0, written out in NumPy: the rate from
    the energy integral, theta_ddot from the equation of motion, then N = m g + m y_c_ddot with
    y_c = (L/2) cos(theta)."""
    L, g = float(rod.length), float(rod.g)
    s, c = np.sin(theta), np.cos(theta)
    rate2 = 12 * g * (np.cos(theta0) - c) / (L * (1 + 3 * s**2))
    acc = 3 * s * (2 * g - L * rate2 * c) / (L * (1 + 3 * s**2))
    return 1 - L / (2 * g) * (rate2 * c + acc * s)


@pytest.mark.parametrize("theta0", [1e-6, 0.05, 0.8])
def test_normal_force_stays_positive_and_ends_at_a_quarter_weight(theta0):
    # The tip never leaves the ice: N > 0 along the whole fall, in the simulation and in the
    # closed form; at the impact cos(theta) = 0 and theta_ddot = 3 g / (2 L), so N = m g / 4
    # whatever the rate.
    t_fall = float(ROD.fall_time(theta0))
    traj = _impact(theta0, ts=jnp.linspace(0.0, t_fall, 201))
    ok = np.asarray(traj.valid)
    n_sim = np.asarray(traj.normal_force_over_weight)[ok]
    theta = np.asarray(traj.theta)[ok]
    assert np.all(n_sim > 0)
    assert np.allclose(n_sim, _normal_force_over_weight(ROD, theta, theta0), rtol=0, atol=1e-8)
    grid = np.linspace(theta0, np.pi / 2, 20001)
    assert np.min(_normal_force_over_weight(ROD, grid, theta0)) > 0
    n_impact = float(traj.final_outputs()["normal_force_over_weight"][0])
    assert abs(n_impact - 0.25) < tol(INTEGRATION)


def test_rate_formula_keeps_digits_at_tiny_angles():
    # theta_dot^2 = (24 g/L) sin((t - t0)/2) sin((t + t0)/2) / (1 + 3 sin^2 t); for tiny angles
    # that is (6 g / L) (t^2 - t0^2) to leading order, where cos(t0) - cos(t) would round to 0.
    theta0, theta = 1e-12, 3e-12
    expected = np.sqrt(6 * 9.81 / 1.3 * (theta**2 - theta0**2))
    assert np.isclose(ROD.rate(theta, theta0), expected, rtol=1e-12)


def test_fall_time_grows_like_log_of_inverse_angle():
    # Small-angle linearisation: theta ~ theta0 cosh(sqrt(6 g / L) t), so
    # T(theta0) - T(theta0 / 10) -> -log(10) / sqrt(6 g / L) as theta0 -> 0.
    k = np.sqrt(6 * 9.81 / 1.3)
    t1, t2 = ROD.fall_time(1e-8), ROD.fall_time(1e-9)
    assert np.isclose(float(t2 - t1), np.log(10) / k, rtol=1e-7)
    # Closer to upright the law holds to the quadrature's own accuracy.
    t1, t2 = ROD.fall_time(4e-12), ROD.fall_time(1e-12)
    assert np.isclose(float(t2 - t1), np.log(4) / k, rtol=1e-8)
    assert np.isfinite(ROD.fall_time(1e-15))


def test_upright_at_rest_stays_up():
    scene = jd.Scene(ROD)
    traj = jd.simulate(scene, scene.state(theta=0.0), 5.0, ts=jnp.linspace(0, 5, 11))
    assert not bool(traj.event["flat"])
    assert float(traj.t_final) == 5.0
    assert np.all(np.asarray(traj.ys["theta"]) == 0.0)
    assert np.isinf(ROD.fall_time(0.0))
    assert traj.report()["impact_time"] is None


def test_gradient_of_impact_time_through_the_event():
    # Only the time scale sqrt(L / g) enters, and the mass cancels: T = sqrt(L / g) f(theta0), so
    # dT/dL = T / (2 L), dT/dg = -T / (2 g) and dT/dm = 0, independent of the quadrature.
    def impact(params):
        scene = SCENE.replace(**params)
        return jd.simulate(scene, scene.state(theta=0.2), 10.0, **TIGHT).t_final

    t_impact, grads = jax.value_and_grad(impact)(SCENE.parameters())
    t_impact = float(t_impact)
    assert np.isclose(grads["length"], t_impact / (2 * float(ROD.length)), rtol=1e-8)
    assert np.isclose(grads["g"], -t_impact / (2 * float(ROD.g)), rtol=1e-8)
    assert abs(float(grads["mass"])) < 1e-8 * t_impact / float(ROD.mass)

    def impact_theta(theta0):
        scene = jd.Scene(ROD)
        return jd.simulate(scene, scene.state(theta=theta0), 10.0, **TIGHT).t_final

    fd = central_difference(lambda x: ROD.fall_time(x[0]), np.array([0.2]), eps=1e-6)[0]
    assert np.isclose(jax.grad(impact_theta)(jnp.asarray(0.2)), fd, rtol=tol(FINITE_DIFF))


def test_fall_time_gradient_matches_finite_differences():
    g = jax.grad(lambda th: ROD.fall_time(th, 0.3))(0.2)
    fd = central_difference(lambda x: ROD.fall_time(x[0], 0.3), np.array([0.2]))[0]
    assert np.isclose(g, fd, rtol=tol(FINITE_DIFF))


def test_float32_runs_and_keeps_dtype():
    rod = jd.FallingRod(length=np.float32(1.0), mass=np.float32(1.0), g=np.float32(9.81))
    scene = jd.Scene(rod)
    y0 = scene.state(theta=np.float32(0.1))
    traj = jd.simulate(scene, y0, 5.0, rtol=1e-5, atol=1e-6)
    assert traj.y_final["theta"].dtype == jnp.float32
    assert traj.t_final.dtype == jnp.float32
    assert np.isclose(traj.t_final, rod.fall_time(np.float32(0.1)), rtol=1e-4)
