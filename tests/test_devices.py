"""Momentum-exchange devices: conservation laws, the motor-work balance, dissipation and the
major-axis rule, stabilisation by a rotor, detumbling and attitude tracking with limits."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import INTEGRATION, tol
from test_cli import run_json

import jaxdyn as jd

TIGHT = dict(rtol=1e-12, atol=1e-13)
INERTIA = [1.0, 2.0, 3.0]


def _own(traj, label="wheels"):
    return {k[len(label) + 1:]: v for k, v in traj.ys.items() if k.startswith(label + ".")}


def test_motor_work_balances_energy_and_momentum_is_conserved():
    motor = lambda t, y, wheels: jnp.stack([0.05 * jnp.sin(t), 0.02 * jnp.cos(2 * t)])  # noqa: E731
    wheels = jd.Wheels(axes=[[0.0, 1.0, 0.0], [1.0, 0.0, 1.0]], inertia=[0.1, 0.05], motor=motor)
    scene = jd.Scene(jd.RigidBody(INERTIA), (wheels,), attitude=True)
    assert scene.conserved == ("momentum", "momentum_inertial")
    y0 = scene.state(omega=[0.01, 1.0, 0.02], **{"wheels.speed": [5.0, -2.0]})
    traj = jd.simulate(scene, y0, 20.0, ts=jnp.linspace(0, 20, 201), **TIGHT)
    energy = np.asarray(traj.energy)
    work = np.asarray(traj.ys["wheels.work"])
    assert np.max(np.abs(energy - energy[0] - work)) < tol(INTEGRATION) * energy[0]
    assert np.max(np.abs(work)) > 1e-3  # the motors did work
    report = traj.report()
    assert report["momentum_rel_error"] < tol(INTEGRATION)
    assert report["momentum_inertial_rel_error"] < tol(INTEGRATION)


def test_initial_wheel_speed_sets_the_absolute_momentum():
    wheels = jd.Wheels(axes=[[0.0, 0.0, 2.0]], inertia=[0.1])  # axes are normalised
    scene = jd.Scene(jd.RigidBody(INERTIA), (wheels,))
    y0 = scene.state(omega=[0.0, 0.0, 1.5], **{"wheels.speed": 10.0})
    assert np.allclose(y0["wheels.momentum"], 0.1 * (10.0 + 1.5))
    out = scene.outputs(0.0, y0)
    assert np.allclose(out["angular_momentum"], [0.0, 0.0, 3 * 1.5 + 0.1 * 11.5])
    # Concrete values are combined on the host; traced ones (under `jit`, `vmap`, `grad`) by
    # JAX, to the same momentum, and its derivative is the wheel's inertia along the axis.
    momentum = lambda s: scene.state(omega=[0.0, 0.0, 1.5], **{"wheels.speed": s})[  # noqa: E731
        "wheels.momentum"]
    assert isinstance(y0["wheels.momentum"], jax.Array)
    np.testing.assert_allclose(jax.jit(momentum)(10.0), y0["wheels.momentum"], rtol=1e-15)
    np.testing.assert_allclose(jax.vmap(momentum)(jnp.array([10.0, 0.0]))[:, 0],
                               [1.15, 0.15], rtol=1e-15)
    assert float(jax.grad(lambda s: momentum(s)[0])(10.0)) == pytest.approx(0.1, rel=1e-15)


def test_free_wheel_is_a_gyrostat():
    # A wheel with no motor and no damping keeps h constant: the constant-momentum rotor.
    wheels = jd.Wheels(axes=[[0.0, 1.0, 0.0]], inertia=[0.1])
    scene = jd.Scene(jd.RigidBody(INERTIA), (wheels,))
    assert scene.conserved == ("energy", "momentum")
    y0 = scene.state(omega=[0.1, 1.0, 0.2], **{"wheels.speed": 20.0})
    h = float(y0["wheels.momentum"][0])
    gyro = jd.Scene(jd.RigidBody(INERTIA), (jd.Rotor([0.0, h, 0.0]),))
    a = jd.simulate(scene, y0, 10.0, **TIGHT).y_final["omega"]
    b = jd.simulate(gyro, gyro.state(omega=[0.1, 1.0, 0.2]), 10.0, **TIGHT).y_final["omega"]
    assert np.allclose(a, b, atol=1e-10)


def test_dual_spinner_stabilises_the_intermediate_axis():
    def run(speed):
        wheels = jd.Wheels(axes=[[0.0, 1.0, 0.0]], inertia=[0.1])
        scene = jd.Scene(jd.RigidBody(INERTIA), (wheels,))
        y0 = scene.state(omega=[1e-3, 2.0, 1e-3], **{"wheels.speed": speed})
        traj = jd.simulate(scene, y0, 60.0, ts=jnp.linspace(0, 60, 601), **TIGHT)
        return np.min(np.asarray(traj.omega)[:, 1])

    # Rotor momentum h = J (Omega + w2): stable when h > (I3 - I2) w2 = 2, i.e. Omega > 18.
    assert run(30.0) > 1.99
    assert run(5.0) < 0.0  # flips


def test_spin_up_of_a_dual_spinner_exchanges_momentum():
    # A motor spins the rotor up about the body's major axis: the body spins down, |H| fixed.
    wheels = jd.Wheels(axes=[[0.0, 0.0, 1.0]], inertia=[0.2], motor=[0.1])
    scene = jd.Scene(jd.RigidBody(INERTIA), (wheels,))
    y0 = scene.state(omega=[0.0, 0.0, 1.0])
    traj = jd.simulate(scene, y0, 10.0, **TIGHT)
    # Axial spin: I3 w3 + h = const with h = h0 + u t.
    assert np.isclose(traj.y_final["omega"][2], 1.0 - 0.1 * 10.0 / 3.0, rtol=1e-10)


def test_ring_damper_dissipates_energy_and_obeys_the_major_axis_rule():
    damper = jd.Wheels(axes=[[1.0, 0.0, 1.0]], inertia=[0.05], damping=[0.02])
    scene = jd.Scene(jd.RigidBody(INERTIA), (damper,))
    assert scene.conserved == ("momentum",)
    y0 = scene.state(omega=[2.0, 0.05, 0.05])  # about the minor axis
    traj = jd.simulate(scene, y0, 4000.0, ts=jnp.linspace(0, 4000, 801), rtol=1e-10,
                       atol=1e-12, max_steps=1_000_000)
    energy = np.asarray(traj.energy)
    assert np.all(np.diff(energy) < 0)  # kinetic energy decreases monotonically
    dissipated = np.asarray(traj.ys["wheels.dissipated"])
    assert np.max(np.abs(energy + dissipated - energy[0])) < 1e-8 * energy[0]
    assert traj.report()["momentum_rel_error"] < 1e-8
    # The end state: the whole (body + fluid) rotating rigidly about the axis of largest inertia,
    # with the least energy compatible with |H|: T = H^2 / (2 I_max).
    g = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    total = np.diag(INERTIA) + 0.05 * np.outer(g, g)
    eigvals, eigvecs = np.linalg.eigh(total)
    h = np.asarray(traj.angular_momentum)[-1]
    assert np.isclose(energy[-1], np.dot(h, h) / (2 * eigvals[-1]), rtol=1e-4)
    axis = eigvecs[:, -1]
    assert abs(np.dot(h, axis)) / np.linalg.norm(h) > 1 - 1e-5


def test_rate_damping_detumbles_within_limits():
    wheels = jd.Wheels(axes=np.eye(3), inertia=[0.05] * 3, motor=jd.RateDamping(0.5),
                       max_torque=[0.02] * 3, max_speed=[600.0] * 3)
    scene = jd.Scene(jd.RigidBody([10.0, 12.0, 15.0]), (wheels,), attitude=True)
    traj = jd.simulate(scene, scene.state(omega=[0.05, -0.03, 0.04]), 800.0,
                       ts=jnp.linspace(0, 800, 401), **TIGHT)
    assert np.linalg.norm(traj.omega[300]) < 1e-8  # at t = 600 s
    assert np.linalg.norm(traj.y_final["omega"]) < 1e-9
    u = jax.vmap(lambda t, y: wheels.motor_torque(t, y, _own_state(y)))(traj.ts, traj.ys)
    assert np.max(np.abs(u)) <= 0.02 + 1e-15
    assert np.isclose(np.max(np.abs(u)), 0.02)  # the limit was active
    assert traj.report()["momentum_inertial_rel_error"] < 1e-9


def _own_state(y, label="wheels"):
    return {k[len(label) + 1:]: v for k, v in y.items() if k.startswith(label + ".")}


def test_wheel_speed_limit_holds():
    # Detumbling a fast body saturates the wheels: the motors stop pushing at the limit.
    wheels = jd.Wheels(axes=np.eye(3), inertia=[0.05] * 3, motor=jd.RateDamping(5.0),
                       max_speed=[100.0] * 3)
    scene = jd.Scene(jd.RigidBody([10.0, 12.0, 15.0]), (wheels,))
    traj = jd.simulate(scene, scene.state(omega=[1.0, -0.5, 0.8]), 50.0,
                       ts=jnp.linspace(0, 50, 501), rtol=1e-10, atol=1e-12,
                       max_steps=1_000_000)
    speeds = jax.vmap(lambda y: wheels.speed(y, _own_state(y)))(traj.ys)
    # The motors stop at the limit; the body's own rotation (Omega = h / J - g . w) can still
    # move the relative speed a little past it.
    assert np.max(np.abs(speeds)) < 100.0 * 1.01
    assert np.max(np.abs(speeds)) > 99.0  # saturated
    assert np.linalg.norm(traj.y_final["omega"]) > 0.1  # so the body keeps some rate


def test_attitude_tracking_reaches_the_target():
    target = jd.quat_from_axis_angle(jnp.array([0.3, -0.2, 1.0]), 1.2)
    law = jd.AttitudeTracking(target, kp=0.5, kd=3.0)
    wheels = jd.Wheels(axes=np.eye(3), inertia=[0.05] * 3, motor=law, max_torque=[0.1] * 3)
    scene = jd.Scene(jd.RigidBody([10.0, 12.0, 15.0]), (wheels,), attitude=True)
    traj = jd.simulate(scene, scene.state(omega=[0.01, 0.0, -0.01]), 300.0, **TIGHT)
    q = traj.y_final["quaternion"]
    assert 1 - abs(float(jnp.dot(q, target))) < 1e-9
    # The error angle itself, 2 atan2(|dq_vec|, |dq_0|) with dq = target* (x) q (the arccos of
    # |dq_0| would read round-off in |q| as an angle).
    dq = jd.quat_multiply(jd.quat_conjugate(target), q)
    assert 2 * np.arctan2(np.linalg.norm(dq[1:]), abs(float(dq[0]))) < 1e-9
    assert np.linalg.norm(traj.y_final["omega"]) < 1e-8


def test_attitude_tracking_needs_attitude():
    law = jd.AttitudeTracking([1.0, 0.0, 0.0, 0.0], kp=1.0, kd=1.0)
    wheels = jd.Wheels(axes=np.eye(3), inertia=[0.05] * 3, motor=law)
    scene = jd.Scene(jd.RigidBody([10.0, 12.0, 15.0]), (wheels,))
    with pytest.raises(jd.ParameterError, match="needs the attitude"):
        jd.simulate(scene, scene.state(omega=[0.0, 0.0, 0.1]), 1.0)


def test_control_gains_are_differentiable():
    def final_rate(gain):
        wheels = jd.Wheels(axes=np.eye(3), inertia=[0.05] * 3, motor=jd.RateDamping(gain))
        scene = jd.Scene(jd.RigidBody([10.0, 12.0, 15.0]), (wheels,))
        y = jd.simulate(scene, scene.state(omega=[0.05, -0.03, 0.04]), 20.0, **TIGHT).y_final
        return jnp.sum(y["omega"] ** 2)

    g = jax.grad(final_rate)(0.5)
    fd = (final_rate(0.5 + 1e-5) - final_rate(0.5 - 1e-5)) / 2e-5
    assert np.isclose(g, fd, rtol=1e-5)


def test_implicit_solver_for_a_stiff_damper():
    damper = jd.Wheels(axes=[[1.0, 0.0, 0.0]], inertia=[0.001], damping=[10.0])
    scene = jd.Scene(jd.RigidBody(INERTIA), (damper,))
    traj = jd.simulate(scene, scene.state(omega=[0.5, 1.0, 0.2], **{"wheels.speed": 3.0}), 5.0,
                       solver=dfx.Kvaerno5(), rtol=1e-8, atol=1e-10)
    # The damping time J / c = 1e-4 s is stiff for an explicit solver; the fluid co-rotates,
    # lagging the body's changing rate by about (J / c) d(g . w)/dt ~ 1e-5 rad/s.
    speed = damper.speed(traj.y_final, _own_state(traj.y_final))
    assert abs(float(speed[0])) < 1e-4
    assert int(traj.stats["num_steps"]) < 5000  # explicit: about 5 s / 3e-4 s > 15000 steps


@pytest.mark.parametrize("scene", ["dual-spinner", "reaction-wheels", "explorer-1"])
def test_builtin_device_scenes(capsys, scene):
    out = run_json(capsys, "run", scene)
    assert out["momentum_rel_error"] < 1e-8


def test_bad_device_input():
    with pytest.raises(jd.ParameterError, match=r"wheels.axes has shape \(2, 2\)"):
        jd.Wheels(axes=[[1.0, 0.0], [0.0, 1.0]], inertia=[1.0, 1.0])
    with pytest.raises(jd.ParameterError, match="wheels.inertia=.*must be positive"):
        jd.Wheels(axes=np.eye(3), inertia=[0.1, -0.1, 0.1])
    with pytest.raises(jd.ParameterError, match="wheels.damping=.*non-negative"):
        jd.Wheels(axes=[[1.0, 0.0, 0.0]], inertia=[0.1], damping=[-1.0])
    with pytest.raises(jd.ParameterError, match="wheels.speed has shape"):
        jd.Scene(jd.RigidBody(INERTIA), (jd.Wheels(axes=np.eye(3), inertia=[0.1] * 3),)).state(
            omega=[0.0, 0.0, 1.0], **{"wheels.speed": [1.0, 2.0]})
