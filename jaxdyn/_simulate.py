"""`simulate`: one entry point over `diffrax.diffeqsolve` for every scene."""

import contextlib
import functools
import math
import threading

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from ._body import AbstractBody
from ._custom_types import State
from ._hybrid import FORWARD, finite, integrate
from ._outcome import Outcome
from ._programs import _signature, forgotten_on_clear, staged, thread_setting, when_lowered
from ._scene import Scene
from ._solution import (  # noqa: F401  (_PROGRAMS: read by benchmarks/latency.py)
    _PROGRAMS,
    Trajectory,
    _concrete_arrays,
    _structure_program,
    raise_on_failure,
)
from ._tolerance import ScaledPIDController
from ._validation import (
    ParameterError,
    as_float_array,
    device_array,
    format_value,
    is_concrete,
    raise_if_violated,
)


def check_tolerances(rtol, atol, dtype) -> tuple:
    """`rtol` and `atol` as arrays of `dtype`, refused where the dtype cannot reach them or
    where they are not tolerances (shared by every entry point that integrates). Traced values
    (a jitted function of `rtol`) are not checked."""
    rtol, atol = tolerance_values(rtol, atol, dtype)
    return device_array(rtol, dtype), device_array(atol, dtype)


def tolerance_values(rtol, atol, dtype) -> tuple:
    """`check_tolerances` on the host: the tolerances as given (the defaults filled in),
    checked, without converting them to arrays."""
    atol = 0.0 if atol is None else atol
    if rtol is None:  # the default: 1e-8, or 1e-6 where the dtype cannot reach it (float32)
        rtol = 1e-8 if jnp.finfo(dtype).eps < 1e-9 else 1e-6
    if is_concrete(rtol, atol):
        eps = float(jnp.finfo(dtype).eps)
        name = jnp.dtype(dtype).name
        for field, value in (("rtol", rtol), ("atol", atol)):
            try:
                v = float(value)
            except (TypeError, ValueError):
                raise ParameterError(f"{field}={value!r}: expected a number") from None
            if not np.isfinite(v) or v < 0 or v >= 1 or (field == "rtol" and v == 0):
                allowed = (f"positive, within [{4 * eps:.2g}, 1)" if field == "rtol" else
                           "within [0, 1) (an absolute floor in the state's units; 0 or None: "
                           "none)")
                raise ParameterError(f"{field}={v:g}: must be {allowed}")
        if float(rtol) < 4 * eps:
            hint = "" if name == "float64" else (
                ", or float64 (jax.config.update('jax_enable_x64', True))")
            raise ParameterError(
                f"rtol={float(rtol):g}: below what {name} can reach (eps = {eps:.2g}); "
                f"use rtol within [{4 * eps:.2g}, 1){hint}"
            )
    return rtol, atol


def _prepare_run(scene, y0, t0, t1, ts, solver, rtol, atol, stepsize_controller, dt0,
                 max_steps):
    """Check the arguments of a run; returns them converted (shared with ensembles)."""
    if not isinstance(scene, Scene):
        raise ParameterError(f"scene={scene!r}: expected a jaxdyn.Scene")
    y0 = scene.check_state(y0)
    _check_state_values(scene, y0)
    dtype = jnp.result_type(*jax.tree_util.tree_leaves(y0))
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ParameterError(f"y0 has dtype {dtype}: expected floating point")
    scene.check_precision(y0)
    t0 = as_float_array("t0", t0, (), dtype)
    t1 = as_float_array("t1", t1, (), dtype)
    if is_concrete(t0, t1):
        _check_span(float(t0), float(t1), dtype)
    if ts is not None:
        ts = as_float_array("ts", ts, None, dtype)
        if ts.ndim != 1 or ts.size == 0:
            raise ParameterError(f"ts has shape {ts.shape}: expected a non-empty 1-D array")
        if is_concrete(ts, t0, t1):
            _check_ts(np.asarray(ts), float(t0), float(t1))
    if not isinstance(max_steps, int) or max_steps <= 0:
        raise ParameterError(f"max_steps={max_steps!r}: must be a positive integer")
    solver = dfx.Tsit5() if solver is None else solver
    if (isinstance(stepsize_controller, dfx.AbstractAdaptiveStepSizeController)
            and not _estimates_error(solver)):
        raise ParameterError(
            f"solver {type(solver).__name__} has no error estimate: an adaptive step-size "
            "controller would grow its steps unchecked; use diffrax.ConstantStepSize() with dt0")
    if stepsize_controller is None and not _estimates_error(solver):
        if dt0 is None:
            raise ParameterError(
                f"solver {type(solver).__name__} takes fixed steps: give dt0 (the step size)"
            )
        stepsize_controller = dfx.ConstantStepSize()
    if stepsize_controller is None:
        rtol, atol = check_tolerances(rtol, atol, dtype)
        stepsize_controller = ScaledPIDController(rtol=rtol, atol=atol)
    if dt0 is not None:
        dt0 = as_float_array("dt0", dt0, (), dtype)
        if is_concrete(dt0) and not (np.isfinite(float(dt0)) and float(dt0) > 0):
            raise ParameterError(f"dt0={format_value(dt0)}: must be a positive finite step (s)")
    return y0, t0, t1, ts, solver, stepsize_controller, dt0


def simulate(
    scene: Scene,
    y0: State,
    t1: float | ArrayLike,
    *,
    t0: float | ArrayLike = 0.0,
    ts: ArrayLike | None = None,
    solver: dfx.AbstractSolver | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    stepsize_controller: dfx.AbstractStepSizeController | None = None,
    dt0: float | None = None,
    max_steps: int = 100_000,
    adjoint: dfx.AbstractAdjoint | None = None,
    events: bool = True,
    progress: bool | dfx.AbstractProgressMeter = False,
    dense: bool = False,
) -> Trajectory:
    """Integrate a scene from `t0` to `t1`.

    **Arguments:**

    - `scene`: the [`jaxdyn.Scene`][].
    - `y0`: the initial state, from `scene.state(...)`.
    - `t1`: final time. The run ends earlier if a terminating event of the scene occurs (the
      falling rod lying flat), located by Newton root finding on the dense interpolant.
    - `t0`: initial time.
    - `ts`: times at which to save the state (within `[t0, t1]`, increasing). By default the
      state is saved at `t0` and at the final time.
    - `solver`: any diffrax solver (default `diffrax.Tsit5()`).
    - `rtol`: relative tolerance of the default PID step-size controller, within
      `[4 eps, 1)` (default `1e-8` in float64, `1e-6` in float32). Each state variable is
      measured against `rtol` times the larger of its magnitude and 1% of its *natural
      scale*, declared by the body and the effects from the
      initial state and the parameters (a rigid body's rates against the largest initial
      rate, the quaternion against 1, the rod's angle against
      `max(|theta0|, |theta_dot0| / sqrt(g/L))`, a wheel's momentum against the body's;
      see `Scene.natural_scales`). So the default settings give the same relative accuracy
      in any units: rates in rad/s or rad/day, inertia in kg m^2 or g mm^2, a rod released
      at `1e-15` rad or at 1.5 rad. Event times are located to `1e-12` relative (float64).
    - `atol`: an optional absolute floor, in the state's own units, within `[0, 1)`
      (default `None`: no floor beyond the natural scales).
    - `stepsize_controller`: any diffrax controller (overrides `rtol`, `atol`); use
      `diffrax.ConstantStepSize()` with `dt0` for fixed steps (the default for solvers without
      error estimates, such as [`jaxdyn.RotationSplitting`][]).
    - `dt0`: the step of fixed steps, or the first step of adaptive ones (chosen
      automatically by default); positive and finite, in the units of `t`.
    - `max_steps`: an error is raised, never a silently truncated result, if more are needed.
    - `adjoint`: any diffrax adjoint (default `diffrax.RecursiveCheckpointAdjoint()` where
      the call is traced by `jax.grad` or another transformation of the caller's; called with
      concrete values, whose results nothing can differentiate, on a scene of arrays with
      the default controller and a built-in explicit solver, diffrax's plain loop,
      `diffrax.ForwardMode()`: the same steps, traced in about two thirds of the time).
    - `events`: whether the scene's terminating events end the run (for a hybrid body, such
      as [`jaxdyn.RoughFloorRod`][], whether its modes switch; see `jaxdyn._hybrid`).
    - `progress`: `True` for a tqdm progress bar, or any diffrax progress meter.
    - `dense`: keep the solver's dense output, for `Trajectory.evaluate` and
      `Trajectory.resample` at any time within the run.

    **Returns:**

    A [`jaxdyn.Trajectory`][]. Gradients flow through it with respect to the scene's parameters,
    the initial state and the times (including the event time).

    **Raises:**

    [`jaxdyn.ParameterError`][] for invalid input, before any work;
    [`jaxdyn.SimulationError`][] (its `outcome` a [`jaxdyn.Outcome`][]) where the run fails
    (step budget, step-size underflow, a non-finite state...), raised on the host from the
    outcome code that the compiled program returns. Called inside a `jit`, `grad` or `vmap` of
    the caller's, where the host cannot see the values, the same checks ride in the program
    (equinox's runtime errors, with the same messages).
    """
    if (solver is None and stepsize_controller is None and adjoint is None and dt0 is None
            and progress is False):
        traj = _fast_simulate(scene, y0, t1, t0, ts, rtol, atol, max_steps, events, dense)
        if traj is not None:
            return traj
    # Explicit solvers of no fields of their own, and jaxdyn's own controller: no Python
    # function of the caller's in them.
    plain = stepsize_controller is None and (solver is None or type(solver) in _PLAIN_SOLVERS)
    y0, t0, t1, ts, solver, stepsize_controller, dt0 = _prepare_run(
        scene, y0, t0, t1, ts, solver, rtol, atol, stepsize_controller, dt0, max_steps)
    if progress is True:
        meter: dfx.AbstractProgressMeter = dfx.TqdmProgressMeter()
    elif progress is False:
        meter = dfx.NoProgressMeter()
    else:
        meter = progress
    # Called with concrete values, every input was checked above and the compiled program
    # carries no runtime check: its outcome code is turned into an error here, on the host
    # (so the program holds no host callback and JAX's persistent cache can keep it). Under a
    # trace of the caller's (jit, grad, vmap) the host cannot see the values: the checks ride
    # in the program (equinox's runtime errors).
    traced = not is_concrete(scene, y0, t0, t1, ts, dt0, rtol, atol) or staged()
    if adjoint is None:
        # Concrete inputs give concrete outputs, which nothing can differentiate: the plain
        # loop (`FORWARD`). Under a trace of the caller's, reverse mode must work; so also
        # where a Python function in the scene, solver or controller may close over the
        # caller's tracers (an eager `jax.grad` through a torque law), which no check sees.
        closed = not traced and plain and _arrays_only(scene)
        adjoint = FORWARD if closed else dfx.RecursiveCheckpointAdjoint()
    traj = _simulate(
        scene, y0, t0, t1, ts,
        solver=solver,
        controller=stepsize_controller,
        dt0=dt0,
        max_steps=max_steps,
        adjoint=adjoint,
        events=events,
        meter=meter,
        dense=dense,
        checks=traced,
        # (Not under a trace of the caller's: its loop over the times is not reverse-mode
        # differentiable, and such a program carries the runtime checks anyway.)
        solver_saves=not traced,
    )
    if not traced:
        raise_on_failure(traj)
    return traj


_PLAIN_SOLVERS = (dfx.Tsit5, dfx.Dopri5, dfx.Dopri8, dfx.Heun, dfx.Bosh3, dfx.Euler,
                  dfx.Midpoint, dfx.Ralston)


def _arrays_only(*trees) -> bool:
    """Whether the leaves of `trees` are concrete arrays and plain numbers only: no Python
    function (which may close over a caller's tracer)."""
    return all(isinstance(x, jax.Array | np.ndarray | np.generic | int | float | bool | str)
               and not isinstance(x, jax.core.Tracer)
               for x in jax.tree_util.tree_leaves(trees))


_FIELDS = ("ts", "ys", "t_final", "y_final", "event", "result", "outcome", "stats",
           "interpolation")
_OUTCOME = _FIELDS.index("outcome")
# The fast path's memory: per scene structure (its tree and its leaves' shapes and dtypes), a
# dict from the call's state layout, sample count and options to what was worked out for them
# once (the layout checked, the dtype, the program's callable); and the last scene called, with
# its leaves and that dict, so that a loop over calls does not take the scene apart each time.
_STRUCTURES: dict = {}
_NO_SCENE = (None, None, None)
_LAST: list = [_NO_SCENE]


@forgotten_on_clear
def _forget_calls() -> None:
    _STRUCTURES.clear()
    _LAST[0] = _NO_SCENE


def _check_state_values(scene: Scene, y0) -> None:
    """Initial values known on the host: finite, and within the body's own state checks
    (traced values are checked inside the program)."""
    for name, value in y0.items():
        if not isinstance(value, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(value))):
            raise ParameterError(f"y0[{name!r}]={format_value(value)}: must be finite")
    body = scene.body
    if type(body).state_checks is not AbstractBody.state_checks:  # (a bound method of a
        raise_if_violated(body.state_checks(y0))                # module costs ~80 us)


def _fast_simulate(scene, y0, t1, t0, ts, rtol, atol, max_steps, events, dense):
    """`simulate` at the default solver and controller for concrete arrays: the checks on the
    host in numpy (the layout once per structure), then one `jax.jit` program per structure,
    dispatched with arrays only. `None` where the general path is needed (traced values,
    Python functions in the scene, unusual types)."""
    if not isinstance(scene, Scene) or type(y0) is not dict or type(max_steps) is not int \
            or max_steps <= 0:
        return None
    last = _LAST[0]  # (one read: another thread may replace it)
    if last[0] is scene:
        leaves, known = last[1], last[2]
    else:
        leaves, treedef = jax.tree_util.tree_flatten(scene)
        if not _concrete_arrays(*leaves):
            return None
        known = _STRUCTURES.setdefault((treedef, _signature(leaves)), {})
        _LAST[0] = (scene, leaves, known)
    values = list(y0.values())
    if not _concrete_arrays(*values) or isinstance(ts, jax.core.Tracer):
        return None
    for t in (t0, t1):
        if not isinstance(t, float | int | np.floating) and (
                not _concrete_arrays(t) or np.ndim(t)):
            return None
    layout = tuple((k, v.shape, v.dtype) for k, v in y0.items())
    checked = known.get(layout)
    if checked is None:
        y0 = scene.check_state(y0)  # raises on a wrong layout
        scene.check_precision(y0)
        dtype = jnp.result_type(*jax.tree_util.tree_leaves(y0))
        if not jnp.issubdtype(dtype, jnp.floating) or len({v.dtype for v in y0.values()}) > 1:
            return None
        checked = known[layout] = (
            values[0].dtype, type(scene.body).state_checks is not AbstractBody.state_checks)
    dtype, state_checks = checked
    if state_checks:
        _check_state_values(scene, y0)  # (its own checks assume finite values)
    # Otherwise the initial state's finiteness is checked inside the program (see below).
    t0f, t1f = float(t0), float(t1)
    _check_span(t0f, t1f, dtype)
    if ts is not None:
        ts = np.asarray(ts, dtype)
        _check_ts(ts, t0f, t1f)
    try:
        rtol, atol = _host_tolerances(rtol, atol, dtype)
    except jax.errors.ConcretizationTypeError:  # staged into the caller's `jit`: see below
        return None
    # The times and tolerances in one array: one transfer instead of four.
    times = np.array([t0f, t1f, rtol, atol], dtype)
    key = (layout, None if ts is None else ts.shape, max_steps, bool(events), bool(dense))
    call = known.get(key)
    if call is None:
        treedef = jax.tree_util.tree_structure(scene)
        options = (max_steps, bool(events), bool(dense))
        program = _structure_program("simulate", treedef, options,
                                     lambda treedef: _build(treedef, *options))
        then = getattr(_THEN, "fn", None)
        with when_lowered(None if then is None else lambda out: then(_trajectory(scene, out))):
            call = known[key] = program.resolve(leaves, y0, times, ts)
    out = call(leaves, y0, times, ts)
    if isinstance(out[_OUTCOME], jax.core.Tracer):  # concrete inputs under the caller's `jit`
        return None  # (the host cannot see the outcome: the checked program, below)
    traj = _trajectory(scene, out)
    if int(np.asarray(out[_OUTCOME])) not in _SUCCESS:  # (`int()` of a jax array: 10 us more)
        _check_state_values(scene, y0)  # raises where the initial state was not finite
        raise_on_failure(traj)
    return traj


def _trajectory(scene: Scene, out) -> Trajectory:
    """The fast path's program's outputs as a `Trajectory` of the caller's scene. Built as
    equinox unflattens a module (its fields were checked inside the program), not through
    `__init__`: the scene is the caller's own, not a copy from the device."""
    traj = object.__new__(Trajectory)
    object.__setattr__(traj, "scene", scene)
    for name, value in zip(_FIELDS, out):
        object.__setattr__(traj, name, value)
    return traj


_THEN = threading.local()


@contextlib.contextmanager
def then_prepare(fn):
    """Within: where `simulate` compiles the program of a new structure on this thread,
    `fn(shape)` is called as that program is lowered, before XLA compiles it, with the
    trajectory it will return (its scene the caller's, its arrays `jax.ShapeDtypeStruct`s), so
    that the programs that follow the run can be `prepare`d to compile on another core
    meanwhile (`jaxdyn run`: `_solution.prepare_report`). (A run that then fails leaves
    them compiling: the process waits for them before it exits.)"""
    with thread_setting(_THEN, "fn", fn):
        yield


def _build(treedef, max_steps, events, dense):
    """The fast path's program for one scene structure and options."""
    def simulate_program(leaves, y0, times, ts):
        scene = jax.tree_util.tree_unflatten(treedef, leaves)
        t0, t1, rtol, atol = times
        traj = _simulate_impl(
            scene, y0, t0, t1, ts, solver=dfx.Tsit5(),
            controller=ScaledPIDController(rtol=rtol, atol=atol), dt0=None,
            max_steps=max_steps, adjoint=FORWARD, events=events,
            meter=dfx.NoProgressMeter(), dense=dense, checks=False, solver_saves=True)
        # A non-finite initial state fails the run as invalid input; the host then names
        # the field (cheaper than reading each state array back before the run).
        outcome = jnp.where(finite(y0), traj.outcome, jnp.int32(Outcome.invalid_input))
        return tuple(outcome if name == "outcome" else getattr(traj, name)
                     for name in _FIELDS)

    return simulate_program


_SUCCESS = (Outcome.completed, Outcome.event)


def _estimates_error(solver) -> bool:
    """Whether `solver` estimates its local error (so that an adaptive controller can choose
    its steps): an adaptive solver, and for a Runge-Kutta tableau, error weights that are not
    all zero (`jaxdyn.RK4` is an explicit Runge-Kutta method to diffrax, but without an
    estimate: an adaptive controller saw zero error and grew the step tenfold at each step)."""
    if not isinstance(solver, dfx.AbstractAdaptiveSolver):
        return False
    b_error = getattr(getattr(solver, "tableau", None), "b_error", None)
    return b_error is None or bool(np.any(np.asarray(b_error) != 0))


def _check_span(t0: float, t1: float, dtype) -> None:
    if not (math.isfinite(t0) and math.isfinite(t1)):
        raise ParameterError(f"t0={t0:g}, t1={t1:g}: times must be finite")
    if not t1 > t0:
        raise ParameterError(f"t1={t1:g}: must be greater than t0={t0:g}")
    tiny, eps = _finfo(dtype)
    span, resolution = t1 - t0, 64 * eps * max(abs(t0), abs(t1))
    if not span >= max(tiny, resolution):
        raise ParameterError(
            f"t1={t1:g}: the span t1 - t0 = {span:g} is below what "
            f"{jnp.dtype(dtype).name} resolves here (at least {max(tiny, resolution):.3g})")


def _check_ts(a: np.ndarray, t0: float, t1: float) -> None:
    if a.ndim != 1 or a.size == 0:
        raise ParameterError(f"ts has shape {a.shape}: expected a non-empty 1-D array")
    if np.any(np.diff(a) < 0) or a[0] < t0 or a[-1] > t1:
        raise ParameterError(f"ts from {a[0]:g} to {a[-1]:g}: must be increasing and within "
                             f"[t0, t1] = [{t0:g}, {t1:g}]")


@functools.lru_cache(maxsize=16)
def _finfo(dtype) -> tuple[float, float]:
    """`tiny` and `eps` of a floating dtype (on every call of `simulate`: cached)."""
    info = jnp.finfo(dtype)
    return float(info.tiny), float(info.eps)


@functools.lru_cache(maxsize=256)
def _host_tolerances_cached(rtol, atol, dtype):
    r, a = check_tolerances(rtol, atol, jnp.dtype(dtype))
    return float(r), float(a)


def _host_tolerances(rtol, atol, dtype):
    try:
        return _host_tolerances_cached(rtol, atol, dtype)
    except TypeError:  # unhashable values: checked (and refused) uncached
        r, a = check_tolerances(rtol, atol, dtype)
        return float(r), float(a)


def simulate_unchecked(scene: Scene, y0: State, t1, *, t0=0.0, ts=None, solver=None,
                       stepsize_controller=None, max_steps: int = 100_000, adjoint=None,
                       events: bool = True, dt0=None) -> Trajectory:
    """`simulate` for uses that run it inside their own compiled programs (`fit`): concrete
    arguments are checked as by `simulate`, but a failure at run time is left in
    `traj.outcome` (no runtime check, no host callback in the caller's program)."""
    y0, t0, t1, ts, solver, stepsize_controller, dt0 = _prepare_run(
        scene, y0, t0, t1, ts, solver, None, None, stepsize_controller, dt0, max_steps)
    adjoint = dfx.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
    # In forward mode (fit's Jacobians) the solver saves at `ts` (no host callback for traced
    # times); its loop over the times is not reverse-mode differentiable.
    return _simulate(scene, y0, t0, t1, ts, solver=solver, controller=stepsize_controller,
                     dt0=dt0, max_steps=max_steps, adjoint=adjoint, events=events,
                     meter=dfx.NoProgressMeter(), dense=False, checks=False,
                     solver_saves=isinstance(adjoint, dfx.ForwardMode))


def _simulate_impl(scene, y0, t0, t1, ts, *, solver, controller, dt0, max_steps, adjoint,
                   events, meter, dense, checks=True, solver_saves=False) -> Trajectory:
    # checks=False (ensembles, fit): failures are left in `Trajectory.outcome`, not raised.
    return integrate(scene, y0, t0, t1, ts, solver=solver, controller=controller, dt0=dt0,
                     max_steps=max_steps, adjoint=adjoint, meter=meter, dense=dense,
                     events=events, checks=checks, solver_saves=solver_saves)


_simulate = eqx.filter_jit(_simulate_impl)
