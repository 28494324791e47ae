"""One enumeration of outcomes (`jd.Outcome`): every outcome, produced on purpose, is labelled
the same by `simulate` and by every ensemble mode (issue 18)."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn as jd
from jaxdyn._outcome import MESSAGES, Outcome

INERTIA = jnp.array([1.0, 2.0, 3.0])
OMEGA = [0.3, 1.0, 0.2]


class NanAfter(eqx.Module):
    """A control law that breaks down (returns NaN) after `t_break`."""

    t_break: float

    def __call__(self, t, y):
        return jnp.where(t > self.t_break, jnp.nan, 0.0) * y["omega"]


class BlowUp(eqx.Module):
    """A torque growing like |w|^2 w: the rates reach infinity in finite time."""

    def __call__(self, t, y):
        return 10.0 * jnp.sum(y["omega"] ** 2) * y["omega"] * INERTIA


def free():
    scene = jd.Scene(jd.RigidBody(INERTIA))
    return scene, scene.state(omega=OMEGA), 1.0, {}


def rod():
    scene = jd.Scene(jd.FallingRod())
    return scene, scene.state(theta=0.1), 5.0, {}


def budget():
    scene = jd.Scene(jd.RigidBody(INERTIA))
    return scene, scene.state(omega=OMEGA), 100.0, {"max_steps": 5}


def broken_law():
    scene = jd.Scene(jd.RigidBody(INERTIA), (jd.ExternalTorque(NanAfter(0.5), feedback=True),))
    return scene, scene.state(omega=OMEGA), 5.0, {}


def singular():
    scene = jd.Scene(jd.RigidBody(INERTIA), (jd.ExternalTorque(BlowUp(), feedback=True),))
    return scene, scene.state(omega=OMEGA), 5.0, {}


CASES = {
    "completed": free,
    "event": rod,
    "max_steps_reached": budget,
    "non_finite": broken_law,
    "step_size_underflow": singular,
}


@pytest.mark.parametrize("expected", list(CASES))
def test_simulate_labels_each_outcome(expected):
    scene, y0, t1, kw = CASES[expected]()
    if Outcome[expected] in (Outcome.completed, Outcome.event):
        traj = jd.simulate(scene, y0, t1, **kw)
        assert traj.outcome_name == expected
    else:
        with pytest.raises(RuntimeError) as info:
            jd.simulate(scene, y0, t1, **kw)
        assert MESSAGES[Outcome[expected]].split(":")[0] in str(info.value)


MODES = ("adaptive", "lockstep", "vmap")


# Each outcome in one mode, the modes taken in turn (each mode labels several outcomes); the
# other modes of each outcome are a sweep.
@pytest.mark.parametrize("expected, mode", [
    pytest.param(expected, mode, id=f"{expected}-{mode}",
                 marks=() if mode == MODES[i % len(MODES)] else pytest.mark.sweep)
    for i, expected in enumerate(CASES) for mode in MODES])
def test_ensemble_labels_each_outcome(expected, mode):
    scene, y0, t1, kw = CASES[expected]()
    res = jd.ensemble(scene, y0, t1, n=3, mode=mode, **kw)
    assert res.status_counts() == {expected: 3}
    if expected not in ("completed", "event"):
        assert res.failures()[0]["message"] == MESSAGES[Outcome[expected]]


@pytest.mark.parametrize("mode", ["adaptive", "lockstep", "vmap"])
def test_invalid_samples_are_labelled_in_every_mode(mode):
    scene = jd.Scene(jd.RigidBody(INERTIA))
    # inertia[2] drawn above I1 + I2 = 3 for some samples: the triangle inequality fails
    res = jd.ensemble(scene, scene.state(omega=OMEGA), 1.0, n=16, key=3, mode=mode,
                      vary={"inertia[2]": jd.Uniform(2.0, 4.0)})
    counts = res.status_counts()
    assert set(counts) == {"completed", "invalid_input"} and counts["invalid_input"] > 0
    bad = [f for f in res.failures(16) if f["status"] == "invalid_input"]
    assert all("inertia" in f["message"] for f in bad)


def test_invalid_input_inside_jit_raises_by_name():
    scene = jd.Scene(jd.RigidBody(INERTIA))

    @jax.jit
    def run(inertia):
        return jd.simulate(scene.replace(inertia=inertia), scene.state(omega=OMEGA), 1.0).t_final

    with pytest.raises(RuntimeError, match="inertia"):
        run(jnp.array([1.0, 2.0, 4.0]))


@pytest.mark.parametrize("case", [free, rod, budget])
def test_concrete_inputs_closed_over_by_the_callers_jit(case):
    """`jax.jit` of a function that closes over a concrete scene and state: the call is staged
    into the caller's program (the host cannot read its outcome), with the same numbers as a
    call outside it, and a failure raised from the program with its message."""
    scene, y0, t1, kw = case()
    staged = jax.jit(lambda: jd.simulate(scene, y0, t1, **kw).y_final)
    if kw.get("max_steps"):
        with pytest.raises(RuntimeError, match="max_steps"):
            jax.block_until_ready(staged())
        return
    direct = jd.simulate(scene, y0, t1).y_final
    for k, v in staged().items():
        assert jnp.array_equal(v, direct[k]), k


def test_hybrid_outcomes():
    scene = jd.Scene(jd.RoughFloorRod(mu_s=0.3, mu_k=0.2))
    traj = jd.simulate(scene, scene.state(theta=0.2), 5.0)
    assert traj.outcome_name == "event"
    res = jd.ensemble(scene, scene.state(theta=0.2), 5.0, n=2, mode="vmap")
    assert res.status_counts() == {"event": 2}
    short = jd.simulate(scene, scene.state(theta=0.2), 0.05)
    assert short.outcome_name == "completed"


def test_outcome_names_and_messages_are_one_table():
    assert [o.name for o in Outcome] == list(jd.Ensemble.status_names)
    assert set(MESSAGES) == set(Outcome)


# (Another solver with saved times is a sweep: the default solver's saved times and dense
# output are the suite's.)
@pytest.mark.parametrize("kw", [
    {"ts": np.linspace(0.0, 2.0, 41)}, {"dense": True},
    pytest.param({"solver": diffrax.Dopri5(), "ts": np.linspace(0.0, 2.0, 9)},
                 marks=pytest.mark.sweep)])
@pytest.mark.optimized  # (bit for bit: the programs a user runs)
def test_a_concrete_run_takes_the_steps_of_the_differentiable_loop(kw):
    """A call with concrete values loops as diffrax's `ForwardMode` (nothing can differentiate
    its results); under the caller's trace it loops as `RecursiveCheckpointAdjoint`, which
    reverse mode needs. The same steps and values to the bit, on a scene with switches and
    its event (the rough-floor rod) and on the rigid body."""
    rough, free = jd.Scene(jd.RoughFloorRod(mu_s=0.3, mu_k=0.2)), jd.Scene(jd.RigidBody(INERTIA))
    for scene, y0 in ((rough, rough.state(theta=0.4)), (free, free.state(omega=OMEGA))):
        direct = jd.simulate(scene, y0, 2.0, **kw)
        staged = jax.jit(lambda scene=scene, y0=y0: jd.simulate(scene, y0, 2.0, **kw))()
        assert int(direct.stats["num_steps"]) == int(staged.stats["num_steps"]) > 3
        times = np.linspace(0.0, float(direct.t_final), 17)
        pairs = [(direct.ys, staged.ys), (direct.y_final, staged.y_final)]
        if kw.get("dense"):
            pairs.append((direct.evaluate(times), staged.evaluate(times)))
        for i, (a, b) in enumerate(pairs):
            for k in a:
                if i == 0 and "solver" in kw:  # (samples: written by jaxdyn from the steps
                    np.testing.assert_allclose(  # outside, by diffrax's SaveAt inside: the
                        a[k], b[k], rtol=1e-14, atol=1e-15)  # last bit may differ)
                else:
                    assert np.array_equal(np.asarray(a[k]), np.asarray(b[k])), k
    # Differentiable where traced: the reverse-mode derivative of the last rate.
    scene = jd.Scene(jd.RigidBody(INERTIA))
    grad = jax.grad(lambda w: jd.simulate(scene, scene.state(omega=w), 2.0, **kw)
                    .y_final["omega"][0])(jnp.asarray(OMEGA))
    assert np.all(np.isfinite(np.asarray(grad)))


@pytest.mark.optimized  # (bit for bit: the programs a user runs)
def test_an_implicit_solver_keeps_the_dense_output_of_a_run_with_switches():
    """Kvaerno5 with `dense=True` on the rough-floor rod (its slip switches, then its impact
    ends the run): the dense table is laid out from the solver's step, whose root finder takes
    the controller's tolerances (it failed with "Type of `other` not understood" before). The
    states along the run agree with a tight explicit run, one time or many."""
    scene = jd.Scene(jd.RoughFloorRod(mu_s=0.3, mu_k=0.2))
    y0 = scene.state(theta=0.4)
    implicit = jd.simulate(scene, y0, 2.0, solver=diffrax.Kvaerno5(), dense=True, rtol=1e-9)
    tight = jd.simulate(scene, y0, 2.0, dense=True, rtol=1e-12)
    assert implicit.outcome_name == tight.outcome_name == "event"
    assert int(implicit.stats["num_switches"]) == int(tight.stats["num_switches"]) == 1
    end = min(float(implicit.t_final), float(tight.t_final))
    times = np.linspace(0.0, end, 23)
    a, b = implicit.evaluate(times), tight.evaluate(times)
    for k in ("theta", "theta_dot", "tip_x", "tip_vx"):
        np.testing.assert_allclose(a[k], b[k], rtol=1e-6, atol=1e-7, err_msg=k)
    one = implicit.evaluate(times[7])  # one time: one state
    for k in a:
        assert one[k].shape == a[k].shape[1:] and np.array_equal(one[k], a[k][7]), k


def test_an_eager_gradient_through_a_torque_law_that_closes_over_its_parameter():
    """`jax.grad` (not under `jit`) of a run whose scene holds a Python torque law closing over
    the differentiated value: the call's arrays are concrete, but the run must loop in reverse
    mode (a concrete run's forward-mode loop would fail here). Against central differences."""
    body = jd.RigidBody(INERTIA)

    def final(a):
        scene = jd.Scene(body, (jd.ExternalTorque(lambda t: a * jnp.array([1.0, 0.0, 0.0])),))
        return jd.simulate(scene, scene.state(omega=jnp.asarray(OMEGA)), 1.0,
                           rtol=1e-12).y_final["omega"][0]

    h = 1e-4
    fd = (final(0.1 + h) - final(0.1 - h)) / (2 * h)
    np.testing.assert_allclose(jax.grad(final)(0.1), fd, rtol=1e-6)


def test_a_float32_body_with_an_effect_of_python_numbers_runs_in_float32():
    """The precision check refuses only a state whose derivative comes out wider (see
    test_bad_input.py): a float32 body whose rotor was given as float64 numbers integrates in
    float32, as before the check."""
    scene = jd.Scene(jd.RigidBody(np.array([1.0, 2.0, 3.0], np.float32)),
                     (jd.Rotor(np.array([0.0, 0.5, 0.0])),), attitude=True)
    traj = jd.simulate(scene, scene.state(omega=np.array([0.1, 1.0, 0.1], np.float32)), 1.0)
    assert traj.y_final["omega"].dtype == np.float32 and traj.outcome_name == "completed"
