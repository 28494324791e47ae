"""Torques that jump at known times (a zero-order hold of commanded motor torques): the
integrator steps to each jump instead of across it (`Scene.jump_times`,
`ScaledPIDController`), so the run reaches the accuracy it is asked for and depends smoothly
on the parameters. Reference: SciPy's DOP853 at rtol=1e-12, restarted at every command (it
never integrates across a jump), on the gyrostat equations `I w' = (I w + h) x w - u`,
`h_i' = u_i` written here from their definition."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxdyn as jd

TENSOR = np.array([[2.1, 0.08, -0.05], [0.08, 2.6, 0.12], [-0.05, 0.12, 3.3]])
J = 0.01
# Command times off any sample grid, one of them at the run's start and one at its end.
TIMES = np.array([0.0, 3.7, 9.1, 15.0, 18.3, 26.9, 31.4, 40.0])
TORQUES = 4e-3 * np.array([[1, 0, 0], [0, -1, 0], [0, 0, 1], [-1, 1, 0], [0, 0, -1],
                           [0, 1, 1], [1, 1, -1], [0, -1, 0]], float)
W0, SPEED0 = np.array([0.02, -0.01, 0.015]), np.array([30.0, -20.0, 10.0])


def scene(scale=1.0):
    wheels = jd.Wheels(np.eye(3), [J] * 3, motor=jd.CommandedTorques(TIMES, TORQUES))
    return jd.Scene(jd.RigidBody(scale * TENSOR), (wheels,))


def reference(ts):
    inv = np.linalg.inv(TENSOR)

    def field(t, y, u):  # (the command held over the piece, also at its end)
        w, h = y[:3], y[3:]
        return np.concatenate([inv @ (np.cross(TENSOR @ w + h, w) - u), u])

    y = np.concatenate([W0, J * (SPEED0 + W0)])
    rates = [W0] if ts[0] == 0.0 else []
    edges = list(TIMES[1:]) + [ts[-1]]
    for a, b, u in zip(TIMES, edges, TORQUES):
        if b <= a:  # (the command at the run's end holds for no time)
            continue
        inside = ts[(ts > a) & (ts <= b)]
        times = np.union1d(inside, [b])  # (the piece's end, to start the next from)
        sol = solve_ivp(field, (a, b), y, t_eval=times, method="DOP853", rtol=1e-12,
                        atol=1e-15, args=(u,))
        y = sol.y[:, -1]
        rates.extend(sol.y[:3, np.isin(times, inside)].T)
    return np.array(rates)


@pytest.mark.parametrize("rtol", [1e-6, 1e-9])
def test_commanded_torques_reach_the_requested_accuracy(rtol):
    """Across eight jumps (one at the start, one at the end), the rates are within a small
    multiple of `rtol` of the reference: 1.9 `rtol` at 1e-6, 0.7 `rtol` at 1e-9. Stepping
    across the jumps gave 100 and 86 `rtol`."""
    sc = scene()
    y0 = sc.state(omega=W0, **{"wheels.speed": SPEED0})
    ts = np.linspace(0.0, 40.0, 401)  # (samples on three of the command times)
    traj = jd.simulate(sc, y0, 40.0, ts=ts, rtol=rtol)
    err = np.max(np.abs(np.asarray(traj.ys["omega"]) - reference(ts))) / np.max(np.abs(W0))
    assert err < 30 * rtol, err / rtol
    assert np.all(np.isfinite(np.asarray(traj.ys["omega"])))


def test_the_run_is_smooth_in_the_parameters():
    """The end state's derivative in the inertia's scale: forward mode through the solver
    agrees with a central difference of step 1e-6 (a step across a jump, accepted by an
    error estimate that assumes a smooth field, made the end state jump with the parameter
    at the level of the integration error, and the difference meaningless)."""
    y0 = scene().state(omega=W0, **{"wheels.speed": SPEED0})

    def end(scale):
        return jd.simulate(scene(scale), y0, 40.0, rtol=1e-8,
                           adjoint=dfx.ForwardMode()).ys["omega"][-1]

    jvp = np.asarray(jax.jacfwd(end)(jnp.asarray(1.0)))
    h = 1e-6
    fd = (np.asarray(end(1.0 + h)) - np.asarray(end(1.0 - h))) / (2 * h)
    assert np.allclose(fd, jvp, rtol=1e-4, atol=1e-4 * np.max(np.abs(jvp))), (fd, jvp)


def test_repeated_commands_are_dropped_and_bad_times_still_refused():
    """A command equal to the one before it changes nothing and is dropped (telemetry holds a
    command over many rows); times that do not increase are refused even where every command
    repeats (the dropping must not hide them)."""
    held = jd.CommandedTorques([0.0, 1.0, 2.0, 3.0], [[1, 0, 0], [1, 0, 0], [0, 1, 0],
                                                      [0, 1, 0]])
    assert np.asarray(held.times).tolist() == [0.0, 2.0]
    with pytest.raises(jd.ParameterError, match="commanded_torques.times"):
        jd.CommandedTorques([0.0, 2.0, 1.0], np.zeros((3, 3)))


def test_a_jump_at_the_runs_end_moves_no_step_past_it():
    """A step that starts just before a jump (within the gap `underflow_step`) restarts just
    after it, except at the run's end: a segment of a fit can end exactly at a command time,
    and a start moved past the end left a step of negative length, rejected until the step
    budget ran out (the 3e5-sample wheel record at rtol 1e-10, a segment ending at 20000 s)."""
    from jaxdyn._tolerance import ScaledPIDController, underflow_step

    sc = scene()
    y0 = sc.state(omega=W0, **{"wheels.speed": SPEED0})
    t1 = float(TIMES[-1])  # (a command time)
    ctrl = ScaledPIDController(rtol=1e-10, atol=0.0).bind(sc, jnp.asarray(0.0),
                                                           jnp.asarray(t1), y0)
    for j, t_stop, moved in [(15.0, t1, True), (t1, t1, False)]:
        m = float(underflow_step(jnp.asarray(j), ctrl.time_scale,
                                 jnp.finfo(jnp.float64).eps))
        start = jnp.asarray(j - 0.5 * m)
        t_start, t_end, bump = ctrl._at_jumps(start, jnp.asarray(j + 1.0), jnp.asarray(t_stop))
        assert bool(bump) == moved
        if moved:
            assert float(t_start) > j and float(t_end) > float(t_start)
        else:
            assert float(t_start) == float(start) and float(t_start) < t_stop
