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


@pytest.fixture(scope="module")
def dumping():
    spec = jd.load_scene("wheels-with-dumping")
    traj = jd.simulate(spec.scene, spec.y0, spec.t1, ts=jnp.linspace(0.0, spec.t1, 401),
                       dense=True)
    return spec.scene, traj


def test_dumped_wheel_momentum_is_the_rods_angular_impulse(dumping):
    """The total (body plus wheels) inertial momentum changes only by the rods' torque:
    `H(t1) - H(0) = int R(q) tau dt`, the integral by Gauss-Legendre quadrature on the dense
    output, and the torque recomputed from the states (perpendicular to the field)."""
    scene, traj = dumping
    wheels, rods = scene.effects
    nodes, weights = np.polynomial.legendre.leggauss(8)
    edges = np.linspace(0.0, float(traj.t_final), 801)
    t = (edges[:-1, None] + 0.5 * np.diff(edges)[:, None] * (nodes + 1)).ravel()
    y = traj.evaluate(jnp.asarray(t))

    def inertial_torque(t, y):
        stored = y["wheels.momentum"] @ wheels.axes
        tau = rods.torque(t, y, {}, scene.body, stored=stored)
        b = rods.field(t, y)
        return jd.quat_rotate(y["quaternion"], tau), jnp.dot(tau, b) / (
            jnp.linalg.norm(tau) * jnp.linalg.norm(b) + 1e-300)

    tau, cos = jax.vmap(inertial_torque)(jnp.asarray(t), y)
    w = np.tile(weights, 800) * np.repeat(0.5 * np.diff(edges), 8)
    impulse = np.asarray(tau).T @ w
    h = np.asarray(traj.momentum_inertial)
    assert float(jnp.max(jnp.abs(cos))) < 1e-12
    assert np.linalg.norm(h[0] - h[-1]) > 0.9 * np.linalg.norm(h[0])  # nearly all dumped
    assert np.allclose(h[-1] - h[0], impulse, rtol=0, atol=1e-6 * np.linalg.norm(h[0]))


def test_dumping_drains_the_wheels_while_they_hold_the_attitude(dumping):
    scene, traj = dumping
    h = np.linalg.norm(np.asarray(traj.ys["wheels.momentum"]), axis=1)
    assert h[-1] < 1e-3 * h[0]
    # Held against the rods' torque: quaternion feedback balances a torque `tau` at an error
    # angle of about `2 |tau| / kp`, and `|tau| <= |m| |b|` with each rod at most 1 A m^2.
    angle = 2 * np.arcsin(np.linalg.norm(np.asarray(traj.ys["quaternion"])[:, 1:], axis=1))
    wheels, rods = scene.effects
    b_max = float(jnp.max(jnp.linalg.norm(jax.vmap(rods.field)(traj.ts, traj.ys), axis=-1)))
    bound = 2 * np.sqrt(3) * 1.0 * b_max / float(wheels.motor.kp)
    assert 0 < angle.max() < bound
    assert angle[-1] < 1e-3 * bound  # nothing left to push once the wheels are empty


def test_residual_dipole_identified_from_gyro_rates():
    """A rod's residual dipole (a disturbance) fitted from noisy gyro rates during B-dot
    detumbling: the estimate within 4 reported standard deviations of the truth, and the
    reported uncertainty of the size that the noise and record give (under 10 % here)."""
    truth = np.array([0.02, -0.01, 0.015])
    rods = jd.MagneticTorquers(altitude=500e3, inclination=0.9, gain=1.2e-4, max_dipole=0.2,
                               residual_dipole=truth)
    scene = jd.Scene(jd.RigidBody(INERTIA), (rods,))
    y0 = scene.state(omega=[0.05, -0.04, 0.06])
    ts = jnp.linspace(0.0, 2400.0, 121)
    sigma = 1e-4
    rates = jd.simulate(scene, y0, ts[-1], ts=ts).ys["omega"]
    noise = sigma * np.random.default_rng(3).standard_normal(rates.shape)
    guess = scene.replace({"magnetorquers.residual_dipole": jnp.zeros(3)})
    result = jd.fit(guess, ts, {"omega": rates + noise}, y0=y0, sigma={"omega": sigma},
                    parameters={"magnetorquers.residual_dipole": jd.Unconstrained()},
                    restarts=1, agree=1)
    estimate = np.asarray(result.values["magnetorquers.residual_dipole"])
    std = np.asarray(result.std["magnetorquers.residual_dipole"])
    assert result.converged
    assert np.all(np.abs(estimate - truth) < 4 * std)
    assert np.all(std < 0.1 * np.abs(truth))


def _averaged_bdot_matrix(inclination):
    """Closed form of the orbit average `<1 - b_hat b_hat^T>` for an axial dipole along a
    circular orbit at `inclination` to the magnetic equator (node on x; the averaged analysis
    of B-dot of Stickler & Alfriend 1976 and Avanzini & Giulietti 2012). With
    `x = sin^2 u`, `a = 3 sin^2 i`, `|b|^2 ~ 1 + a x`, and the averages over the argument of
    latitude `g0 = <1/(1 + a x)> = (1 + a)^(-1/2)`, `g1 = <x/(1 + a x)> = (1 - g0)/a`,
    `g2 = <x^2/(1 + a x)> = (1/2 - g1)/a`."""
    a = 3 * np.sin(inclination) ** 2
    g0 = 1 / np.sqrt(1 + a)
    g1 = (1 - g0) / a
    g2 = (0.5 - g1) / a
    b = np.zeros((3, 3))
    b[0, 0] = 3 * a * (g1 - g2)
    b[1, 1] = 3 * a * np.cos(inclination) ** 2 * g2
    b[2, 2] = a / 2 - 3 + 4 * g0
    b[1, 2] = b[2, 1] = 3 * np.sin(inclination) * np.cos(inclination) * (0.5 - 2 * g1)
    return np.eye(3) - b


@pytest.mark.parametrize("inclination", [0.3, 0.9, 1.4])
def test_averaged_bdot_matrix_closed_form_against_the_field(inclination):
    """The closed form against the library's IGRF dipole averaged numerically over an orbit
    inclined by `inclination` to the dipole's equator (the Earth held still)."""
    m = np.array(DIPOLE_NT)
    axis = m / np.linalg.norm(m)
    e1 = np.cross(axis, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)  # the orbit's node, on the magnetic equator
    e2 = np.cross(axis, e1)
    along = np.cos(inclination) * e2 + np.sin(inclination) * axis
    u = np.linspace(0.0, 2 * np.pi, 4001)[:-1]
    r_hat = np.cos(u)[:, None] * e1 + np.sin(u)[:, None] * along
    b = np.asarray(jax.vmap(lambda r: dipole_field(0.0, r, 6878137.0))(jnp.asarray(r_hat)))
    b_hat = b / np.linalg.norm(b, axis=1, keepdims=True)
    numeric = np.eye(3) - np.einsum("ki,kj->ij", b_hat, b_hat) / len(u)
    frame = np.stack([e1, e2, axis])  # the closed form's axes: node, 90 deg on, dipole axis
    closed = frame.T @ _averaged_bdot_matrix(inclination) @ frame
    assert np.allclose(numeric, closed, atol=1e-12)


def test_detumbling_time_constant_against_the_averaged_analysis():
    """The slowest B-dot time constant `tau = J / (k lambda_min)`, `lambda_min` the smallest
    eigenvalue of the closed-form averaged matrix at the orbit's magnetic inclination (an
    equatorial orbit: the dipole's tilt, 9.4 deg, whatever the Earth's rotation). A spherical
    body spinning about the orbit normal: its rate decays at `1/tau` within 1 % over twelve
    orbits (k chosen so that `tau` is 80 / (2 pi) orbits: slow against the orbit, where
    averaging holds)."""
    m = np.array(DIPOLE_NT)
    tilt = np.arccos(abs(m[2]) / np.linalg.norm(m))
    lam = np.linalg.eigvalsh(_averaged_bdot_matrix(tilt))[0]
    j = 0.05
    n = float(orbit_rate(500e3))
    k = j * n / (80 * lam)
    rods = jd.MagneticTorquers(altitude=500e3, inclination=0.0, gain=k)
    scene = jd.Scene(jd.RigidBody([j, j, j]), (rods,))
    ts = jnp.arange(13.0) * 2 * np.pi / n  # whole orbits: the ripple averages out
    traj = jd.simulate(scene, scene.state(omega=[0.0, 0.0, 0.01]), ts[-1], ts=ts)
    rate = np.linalg.norm(np.asarray(traj.ys["omega"]), axis=1)
    slope = np.polyfit(np.asarray(ts[2:]), np.log(rate[2:]), 1)[0]
    assert np.isclose(-1 / slope, j / (k * lam), rtol=0.01)
