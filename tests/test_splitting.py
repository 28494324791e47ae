"""Splitting integrators: observed convergence order, invariants preserved to round-off, energy
error bounded for all time (against an explicit Runge-Kutta method, whose drift grows)."""

import diffrax as dfx
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn as jd

INERTIA = jnp.array([1.0, 2.0, 3.0])
OMEGA0 = jnp.array([0.3, 0.2, 1.0])


def _slope(dts, errors):
    return np.polyfit(np.log(dts), np.log(errors), 1)[0]


@pytest.mark.parametrize("order, dts", [(2, [0.1, 0.05, 0.025, 0.0125]),
                                        (4, [0.2, 0.1, 0.05, 0.025])])
def test_observed_convergence_order(order, dts):
    scene = jd.Scene(jd.RigidBody(INERTIA))
    exact = jd.torque_free_omega(INERTIA, OMEGA0, 10.0)
    errors = []
    for dt in dts:
        traj = jd.simulate(scene, scene.state(omega=OMEGA0), 10.0,
                           solver=jd.RotationSplitting(order), dt0=dt)
        errors.append(float(jnp.max(jnp.abs(traj.y_final["omega"] - exact))))
    assert abs(_slope(dts, errors) - order) < 0.2


def test_gyrostat_convergence_against_tight_runge_kutta():
    scene = jd.Scene(jd.RigidBody(INERTIA), (jd.Rotor([0.2, 0.5, -0.1]),), attitude=True)
    y0 = scene.state(omega=OMEGA0)
    ref = jd.simulate(scene, y0, 5.0, rtol=1e-13, atol=1e-14).y_final
    errors = []
    dts = [0.1, 0.05, 0.025]
    for dt in dts:
        y = jd.simulate(scene, y0, 5.0, solver=jd.RotationSplitting(4), dt0=dt).y_final
        errors.append(max(float(jnp.max(jnp.abs(y[k] - ref[k]))) for k in ref))
    assert abs(_slope(dts, errors) - 4) < 0.2


def _drift(solver, t1, dt, attitude=True):
    scene = jd.Scene(jd.RigidBody(INERTIA), attitude=attitude)
    ts = jnp.linspace(0.0, t1, 2001)
    traj = jd.simulate(scene, scene.state(omega=OMEGA0), t1, ts=ts, solver=solver, dt0=dt,
                       stepsize_controller=dfx.ConstantStepSize(), max_steps=int(t1 / dt) + 10)
    out = traj.outputs()
    energy = np.abs(np.asarray(out["energy"]) / float(out["energy"][0]) - 1)
    momentum = np.abs(np.asarray(out["momentum"]) / float(out["momentum"][0]) - 1)
    h = np.asarray(out["momentum_inertial"])
    inertial = np.linalg.norm(h - h[0], axis=1) / np.linalg.norm(h[0])
    early = np.asarray(ts) <= t1 / 10
    return {
        "energy_early": energy[early].max(), "energy_late": energy[~early].max(),
        "momentum": momentum.max(), "inertial": inertial.max(),
        "quaternion_norm": float(np.max(np.abs(np.asarray(out["quaternion_norm"]) - 1))),
    }


@pytest.mark.optimized  # (round-off over 2e5 steps of the code a user runs)
def test_invariants_over_a_long_horizon():
    split = _drift(jd.RotationSplitting(2), 1e4, 0.05)
    # |h| and the inertial H are preserved to round-off; the quaternion stays unit.
    assert split["momentum"] < 1e-13 and split["inertial"] < 1e-12
    assert split["quaternion_norm"] < 1e-12
    # Energy error bounded: no growth from [0, 1e3] to [1e3, 1e4].
    assert split["energy_late"] < 1.5 * split["energy_early"]
    # An explicit Runge-Kutta method at the same step drifts: its error keeps growing.
    rk = _drift(dfx.Tsit5(), 1e4, 0.5)
    assert rk["energy_late"] > 5 * rk["energy_early"]
    assert rk["momentum"] > 1e3 * split["momentum"]


def test_unsplittable_scene_is_refused():
    scene = jd.Scene(jd.RigidBody(INERTIA), (jd.ExternalTorque([0.0, 0.0, 0.1]),))
    with pytest.raises(jd.ParameterError, match="cannot use a splitting integrator"):
        jd.simulate(scene, scene.state(omega=OMEGA0), 1.0, solver=jd.RotationSplitting(),
                    dt0=0.1)
    rod = jd.Scene(jd.FallingRod())
    with pytest.raises(jd.ParameterError, match="has no rotation splitting"):
        jd.simulate(rod, rod.state(theta=0.1), 1.0, solver=jd.RotationSplitting(), dt0=0.1)
    with pytest.raises(jd.ParameterError, match="takes fixed steps: give dt0"):
        jd.simulate(jd.Scene(jd.RigidBody(INERTIA)), {"omega": OMEGA0}, 1.0,
                    solver=jd.RotationSplitting())
    with pytest.raises(jd.ParameterError, match="allowed are 2, 4"):
        jd.RotationSplitting(3)
