"""Thrusters: each pulse's impulse delivered exactly (switches located as events), the
propellant used, rate damping settling in the dead band, and the limit cycle that the minimum
impulse bit sets. The reference is an independent replay of the sampled controller in numpy:
on a spherical body (`I = J 1`, no gyroscopic torque) the rates change at each sample by
exactly the commanded angular impulse over `J`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn as jd

LEVER = 0.5


def couples():
    """Six thrusters, one per direction of each body axis: thruster `2j` turns the body about
    `+e_j`, `2j + 1` about `-e_j`, each with lever `LEVER`."""
    positions, directions = [], []
    for j in range(3):
        for sign in (1.0, -1.0):
            r, d = np.zeros(3), np.zeros(3)
            r[(j + 1) % 3] = LEVER
            d[(j + 2) % 3] = sign
            positions.append(r)
            directions.append(d)
    return np.array(positions), np.array(directions)


def replay(w0, J, thrust, gain, deadband, period, min_impulse, v_e, samples):
    """The controller and a spherical body in numpy, independently of the library: the rates
    at each sample and the propellant used."""
    positions, directions = couples()
    arms = np.cross(positions, thrust * directions)
    w, fuel, out = np.array(w0, float), 0.0, []
    for _ in range(samples):
        out.append(w.copy())
        wanted = -gain * np.where(np.abs(w) > deadband, w, 0.0)
        share = period * np.maximum(arms @ wanted, 0) / np.sum(arms**2, axis=1)
        on = np.where(share > 0, np.maximum(share, min_impulse / thrust), 0.0)
        on = np.minimum(on, period)
        w = w + arms.T @ on / J
        fuel += thrust * on.sum() / v_e
    out.append(w.copy())
    return np.array(out), fuel


def run(w0, J=2.0, thrust=0.5, gain=1.0, deadband=0.005, period=0.5, min_impulse=0.01,
        v_e=2000.0, t1=40.0, inertia=None, attitude=False, dense=False, rtol=None):
    positions, directions = couples()
    thrusters = jd.Thrusters(positions, directions, thrust=thrust, exhaust_velocity=v_e,
                             min_impulse=min_impulse, gain=gain, deadband=deadband,
                             period=period, max_switches=1000)
    scene = jd.Scene(jd.RigidBody([J, J, J] if inertia is None else inertia), (thrusters,),
                     attitude=attitude)
    y0 = scene.state(omega=w0)
    ts = jnp.arange(0.0, t1 + period / 2, period)
    options = {} if rtol is None else {"rtol": rtol, "atol": 1e-3 * rtol}
    return jd.simulate(scene, y0, t1, ts=ts, dense=dense, **options), thrusters


@pytest.mark.parametrize("w0", [[0.3, -0.2, 0.1], [-0.05, 0.4, 0.02]])
def test_each_pulse_delivers_its_impulse_exactly(w0):
    """Rates at every sample and the propellant used equal the replay to round-off: the pulse
    ends are located, not smeared over a step (an error of one step's worth of thrust would be
    of order 1e-4 here)."""
    traj, thrusters = run(w0)
    samples = traj.ts.shape[0] - 1
    w_ref, fuel_ref = replay(w0, 2.0, 0.5, 1.0, 0.005, 0.5, 0.01, 2000.0, samples)
    assert np.allclose(traj.ys["omega"], w_ref, rtol=0, atol=1e-11)
    fuel = float(traj.y_final["thrusters.propellant"])
    assert fuel > 0
    assert abs(fuel - fuel_ref) <= 1e-10 * fuel_ref
    # Fuel used is thrust times on-time over the exhaust velocity.
    on = np.asarray(traj.y_final["thrusters.on_time"])
    assert np.isclose(fuel, float(np.sum(0.5 * on) / 2000.0), rtol=1e-13)


def test_rate_damping_settles_inside_the_dead_band():
    """Minimum impulse bit 0.01 N s: the smallest rate step `MIB L / J` = 0.0025 rad/s is
    below twice the dead band, so every rate ends within the band and stays (no firing)."""
    traj, _ = run([0.3, -0.2, 0.1], t1=60.0)
    w = np.asarray(traj.ys["omega"])
    assert np.all(np.abs(w[-20:]) <= 0.005)
    assert np.all(np.abs(w[0]) > 0.05)
    assert np.allclose(w[-20:], w[-1], atol=0, rtol=0)  # nothing fires once settled


@pytest.mark.parametrize("min_impulse", [0.05, 0.08])
def test_limit_cycle_amplitude_is_the_minimum_impulse_step(min_impulse):
    """A minimum impulse bit whose rate step `dw = MIB L / J` exceeds twice the dead band: the
    rate cannot land inside the band and jumps across it and back at every sample, a limit
    cycle of peak-to-peak amplitude `dw`, to round-off."""
    J, deadband = 2.0, 0.005
    step = min_impulse * LEVER / J
    assert step > 2 * deadband
    traj, _ = run([0.0, 0.0, 0.0314], J=J, gain=0.05, deadband=deadband,
                  min_impulse=min_impulse, t1=40.0)
    wz = np.asarray(traj.ys["omega"][:, 2])
    tail = wz[-20:]
    assert np.isclose(tail.max() - tail.min(), step, rtol=1e-10)
    assert np.all(np.abs(np.diff(tail)) > 0.99 * step)  # a jump at every sample
    assert np.all(np.abs(tail) > deadband)


def test_inertial_momentum_changes_by_the_thruster_impulses():
    """On a body with three different moments (gyroscopic coupling, the body turning during
    the pulses): between pulses the inertial angular momentum is constant; over the run it
    changes by the thruster angular impulses `sum int R(q) a_i dt`, integrated here by
    Gauss-Legendre quadrature over each pulse on the dense output. The agreement is that of
    the dense output's 4th-order interpolant of the attitude (a few 1e-8 here, with steps of
    0.1 s), not of the steps (1e-12); the exact check is the spherical body's above."""
    traj, thrusters = run([0.2, -0.15, 0.3], inertia=[1.5, 2.0, 2.6], attitude=True,
                          dense=True, t1=20.0, rtol=1e-12)
    arms = np.asarray(thrusters.arms)
    nodes, weights = np.polynomial.legendre.leggauss(12)
    h0 = np.asarray(traj.momentum_inertial[0])
    impulse = np.zeros(3)
    starts = np.asarray(traj.ts[:-1])
    on = []
    for w in traj.ys["omega"][:-1]:  # each sample's pulses, from the rates at the sample
        on.append(np.asarray(thrusters.on_times(w)))
    for t_s, pulses in zip(starts, on):
        for i, length in enumerate(pulses):
            if length <= 0:
                continue
            t = t_s + 0.5 * length * (nodes + 1)
            q = traj.evaluate(jnp.asarray(t))["quaternion"]
            r = jax.vmap(jd.quat_to_dcm)(q)
            impulse += 0.5 * length * np.einsum("k,kij,j->i", weights, np.asarray(r), arms[i])
    h1 = np.asarray(traj.momentum_inertial[-1])
    assert np.linalg.norm(impulse) > 0.1 * np.linalg.norm(h0)
    assert np.allclose(h1 - h0, impulse, rtol=0, atol=2e-7 * np.linalg.norm(h0))
    assert sum(p.sum() > 0 for p in on) > 5


def test_thrusters_from_a_scene_file_and_the_command(tmp_path):
    spec = jd.load_scene("thruster-despin")
    scene = spec.scene
    assert scene.max_switches > 0
    traj = jd.simulate(scene, spec.y0, spec.t1)
    w_end = np.abs(np.asarray(traj.y_final["omega"]))
    assert np.all(w_end <= float(scene.effects[0].deadband) + 1e-12)
    assert float(traj.y_final["thrusters.propellant"]) > 0


def test_bad_thruster_inputs_name_the_field():
    positions, directions = couples()
    with pytest.raises(jd.ParameterError, match="thrusters.directions"):
        jd.Thrusters(positions, directions[:4], thrust=1.0)
    with pytest.raises(jd.ParameterError, match="thrusters.thrust"):
        jd.Thrusters(positions, directions, thrust=-1.0)
    with pytest.raises(jd.ParameterError, match="thrusters.max_switches"):
        jd.Thrusters(positions, directions, thrust=1.0, max_switches=2.5)
    with pytest.raises(jd.ParameterError, match="thrusters.control"):
        jd.Thrusters(positions, directions, thrust=1.0, control="bang")


def test_too_many_switches_is_reported():
    positions, directions = couples()
    thrusters = jd.Thrusters(positions, directions, thrust=0.5, gain=1.0, period=0.5,
                             max_switches=10)
    scene = jd.Scene(jd.RigidBody([2.0, 2.0, 2.0]), (thrusters,))
    with pytest.raises(jd.SimulationError, match="max_switches"):
        jd.simulate(scene, scene.state(omega=[0.3, 0.2, 0.1]), 30.0)


def test_thrusters_in_an_ensemble_match_single_runs():
    """Thruster scenes run in ensembles (`mode="vmap"`: each trajectory locates its own
    switches): the propellant each member uses equals its single run's."""
    positions, directions = couples()
    thrusters = jd.Thrusters(positions, directions, thrust=0.5, min_impulse=0.01, gain=1.0,
                             deadband=0.005, period=0.5, max_switches=400)
    scene = jd.Scene(jd.RigidBody([2.0, 2.0, 2.0]), (thrusters,))
    w0 = np.array([[0.3, -0.2, 0.1], [0.05, 0.1, -0.2], [0.0, 0.0, 0.004]])
    states = [scene.state(omega=w) for w in w0]
    y0 = {k: np.stack([y[k] for y in states]) for k in states[0]}
    with pytest.raises(jd.ParameterError, match="thrusters"):
        jd.ensemble(scene, y0, 20.0, mode="adaptive")
    runs = jd.ensemble(scene, y0, 20.0, mode="vmap",
                       observe=lambda traj: {"fuel": traj.y_final["thrusters.propellant"]})
    single = [float(jd.simulate(scene, scene.state(omega=w), 20.0)
                    .y_final["thrusters.propellant"]) for w in w0]
    assert np.allclose(runs.values["fuel"], single, rtol=1e-12, atol=0)
    assert single[2] == 0.0 and single[0] > 0  # inside the dead band nothing fires
