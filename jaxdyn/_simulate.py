"""`simulate`: one entry point over `diffrax.diffeqsolve` for every scene."""

import functools
from typing import Any

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._body import AbstractBody
from ._custom_types import State
from ._outcome import MESSAGES, NAMES, Outcome, SimulationError, from_diffrax, is_success
from ._scene import Scene
from ._solvers._sampled import Sampled
from ._tolerance import ScaledPIDController
from ._validation import (
    ParameterError,
    as_float_array,
    format_value,
    is_concrete,
    raise_if_violated,
)


class Trajectory(eqx.Module):
    """The result of [`jaxdyn.simulate`][]: states at the saved times, and the final state.

    `outcome` is how the run ended, a [`jaxdyn.Outcome`][] code (`traj.outcome_name` gives its
    name); `result` is diffrax's own result.

    Derived outputs are computed on demand from the scene: `traj.energy`, `traj.omega`,
    `traj.normal_force`... (any name in `traj.output_names`). Saved times after a terminating
    event are `inf` (and their states and outputs are not meaningful): `traj.valid` masks them.
    """

    scene: Scene
    ts: Float[Array, " times"]
    ys: State
    t_final: Float[Array, ""]
    y_final: State
    event: dict[str, Bool[Array, ""]]
    result: dfx.RESULTS
    outcome: Int[Array, ""]
    stats: dict[str, Any]
    interpolation: dfx.DenseInterpolation | None = None

    def evaluate(self, t: Float[ArrayLike, " times"]) -> State:
        """States at times `t` within the run, from the solver's dense output
        (`simulate(..., dense=True)`)."""
        if self.interpolation is None:
            raise ParameterError("evaluate needs the dense output: simulate(..., dense=True)")
        t = jnp.asarray(t, self.t_final.dtype)
        return jax.vmap(self.interpolation.evaluate)(t)

    def resample(self, num: int) -> "Trajectory":
        """The same run saved at `num` evenly spaced times from its start to its end (the event
        time if one ended it), from the dense output."""
        if self.interpolation is None:
            raise ParameterError("resample needs the dense output: simulate(..., dense=True)")
        return _resample(self, num)

    @property
    def outcome_name(self) -> str:
        """The name of `outcome` (`"completed"`, `"event"`, `"max_steps_reached"`...)."""
        return NAMES[int(self.outcome)]

    @property
    def valid(self) -> Bool[Array, " times"]:
        """True for saved times reached before the run ended."""
        return jnp.isfinite(self.ts) & (self.ts <= self.t_final)

    @property
    def output_names(self) -> tuple[str, ...]:
        return self.scene.output_names()

    def outputs(self) -> dict[str, Array]:
        """All derived outputs at the saved times."""
        return _outputs(self.scene, self.ts, self.ys)

    def final_outputs(self) -> dict[str, Array]:
        """All derived outputs at the final time (the event time if one ended the run)."""
        return _outputs(self.scene, self.t_final[None], jax.tree.map(lambda x: x[None],
                                                                    self.y_final))

    @property
    def event_occurred(self) -> Bool[Array, ""]:
        """Whether a terminating event ended the run."""
        flags = list(self.event.values())
        return jnp.any(jnp.stack(flags)) if flags else jnp.asarray(False)

    def to_xarray(self):
        """The run as an xarray `Dataset`: time `t` as the coordinate (the samples reached),
        every state variable and derived output as a variable (array values with a dimension
        per axis), units in each variable's attributes where the body declares them, and the
        outcome in the dataset's attributes. Needs xarray (`pip install "jaxdyn[data]"`)."""
        from ._export import trajectory_to_xarray

        return trajectory_to_xarray(self, self.scene.units())

    def to_dataframe(self):
        """The run as a pandas `DataFrame` indexed by time (the samples reached): every state
        variable and derived output, array values split into columns (`omega[0]`, ...).
        Needs pandas (`pip install "jaxdyn[data]"`)."""
        from ._export import trajectory_to_dataframe

        return trajectory_to_dataframe(self)

    def report(self) -> dict[str, Any]:
        """JSON-ready summary of the run (see `Scene.summary`): plain Python numbers and lists,
        with `None` for values that do not exist for this run."""
        out = jax.tree.map(_to_python, _summary(self))
        for key, labels in self.scene.body.report_labels.items():
            if out.get(key) is not None:
                out[key] = labels[out[key]]
        return out

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        names = Scene.output_names(self.scene)  # (not a bound method: equinox wraps those)
        if name in names:
            return _outputs(self.scene, self.ts, self.ys)[name]
        raise AttributeError(
            f"Trajectory has no attribute {name!r}; derived outputs of this scene: {list(names)}"
        )


@eqx.filter_jit
def _summary(traj: Trajectory) -> dict[str, Any]:
    return traj.scene.summary(traj.ts, traj.ys, traj.valid, traj.t_final, traj.y_final,
                              traj.event)


def _to_python(x):
    a = np.asarray(x)
    if a.ndim == 0:
        v = a.item()
        return v if not isinstance(v, float) or np.isfinite(v) else None
    return [_to_python(v) for v in a]


@eqx.filter_jit
def _resample(traj: Trajectory, num: int) -> Trajectory:
    t0 = traj.interpolation.t0
    ts = jnp.linspace(t0, traj.t_final, num)
    ys = jax.vmap(traj.interpolation.evaluate)(ts)
    return eqx.tree_at(lambda tr: (tr.ts, tr.ys), traj, (ts, ys))


_PROGRAMS: dict = {}  # jax.jit programs by (name, scene structure, options)


def _concrete_arrays(*values) -> bool:
    """Whether every value is a concrete array (no tracer, no Python function): a scene made
    of such leaves can be passed to a `jax.jit` program as its flat leaves."""
    return all(isinstance(x, jax.Array | np.ndarray) and not isinstance(x, jax.core.Tracer)
               for x in values)


def _structure_program(name: str, treedef, options, build):
    """The `jax.jit` program `build(treedef)` for one scene structure (and static options),
    built once: later calls pass only arrays, so dispatch costs what `jax.jit`'s costs."""
    key = (name, treedef, options)
    if key not in _PROGRAMS:
        _PROGRAMS[key] = jax.jit(build(treedef))
    return _PROGRAMS[key]


def _outputs(scene: Scene, ts, ys) -> dict[str, Array]:
    """Every derived output at the times `ts`: one `jax.jit` program per scene structure,
    called with arrays only (equinox's filtered call where the scene holds Python functions
    or the values are traced)."""
    leaves, treedef = jax.tree_util.tree_flatten(scene)
    if not _concrete_arrays(*leaves):
        return _outputs_filtered(scene, ts, ys)

    def build(treedef):
        def outputs_program(leaves, ts, ys):
            scene = jax.tree_util.tree_unflatten(treedef, leaves)
            return jax.vmap(scene.outputs)(ts, ys)

        return outputs_program

    return _structure_program("outputs", treedef, (), build)(leaves, ts, ys)


@eqx.filter_jit
def _outputs_filtered(scene: Scene, ts, ys) -> dict[str, Array]:
    return jax.vmap(scene.outputs)(ts, ys)


def _finite(y) -> Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(y)]))


def _check_result(result, y_final):
    """The outcome code of a run (`jaxdyn.Outcome`), and `y_final` with a runtime error
    attached where it is a failure, whose message names the cause and what to change."""
    code = from_diffrax(result, _finite(y_final))
    y_final = eqx.branched_error_if(y_final, ~is_success(code), code,
                                    [MESSAGES[o] for o in Outcome])
    return y_final, code


def check_tolerances(rtol, atol, dtype) -> tuple:
    """`rtol` and `atol` as arrays of `dtype`, refused where the dtype cannot reach them or
    where they are not tolerances (shared by every entry point that integrates). Traced values
    (a jitted function of `rtol`) are not checked."""
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
    return jnp.asarray(rtol, dtype), jnp.asarray(atol, dtype)


def _event(scene: Scene, t0, y0, time_scale) -> dfx.Event | None:
    fns = scene.events()
    if not fns:
        return None

    def wrap(f):
        # The root finder's tolerance applies to the time and to the condition alike: the
        # condition is measured in units of its initial value and of the scene's time scale,
        # so both are relative, whatever the units. diffrax compares the condition with a
        # Python 0.0 in a `lax.cond`: with x64 enabled that is float64, so the condition is
        # returned in the default float type.
        c0 = f(t0, y0)
        k = time_scale / jnp.where(jnp.isfinite(c0) & (c0 > 0), c0, 1.0)
        return lambda t, y, args, **kwargs: (k * f(t, y)).astype(jnp.result_type(float))

    tol = 1e-12 if t0.dtype == jnp.float64 else 1e-6
    return dfx.Event(
        cond_fn={name: wrap(f) for name, f in fns.items()},
        root_finder=optx.Newton(rtol=tol, atol=tol * time_scale),
    )


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
    if stepsize_controller is None and not isinstance(solver, dfx.AbstractAdaptiveSolver):
        if dt0 is None:
            raise ParameterError(
                f"solver {type(solver).__name__} takes fixed steps: give dt0 (the step size)"
            )
        stepsize_controller = dfx.ConstantStepSize()
    if stepsize_controller is None:
        rtol, atol = check_tolerances(rtol, atol, dtype)
        stepsize_controller = ScaledPIDController(rtol=rtol, atol=atol)
    dt0 = None if dt0 is None else jnp.asarray(dt0, dtype)
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
    - `dt0`: initial step (chosen automatically by default for adaptive controllers).
    - `max_steps`: an error is raised, never a silently truncated result, if more are needed.
    - `adjoint`: any diffrax adjoint (default `diffrax.RecursiveCheckpointAdjoint()`).
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
    traced = not is_concrete(scene, y0, t0, t1, ts)
    adjoint = dfx.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
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


_FIELDS = ("ts", "ys", "t_final", "y_final", "event", "result", "outcome", "stats",
           "interpolation")
_CHECKED: set = set()  # (scene structure, state layout) pairs whose layout was checked


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
    if not isinstance(scene, Scene) or not isinstance(y0, dict) or not isinstance(
            max_steps, int) or isinstance(max_steps, bool) or max_steps <= 0:
        return None
    leaves, treedef = jax.tree_util.tree_flatten(scene)
    values = list(y0.values())
    times = [t for t in (t0, t1) if not isinstance(t, float | int | np.floating)]
    if not _concrete_arrays(*leaves, *values, *times) or any(np.ndim(t) for t in times) \
            or isinstance(ts, jax.core.Tracer):
        return None
    layout = (treedef, tuple((k, np.shape(v), v.dtype) for k, v in y0.items()))
    if layout not in _CHECKED:
        y0 = scene.check_state(y0)  # raises on a wrong layout
        dtype = jnp.result_type(*jax.tree_util.tree_leaves(y0))
        if not jnp.issubdtype(dtype, jnp.floating) or len({v.dtype for v in y0.values()}) > 1:
            return None
        _CHECKED.add(layout)
    dtype = values[0].dtype
    _check_state_values(scene, y0)
    t0f, t1f = float(t0), float(t1)
    _check_span(t0f, t1f, dtype)
    if ts is not None:
        ts = np.asarray(ts, dtype)
        _check_ts(ts, t0f, t1f)
    rtol, atol = _host_tolerances(rtol, atol, dtype)
    def build(treedef):
        def simulate_program(leaves, y0, t0, t1, ts, rtol, atol):
            scene = jax.tree_util.tree_unflatten(treedef, leaves)
            traj = _simulate_impl(
                scene, y0, t0, t1, ts, solver=dfx.Tsit5(),
                controller=ScaledPIDController(rtol=rtol, atol=atol), dt0=None,
                max_steps=max_steps, adjoint=dfx.RecursiveCheckpointAdjoint(), events=events,
                meter=dfx.NoProgressMeter(), dense=dense, checks=False, solver_saves=True)
            return tuple(getattr(traj, name) for name in _FIELDS)

        return simulate_program

    program = _structure_program("simulate", treedef, (max_steps, bool(events), bool(dense)),
                                 build)
    out = program(leaves, y0, np.asarray(t0f, dtype), np.asarray(t1f, dtype), ts,
                  np.asarray(rtol, dtype), np.asarray(atol, dtype))
    # Built as equinox unflattens a module (its fields were checked inside the program), not
    # through `__init__`: the scene is the caller's own, not a copy from the device.
    traj = object.__new__(Trajectory)
    object.__setattr__(traj, "scene", scene)
    for name, value in zip(_FIELDS, out):
        object.__setattr__(traj, name, value)
    raise_on_failure(traj)
    return traj


def _check_span(t0: float, t1: float, dtype) -> None:
    if not (np.isfinite(t0) and np.isfinite(t1)):
        raise ParameterError(f"t0={t0:g}, t1={t1:g}: times must be finite")
    if not t1 > t0:
        raise ParameterError(f"t1={t1:g}: must be greater than t0={t0:g}")
    span, tiny = t1 - t0, float(jnp.finfo(dtype).tiny)
    resolution = 64 * float(jnp.finfo(dtype).eps) * max(abs(t0), abs(t1))
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


@functools.lru_cache(maxsize=256)
def _host_tolerances_cached(rtol, atol, dtype_name):
    r, a = check_tolerances(rtol, atol, jnp.dtype(dtype_name))
    return float(r), float(a)


def _host_tolerances(rtol, atol, dtype):
    try:
        return _host_tolerances_cached(rtol, atol, jnp.dtype(dtype).name)
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


def raise_on_failure(traj: Trajectory) -> None:
    """Raise [`jaxdyn.SimulationError`][] on the host where a run failed (its message names
    the cause and what to change)."""
    code = int(traj.outcome)
    if code in (Outcome.completed, Outcome.event):
        return
    stats = traj.stats
    if (code == Outcome.max_steps_reached and "num_switches" in stats
            and int(stats["num_steps"]) <= int(stats["max_steps"])):
        from ._hybrid import _too_many_switches

        raise SimulationError(code, _too_many_switches(traj.scene))
    raise SimulationError(code)


def _simulate_impl(scene, y0, t0, t1, ts, *, solver, controller, dt0, max_steps, adjoint,
                   events, meter, dense, checks=True, solver_saves=False) -> Trajectory:
    # checks=False (ensembles): failures are left in `Trajectory.result` instead of raised.
    # solver_saves: the solver saves at `ts` (see `Sampled`), not diffrax's `SaveAt(ts)`.
    if checks:
        y0 = scene.check(y0)
    if isinstance(controller, ScaledPIDController):
        controller = controller.bind(scene, t0, t1, y0)
        time_scale = controller.time_scale
    else:  # a controller of the user's: the time scale is still the events'
        time_scale = scene.natural_scales(t0, t1, y0)[1]
    if events and scene.max_switches > 0:
        from ._hybrid import simulate_hybrid

        return simulate_hybrid(scene, y0, t0, t1, ts, solver=solver, controller=controller,
                               dt0=dt0, max_steps=max_steps, adjoint=adjoint, meter=meter,
                               dense=dense, checks=checks, time_scale=time_scale)
    event = _event(scene, t0, y0, time_scale) if events else None
    # Traced sample times are saved by the solver itself (`Sampled`): `SaveAt(ts)` of traced
    # times carries diffrax's runtime check of them, a host callback.
    # (Not for implicit solvers: diffrax reads their root finder, which the wrapper hides.)
    sampled = (solver_saves and ts is not None
               and not isinstance(solver, dfx.AbstractImplicitSolver))
    if sampled:
        if isinstance(adjoint, dfx.ForwardMode) and getattr(solver, "scan_kind", "") is None:
            # What diffrax does for forward mode, done before wrapping (it cannot see inside).
            solver = eqx.tree_at(lambda s: s.scan_kind, solver, "lax",
                                 is_leaf=lambda x: x is None)
        solver = Sampled(solver, ts)
        saveat = dfx.SaveAt(t1=True, solver_state=True, dense=dense)
    else:
        first = dfx.SubSaveAt(t0=True) if ts is None else dfx.SubSaveAt(ts=ts)
        saveat = dfx.SaveAt(subs=[first, dfx.SubSaveAt(t1=True)], dense=dense)
    sol = dfx.diffeqsolve(
        dfx.ODETerm(scene.vector_field),
        solver,
        t0,
        t1,
        dt0,
        y0,
        saveat=saveat,
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,
        args=scene,  # solvers that exploit the scene's structure (splittings) read it here
        event=event,
        progress_meter=meter,
        throw=False,
    )
    if sampled:
        # Times not reached, or after a terminating event, are inf, as diffrax leaves them.
        _, ys_saved, reached = sol.solver_state
        t_end, y_end = sol.ts, sol.ys
        kept = (jnp.arange(ts.size) < reached) & (ts <= t_end[0])
        ts_saved = jnp.where(kept, ts, jnp.inf)
        ys_saved = jax.tree.map(
            lambda a: jnp.where(kept.reshape((-1,) + (1,) * (a.ndim - 1)), a, jnp.inf),
            ys_saved)
    else:
        (ts_saved, t_end), (ys_saved, y_end) = sol.ts, sol.ys
    if ts is None:
        ts_saved = jnp.concatenate([ts_saved, t_end])
        ys_saved = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), ys_saved, y_end)
    fired = {} if event is None else dict(sol.event_mask)
    y_final = jax.tree.map(lambda a: a[0], y_end)
    if checks:
        y_final, outcome = _check_result(sol.result, y_final)
    else:
        outcome = from_diffrax(sol.result, _finite(y_final))
    t_final = t_end[0]
    if event is not None:
        # A terminating event already reached at the start ends the run there.
        at_start = {name: f(t0, y0) <= 0 for name, f in scene.events().items()}
        started = jnp.any(jnp.stack(list(at_start.values())))
        fired = {name: fired[name] | at_start[name] for name in fired}
        t_final = jnp.where(started, t0, t_final)
        y_final = jax.tree.map(lambda a, b: jnp.where(started, a, b), y0, y_final)
    return Trajectory(
        scene=scene,
        ts=ts_saved,
        ys=ys_saved,
        t_final=t_final,
        y_final=y_final,
        event=fired,
        result=sol.result,
        outcome=outcome,
        stats=dict(sol.stats),
        interpolation=sol.interpolation,
    )


_simulate = eqx.filter_jit(_simulate_impl)
