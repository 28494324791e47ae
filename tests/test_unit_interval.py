"""Segments integrated on the unit interval (`jaxdyn._hybrid`, "Time on the unit interval"):
the times handed in and out are the caller's own, the run is the same wherever its interval
lies, the final state moves with the end time as the vector field says, and the compiled
program stays under XLA:CPU's estimate of a cheap program (what lets it run on the calling
thread)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import FINITE_DIFF, tol

import jaxdyn as jd
from jaxdyn import _simulate

FREE = jd.Scene(jd.RigidBody(jnp.array([1.0, 2.0, 3.0])))
W0 = FREE.state(omega=[0.3, 1.0, 0.2])
ROD = jd.Scene(jd.FallingRod(length=1.0, mass=1.0, g=9.81))


def test_the_run_is_the_same_wherever_its_interval_lies():
    """An autonomous system from `t0 = 1e5` takes the steps it takes from 0 (the same span:
    the same steps in `tau`, so the same final state to the last bit), ends at exactly `t1`,
    and saves at exactly the times asked for (which `1e5 + ts` rounds to 1.5e-11: the states
    there differ by that times the rates)."""
    ts = np.linspace(0.0, 20.0, 7)
    here = jd.simulate(FREE, W0, 20.0, ts=ts)
    there = jd.simulate(FREE, W0, 1e5 + 20.0, t0=1e5, ts=1e5 + ts)
    assert float(there.t_final) == 1e5 + 20.0 and float(here.t_final) == 20.0
    np.testing.assert_array_equal(np.asarray(there.ts), 1e5 + ts)
    assert int(there.stats["num_steps"]) == int(here.stats["num_steps"])
    np.testing.assert_array_equal(np.asarray(there.y_final["omega"]),
                                  np.asarray(here.y_final["omega"]))
    np.testing.assert_allclose(np.asarray(there.ys["omega"]), np.asarray(here.ys["omega"]),
                               rtol=0, atol=4 * np.spacing(1e5))


def test_dense_output_is_in_the_callers_time():
    """`evaluate` between the saved times of a run from `t0 = 5` agrees with a run that saves
    there, and its ends are the run's."""
    inside = np.array([5.0, 6.25, 13.5, 25.0])
    dense = jd.simulate(FREE, W0, 25.0, t0=5.0, dense=True)
    saved = jd.simulate(FREE, W0, 25.0, t0=5.0, ts=inside)
    np.testing.assert_allclose(np.asarray(dense.evaluate(inside)["omega"]),
                               np.asarray(saved.ys["omega"]), rtol=1e-12)
    assert np.all(np.isnan(np.asarray(dense.evaluate(jnp.array([4.9, 25.1]))["omega"])))
    one = dense.evaluate(13.5)["omega"]  # one time: one state
    assert one.shape == (3,) and np.array_equal(one, dense.evaluate(inside)["omega"][2])
    assert np.all(np.isnan(np.asarray(dense.evaluate(25.1)["omega"])))


def test_dense_output_ends_at_the_event():
    """A run ended by an event (the rod lying flat) within its last step: `evaluate` past
    the event time gives nan, not the step's interpolant going on past lying flat."""
    rod = jd.Scene(jd.FallingRod())
    traj = jd.simulate(rod, rod.state(theta=0.3), 5.0, dense=True)
    end = float(traj.t_final)
    assert traj.outcome_name == "event"
    assert np.isclose(float(traj.evaluate(end)["theta"]), np.pi / 2, atol=1e-9)
    assert np.isnan(float(traj.evaluate(end * (1 + 1e-9))["theta"]))
    assert np.all(np.isnan(np.asarray(traj.evaluate(jnp.array([end + 1e-3, 7.0]))["theta"])))


def test_the_final_state_moves_with_the_end_time_as_the_vector_field_says():
    """`d y(t1) / d t1 = f(y(t1))`: the span now scales every step of the run, so a wrong
    scale shows here (central differences of concrete runs at tight tolerances; reverse-mode
    gradients through runs are checked against finite differences elsewhere)."""
    def final(t1):
        return np.asarray(jd.simulate(FREE, W0, t1, rtol=1e-12).y_final["omega"])

    t1, h = 7.0, 1e-3
    slope = (final(t1 + h) - final(t1 - h)) / (2 * h)
    expected = FREE.vector_field(t1, {"omega": jnp.asarray(final(t1))})["omega"]
    np.testing.assert_allclose(slope, np.asarray(expected), rtol=tol(FINITE_DIFF), atol=1e-9)


@pytest.mark.parametrize("samples", [None, 20, 10_000])
@pytest.mark.parametrize("scene, y0, t1", [(FREE, W0, 20.0),
                                           (ROD, ROD.state(theta=0.1), 10.0)])
def test_the_program_is_cheap_by_xlas_estimate(scene, y0, t1, samples):
    """XLA:CPU runs a program estimated under 1000 operations on the calling thread (no
    hand-over to a worker thread and back). diffrax's 100 `nextafter`s below a traced end of
    the interval alone were estimated at 1400: on the unit interval they fold away. With
    saved times the estimate does not grow with their number (each operation over them is a
    loop, whose body XLA counts once): 200 times put the free body's program at 5400 when
    the buffers were filled and masked element by element."""
    ts = None if samples is None else np.linspace(0.0, t1, samples)
    jd.simulate(scene, y0, t1, ts=ts)
    leaves, treedef = jax.tree_util.tree_flatten(scene)
    # The program of this call's options (others of the same scene, built by other tests in
    # this process, keep more: a dense table, another step budget).
    key = ("simulate", treedef, (100_000, True, False))
    args = (leaves, y0, np.array([0.0, t1, 1e-8, 0.0]), ts)
    cost = _simulate._PROGRAMS[key].jitted.lower(*args).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    assert 0 < cost["flops"] < 1000
