"""Long sample records: `simulate(..., ts=...)` with thousands of sample times.

The samples of a concrete run (and of forward-mode Jacobians) are written from each accepted
step into a buffer that diffrax leaves in place (`jaxdyn._solvers._accepted`), not by diffrax's
`SaveAt(ts)` (whose runtime check of traced times is a host callback). Checked against
diffrax's own `SaveAt(ts)` (the same steps: equal to round-off), a SciPy reference, the energy
integral, finite differences, single runs (for a batch) and float64 (for float32).
"""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import INTEGRATION, ROUNDOFF, tol
from scipy.integrate import solve_ivp

import jaxdyn as jd
from jaxdyn._simulate import simulate_unchecked

INERTIA = np.array([1.0, 2.0, 2.5])
W0 = [1e-3, 2.0, 1e-3]
TIGHT = dict(rtol=1e-12, atol=1e-12)


def free_body(inertia=INERTIA, dtype=np.float64, w0=W0):
    scene = jd.Scene(jd.RigidBody(inertia=np.asarray(inertia, dtype)), effects=())
    return scene, scene.state(omega=np.asarray(w0, dtype))


def diffrax_saveat(scene, y0, t1, ts, **kw):
    """The same run with diffrax's own `SaveAt(ts)`: under a trace of the caller's the sample
    times are traced, and `simulate` hands them to diffrax."""
    return jax.jit(lambda ts: jd.simulate(scene, y0, t1, ts=ts, **kw))(ts)


def assert_same_samples(a, b, rtol):
    finite = np.isfinite(np.asarray(a.ts))
    np.testing.assert_array_equal(np.asarray(a.ts), np.asarray(b.ts))
    for k in a.ys:
        x, y = np.asarray(a.ys[k]), np.asarray(b.ys[k])
        assert np.all(np.isinf(x[~finite])) and np.all(np.isinf(y[~finite]))
        scale = np.max(np.abs(y[finite]))
        np.testing.assert_allclose(x[finite], y[finite], rtol=0, atol=rtol * scale, err_msg=k)


def test_many_samples_match_diffrax_saveat_and_scipy():
    scene, y0 = free_body()
    t1, ts = 60.0, np.linspace(0.0, 60.0, 20_001)
    traj = jd.simulate(scene, y0, t1, ts=ts, **TIGHT)
    assert_same_samples(traj, diffrax_saveat(scene, y0, t1, ts, **TIGHT), tol(ROUNDOFF))
    assert int(traj.stats["num_steps"]) < 5_000  # many samples to each step

    def euler(t, w):
        return (INERTIA[[1, 2, 0]] - INERTIA[[2, 0, 1]]) * w[[1, 2, 0]] * w[[2, 0, 1]] / INERTIA

    ref = solve_ivp(euler, (0.0, t1), W0, method="DOP853", t_eval=ts, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(np.asarray(traj.ys["omega"]), ref.y.T, rtol=0,
                               atol=50 * tol(INTEGRATION) * np.max(np.abs(W0)))


def test_event_among_many_samples():
    """The falling rod hits the floor inside the record: samples up to the impact match
    diffrax's `SaveAt(ts)` and keep the energy; those after it are `inf` (times and states)."""
    scene = jd.Scene(jd.FallingRod(length=1.3, mass=2.0, g=9.81))
    y0 = scene.state(theta=0.3)
    t1, ts = 5.0, np.linspace(0.0, 5.0, 10_000)
    traj = jd.simulate(scene, y0, t1, ts=ts, **TIGHT)
    t_final = float(traj.t_final)
    assert 0.0 < t_final < t1 and any(bool(v) for v in traj.event.values())
    finite = np.isfinite(np.asarray(traj.ts))
    np.testing.assert_array_equal(finite, ts <= t_final)
    assert_same_samples(traj, diffrax_saveat(scene, y0, t1, ts, **TIGHT), tol(ROUNDOFF))
    theta, rate = np.asarray(traj.ys["theta"])[finite], np.asarray(traj.ys["theta_dot"])[finite]
    m, L, g = 2.0, 1.3, 9.81
    energy = m * L**2 / 24 * (1 + 3 * np.sin(theta) ** 2) * rate**2 + m * g * L / 2 * np.cos(theta)
    np.testing.assert_allclose(energy, energy[0], rtol=1e-9)


@pytest.mark.optimized  # (bit for bit: the programs a user runs)
def test_switching_scene_with_many_samples_and_its_dense_table():
    """A rough-floor rod that slips (several segments): the samples match diffrax's
    `SaveAt(ts)`, and the dense output (the table of accepted steps, written beside them)
    gives the same states."""
    scene = jd.Scene(jd.RoughFloorRod(length=1.0, mass=1.0, g=9.81, mu_s=0.3, mu_k=0.25))
    y0 = scene.state(theta=0.2)
    t1, ts = 2.0, np.linspace(0.0, 2.0, 8_000)
    traj = jd.simulate(scene, y0, t1, ts=ts, dense=True, **TIGHT)
    assert int(traj.stats["num_switches"]) >= 1
    assert_same_samples(traj, diffrax_saveat(scene, y0, t1, ts, **TIGHT), tol(ROUNDOFF))
    rows = np.flatnonzero(np.asarray(ts) < float(traj.t_final))[1::97]
    at = traj.evaluate(jnp.asarray(ts[rows]))
    for k in ("theta", "theta_dot"):
        np.testing.assert_allclose(np.asarray(at[k]), np.asarray(traj.ys[k])[rows],
                                   rtol=0, atol=1e-12, err_msg=k)


def _samples_of_inertia(inertia, ts, adjoint):
    scene = jd.Scene(jd.RigidBody(inertia=inertia), effects=())
    traj = simulate_unchecked(scene, scene.state(omega=jnp.asarray(W0)), 20.0, ts=ts,
                                 adjoint=adjoint)
    return traj.ys["omega"]


def test_forward_jacobian_through_many_samples():
    """`jax.jacfwd` with respect to the inertia, through 4000 samples written from each step,
    against the same Jacobian through diffrax's `SaveAt(ts)` and central differences."""
    ts = jnp.linspace(0.0, 20.0, 4_000)
    inertia = jnp.asarray(INERTIA)
    jac = jax.jit(jax.jacfwd(lambda i: _samples_of_inertia(i, ts, dfx.ForwardMode())))(inertia)

    def through_saveat(i):
        scene = jd.Scene(jd.RigidBody(inertia=i), effects=())
        return jd.simulate(scene, scene.state(omega=jnp.asarray(W0)), 20.0, ts=ts,
                           adjoint=dfx.ForwardMode()).ys["omega"]

    ref = jax.jit(jax.jacfwd(through_saveat))(inertia)
    scale = np.max(np.abs(np.asarray(ref)))
    np.testing.assert_allclose(np.asarray(jac), np.asarray(ref), rtol=0, atol=1e-9 * scale)
    eps = 1e-5
    for j in range(3):
        e = np.zeros(3)
        e[j] = eps
        plus = jd.simulate(jd.Scene(jd.RigidBody(inertia=INERTIA + e), effects=()),
                           free_body()[1], 20.0, ts=np.asarray(ts), **TIGHT).ys["omega"]
        minus = jd.simulate(jd.Scene(jd.RigidBody(inertia=INERTIA - e), effects=()),
                            free_body()[1], 20.0, ts=np.asarray(ts), **TIGHT).ys["omega"]
        fd = (np.asarray(plus) - np.asarray(minus)) / (2 * eps)
        # (the Jacobian at the default tolerance, the differences at a tight one)
        np.testing.assert_allclose(np.asarray(jac)[..., j], fd, rtol=0, atol=2e-4 * scale)


@pytest.mark.optimized  # (to round-off, through the spin about the intermediate axis, which
# amplifies it: the programs a user runs. With most of XLA's optimisations off, the single
# run, its step loop compiled as one function (`jaxdyn._xla`), and the batch, launched kernel
# by kernel, round differently, 7e-10 apart after 24 s.)
def test_vmap_over_a_batch_matches_single_runs():
    ts = jnp.linspace(0.0, 30.0, 5_000)
    scene, _ = free_body()
    omegas = jnp.asarray([W0, [0.5, 0.1, 1.0], [1.0, 1e-3, 0.2]])

    def run(w):
        return simulate_unchecked(scene, scene.state(omega=w), 30.0, ts=ts,
                                     adjoint=dfx.ForwardMode()).ys["omega"]

    batch = jax.jit(jax.vmap(run))(omegas)
    for k, w in enumerate(omegas):
        single = jd.simulate(scene, scene.state(omega=np.asarray(w)), 30.0, ts=np.asarray(ts))
        np.testing.assert_allclose(np.asarray(batch[k]), np.asarray(single.ys["omega"]),
                                   rtol=0, atol=tol(ROUNDOFF) * float(jnp.max(jnp.abs(w))))


def test_batched_sample_loops_write_rows_not_whole_buffers():
    """Under `vmap` a `while_loop` whose predicate differs between members selects its whole
    carry at every iteration. The loops over samples (the start, the writing from each step,
    one sample an iteration) are equinox's loops with buffers, which write one row: in the
    lowered program of batched forward-mode Jacobians (as multiple shooting linearises its
    segments), the only select over a whole sample buffer is diffrax's step loop's, once a
    step. (With `lax.while_loop`s there were three for each buffer: 8 such Jacobians of a free
    body saving 2000 times took 289 ms against 44.5 ms.)"""
    import re
    from collections import Counter

    scene, y0 = free_body()
    ts = jnp.linspace(0.0, 5.0, 37)

    def states(w0):
        return simulate_unchecked(scene, {"omega": w0}, 5.0, ts=ts,
                                  adjoint=dfx.ForwardMode()).ys["omega"]

    batch = jnp.tile(jnp.asarray(y0["omega"]), (4, 1))
    text = jax.jit(jax.vmap(jax.jacfwd(states))).lower(batch).as_text()
    shapes = Counter(re.findall(r"stablehlo\.select [^\n]*: tensor<[^>]*xi1>, "
                                r"tensor<(4x37(?:x3)?)xf64>", text))
    assert shapes["4x37x3"] >= 1  # (the search finds the step loop's: it reads this program)
    assert shapes["4x37x3"] <= 1 and shapes["4x37"] <= 1, shapes


def test_float32_long_record_keeps_its_dtype_and_accuracy():
    """(Near the major axis: a flip about the intermediate axis would amplify round-off.)"""
    ts, w0 = np.linspace(0.0, 30.0, 20_000), [0.2, 0.1, 1.0]
    scene32, y32 = free_body(dtype=np.float32, w0=w0)
    traj32 = jd.simulate(scene32, y32, np.float32(30.0), ts=ts.astype(np.float32))
    scene64, y64 = free_body(w0=w0)
    traj64 = jd.simulate(scene64, y64, 30.0, ts=ts, **TIGHT)
    assert traj32.ys["omega"].dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(traj32.ys["omega"]), np.asarray(traj64.ys["omega"]),
                               rtol=0, atol=50 * tol(INTEGRATION, jnp.float32))


@pytest.mark.parametrize("adjoint, callbacks", [(dfx.ForwardMode(), False),
                                                (dfx.RecursiveCheckpointAdjoint(), True)])
def test_no_host_callback_where_the_samples_are_written_from_the_steps(adjoint, callbacks):
    """The program of a run with traced sample times written from the steps (forward mode,
    as `fit` runs it) holds no host callback; diffrax's `SaveAt(ts)` of traced times (reverse
    mode) holds one, its check of the times (the control: the test can see one)."""
    ts = jnp.linspace(0.0, 20.0, 1_000)
    text = jax.jit(lambda ts: _samples_of_inertia(jnp.asarray(INERTIA), ts, adjoint)).lower(
        ts).as_text()
    assert ("callback" in text) is callbacks
