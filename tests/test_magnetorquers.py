"""Magnetic torque rods: the IGRF dipole field against the gradient of its potential (an
independent route), torque perpendicular to the field, B-dot removing energy at the rate the
analysis gives, and a tumbling small satellite detumbled below the orbit rate."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn as jd
from jaxdyn._orbit import DIPOLE_NT, IGRF_RADIUS, dipole_field, orbit_direction, orbit_rate

INERTIA = [0.03, 0.04, 0.05]


def _potential(r):
    """IGRF degree-1 potential (T m): V = a (a/r)^2 (g10 cos th + (g11 cos ph + h11 sin ph)
    sin th), in the Earth-fixed frame."""
    g11, h11, g10 = (c * 1e-9 for c in DIPOLE_NT)
    rho = jnp.linalg.norm(r)
    cos_th = r[2] / rho
    sin_th = jnp.sqrt(r[0] ** 2 + r[1] ** 2) / rho
    ph = jnp.arctan2(r[1], r[0])
    return IGRF_RADIUS * (IGRF_RADIUS / rho) ** 2 * (
        g10 * cos_th + (g11 * jnp.cos(ph) + h11 * jnp.sin(ph)) * sin_th)


@pytest.mark.parametrize("direction", [[1.0, 0.2, 0.3], [-0.3, 0.8, -0.5], [0.1, -0.2, 0.97]])
def test_dipole_field_is_minus_the_gradient_of_the_igrf_potential(direction):
    r_hat = jnp.asarray(direction) / jnp.linalg.norm(jnp.asarray(direction))
    radius = 6878137.0
    b = dipole_field(0.0, r_hat, radius, earth_angle=0.0)
    expected = -jax.grad(_potential)(radius * r_hat)
    assert np.allclose(b, expected, rtol=1e-12, atol=1e-18)
    # Order of magnitude at 500 km: tens of microtesla.
    assert 1e-5 < float(jnp.linalg.norm(b)) < 6e-5


def test_orbit_shared_with_gravity_gradient():
    n, phase = 0.0011, 0.4
    t = jnp.linspace(0.0, 6000.0, 7)
    r = jax.vmap(lambda s: orbit_direction(s, n, phase))(t)
    assert np.allclose(r, np.stack([np.cos(n * t + phase), np.sin(n * t + phase),
                                    0 * t], axis=-1), atol=1e-15)
    r = jax.vmap(lambda s: orbit_direction(s, n, phase, 0.9, 1.3))(t)
    normal = np.array([np.sin(1.3) * np.sin(0.9), -np.cos(1.3) * np.sin(0.9), np.cos(0.9)])
    assert np.allclose(r @ normal, 0.0, atol=1e-15)  # in the inclined orbit's plane
    assert np.isclose(float(orbit_rate(500e3)), 2 * np.pi / 5677.0, rtol=2e-3)  # 94.6 min


@pytest.fixture(scope="module")
def detumble():
    rods = jd.MagneticTorquers(altitude=500e3, inclination=0.9, gain=1.2e-4, max_dipole=0.2)
    scene = jd.Scene(jd.RigidBody(INERTIA), (rods,))
    y0 = scene.state(omega=[0.10, -0.08, 0.12])
    t1 = 3 * 2 * np.pi / float(rods.orbit_rate)
    traj = jd.simulate(scene, y0, t1, ts=jnp.linspace(0.0, t1, 3001))
    return rods, scene, traj


def test_torque_is_perpendicular_to_the_field_at_every_sample(detumble):
    rods, scene, traj = detumble
    own = {}
    tau = jax.vmap(lambda t, y: rods.torque(t, y, own, scene.body))(traj.ts, traj.ys)
    b = jax.vmap(rods.field)(traj.ts, traj.ys)
    cos = jnp.sum(tau * b, axis=-1) / (jnp.linalg.norm(tau, axis=-1)
                                       * jnp.linalg.norm(b, axis=-1) + 1e-300)
    assert float(jnp.max(jnp.abs(cos))) < 1e-12


def test_bdot_never_increases_the_kinetic_energy(detumble):
    rods, scene, traj = detumble
    energy = np.asarray(traj.kinetic_energy)
    assert np.all(np.diff(energy) <= 1e-15 * energy[0])
    # dT/dt = w . tau = -k |w x b_hat|^2 where no rod saturates (the analysis).
    w = traj.ys["omega"]
    tau = jax.vmap(lambda t, y: rods.torque(t, y, {}, scene.body))(traj.ts, traj.ys)
    b = jax.vmap(rods.field)(traj.ts, traj.ys)
    b_hat = b / jnp.linalg.norm(b, axis=-1, keepdims=True)
    m = jax.vmap(rods.dipole)(traj.ts, traj.ys)
    free = np.asarray(jnp.all(jnp.abs(m) < 0.2, axis=-1))
    rate = np.asarray(jnp.sum(w * tau, axis=-1))
    expected = -1.2e-4 * np.asarray(jnp.sum(jnp.cross(w, b_hat) ** 2, axis=-1))
    assert free.sum() > 100
    assert np.allclose(rate[free], expected[free], rtol=1e-10, atol=1e-30)
    assert np.all(rate <= 1e-30)  # saturated samples too


def test_a_tumbling_satellite_is_detumbled_below_the_orbit_rate(detumble):
    rods, scene, traj = detumble
    rates = np.linalg.norm(np.asarray(traj.omega), axis=-1)
    assert rates[0] > 50 * float(rods.orbit_rate)
    assert rates[-1] < float(rods.orbit_rate)


def test_scene_file_and_bad_input(tmp_path):
    spec = jd.load_scene("bdot-detumble")
    assert spec.scene.attitude and spec.scene.labels == ("magnetorquers",)
    with pytest.raises(jd.ParameterError, match=r"magnetorquers.control='pd': expected one of"):
        jd.load_scene("bdot-detumble", {"magnetorquers.control": "pd"})
    with pytest.raises(jd.ParameterError, match=r"magnetorquers.altitude=-1: expected"):
        jd.load_scene("bdot-detumble", {"magnetorquers.altitude": -1.0})


def test_bdot_decay_matches_the_averaged_analysis():
    """For a spherical body the inertial rates obey the linear law
    `dw/dt = -(k/J) (1 - b_hat b_hat^T) w`, b_hat the field direction along the orbit. When the
    damping is slow against the orbit (k/J = n/20), averaging (the first Magnus term) predicts
    `w(T) = expm(-(k/J) int_0^T (1 - b_hat b_hat^T) dt) w0`: the decay of each direction at the
    rate that the field's geometry allows. The simulation, with attitude, agrees to 1.3 %
    (0.3 % at k/J = n/40: the error falls as (k/(J n))^2, as the next Magnus term does)."""
    from scipy.linalg import expm

    j = 0.05
    rods = jd.MagneticTorquers(altitude=500e3, inclination=0.9, gain=1.0)
    n = float(rods.orbit_rate)
    k = 0.05 * n * j
    rods = jd.MagneticTorquers(altitude=500e3, inclination=0.9, gain=k)
    scene = jd.Scene(jd.RigidBody([j, j, j]), (rods,))
    w0 = np.array([0.01, -0.02, 0.015])
    t1 = 10 * 2 * np.pi / n
    traj = jd.simulate(scene, scene.state(omega=w0), t1)
    w_end = np.asarray(traj.dcm[-1]) @ np.asarray(traj.y_final["omega"])  # inertial frame
    ts = np.linspace(0.0, t1, 40001)
    b = np.asarray(jax.vmap(rods.field_inertial)(jnp.asarray(ts)))
    b_hat = b / np.linalg.norm(b, axis=-1, keepdims=True)
    integrand = np.eye(3) - b_hat[:, :, None] * b_hat[:, None, :]
    integral = np.trapezoid(integrand, ts, axis=0)
    predicted = expm(-(k / j) * integral) @ w0
    assert np.linalg.norm(w_end) < 0.3 * np.linalg.norm(w0)  # it did decay
    assert np.linalg.norm(w_end - predicted) < 0.03 * np.linalg.norm(predicted)
