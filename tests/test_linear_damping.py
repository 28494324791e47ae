"""The linear-damping effect against a closed form and its energy balance."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn as jd

INERTIA = np.array([1.0, 2.0, 3.0])


@pytest.mark.parametrize("scale", [1.0, 1e-4])  # the same motion in other units of time
def test_proportional_damping_is_torque_free_motion_slowed_down(scale):
    # c_i = k I_i: w(t) = exp(-k t) w_free(s), s = (1 - exp(-k t)) / k (closed form).
    k = 0.05 * scale
    scene = jd.Scene(jd.RigidBody(INERTIA), (jd.LinearDamping(k * INERTIA),))
    w0 = np.array([0.3, 1.0, 0.2]) * scale
    ts = jnp.linspace(0.0, 40.0 / scale, 81)
    traj = jd.simulate(scene, scene.state(omega=w0), ts[-1], ts=ts)
    s = (1 - np.exp(-k * np.asarray(ts))) / k
    expected = np.exp(-k * np.asarray(ts))[:, None] * np.asarray(
        jd.torque_free_omega(INERTIA, w0, jnp.asarray(s)))
    err = np.max(np.abs(np.asarray(traj.omega) - expected)) / np.max(np.abs(w0))
    assert err < 1e-6, err


def test_energy_lost_equals_the_dissipation():
    scene = jd.Scene(jd.RigidBody(INERTIA), (jd.LinearDamping([0.01, 0.2, 0.05]),))
    traj = jd.simulate(scene, scene.state(omega=[0.3, 1.0, 0.2]), 60.0,
                       ts=jnp.linspace(0.0, 60.0, 61))
    energy = np.asarray(traj.energy)
    total = energy + np.asarray(traj.ys["linear-damping.dissipated"])
    assert energy[-1] < 0.5 * energy[0]
    assert np.max(np.abs(total - total[0])) < 1e-7 * total[0]
    assert scene.conserved == ()


def test_from_a_scene_file(tmp_path):
    path = tmp_path / "damped.toml"
    path.write_text('body = "rigid-body"\nt1 = 20.0\n[parameters]\ninertia = [1.0, 2.0, 3.0]\n'
                    'omega0 = [0.3, 1.0, 0.2]\n[[effects]]\ntype = "linear-damping"\n'
                    "coefficients = 0.1\n")
    spec = jd.load_scene(str(path), {"linear-damping.coefficients": [0.1, 0.2, 0.3]})
    assert np.allclose(spec.scene.effects[0].coefficients, [0.1, 0.2, 0.3])
    with pytest.raises(jd.ParameterError, match=r"linear-damping.coefficients=-1: expected"):
        jd.load_scene(str(path), {"linear-damping.coefficients": -1.0})
