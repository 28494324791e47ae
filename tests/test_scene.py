"""The scene protocol: only declared effects are traced, stored and integrated."""

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import COST_MARGIN, ROUNDOFF, compiled_flops, tol, tree_allclose

import jaxdyn as jd

INERTIA = jnp.array([1.0, 2.0, 3.0])
OMEGA = jnp.array([0.3, 1.2, -0.4])


CYCLIC = ((0, 1, 2), (1, 2, 0), (2, 0, 1))


def euler(t, w, inertia):
    """Euler's equations written by hand, component by component (the form that batches
    best): the baseline a scene must match."""
    w = [w[i] for i in range(3)]
    inv = [1 / inertia[i] for i in range(3)]
    return jnp.stack([(inertia[j] - inertia[k]) * inv[i] * (w[j] * w[k]) for i, j, k in CYCLIC])


def gyrostat(t, w, args):
    """The same with a rotor of constant momentum `hr`: `(hr_j w_k - hr_k w_j) / I_i` more."""
    inertia, hr = args
    w = [w[i] for i in range(3)]
    inv = [1 / inertia[i] for i in range(3)]
    return jnp.stack([(inertia[j] - inertia[k]) * inv[i] * (w[j] * w[k])
                      + (hr[j] * w[k] - hr[k] * w[j]) * inv[i] for i, j, k in CYCLIC])


def _solve(vector_field, y0, args):
    return dfx.diffeqsolve(
        dfx.ODETerm(vector_field), dfx.Tsit5(), 0.0, 10.0, None, y0, args=args,
        stepsize_controller=dfx.PIDController(rtol=1e-8, atol=1e-10), max_steps=1000,
    ).ys


def _states(n=5, seed=0):
    return np.random.default_rng(seed).normal(size=(n, 3))


def _solve_cost(vector_field, y0, args):
    """XLA's flop count of a whole adaptive solve of `vector_field`."""
    return compiled_flops(lambda y, a: _solve(vector_field, y, a), y0, args)


def test_torque_free_scene_costs_what_hand_written_euler_costs():
    scene = jd.Scene(jd.RigidBody(INERTIA))
    assert scene.state_shapes() == {"omega": (3,)}
    # The same vector field, value for value...
    for w in _states():
        y = scene.state(omega=w)
        assert tree_allclose(scene.vector_field(0.0, y)["omega"], euler(0.0, jnp.asarray(w),
                                                                         INERTIA),
                             rtol=tol(ROUNDOFF), atol=1e-15)
    # ...and the same compiled cost for a whole adaptive solve, within a margin that the
    # smallest extra term (a rotor, positive control) exceeds several times over.
    y = scene.state(omega=OMEGA)
    f_scene = _solve_cost(lambda t, y, s: s.vector_field(t, y), y, scene)
    f_hand = _solve_cost(euler, OMEGA, INERTIA)
    f_more = _solve_cost(gyrostat, OMEGA, (INERTIA, jnp.array([0.0, 0.5, 0.0])))
    assert abs(f_scene - f_hand) <= COST_MARGIN * f_hand
    assert f_more - f_hand > 3 * COST_MARGIN * f_hand


def test_an_effect_adds_only_its_own_terms_and_state():
    h = jnp.array([0.0, 0.5, 0.0])
    scene = jd.Scene(jd.RigidBody(INERTIA), (jd.Rotor(h),))
    assert scene.state_shapes() == {"omega": (3,)}  # a constant-momentum rotor has no state
    for w in _states(seed=1):
        y = scene.state(omega=w)
        assert tree_allclose(scene.vector_field(0.0, y)["omega"],
                             gyrostat(0.0, jnp.asarray(w), (INERTIA, h)),
                             rtol=tol(ROUNDOFF), atol=1e-15)
    # The rotor costs what its terms written by hand cost, no more.
    f_scene = _solve_cost(lambda t, y, s: s.vector_field(t, y), scene.state(omega=OMEGA), scene)
    f_hand = _solve_cost(gyrostat, OMEGA, (INERTIA, h))
    assert abs(f_scene - f_hand) <= COST_MARGIN * f_hand
    # An effect that needs attitude brings the quaternion and only that.
    gg = jd.Scene(jd.RigidBody(INERTIA), (jd.GravityGradient(0.001),))
    assert gg.state_shapes() == {"omega": (3,), "quaternion": (4,)}


def test_attitude_only_when_asked_or_needed():
    body = jd.RigidBody(INERTIA)
    assert not jd.Scene(body).attitude
    assert jd.Scene(body, attitude=True).attitude
    assert jd.Scene(body, (jd.ExternalTorque([0.0, 0.0, 1.0], frame="inertial"),)).attitude
    assert not jd.Scene(body, (jd.ExternalTorque([0.0, 0.0, 1.0]),)).attitude


def test_parameters_and_replace():
    scene = jd.Scene(jd.RigidBody(INERTIA), (jd.Rotor([0.0, 1.0, 0.0]),))
    assert set(scene.parameters()) == {"inertia", "rotor.momentum"}
    new = scene.replace({"rotor.momentum": [0.0, 2.0, 0.0]}, inertia=[1.0, 2.0, 2.5])
    assert np.allclose(new.parameters()["rotor.momentum"], [0.0, 2.0, 0.0])
    assert np.allclose(new.body.inertia, [1.0, 2.0, 2.5])
    with pytest.raises(jd.ParameterError, match="unknown parameter"):
        scene.replace(mass=1.0)


def test_vmap_over_parameters():
    scene = jd.Scene(jd.RigidBody(INERTIA))
    inertias = jnp.array([[1.0, 2.0, 3.0], [1.2, 2.0, 3.0], [1.0, 2.2, 3.0]])

    def final(inertia):
        s = scene.replace(inertia=inertia)
        return jd.simulate(s, s.state(omega=OMEGA), 2.0, rtol=1e-10, atol=1e-12).y_final["omega"]

    batched = jax.vmap(final)(inertias)
    for i, inertia in enumerate(inertias):
        exact = jd.torque_free_omega(inertia, OMEGA, 2.0)
        assert np.allclose(batched[i], exact, atol=1e-8)


def test_state_errors_name_the_variable():
    scene = jd.Scene(jd.RigidBody(INERTIA))
    with pytest.raises(jd.ParameterError, match="omega is required"):
        scene.state()
    with pytest.raises(jd.ParameterError, match="quaternion given"):
        scene.state(omega=OMEGA, quaternion=[1.0, 0, 0, 0])
    with pytest.raises(jd.ParameterError, match="expected shape"):
        scene.state(omega=[1.0, 2.0])
    with pytest.raises(jd.ParameterError, match="this scene integrates"):
        jd.simulate(scene, {"theta": 0.1}, 1.0)
    with pytest.raises(jd.ParameterError, match="cannot act on a falling-rod"):
        jd.Scene(jd.FallingRod(), (jd.Rotor([0.0, 0.0, 1.0]),))


def test_output_names_and_derived_outputs():
    scene = jd.Scene(jd.RigidBody(INERTIA), attitude=True)
    traj = jd.simulate(scene, scene.state(omega=OMEGA), 1.0, ts=jnp.linspace(0, 1, 5))
    for name in ("omega", "energy", "momentum", "momentum_inertial", "quaternion"):
        assert name in traj.output_names
        assert getattr(traj, name).shape[0] == 5
    with pytest.raises(AttributeError, match="derived outputs"):
        traj.normal_force


def test_derived_outputs_of_alternating_trajectories_are_their_own():
    # The last access is remembered (its names and program call): trajectories of one
    # structure read in turn, and one rebuilt with other states, each give their own outputs.
    # Independent route: the angular momentum I omega and the energy from the saved rates.
    trajs = []
    for inertia, omega in ((INERTIA, OMEGA), (INERTIA * 1.7, OMEGA[::-1]), (INERTIA, -OMEGA)):
        scene = jd.Scene(jd.RigidBody(inertia))
        trajs.append(jd.simulate(scene, scene.state(omega=omega), 2.0,
                                 ts=jnp.linspace(0, 2, 7)))
    for traj in trajs + trajs[::-1] + trajs:
        inertia = np.asarray(traj.scene.body.inertia)
        w = np.asarray(traj.ys["omega"])
        np.testing.assert_allclose(traj.angular_momentum, w * inertia, rtol=1e-14)
        np.testing.assert_allclose(traj.energy, 0.5 * np.sum(inertia * w**2, axis=1),
                                   rtol=1e-14)
    other = eqx.tree_at(lambda t: t.ys, trajs[0], {"omega": trajs[1].ys["omega"]})
    np.testing.assert_allclose(other.angular_momentum,
                               np.asarray(trajs[1].ys["omega"]) * np.asarray(INERTIA),
                               rtol=1e-14)
    # The same scene with another number of samples: another program (its own shapes).
    trajs[0].angular_momentum
    fewer = jd.simulate(trajs[0].scene, trajs[0].scene.state(omega=OMEGA), 2.0,
                        ts=jnp.linspace(0, 2, 4))
    np.testing.assert_allclose(fewer.angular_momentum,
                               np.asarray(fewer.ys["omega"]) * np.asarray(INERTIA), rtol=1e-14)
    # The last access's trajectory is not kept alive by that memory (its samples can be
    # large: a long run's, on a device).
    import gc
    import weakref

    samples = weakref.ref(fewer.ys["omega"])
    del fewer
    gc.collect()
    assert samples() is None


class _Gated(jd.AbstractEffect):
    """An effect whose checks depend on plain (non-static) Python fields."""
    kind = "gated-test"
    gain: jax.Array
    strict: bool
    frame: str

    def checks(self):
        found = [("gated.gain", self.gain, self.gain < 0, "must be >= 0")]
        if self.strict:
            found.append(("gated.gain", self.gain, self.gain > 1, "must be <= 1 when strict"))
        return found


def test_check_messages_are_those_of_each_scenes_values():
    # The messages of a scene's checks are kept per structure (`Scene.violation_messages`,
    # read by every ensemble call): arrays by shape and dtype, other fields by value, so a
    # plain field that adds a check gives its own messages, and a string field is a value.
    body = jd.RigidBody([1.0, 2.0, 2.5])
    for strict in (False, True, False):
        scene = jd.Scene(body, (_Gated(jnp.asarray(0.5), strict, "body"),))
        y = scene.state(omega=[0.1, 1.0, 0.1])
        flags, fresh = scene.violations(y)
        assert scene.violation_messages(y) == tuple(fresh)
        assert len(fresh) == flags.size == 4 + strict
