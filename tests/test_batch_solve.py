"""The batch engine (`batch_solve`, behind `jaxdyn.ensemble`) as a component: on the same
tableau and problem it takes the steps `diffrax.diffeqsolve` takes and gives the same values
(to what its step-size root leaves, 1e-5 of a step size), and each tableau's observed order of
convergence is its order."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from jaxdyn import _batch_solve
from jaxdyn._batch_solve import Tableau, batch_solve, rk_step, tableau

SOLVERS = [dfx.Tsit5(), dfx.Dopri5(), dfx.Dopri8(), dfx.Bosh3(), dfx.Heun()]
RTOL, ATOL = 1e-6, 1e-8
# The first step, given to both: diffrax 0.7 chooses 0.01 whatever the problem (its
# `PIDController` sees the term wrapped and skips its starting-step rule), the engine
# Hairer, Norsett & Wanner's starting step. Large enough that the first step's error estimate
# is not round-off (a difference of nearly equal sums, whose last bits depend on the order in
# which they are added).
DT0 = 0.5
# Values of two implementations of the same steps, at RTOL: their step sizes differ by the
# engine's step-size root (`_inv_root`, to about 1e-5 relative), their values by a hundredth
# of the tolerance at most (about 1e-9 relative, 2e-9 absolute for Dopri8).
SAME_STEPS = 1e-2 * RTOL


def euler(p, t, y):
    """Euler's equations of a torque-free body, principal moments `p["inertia"]`."""
    w, i = y["omega"], p["inertia"]
    return {"omega": jnp.stack([(i[1] - i[2]) * w[1] * w[2] / i[0],
                                (i[2] - i[0]) * w[2] * w[0] / i[1],
                                (i[0] - i[1]) * w[0] * w[1] / i[2]])}


def pendulum(p, t, y):
    """A driven pendulum: non-autonomous and nonlinear."""
    return {"q": y["v"], "v": -p["k"] * jnp.sin(y["q"]) + 0.3 * jnp.cos(t)}


def _cases(n=4, seed=0):
    rng = np.random.default_rng(seed)
    euler_case = ({"inertia": jnp.asarray(rng.uniform(1.0, 3.0, (n, 3)))},
                  {"omega": jnp.asarray(rng.normal(size=(n, 3)))})
    pendulum_case = ({"k": jnp.asarray(rng.uniform(1.0, 10.0, n))},
                     {"q": jnp.asarray(rng.uniform(0.1, 1.0, n)), "v": jnp.zeros(n)})
    return {"euler": (euler, *euler_case), "pendulum": (pendulum, *pendulum_case)}


def _engine(field, params, y0, t1, ts, solver, *, conditions=None, names=(), lockstep=False):
    n = jax.tree.leaves(y0)[0].shape[0]
    flags = jnp.zeros((n, 1), bool)
    return jax.jit(lambda p, y: batch_solve(
        field, conditions, names, flags, p, y, 0.0, t1, ts, solver=solver, rtol=RTOL,
        atol=ATOL, max_steps=100_000, lockstep=lockstep, dt0=DT0))(params, y0)


def _diffrax(field, p, y0, t1, ts, solver, event=None):
    """One trajectory by `diffrax.diffeqsolve`, with its PID controller's defaults."""
    saveat = dfx.SaveAt(t1=True) if ts is None else dfx.SaveAt(ts=ts, t1=True)
    return dfx.diffeqsolve(
        dfx.ODETerm(lambda t, y, p: field(p, t, y)), solver, 0.0, t1, DT0, y0, args=p,
        saveat=saveat, stepsize_controller=dfx.PIDController(rtol=RTOL, atol=ATOL),
        max_steps=100_000, event=event)


def _row(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def _close(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=SAME_STEPS,
                                   atol=SAME_STEPS)


# Every tableau on the driven pendulum (non-autonomous: its nodes `c` count), the free body's
# several variables with Tsit5; the free body with the other tableaus is a sweep.
@pytest.mark.parametrize("problem, solver", [
    pytest.param(problem, solver, id=f"{problem}-{type(solver).__name__}",
                 marks=() if problem == "pendulum" or isinstance(solver, dfx.Tsit5)
                 else pytest.mark.sweep)
    for problem in ("euler", "pendulum") for solver in SOLVERS])
def test_same_steps_and_values_as_diffeqsolve(problem, solver):
    field, params, y0 = _cases()[problem]
    t1, ts = 10.0, jnp.linspace(0.0, 10.0, 7)
    r = _engine(field, params, y0, t1, ts, solver)
    assert np.all(np.asarray(r.status) == 0)  # completed
    reference = jax.jit(lambda p, y: _diffrax(field, p, y, t1, ts, solver))  # (traced once)
    for i in range(jax.tree.leaves(y0)[0].shape[0]):
        sol = reference(_row(params, i), _row(y0, i))
        assert int(r.steps[i]) == int(sol.stats["num_accepted_steps"])
        assert int(r.rejected[i]) == int(sol.stats["num_rejected_steps"])
        _close(_row(r.y_final, i), jax.tree.map(lambda x: x[-1], sol.ys))
        _close(_row(r.ys, i), jax.tree.map(lambda x: x[:-1], sol.ys))  # dense output at ts


def test_lockstep_alone_takes_the_steps_of_diffeqsolve():
    """A lock-step batch of one trajectory chooses its steps as diffrax does."""
    field, params, y0 = _cases()["euler"]
    params, y0 = _row(params, slice(0, 1)), _row(y0, slice(0, 1))
    r = _engine(field, params, y0, 10.0, None, dfx.Tsit5(), lockstep=True)
    sol = _diffrax(field, _row(params, 0), _row(y0, 0), 10.0, None, dfx.Tsit5())
    assert int(r.steps[0]) == int(sol.stats["num_accepted_steps"])
    assert int(r.rejected[0]) == int(sol.stats["num_rejected_steps"])
    _close(_row(r.y_final, 0), jax.tree.map(lambda x: x[-1], sol.ys))


def _force_the_loop(monkeypatch):
    """Every field's stages in a loop from here on; returns the list that records each step
    traced so (a test that compared the unrolled stages with themselves would pass)."""
    traced = []
    looped = _batch_solve._stages_in_a_loop

    def spy(*args):
        traced.append(1)
        return looped(*args)

    monkeypatch.setattr(_batch_solve, "ROLL_EQUATIONS", 0)
    monkeypatch.setattr(_batch_solve, "_stages_in_a_loop", spy)
    return traced


def test_large_fields_have_their_stages_evaluated_in_a_loop():
    """The engine loops over the stages of a field of more than `ROLL_EQUATIONS` operations
    (counted in its jaxpr, the bodies of its calls included) and unrolls smaller ones."""
    _, params, y0 = _cases()["pendulum"]
    t = jnp.zeros(4)

    def driven(harmonics):
        @jax.jit  # (a call: its body counts)
        def drive(t):
            return sum(0.3 / m**2 * jnp.cos(m * t) for m in range(1, harmonics + 1))

        return lambda p, t, y: {"q": y["v"], "v": -p["k"] * jnp.sin(y["q"]) + drive(t)}

    assert not _batch_solve._rolled(pendulum, params, t, y0)
    assert not _batch_solve._rolled(driven(10), params, t, y0)
    assert _batch_solve._rolled(driven(100), params, t, y0)


@pytest.mark.parametrize("solver", [dfx.Tsit5(), dfx.Dopri8()], ids=lambda s: type(s).__name__)
def test_stages_in_a_loop_take_the_steps_of_the_unrolled_stages(solver, monkeypatch):
    """A run with its stages in a loop (forced here on the pendulum) against the same run
    unrolled (whose steps are diffrax's, above): the same accepted and rejected steps, the
    same saved values to round-off (Dopri8: 13 stages, zeros in its tableau)."""
    field, params, y0 = _cases()["pendulum"]
    t1, ts = 10.0, jnp.linspace(0.0, 10.0, 7)
    unrolled = _engine(field, params, y0, t1, ts, solver)
    traced = _force_the_loop(monkeypatch)
    looped = _engine(field, params, y0, t1, ts, solver)
    assert traced
    assert np.all(np.asarray(looped.status) == 0)
    assert np.array_equal(looped.steps, unrolled.steps) and np.all(np.asarray(looped.steps) > 10)
    assert np.array_equal(looped.rejected, unrolled.rejected)
    for a, b in zip(jax.tree.leaves((looped.ys, looped.y_final)),
                    jax.tree.leaves((unrolled.ys, unrolled.y_final))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: type(s).__name__)
def test_stages_in_a_loop_are_the_unrolled_stages(solver, monkeypatch):
    """One step of every tableau, its stages in a loop against unrolled: the same to a few
    units in the last place (the same sums, compiled apart), the error estimate (a difference
    of nearly equal sums) to its own round-off."""
    tab = tableau(solver)
    rng = np.random.default_rng(5)
    p = {"k": jnp.asarray(rng.uniform(1.0, 10.0, 8))}
    y = (jnp.asarray(rng.uniform(-1.0, 1.0, 8)), jnp.asarray(rng.normal(size=8)))
    t, h = jnp.asarray(rng.uniform(0.0, 5.0, 8)), jnp.asarray(rng.uniform(0.05, 0.3, 8))

    def f(p, t, y):
        out = pendulum(p, t, {"q": y[0], "v": y[1]})
        return (out["q"], out["v"])

    def step(p, t, y, h):
        return rk_step(tab, f, p, t, y, h)

    # (A new function for each `jax.jit`: a second `jax.jit(step)` would reuse the first's
    # trace, whatever `ROLL_EQUATIONS` says by then.)
    unrolled = jax.jit(lambda *a: step(*a))(p, t, y, h)
    traced = _force_the_loop(monkeypatch)
    looped = jax.jit(lambda *a: step(*a))(p, t, y, h)
    assert traced or len(tab.a) == 1  # (Heun: one stage after the first, nothing to loop)
    (fs_l, y1_l, err_l), (fs_u, y1_u, err_u) = looped, unrolled
    assert len(fs_l) == len(fs_u) == len(tab.a) + 1
    for a, b in zip(jax.tree.leaves((fs_l, y1_l)), jax.tree.leaves((fs_u, y1_u))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-14, atol=1e-15)
    scale = max(float(jnp.max(jnp.abs(x))) for x in jax.tree.leaves(fs_u)) * float(h.max())
    for a, b in zip(err_l, err_u):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-14 * scale)


@pytest.mark.parametrize("solver", [dfx.Tsit5(), pytest.param(dfx.Dopri8(),
                                                               marks=pytest.mark.sweep)],
                         ids=lambda s: type(s).__name__)  # (Dopri8's events: a sweep)
def test_events_are_located_where_diffeqsolve_locates_them(solver):
    """The pendulum stopped when it first swings through q = -0.05: the same steps, and the
    same event time (Illinois on the engine's side, Newton on diffrax's)."""
    field, params, y0 = _cases()["pendulum"]

    def conditions(p, t, y):
        return jnp.stack([y["q"] + 0.05])

    r = _engine(field, params, y0, 10.0, None, solver, conditions=conditions, names=("low",))
    assert np.all(np.asarray(r.status) == 1) and np.all(np.asarray(r.event["low"]))
    event = dfx.Event(lambda t, y, args, **kw: y["q"] + 0.05,
                      root_finder=optx.Newton(rtol=1e-14, atol=1e-14))
    reference = jax.jit(lambda p, y: _diffrax(field, p, y, 10.0, None, solver, event=event))
    for i in range(params["k"].shape[0]):
        sol = reference(_row(params, i), _row(y0, i))
        assert int(r.steps[i]) == int(sol.stats["num_accepted_steps"])
        np.testing.assert_allclose(float(r.t_final[i]), float(sol.ts[-1]), rtol=SAME_STEPS)
        _close(_row(r.y_final, i), jax.tree.map(lambda x: x[-1], sol.ys))


def _fixed_step_error(tab: Tableau, steps: int) -> float:
    """`y' = -2 t y^2`, `y(0) = 1` to `t = 2` in `steps` equal steps of the engine's
    Runge-Kutta step: the error against the exact `1 / (1 + t^2)`."""
    def f(p, t, y):
        return (-2 * t * y[0] ** 2,)

    h = jnp.asarray(2.0 / steps)
    y, t = (jnp.ones(1),), jnp.zeros(1)
    for _ in range(steps):
        y = rk_step(tab, f, None, t, y, h)[1]
        t = t + h
    return abs(float(y[0][0]) - 1 / 5)


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: type(s).__name__)
def test_observed_order_is_the_tableau_order(solver):
    """Log error against log step size (as diffrax's own order tests fit it)."""
    tab = tableau(solver)
    steps = np.array([8, 11, 16, 23, 32])
    errors = np.array([_fixed_step_error(tab, int(s)) for s in steps])
    slope = np.polyfit(np.log(2.0 / steps), np.log(errors), 1)[0]
    assert tab.order - 0.2 < slope < tab.order + 0.9, slope
