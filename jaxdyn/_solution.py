"""The result of a run: [`jaxdyn.Trajectory`][] (as diffrax keeps `Solution` in
`_solution.py`), the dense output merged over the segments of a run, derived outputs, and the
host-side report of a failure."""

import dataclasses
import weakref
from typing import Any

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._custom_types import State
from ._outcome import NAMES, Outcome, SimulationError
from ._padded import over_padded_times
from ._programs import StoredProgram, forgotten_on_clear
from ._scene import Scene
from ._validation import ParameterError, as_float_array, is_concrete, on_host


class MergedInterpolation(eqx.Module):
    """Dense output of a run of several segments: the solver's local interpolants of every
    accepted step, merged into one table (the same interface as
    `diffrax.DenseInterpolation.evaluate`).

    Times within a run are looked up among the step boundaries, where the last step of each
    segment ends at its event time; at a switch time the state before the switch is returned.
    """

    t0: Array
    t1: Array
    bounds: Array  # step start times, then the end of the run, then inf
    t_lo: Array  # each step's own interval, for its interpolant
    t_hi: Array
    infos: dict
    rows: Array  # number of steps
    y_end: State
    interpolation_cls: type = eqx.field(static=True)

    def evaluate(self, t, t1=None, left: bool = True) -> State:
        """The state at time `t` (nan outside the run)."""
        t = jnp.asarray(t, self.t0.dtype)
        i = jnp.searchsorted(self.bounds, t, side="left" if left else "right")
        i = jnp.clip(i.astype(self.rows.dtype) - 1, 0, jnp.maximum(self.rows - 1, 0))
        info = jax.tree.map(lambda a: a[i], self.infos)
        y = self.interpolation_cls(t0=self.t_lo[i], t1=self.t_hi[i], **info).evaluate(t)
        outside = (t < self.t0) | (t > self.t1)
        return jax.tree.map(
            lambda a, b: jnp.where(outside, jnp.nan, jnp.where(self.rows == 0, b, a)),
            y, self.y_end,
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
    interpolation: dfx.DenseInterpolation | MergedInterpolation | None = None

    def evaluate(self, t: Float[ArrayLike, " times"]) -> State:
        """States at times `t` within the run, from its start to `t_final` (the event time
        where an event ended it), from the solver's dense output (`simulate(..., dense=True)`):
        for one time, a state; for a 1-D array of times, the states stacked along a first
        axis. Times outside the run give nan (as saved times after an event are `inf`): also
        past an event within the last step, where the step's interpolant would go on. A new
        number of times reuses the compiled program (the times are padded to one of a few
        lengths), so a slider over the resolution costs a call, not a compilation."""
        if self.interpolation is None:
            raise ParameterError("evaluate needs the dense output: simulate(..., dense=True)")
        dtype = self.t_final.dtype
        if is_concrete(t):  # (times given on the host stay there, copied, until the call)
            t = as_float_array("t", t, None, dtype, host=True)
        else:  # traced, or a list holding traced values
            t = jnp.asarray(t, dtype)
        if t.ndim > 1:
            raise ParameterError(f"t has shape {t.shape}: expected a time or a 1-D array of "
                                 "times")

        def evaluate(t):
            return _trajectory_program("evaluate", _evaluate_of, _evaluate_filtered, self,
                                       dynamic=(t,))

        if t.ndim == 1:  # a new number of times reuses the program (`jaxdyn._padded`)
            return over_padded_times(evaluate, t, self.t_final)
        return evaluate(t)

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
        xp, ts, t_final = on_host(self.ts, self.t_final)  # (NumPy where concrete: eager
        valid = xp.isfinite(ts) & (ts <= t_final)  # `jnp` compiled three programs)
        return jax.device_put(valid) if xp is np else valid

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
        scene = self.scene
        last = _LAST_OUTPUTS[0]  # (one read: another thread may replace it)
        if last[0] is scene:
            # The scene of the last access (`jd.simulate` keeps the caller's scene, so every
            # run of it): its leaves, output names and program, without flattening the scene
            # or looking them up; and the program's call, where this is the last access's
            # trajectory too.
            _, leaves, names, program, last_traj, call = last
            if name in names:
                ts, ys = self.ts, self.ys
                if last_traj() is not self:
                    call = program.resolve(leaves, ts, ys)
                    _remember(self, scene, leaves, names, program, call)
                return call(leaves, ts, ys)[name]
        flat = jax.tree_util.tree_flatten(scene)  # (once for both)
        names = Scene.output_names(scene, flat)  # (not a bound method: equinox wraps those)
        if name in names:
            ts, ys = self.ts, self.ys
            found = _outputs_call(scene, ts, ys, flat)
            if found is None:
                return _outputs_filtered(scene, ts, ys)[name]
            program, call, leaves = found
            _remember(self, scene, leaves, names, program, call)
            return call(leaves, ts, ys)[name]
        raise AttributeError(
            f"Trajectory has no attribute {name!r}; derived outputs of this scene: {list(names)}"
        )


def _summary(traj: Trajectory) -> dict[str, Any]:
    return _trajectory_program("summary", _summary_of, _summary_filtered, traj)


def _summary_of(traj: Trajectory) -> dict[str, Any]:
    return traj.scene.summary(traj.ts, traj.ys, traj.valid, traj.t_final, traj.y_final,
                              traj.event)


_summary_filtered = eqx.filter_jit(_summary_of)


def _to_python(x):
    a = np.asarray(x)
    if a.ndim == 0:
        v = a.item()
        return v if not isinstance(v, float) or np.isfinite(v) else None
    return [_to_python(v) for v in a]


def _evaluate_of(traj: Trajectory, t) -> State:
    interpolation = traj.interpolation
    y = (jax.vmap(interpolation.evaluate) if t.ndim else interpolation.evaluate)(t)
    outside = ~((t >= interpolation.t0) & (t <= traj.t_final))
    return jax.tree.map(
        lambda v: jnp.where(outside.reshape(outside.shape + (1,) * (v.ndim - t.ndim)),
                            jnp.nan, v), y)


_evaluate_filtered = eqx.filter_jit(_evaluate_of)


def _resample(traj: Trajectory, num: int) -> Trajectory:
    ts, ys = _trajectory_program("resample", _resample_of, _resample_filtered, traj, num)
    return dataclasses.replace(traj, ts=ts, ys=ys)  # (a third of `eqx.tree_at`'s cost)


def _resample_of(traj: Trajectory, num: int):
    """The new samples only: the rest of the trajectory (its dense table, as long as the step
    budget) is not copied through the program's outputs."""
    ts = jnp.linspace(traj.interpolation.t0, traj.t_final, num)
    return ts, jax.vmap(traj.interpolation.evaluate)(ts)


_resample_filtered = eqx.filter_jit(_resample_of)  # (`num`, a Python int, is static)


_PROGRAMS: dict = {}  # jax.jit programs by (name, scene structure, options)


def _concrete_arrays(*values) -> bool:
    """Whether every value is a concrete array (no tracer, no Python function): a scene made
    of such leaves can be passed to a `jax.jit` program as its flat leaves."""
    return all(isinstance(x, jax.Array | np.ndarray) and not isinstance(x, jax.core.Tracer)
               for x in values)


def _structure_program(name: str, treedef, options, build, *, light: bool = False):
    """The `jax.jit` program `build(treedef)` for one scene structure (and static options),
    built once: later calls pass only arrays, so dispatch costs what `jax.jit`'s costs.
    `light`: compiled with XLA's cheap settings (`_programs`)."""
    key = (name, treedef, options)
    program = _PROGRAMS.get(key)
    if program is None:  # (one for all threads: a prepared program's worker may make it)
        program = _PROGRAMS.setdefault(key, StoredProgram(name, treedef, options,
                                                          build(treedef), light=light))
    return program


def _trajectory_program(name: str, fn, filtered, traj: Trajectory, *static, dynamic=()):
    """`fn(traj, *dynamic, *static)` as one program per trajectory structure (and static
    values), called with the trajectory's arrays and the `dynamic` arrays (`filtered`,
    equinox's filtered `fn`, where any of them holds anything else)."""
    leaves, treedef = jax.tree_util.tree_flatten(traj)
    if not _concrete_arrays(*leaves, *dynamic):
        return filtered(traj, *dynamic, *static)
    return _trajectory_stored(name, fn, treedef, static)(leaves, *dynamic)


# Light programs (`_programs`): the trajectory's summary and its resampling, each one pass over
# the trajectory made once per run (a command's report), where compiling costs a hundred to a
# thousand times running. Not `evaluate`, which a user calls again and again at the same
# times (a plot, an animation's frames) and whose compilation is shared by every number of
# times of a padded length: compiled so, a call at 200 times took 2.8-3.0x a hand-written
# `jax.jit` of the same interpolation instead of 1.5-2.5x (`benchmarks/latency.py`, 7 Dec 2026).
_LIGHT_PROGRAMS = ("summary", "resample")  # (by name)


def _trajectory_stored(name: str, fn, treedef, static) -> StoredProgram:
    """The program of `_trajectory_program` for one trajectory structure."""
    def build(treedef):
        def program(leaves, *dynamic):
            return fn(jax.tree_util.tree_unflatten(treedef, leaves), *dynamic, *static)

        program.__name__ = program.__qualname__ = name
        return program

    return _structure_program(name, treedef, static, build, light=name in _LIGHT_PROGRAMS)


def prepare_report(traj: Trajectory, num: int | None = None) -> None:
    """Have the programs of `traj.resample(num).report()` (`num=None`: of `traj.report()`)
    `prepare`d for a trajectory of `traj`'s structure, shapes and dtypes (its arrays may be
    `jax.ShapeDtypeStruct`s: the shapes of a run not yet compiled, `_simulate.then_prepare`),
    so that they are traced and compiled on another core while this thread compiles the run
    (`StoredProgram.prepare`); the summary's once the resampling's outputs are known.
    Nothing where the trajectory holds anything but arrays (its calls go through equinox's
    filtered programs, not these)."""
    def summary(traj):
        leaves, treedef = jax.tree_util.tree_flatten(traj)
        if _shapes_and_arrays(leaves):
            _trajectory_stored("summary", _summary_of, treedef, ()).prepare(leaves)

    if num is None:
        summary(traj)
        return
    leaves, treedef = jax.tree_util.tree_flatten(traj)
    if _shapes_and_arrays(leaves) and traj.interpolation is not None:
        _trajectory_stored("resample", _resample_of, treedef, (num,)).prepare(
            leaves, then=lambda samples: summary(
                dataclasses.replace(traj, ts=samples[0], ys=samples[1])))


def _shapes_and_arrays(leaves) -> bool:
    return all(isinstance(x, jax.ShapeDtypeStruct) or _concrete_arrays(x) for x in leaves)


# The last concrete derived-output access: its scene (held, so that its identity cannot be
# reused while it is here; a scene holds parameters), the scene's leaves, output names and
# program, its trajectory (a weak reference: its samples are not kept alive) and the
# program's call for that trajectory's times and states.
_NO_OUTPUTS = (None, None, None, None, lambda: None, None)
_LAST_OUTPUTS: list = [_NO_OUTPUTS]


@forgotten_on_clear
def _forget_last_outputs() -> None:
    _LAST_OUTPUTS[0] = _NO_OUTPUTS


def _remember(traj, scene, leaves, names, program, call) -> None:
    """Remember a derived-output access for the next (not one of traced times or states)."""
    if _concrete_arrays(traj.ts, *jax.tree.leaves(traj.ys)):
        _LAST_OUTPUTS[0] = (scene, leaves, names, program, weakref.ref(traj), call)


def _outputs_call(scene: Scene, ts, ys, flat=None):
    """The derived-output program of the scene's structure, its call for these times and
    states and the scene's leaves; `None` where the scene holds anything but arrays (Python
    functions, traced values: equinox's filtered call instead)."""
    leaves, treedef = flat if flat is not None else jax.tree_util.tree_flatten(scene)
    if not _concrete_arrays(*leaves):
        return None

    def build(treedef):
        def outputs_program(leaves, ts, ys):
            scene = jax.tree_util.tree_unflatten(treedef, leaves)
            return jax.vmap(scene.outputs)(ts, ys)

        return outputs_program

    program = _structure_program("outputs", treedef, (), build)
    return program, program.resolve(leaves, ts, ys), leaves


def _outputs(scene: Scene, ts, ys, flat=None) -> dict[str, Array]:
    """Every derived output at the times `ts`: one `jax.jit` program per scene structure,
    called with arrays only (equinox's filtered call where the scene holds Python functions
    or the values are traced). `flat`: the scene's `tree_flatten`, where the caller has it."""
    found = _outputs_call(scene, ts, ys, flat)
    if found is None:
        return _outputs_filtered(scene, ts, ys)
    _, call, leaves = found
    return call(leaves, ts, ys)


@eqx.filter_jit
def _outputs_filtered(scene: Scene, ts, ys) -> dict[str, Array]:
    return jax.vmap(scene.outputs)(ts, ys)


def raise_on_failure(traj: Trajectory) -> None:
    """Raise [`jaxdyn.SimulationError`][] on the host where a run failed (its message names
    the cause and what to change)."""
    code = int(traj.outcome)
    if code in (Outcome.completed, Outcome.event):
        return
    stats = traj.stats
    if (code == Outcome.max_steps_reached and "num_switches" in stats
            and int(stats["num_steps"]) <= int(stats["max_steps"])):
        raise SimulationError(code, too_many_switches(traj.scene))
    raise SimulationError(code)



def too_many_switches(scene) -> str:
    """The message of a run that needed more switches than its scene allows."""
    whose = [f"a {scene.body.kind}"] if scene.body.max_switches else []
    whose += [f"{label} {e.max_switches}" for label, e in zip(scene.labels, scene.effects)
              if e.max_switches]
    return (f"the run needed more than {scene.max_switches} mode switches before t1 (the most "
            f"{', '.join(whose)} allows): shorten t1"
            + ("" if scene.body.max_switches else " or raise max_switches"))
