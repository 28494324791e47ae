"""Monte Carlo ensembles: many runs of one scene with varied parameters and initial states."""

import concurrent.futures
import dataclasses
import functools
import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from typing import Any, NamedTuple

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _batch_solve
from ._batch_solve import STATUS, STATUS_HELP, Switching, batch_solve, tableau
from ._chunkstore import ChunkStore, digest
from ._distributions import AbstractDistribution, name_seed, split_name
from ._hybrid import FORWARD, Watch
from ._outcome import Outcome, to_diffrax
from ._programs import forgotten_on_clear, start_prepared
from ._scene import Scene
from ._simulate import _prepare_run, _simulate, tolerance_values
from ._solution import Trajectory
from ._stored_jit import stored_filter_jit
from ._tolerance import FLOOR, ScaledPIDController
from ._validation import ParameterError, device_array, key_from_seed

MODES = ("adaptive", "lockstep", "vmap")
_OK = (STATUS.index("completed"), STATUS.index("event"))
_QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)


def final_state(traj: Trajectory) -> dict[str, jax.Array]:
    """The default observation of one run: every derived output at the final time, the final
    time `t_final`, and for each terminating event whether it ended the run."""
    out = {k: v[0] for k, v in traj.final_outputs().items()}
    out["t_final"] = traj.t_final
    out.update({f"event.{k}": v for k, v in traj.event.items()})
    return out


@dataclasses.dataclass(frozen=True)
class Ensemble:
    """The result of [`jaxdyn.ensemble`][].

    - `n`, `completed`, `failed`: trajectories in all, those that reached `t1` or ended in a
      terminating event, and those that did not (see `status`).
    - `status`: per-trajectory codes, names in `status_names` (`"completed"`, `"event"`,
      `"max_steps_reached"`, `"step_size_underflow"`, `"non_finite"`, `"invalid_input"`).
    - `values`: the kept observations, name -> array with a leading axis of length `n` (values of
      failed trajectories are not meaningful: mask with `ok`).
    - `statistics`: name -> `count`, `mean`, `std`, `min`, `max` (and `quantiles` for kept
      values) over the successful trajectories. The moments are accumulated chunk by chunk;
      the quantiles, a sort of the kept values, are computed when first asked for
      (`moments`: the statistics without quantiles).
    - `steps`: accepted steps per trajectory.
    - `timing`: `compile_s`, `run_s` (after compilation), `trajectories_per_s`.
    """

    n: int
    status: np.ndarray
    values: dict[str, np.ndarray]
    moments: dict[str, dict[str, np.ndarray]] = dataclasses.field(repr=False)
    steps: np.ndarray
    reasons: dict[int, str]
    mode: str
    chunk_size: int
    devices: int
    timing: dict[str, float]
    resumed_chunks: int = 0
    recomputed_chunks: tuple[int, ...] = ()
    drawn: Callable[[], dict[str, np.ndarray]] | None = dataclasses.field(
        default=None, repr=False, compare=False)

    def varied(self) -> dict[str, np.ndarray]:
        """The values each trajectory ran with, name -> array with a leading axis of length
        `n`: the per-trajectory inputs given (`y0` or `parameters` with a batch axis) and the
        values drawn for `vary` (recomputed from the key: trajectory `i` draws from
        `fold_in(key, i)`, so they are the very values it ran with)."""
        return {} if self.drawn is None else self.drawn()

    @staticmethod
    def read(directory: str | os.PathLike) -> "Ensemble":
        """The ensemble of a run written to `directory` by `jaxdyn montecarlo --out DIR` or
        `jd.ensemble(..., out=DIR)`, every chunk file checked; `varied()`, `to_dataframe()`
        and `to_xarray()` work as on the run itself. A run that has not finished is refused,
        naming its missing chunks."""
        return read_ensemble(directory)

    def to_dataframe(self):
        """A pandas `DataFrame`, one row per trajectory: `status` (by name), `steps`, the
        varied values, then the kept observations (array values split into columns
        `omega[0]`, ...). Needs the values kept (`keep=True`) and pandas (`jaxdyn[data]`)."""
        from ._export import ensemble_to_dataframe

        return ensemble_to_dataframe(self)

    def to_xarray(self):
        """An xarray `Dataset` over the dimension `trajectory`: `status`, `steps`, the varied
        values and the kept observations as variables (xarray: `jaxdyn[data]`); write it with
        `.to_netcdf(path)`."""
        from ._export import ensemble_to_xarray

        return ensemble_to_xarray(self)

    status_names = STATUS

    @functools.cached_property
    def statistics(self) -> dict[str, dict[str, Any]]:
        out = {}
        ok = self.ok
        for name, s in self.moments.items():
            s = dict(s)
            if name in self.values:
                v = self.values[name][ok].astype(np.float64)
                finite = np.isfinite(v)
                with np.errstate(invalid="ignore"):
                    if not v.shape[0]:
                        q = np.full((len(_QUANTILES),) + v.shape[1:], np.nan)
                    elif finite.all():  # (nanquantile goes column by column in Python)
                        q = np.quantile(v, _QUANTILES, axis=0)
                    else:
                        q = np.nanquantile(np.where(finite, v, np.nan), _QUANTILES, axis=0)
                s["quantiles"] = {f"{int(p * 100)}%": q[i] for i, p in enumerate(_QUANTILES)}
            out[name] = s
        return out

    @property
    def ok(self) -> np.ndarray:
        return np.isin(self.status, _OK)

    @property
    def completed(self) -> int:
        return int(np.sum(self.ok))

    @property
    def failed(self) -> int:
        return self.n - self.completed

    def status_counts(self) -> dict[str, int]:
        return {name: int(np.sum(self.status == i)) for i, name in enumerate(STATUS)
                if np.any(self.status == i)}

    def failures(self, limit: int = 10) -> list[dict[str, Any]]:
        """The first `limit` failed trajectories: index, status and what it means."""
        out = []
        for i in np.flatnonzero(~self.ok)[:limit]:
            name = STATUS[int(self.status[i])]
            why = self.reasons.get(int(i), STATUS_HELP.get(name, ""))
            out.append({"index": int(i), "status": name, "message": why})
        return out

    def report(self) -> dict[str, Any]:
        """JSON-ready summary: `n`, `completed`, `failed`, `status`, `statistics`, and how the
        run went (mode, chunk size, devices, timing)."""
        return {
            "n": self.n,
            "completed": self.completed,
            "failed": self.failed,
            "status": self.status_counts(),
            "failures": self.failures(5),
            "statistics": _jsonable(self.statistics),
            "mode": self.mode,
            "chunk_size": self.chunk_size,
            "devices": self.devices,
            "mean_steps": float(np.mean(self.steps)) if self.n else 0.0,
            "timing": self.timing,
            "resumed_chunks": self.resumed_chunks,
            "recomputed_chunks": list(self.recomputed_chunks),
        }


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    a = np.asarray(x)
    if a.ndim == 0:
        v = a.item()
        return None if isinstance(v, float) and not math.isfinite(v) else v
    return [_jsonable(v) for v in a]


# -- streaming statistics ----------------------------------------------------------------------

class _Moments:
    """Count, mean, sum of squared deviations, min and max, merged chunk by chunk (Chan et
    al. 1979), per component, over finite values."""

    FIELDS = ("count", "mean", "m2", "min", "max")

    def __init__(self):
        self.count = self.mean = self.m2 = self.min = self.max = None

    def add(self, count, mean, m2, lo, hi) -> None:
        """Merge one chunk's moments (as `_chunk_moments` computes them)."""
        n, mean, m2 = (np.asarray(x, np.float64) for x in (count, mean, m2))
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        if self.count is None:
            self.count, self.mean, self.m2, self.min, self.max = n, mean, m2, lo, hi
            return
        total = self.count + n
        delta = mean - self.mean
        with np.errstate(invalid="ignore", divide="ignore"):
            w = np.where(total > 0, n / np.maximum(total, 1), 0.0)
        self.mean = self.mean + delta * w
        self.m2 = self.m2 + m2 + delta**2 * self.count * w
        self.count = total
        self.min = np.minimum(self.min, lo)
        self.max = np.maximum(self.max, hi)

    def result(self) -> dict[str, Any]:
        with np.errstate(invalid="ignore", divide="ignore"):
            std = np.sqrt(np.where(self.count > 1, self.m2 / np.maximum(self.count - 1, 1),
                                   np.nan))
        nan = np.where(self.count > 0, 0.0, np.nan)
        return {"count": self.count.astype(np.int64), "mean": self.mean + nan, "std": std,
                "min": self.min + nan, "max": self.max + nan}


# -- what is varied ----------------------------------------------------------------------------

class _Target(NamedTuple):
    """One varied name, resolved: `kind` is `"state"` or `"parameter"`, `base` the variable or
    parameter, `index` the component (or `None`: all of it), `shape` what is drawn."""

    name: str
    kind: str
    base: str
    index: tuple[int, ...] | None
    shape: tuple[int, ...]
    dist: AbstractDistribution | None


def _targets(scene: Scene, vary: Mapping[str, AbstractDistribution]) -> tuple[_Target, ...]:
    """Resolve and check the varied names."""
    state = scene.state_shapes()
    params = scene.parameters()
    out = []
    for name, dist in vary.items():
        if not isinstance(dist, AbstractDistribution):
            raise ParameterError(
                f"vary[{name!r}]={dist!r}: expected a distribution (jaxdyn.Normal, Uniform, "
                "LogNormal, Fixed)")
        base, index = split_name(name)
        if base in state:
            kind, shape = "state", state[base]
        elif base in params:
            kind, shape = "parameter", tuple(np.shape(params[base]))
        else:
            raise ParameterError(
                f"vary: unknown name {base!r}: this scene's parameters are {sorted(params)} and "
                f"its initial values {sorted(state)}")
        if index is not None:
            if len(index) != len(shape) or any(not -s <= i < s for i, s in zip(index, shape)):
                raise ParameterError(
                    f"vary: {name!r}: index out of range for {base} of shape {shape}")
            shape = ()
        try:
            np.broadcast_shapes(dist.shape, shape)
            if np.broadcast_shapes(dist.shape, shape) != shape:
                raise ValueError
        except ValueError:
            raise ParameterError(
                f"vary[{name!r}]: a distribution of shape {dist.shape} does not fit {base} "
                f"{'component' if index is not None else 'of shape ' + str(shape)}") from None
        out.append(_Target(name, kind, base, index, shape, dist))
    return tuple(out)


def _drawn(targets, key, index, dtype) -> dict[str, jax.Array]:
    """The values trajectory `index` draws, by varied name: one sub-key per name from
    `fold_in(key, index)`."""
    k = jax.random.fold_in(key, index)
    return {t.name: t.dist.sample(jax.random.fold_in(k, name_seed(t.name)), t.shape, dtype)
            for t in targets}


def _apply(targets, drawn, y0, params, dtype):
    """A trajectory's drawn values (by varied name) applied to its `y0` and parameters."""
    y0, params = dict(y0), dict(params)
    for t in targets:
        v = drawn[t.name]
        store = y0 if t.kind == "state" else params
        old = jnp.asarray(store[t.base], dtype)
        store[t.base] = v if t.index is None else old.at[t.index].set(v)
    return y0, params


@stored_filter_jit
def _draws_of(targets, key, indices, dtype):
    """The values of the varied names (`_drawn`) of trajectories `indices`, by name."""
    return jax.vmap(lambda i: _drawn(targets, key, i, dtype))(indices)


class _Draws:
    """A run's draws: each trajectory's values of the varied names (`_drawn`: from
    `fold_in(key, index)`), for a chunk's indices at a time, by a program of their own. The
    chunk's program takes them as inputs, like the batched rows.

    The program is `prepare`d when the first chunk is launched: it is made ready on the other
    core while XLA compiles the chunk's program (`_programs.start_prepared`, called by
    `_compile_sharded` and `_compile_per_device`). Inside the chunk's program, the random
    bits (threefry's loops) cost 0.3 s of its 1.0-1.15 s of XLA time in a cold `jaxdyn
    montecarlo` of one normal draw on 2 cores. The values each trajectory ran with
    (`Ensemble.varied()`, the chunk files' `varied/`) come from the same program, so they are
    the values the chunks were given, by construction."""

    def __init__(self, inputs: "_Inputs", size: int):
        self.inputs, self.size = inputs, size
        self.compile_s = 0.0  # waiting for the program, or making it, on its first call
        self._made = False
        self._ahead = None  # (first index, draws started) of the next chunk
        # a chunk's draws (a distribution draws in the run's dtype, in its target's shape)
        dtype = np.dtype(inputs.dtype)
        self.spec = {t.name: jax.ShapeDtypeStruct((size, *t.shape), dtype)
                     for t in inputs.targets}

    def prepare(self, indices: np.ndarray) -> None:
        """Have the program made ready on another core while the chunk's compiles."""
        if self.inputs.targets:
            _draws_of.prepare(self.inputs.targets, self.inputs.key, indices, self.inputs.dtype)

    def __call__(self, indices: np.ndarray) -> dict[str, np.ndarray]:
        """The draws of trajectories `indices` (`size` of them), on the host."""
        if not self.inputs.targets:
            return {}
        if self._ahead is not None and self._ahead[0] == int(indices[0]):
            drawn, self._ahead = self._ahead[1], None
        else:
            drawn = self._start(indices)
        return self._on_host(drawn)

    def values(self, indices: np.ndarray) -> dict[str, np.ndarray]:
        """The draws of trajectories `indices`, drawn again (the next chunk's, started
        `ahead`, are left for its launch)."""
        return self._on_host(self._start(indices)) if self.inputs.targets else {}

    def _on_host(self, drawn) -> dict[str, np.ndarray]:
        return {k: np.asarray(drawn[k], s.dtype).reshape(s.shape) for k, s in self.spec.items()}

    def ahead(self, indices: np.ndarray) -> None:
        """Start drawing for trajectories `indices` (the next chunk's to be launched here),
        so that their draws are ready when it is launched. Called before the chunk before it
        is started: a device runs its programs in order, and drawn after it they would wait
        for it."""
        if self.inputs.targets:
            self._ahead = (int(indices[0]), self._start(indices))

    def _start(self, indices):
        start = time.perf_counter()
        drawn = _draws_of(self.inputs.targets, self.inputs.key, indices, self.inputs.dtype)
        if not self._made:
            self._made = True
            self.compile_s += time.perf_counter() - start
        return drawn


# -- one chunk ---------------------------------------------------------------------------------

class _Shared(NamedTuple):
    """What every chunk of a run shares. Its arrays travel as arguments of the compiled chunk
    (new values do not recompile); the rest is static."""

    scene: Scene
    y0: dict[str, Any]  # the unbatched initial values
    params: dict[str, Any]  # the unbatched parameters (varied ones start from the scene's)
    t0: jax.Array
    t1: jax.Array
    ts: Any
    rtol: jax.Array
    atol: jax.Array
    dt0: Any
    n: jax.Array  # trajectories in the run (rows past it are a last chunk's padding)


@dataclasses.dataclass(frozen=True)
class _ChunkConfig:
    """The static settings of the compiled chunk (part of its cache key)."""

    targets: tuple[_Target, ...]  # without their distributions (`_Draws` draws)
    solver: Any
    mode: str
    max_steps: int
    observe: Callable
    events: bool
    compact_rows: int | None


def _scene_of(scene, p):
    return scene.replace(p) if p else scene


def _chunk_core(dyn, rows, *, static, config: _ChunkConfig, axis_name):
    """Simulate and observe one chunk (or one device's shard of it): its observed values,
    their moments over the successful trajectories, and each trajectory's status, reason
    and steps. `rows`: the trajectories' indices, their rows of the batched inputs and their
    draws (`_Draws`)."""
    shared = eqx.combine(dyn, static)
    indices = rows[0]
    y0, params = _chunk_inputs(shared, config, rows)
    flags = jax.vmap(lambda p, y: _scene_of(shared.scene, p).violations(y)[0])(params, y0)
    if config.mode == "vmap":
        trajs, status, reason, steps = _run_vmap(shared, config, params, y0, flags)
    else:
        trajs, status, reason, steps = _run_engine(shared, config, params, y0, flags, axis_name)
    observed = eqx.filter_vmap(config.observe)(trajs)
    if not isinstance(observed, Mapping):
        raise ParameterError(f"observe returned {type(observed).__name__}: expected a dict of "
                             "arrays")
    # Per-chunk moments of every observed value over the successful trajectories (the padding
    # of a last, partial chunk excluded), merged on the host chunk by chunk.
    ok = ((status == _OK[0]) | (status == _OK[1])) & (indices < shared.n)
    # All values as columns of one array: five reductions in all, whatever the outputs.
    m = indices.shape[0]
    columns = [jnp.asarray(observed[k]).astype(shared.t0.dtype).reshape(m, -1)
               for k in sorted(observed)]
    moments = _chunk_moments(jnp.concatenate(columns, axis=1), ok)
    return {"values": dict(observed), "moments": moments, "status": status, "reason": reason,
            "steps": steps}


def _chunk_inputs(shared: _Shared, config: _ChunkConfig, rows):
    """Each trajectory's initial state and parameters: the shared values, its rows of the
    batched inputs, then its draws (drawn by the chunk's draw program, `_Draws`)."""
    indices, batch_y0, batch_params, drawn = rows

    def one(_, by0, bp, values):  # (the indices give the batch its size)
        return _apply(config.targets, values, {**shared.y0, **by0}, {**shared.params, **bp},
                      shared.t0.dtype)

    return jax.vmap(one)(indices, batch_y0, batch_params, drawn)


def _run_vmap(shared: _Shared, config: _ChunkConfig, params, y0, flags):
    """`jax.vmap` over `simulate`'s program: the trajectories, status, reasons and steps."""
    controller = ScaledPIDController(rtol=shared.rtol, atol=shared.atol)

    def run(p, y):
        return _simulate(_scene_of(shared.scene, p), y, shared.t0, shared.t1, shared.ts,
                         solver=config.solver, controller=controller, dt0=shared.dt0,
                         max_steps=config.max_steps, adjoint=FORWARD,
                         events=config.events, meter=dfx.NoProgressMeter(), dense=False,
                         checks=False, solver_saves=True)  # not diffrax's `SaveAt(ts)`: its
        # check of traced times is a host callback, which keeps a program out of the cache

    trajs = eqx.filter_vmap(run)(params, y0)
    invalid = jnp.any(flags, axis=1)
    status = jnp.where(invalid, jnp.int32(Outcome.invalid_input), trajs.outcome)
    reason = jnp.argmax(flags, axis=1).astype(jnp.int32)
    return trajs, status, reason, trajs.stats["num_accepted_steps"]


def _run_engine(shared: _Shared, config: _ChunkConfig, params, y0, flags, axis_name):
    """The batch engine (`batch_solve`): the trajectories, status, reasons and steps."""
    scene, t0, t1, rtol = shared.scene, shared.t0, shared.t1, shared.rtol
    names = tuple(scene.events()) if config.events else ()

    def field(p, t, y):
        return _scene_of(scene, p).vector_field(t, y)

    conditions = None
    if names:
        def conditions(p, t, y):
            fns = _scene_of(scene, p).events()
            return jnp.stack([fns[k](t, y) for k in names])

    def tolerances(p, t, y):  # each variable's floor: FLOOR rtol times its natural scale
        bound = ScaledPIDController(rtol=rtol, atol=shared.atol).bind(
            _scene_of(scene, p), t, t1, y)
        return {k: FLOOR * rtol * v for k, v in bound.scales.items()}, bound.time_scale

    switching = None
    if names and scene.max_switches:
        y0, switching = _switching(scene, t0, params, y0, tolerances)
    floors, time_scale = jax.vmap(partial(tolerances, t=t0))(params, y=y0)
    r = batch_solve(field, conditions, names, flags, params, y0, t0, t1, shared.ts,
                    solver=config.solver, rtol=rtol, atol=floors, max_steps=config.max_steps,
                    lockstep=config.mode == "lockstep", dt0=shared.dt0, axis_name=axis_name,
                    compact_rows=config.compact_rows, time_scale=time_scale,
                    switching=switching)
    trajs = eqx.filter_vmap(partial(_engine_trajectory, scene, t0, shared.ts,
                                    switching is not None))(
        params, y0, r.t_final, r.y_final, r.ys, r.event, r.status, r.steps, r.rejected,
        r.switches)
    return trajs, r.status, r.reason, r.steps


def _switching(scene, t0, params, y0, tolerances):
    """A hybrid scene in the engine: each trajectory's state in its first mode, and how the
    trajectories switch (`Switching`), by the rules of `simulate`'s driver (`Watch`)."""
    dtype = t0.dtype

    def start(p, y):
        y, _, ended = Watch(_scene_of(scene, p), 1.0, dtype).start(t0, y)
        return y, ended

    def switch(p, t, y, hit):
        return Watch(_scene_of(scene, p), 1.0, dtype).at_event(t, y, hit)

    def rescale(p, t, y):  # the floors with the shape of each variable
        floors, time_scale = tolerances(p, t, y)
        return {k: jnp.broadcast_to(v, jnp.shape(y[k])) for k, v in floors.items()}, time_scale

    y0, ended = jax.vmap(start)(params, y0)
    return y0, Switching(switch=switch, rescale=rescale, ended_at_start=ended,
                         max_switches=scene.max_switches)


def _engine_trajectory(scene, t0, ts, switches_kept, p, y_start, t_final, y_final, ys, event,
                       status, steps, rejected, switches) -> Trajectory:
    """One trajectory of the batch engine's results, as `simulate` returns it."""
    if ts is None:
        ts_i = jnp.stack([t0, t_final])
        ys_i = jax.tree.map(lambda a, b: jnp.stack([a, b]), y_start, y_final)
    else:
        ts_i = jnp.where(ts <= t_final, ts, jnp.inf)
        ys_i = ys
    return Trajectory(scene=_scene_of(scene, p), ts=ts_i, ys=ys_i, t_final=t_final,
                      y_final=y_final, event=event, result=to_diffrax(status), outcome=status,
                      stats={"num_accepted_steps": steps, "num_rejected_steps": rejected,
                             **({"num_switches": switches} if switches_kept else {})})


def _chunk_moments(v, ok):
    """Count, mean, sum of squared deviations, min and max of each column of `v` over the rows
    where `ok` and the value is finite."""
    use = ok[:, None] & jnp.isfinite(v)
    count = jnp.sum(use, axis=0).astype(v.dtype)
    mean = jnp.sum(jnp.where(use, v, 0), axis=0) / jnp.maximum(count, 1)
    m2 = jnp.sum(jnp.where(use, (v - mean) ** 2, 0), axis=0)
    lo = jnp.min(jnp.where(use, v, jnp.inf), axis=0)
    hi = jnp.max(jnp.where(use, v, -jnp.inf), axis=0)
    # A leading axis of one: sharded chunks stack their shards' moments along it.
    return {k: x[None] for k, x in
            {"count": count, "mean": mean, "m2": m2, "min": lo, "max": hi}.items()}


_COMPILED: dict = {}
forgotten_on_clear(_COMPILED.clear)

DEFAULT_CHUNK = 16384
"""The largest chunk `ensemble` chooses by itself: large enough that the per-call overhead is
small, small enough that a chunk's working set stays near the CPU's caches."""

CPU_COMPILER_OPTIONS = {"xla_cpu_prefer_vector_width": 512}
"""XLA options of the compiled chunk on CPU devices. XLA's CPU backend prefers 256-bit vectors by
default; the chunk is long runs of arithmetic on contiguous rows, which 512-bit vectors (where
the CPU has them, AVX-512) do about 1.4 times faster. Elsewhere the option changes nothing."""


def _compiled_chunk(dyn, static, sharded, config: _ChunkConfig, devices, chunks: int):
    """The compiled chunk function for these shapes and this configuration (cached), and how
    its inputs are placed: `"per_device"` (a list of single-device programs), a sharding, or
    `None` (one device); also the seconds spent compiling it now. The programs `prepare`d
    meanwhile (the draws') are made ready on the other core while XLA compiles it.

    An adaptive run of several chunks on several devices gets one program per device (see
    `_compile_per_device`); a run of one chunk gets one program over all of them: there is no
    next chunk for a device to go on to, and XLA compiles one program instead of one per device
    (a cold `jaxdyn montecarlo` of 1000 trajectories on 2 cores: 1.2 s of compilation against
    1.85 s for two programs compiled side by side)."""
    leaves, treedef = jax.tree_util.tree_flatten(static)
    per_device = len(devices) > 1 and config.mode == "adaptive" and chunks > 1
    key = (treedef, tuple(leaves), jax.tree.structure(dyn),
           tuple((x.shape, x.dtype) for x in jax.tree.leaves(dyn)),
           jax.tree.structure(sharded),
           tuple((x.shape, x.dtype) for x in jax.tree.leaves(sharded)),
           config, tuple(devices), per_device)
    if key in _COMPILED:
        return _COMPILED[key], 0.0
    options = CPU_COMPILER_OPTIONS if devices[0].platform == "cpu" else None
    start = time.perf_counter()
    if per_device:
        _COMPILED[key] = (_compile_per_device(dyn, static, sharded, config, devices, options),
                          "per_device")
    else:
        _COMPILED[key] = _compile_sharded(dyn, static, sharded, config, devices, options)
    return _COMPILED[key], time.perf_counter() - start


def _compile_per_device(dyn, static, sharded, config, devices, options):
    """One single-device program per device, each given its rows of the chunk.

    Per-trajectory stepping needs nothing across devices. (A program spanning several CPU
    devices is dispatched only once the one before it has finished on every device, so each
    chunk would wait for its slowest shard; single-device programs queue up, and each device
    goes on to its next chunk when it is done with its own rows.)"""
    body = partial(_chunk_core, static=static, config=config, axis_name=None)
    rows = jax.tree.leaves(sharded)[0].shape[0] // len(devices)

    def lower(device):
        where = jax.sharding.SingleDeviceSharding(device)
        spec = [jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype,
                                                            sharding=where), dyn),
                jax.tree.map(lambda x: jax.ShapeDtypeStruct((rows,) + x.shape[1:], x.dtype,
                                                            sharding=where), sharded)]
        return jax.jit(body).lower(*spec)

    lowered = [lower(device) for device in devices]
    start_prepared()
    with concurrent.futures.ThreadPoolExecutor(len(devices)) as pool:  # XLA frees the GIL
        return list(pool.map(lambda lw: lw.compile(options), lowered))


def _compile_sharded(dyn, static, sharded, config, devices, options):
    """One program over every device (the chunk's rows split across a mesh), or over the one
    device: the compiled program and the sharding of its batched inputs."""
    body = partial(_chunk_core, static=static, config=config, axis_name=None)
    sharding, shardings = None, {}
    if len(devices) > 1:
        mesh = jax.sharding.Mesh(np.asarray(devices), ("batch",))
        spec, whole = jax.sharding.PartitionSpec("batch"), jax.sharding.PartitionSpec()
        sharding = jax.sharding.NamedSharding(mesh, spec)
        if config.mode == "vmap":
            # jax.vmap over simulate: XLA partitions the batch itself (diffrax's event root
            # finding does not trace inside shard_map).
            replicated = jax.sharding.NamedSharding(mesh, whole)
            shardings = {"in_shardings": (replicated, sharding), "out_shardings": {
                "values": sharding, "moments": replicated, "status": sharding,
                "reason": sharding, "steps": sharding}}
        else:  # the reductions over the batch (lock-step's step, whether any row still
            # runs) span the shards
            body = jax.shard_map(
                partial(_chunk_core, static=static, config=config, axis_name="batch"),
                mesh=mesh, in_specs=(whole, spec), out_specs=spec, check_vma=False)
    lowered = jax.jit(body, **shardings).lower(dyn, sharded)
    start_prepared()
    return lowered.compile(options), sharding


# -- the ensemble ------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class _Inputs:
    """An ensemble's inputs, resolved and checked."""

    scene: Scene
    targets: tuple[_Target, ...]
    y_single: dict[str, Any]  # unbatched initial values
    y_batch: dict[str, Any]  # initial values with a leading axis of length n
    p_single: dict[str, Any]
    p_batch: dict[str, Any]
    n: int
    key: jax.Array
    t0: jax.Array
    t1: jax.Array
    ts: Any
    solver: Any
    rtol: float
    atol: float
    dt0: Any
    max_steps: int
    mode: str
    events: bool
    observe: Callable
    keep: tuple[str, ...] | None  # the kept observations (None: all)
    vary: dict[str, AbstractDistribution]
    messages: tuple[str, ...]  # what each check of the inputs means, by the index in `reason`

    @property
    def dtype(self):
        return self.t0.dtype


@dataclasses.dataclass(frozen=True)
class Plan:
    """How an ensemble runs: `chunks` chunks of `chunk_size` trajectories, each sharded across
    `devices`, in `mode`; `fingerprint` describes the run for the chunk files of a resumable
    one (`None`: no files)."""

    chunk_size: int
    chunks: int
    devices: tuple[jax.Device, ...]
    mode: str
    fingerprint: dict[str, Any] | None


def _batched(name, tree, shapes, n):
    """Split `tree` (a dict) into unbatched values and values with a leading batch axis."""
    single, batch = {}, {}
    for k, v in tree.items():
        v = np.asarray(v) if not isinstance(v, jax.Array) else v
        want = shapes[k]
        if tuple(v.shape) == tuple(want):
            single[k] = v
        elif tuple(v.shape[1:]) == tuple(want):
            if n is not None and v.shape[0] != n:
                raise ParameterError(
                    f"{name}[{k!r}] has {v.shape[0]} rows: expected n={n} (or shape {want} "
                    "for a value shared by all trajectories)")
            n = v.shape[0]
            batch[k] = v
        else:
            raise ParameterError(
                f"{name}[{k!r}] has shape {tuple(v.shape)}: expected {want} or (n,) + {want}")
    return single, batch, n


def _split_inputs(scene, y0, parameters, targets, n):
    """`y0` and `parameters` split into unbatched and batched values, and the number of
    trajectories (given, or the rows of the batched inputs)."""
    shapes = scene.state_shapes()
    if not isinstance(y0, Mapping) or set(y0) != set(shapes):
        raise ParameterError(
            f"y0 has variables {sorted(y0) if isinstance(y0, Mapping) else type(y0).__name__}: "
            f"this scene integrates {sorted(shapes)}")
    y_single, y_batch, n_rows = _batched("y0", y0, shapes, None)
    nominal = scene.parameters()
    param_shapes = {k: tuple(np.shape(v)) for k, v in nominal.items()}
    parameters = dict(parameters or {})
    unknown = sorted(set(parameters) - set(param_shapes))
    if unknown:
        raise ParameterError(f"parameters: unknown {unknown}: this scene has "
                             f"{sorted(param_shapes)}")
    p_single, p_batch, n_rows = _batched("parameters", parameters, param_shapes, n_rows)
    for t in targets:  # varied parameters start from the scene's values
        if t.kind == "parameter" and t.base not in p_single and t.base not in p_batch:
            p_single[t.base] = nominal[t.base]
    if n is None:
        if n_rows is None:
            raise ParameterError("n: give the number of trajectories (no input has a batch axis)")
        n = n_rows
    if not isinstance(n, int | np.integer) or n <= 0:
        raise ParameterError(f"n={n!r}: must be a positive integer")
    if n_rows is not None and n_rows != n:
        raise ParameterError(f"n={n}: the batched inputs have {n_rows} rows")
    return y_single, y_batch, p_single, p_batch, int(n)


def _resolve(scene, y0, t1, *, n, key, vary, parameters, t0, ts, observe, keep, solver, rtol,
             atol, dt0, max_steps, mode, events) -> _Inputs:
    """The inputs of `ensemble`, checked as `simulate` checks one run's, with defaults
    filled in."""
    if not isinstance(scene, Scene):
        raise ParameterError(f"scene={scene!r}: expected a jaxdyn.Scene")
    if mode not in MODES:
        raise ParameterError(f"mode={mode!r}: allowed are {list(MODES)}")
    vary = dict(vary or {})
    targets = _targets(scene, vary)
    y_single, y_batch, p_single, p_batch, n = _split_inputs(scene, y0, parameters, targets, n)
    # Check the run's settings on one unbatched trajectory, as simulate would.
    example = {k: jnp.asarray(v[0] if k in y_batch else v) for k, v in y0.items()}
    ex_y0, t0, t1, ts, solver, controller, dt0 = _prepare_run(
        scene, example, t0, t1, ts, solver, rtol, atol, None, dt0, max_steps)
    if not isinstance(controller, ScaledPIDController):  # (every mode steps adaptively)
        raise ParameterError(
            f"solver {type(solver).__name__} takes fixed steps: an ensemble's trajectories "
            "take adaptive steps (rtol, atol); use an explicit Runge-Kutta solver with an "
            "error estimate (diffrax.Tsit5, Dopri5, Dopri8), or jd.simulate under jax.vmap")
    rtol, atol = (float(np.asarray(x, t0.dtype)) for x in tolerance_values(rtol, atol, t0.dtype))
    if mode != "vmap":
        switching = [e.kind for e in scene.effects if e.max_switches]
        if events and switching:  # (a body's modes switch in the engine too)
            raise ParameterError(
                f"mode={mode!r}: this scene's effects switch during a run "
                f"({', '.join(switching)}); use mode='vmap'")
        tableau(solver)
    if isinstance(key, int | np.integer):
        key = key_from_seed(key)
    return _Inputs(
        scene=scene, targets=targets, y_single=y_single, y_batch=y_batch, p_single=p_single,
        p_batch=p_batch, n=n, key=key, t0=t0, t1=t1, ts=ts, solver=solver, rtol=rtol,
        atol=atol, dt0=dt0, max_steps=int(max_steps), mode=mode, events=bool(events),
        observe=final_state if observe is None else observe,
        keep=(None if keep else ()) if isinstance(keep, bool) else tuple(keep), vary=vary,
        messages=scene.violation_messages(ex_y0))


def _chunk_size(n: int, d: int, chunk_size) -> int:
    """Trajectories per chunk, a multiple of the `d` devices, no more than the run needs."""
    if chunk_size is None:
        # Equal chunks of at most DEFAULT_CHUNK, so that no chunk is mostly padding, with rows
        # per device a multiple of 8: XLA's CPU loops vectorise whole only over such lengths
        # (a chunk of 7143 rows per device ran at half the speed of one of 7144).
        per_device = math.ceil(n / (math.ceil(n / DEFAULT_CHUNK) * d))
        chunk_size = math.ceil(per_device / 8) * 8 * d
    if not isinstance(chunk_size, int | np.integer) or chunk_size <= 0:
        raise ParameterError(f"chunk_size={chunk_size!r}: must be a positive integer")
    # No larger than the run needs (a chunk of 1e8 rows for n = 10 would only allocate padding).
    return int(math.ceil(min(int(chunk_size), n) / d) * d)


def _fingerprint(inputs: _Inputs, devices) -> dict[str, Any]:
    """The run's description, which the chunk files of a resumable run are checked against."""
    observe = inputs.observe
    return {
        "format": 2,  # chunk files hold per-chunk moments
        "scene": repr(jax.tree.map(lambda x: np.asarray(x).tolist()
                                   if eqx.is_array(x) else x, inputs.scene)),
        "y0": {k: np.asarray(v).tolist() for k, v in inputs.y_single.items()},
        "batched": {k: digest({k: np.asarray(v)})
                    for k, v in {**inputs.y_batch, **inputs.p_batch}.items()},
        "parameters": {k: np.asarray(v).tolist() for k, v in inputs.p_single.items()},
        "vary": {name: repr(d) for name, d in inputs.vary.items()},
        "key": np.asarray(jax.random.key_data(inputs.key)).tolist(),
        "t0": float(inputs.t0), "t1": float(inputs.t1),
        "ts": None if inputs.ts is None else np.asarray(inputs.ts).tolist(),
        "solver": repr(inputs.solver), "rtol": float(inputs.rtol), "atol": float(inputs.atol),
        "tolerance": "natural-scales",
        "dt0": None if inputs.dt0 is None else float(inputs.dt0),
        "max_steps": int(inputs.max_steps),
        "mode": inputs.mode, "events": bool(inputs.events), "dtype": str(inputs.dtype),
        # the results' last bits depend on how a chunk is split across devices
        "devices": len(devices), "platform": devices[0].platform,
        "observe": f"{getattr(observe, '__module__', '')}."
                   f"{getattr(observe, '__qualname__', repr(observe))}",
    }


def _plan(inputs: _Inputs, chunk_size, devices, out) -> Plan:
    """Chunks, devices and (for a run with chunk files) the fingerprint."""
    devices = tuple(jax.local_devices() if devices is None else devices)
    if not devices:
        raise ParameterError("devices: empty list")
    size = _chunk_size(inputs.n, len(devices), chunk_size)
    if out is None and jax.process_count() > 1:
        raise ParameterError(
            f"out: a run shared by {jax.process_count()} processes (jax.distributed) needs an "
            "output directory on a shared file system, where each process writes its chunks")
    return Plan(chunk_size=size, chunks=math.ceil(inputs.n / size), devices=devices,
                mode=inputs.mode,
                fingerprint=None if out is None else _fingerprint(inputs, devices))


class _Chunks:
    """Launches the compiled chunks of a run and brings their results to the host."""

    def __init__(self, inputs: _Inputs, plan: Plan, store: ChunkStore | None):
        self.inputs, self.plan, self.store = inputs, plan, store
        dtype = inputs.dtype
        shared = _Shared(
            scene=inputs.scene,
            y0={k: device_array(v, dtype) for k, v in inputs.y_single.items()},
            params={k: jnp.asarray(v) for k, v in inputs.p_single.items()},
            t0=inputs.t0, t1=inputs.t1, ts=inputs.ts,
            rtol=device_array(inputs.rtol, dtype), atol=device_array(inputs.atol, dtype),
            dt0=inputs.dt0,
            n=device_array(inputs.n, np.uint32))
        self.dyn, self.static = eqx.partition(shared, eqx.is_array)
        self.config = _ChunkConfig(
            targets=tuple(t._replace(dist=None) for t in inputs.targets), solver=inputs.solver,
            mode=inputs.mode, max_steps=inputs.max_steps, observe=inputs.observe,
            events=inputs.events, compact_rows=_batch_solve.COMPACT_ROWS)
        self._compile_s = 0.0
        self._launched = False
        self.draws = _Draws(inputs, plan.chunk_size)
        self._dyn_on: list = []  # the shared inputs, on each device
        self._varied: dict[str, np.ndarray] | None = None  # for the chunk files

    @property
    def compile_s(self) -> float:
        """Seconds spent compiling the chunk's program and the draws' (where waited for)."""
        return self._compile_s + self.draws.compile_s

    def bounds(self, c: int) -> tuple[int, int]:
        size = self.plan.chunk_size
        return c * size, min((c + 1) * size, self.inputs.n)

    def launch(self, c: int, following: int | None = None):
        """Start chunk `c` (JAX dispatches asynchronously), and the draws of chunk `following`
        (the next to be launched here) before it; returns its unfinished results."""
        inputs, devices, size = self.inputs, self.plan.devices, self.plan.chunk_size
        lo, hi = self.bounds(c)
        idx = np.arange(lo, lo + size)
        rows = np.minimum(idx, hi - 1)  # the last chunk is padded with copies of its last row
        # NumPy rows, moved to the devices in one transfer (not a JAX array on the first device
        # first, then resharded).
        batch = (idx.astype(np.uint32),
                 {k: np.asarray(np.asarray(v)[rows], inputs.dtype)
                  for k, v in inputs.y_batch.items()},
                 {k: np.asarray(np.asarray(v)[rows]) for k, v in inputs.p_batch.items()})
        if not self._launched:
            self._launched = True
            self.draws.prepare(batch[0])
        (fn, sharding), seconds = _compiled_chunk(self.dyn, self.static,
                                                  (*batch, self.draws.spec), self.config,
                                                  list(devices), self.plan.chunks)
        self._compile_s += seconds
        sharded = (*batch, self.draws(batch[0]))
        if following is not None:
            self.draws.ahead(np.arange(following * size, (following + 1) * size,
                                       dtype=np.uint32))
        if sharding == "per_device":
            k = size // len(devices)
            if not self._dyn_on:
                self._dyn_on.extend(jax.device_put(self.dyn, device) for device in devices)
            parts = [jax.device_put(jax.tree.map(lambda x: x[i * k:(i + 1) * k], sharded),
                                    device) for i, device in enumerate(devices)]
            result = [f(dy, part) for f, dy, part in zip(fn, self._dyn_on, parts)]
        else:
            sharded = jax.device_put(sharded, sharding if sharding is not None else devices[0])
            result = fn(self.dyn, sharded)
        return c, hi - lo, result

    def finish(self, started) -> dict[str, np.ndarray]:
        """Bring a started chunk's results to the host: what is kept (all values when the
        chunks go to files), the chunk's moments, status, reasons and steps."""
        c, m, result = started
        keep = self.inputs.keep
        if isinstance(result, list):  # one result per device, rows in device order
            result = jax.tree.map(lambda *xs: np.concatenate([np.asarray(x) for x in xs]),
                                  *result)
        arrays = {f"values/{k}": np.asarray(v)[:m] for k, v in result["values"].items()
                  if self.store is not None or keep is None or k in keep}
        arrays.update({f"moments/{f}": np.asarray(v) for f, v in result["moments"].items()})
        arrays.update({f"shape/{k}": np.asarray(v.shape[1:], np.int64)
                       for k, v in result["values"].items()})
        arrays.update({k: np.asarray(result[k])[:m] for k in ("status", "reason", "steps")})
        if self.store is not None:
            # What a reader of the files needs beyond the results: the values each trajectory
            # ran with, and the texts of the invalid-input reasons.
            lo, hi = self.bounds(c)
            if self._varied is None:
                self._varied = _varied(self.inputs, self.draws)()
            arrays.update({f"varied/{k}": v[lo:hi] for k, v in self._varied.items()})
            arrays["messages"] = np.array(list(self.inputs.messages), dtype=np.str_)
            self.store.write(c, arrays)
        return arrays


def _run_chunks(chunks: _Chunks, plan: Plan, store, progress: bool):
    """Every chunk's results, by chunk: read from the store where written, computed where this
    process's share, waited for where another's. Also the number of trajectories computed
    here, their run time (after compilation) and how many chunks were resumed."""
    process, processes = jax.process_index(), jax.process_count()
    results: dict[int, dict] = {}
    todo = []
    for c in range(plan.chunks):
        arrays = store.read(c) if store is not None else None
        if arrays is not None:
            results[c] = arrays
        elif c % processes == process:
            todo.append(c)
    resumed = len(results)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=chunks.inputs.n, unit="traj", desc="ensemble")
        bar.update(sum(hi - lo for lo, hi in map(chunks.bounds, results)))
    # One chunk runs while the host finishes the one before it. The run time excludes the
    # compilation, which happens (once) inside the first launch.
    started, computed, clock = None, 0, time.perf_counter()
    for c, following in zip(todo + [None], todo[1:] + [None, None]):
        nxt = chunks.launch(c, following) if c is not None else None
        if started is not None:
            results[started[0]] = chunks.finish(started)
            computed += started[1]
            if bar is not None:
                bar.update(started[1])
        started = nxt
    run_s = max(time.perf_counter() - clock - chunks.compile_s, 0.0) if todo else 0.0
    if bar is not None:
        bar.close()
    if len(results) < plan.chunks:
        results.update(_wait_for_chunks(store, [c for c in range(plan.chunks)
                                                if c not in results]))
    return results, computed, run_s, resumed


def _moments_by_name(results) -> dict[str, dict[str, np.ndarray]]:
    """The chunks' moments merged (`results`: each chunk's arrays, in chunk order), split by
    observed name: the columns are the observed values in the order of their names."""
    moments = _Moments()
    for arrays in results:
        parts = [arrays[f"moments/{f}"] for f in _Moments.FIELDS]
        for shard in range(parts[0].shape[0]):  # one row of moments per shard
            moments.add(*(x[shard] for x in parts))
    layout = sorted((k[len("shape/"):], tuple(int(d) for d in v))
                    for k, v in results[0].items() if k.startswith("shape/"))
    columns = moments.result()
    by_name, col = {}, 0
    for name, shape in layout:
        size = int(np.prod(shape))
        by_name[name] = {f: x[col: col + size].reshape(shape) for f, x in columns.items()}
        col += size
    return by_name


def _kept_values(results, keep) -> dict[str, np.ndarray]:
    """The kept observations of every chunk, joined in chunk order."""
    kept: dict[str, list] = {}
    for arrays in results:
        for k, v in arrays.items():
            name = k[len("values/"):]
            if k.startswith("values/") and (keep is None or name in keep):
                kept.setdefault(name, []).append(v)
    return {k: np.concatenate(v) for k, v in kept.items()}


def _reasons(results, chunk_size: int, messages) -> dict[int, str]:
    """Why each trajectory with invalid inputs was invalid, by trajectory."""
    reasons = {}
    for c, arrays in enumerate(results):
        for i in np.flatnonzero(arrays["status"] == STATUS.index("invalid_input")):
            reasons[c * chunk_size + int(i)] = messages[int(arrays["reason"][i])]
    return reasons


def _varied(inputs: _Inputs, draws: _Draws) -> Callable[[], dict[str, np.ndarray]]:
    """The values each trajectory ran with, recomputed on demand by the chunks' draw
    program."""
    given = {k: np.asarray(v) for k, v in {**inputs.y_batch, **inputs.p_batch}.items()}

    def varied():
        out = dict(given)
        if inputs.targets:
            chunks = [draws.values(np.arange(lo, lo + draws.size, dtype=np.uint32))
                      for lo in range(0, inputs.n, draws.size)]
            out.update({k: np.concatenate([c[k] for c in chunks])[:inputs.n]
                        for k in chunks[0]})
        return out

    return varied


def ensemble(
    scene: Scene,
    y0: Mapping[str, Any],
    t1: float,
    *,
    n: int | None = None,
    key: jax.Array | int = 0,
    vary: Mapping[str, AbstractDistribution] | None = None,
    parameters: Mapping[str, Any] | None = None,
    t0: float = 0.0,
    ts: Any = None,
    observe: Callable[[Trajectory], Mapping[str, jax.Array]] | None = None,
    keep: bool | Sequence[str] = True,
    solver: dfx.AbstractSolver | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    dt0: float | None = None,
    max_steps: int = 100_000,
    mode: str = "adaptive",
    chunk_size: int | None = None,
    devices: Sequence[jax.Device] | None = None,
    out: str | os.PathLike | None = None,
    progress: bool = False,
    events: bool = True,
) -> Ensemble:
    """Run a scene over a batch of initial states and parameters.

    Trajectory `i` starts from `y0` (row `i` of it where it has a leading batch axis) with the
    scene's parameters (row `i` of `parameters`), then draws the values in `vary` from
    `jax.random.fold_in(key, i)`. It is simulated from `t0` to `t1` (or its terminating event),
    and `observe` reduces it to a few numbers; only those are kept, so memory is bounded by
    `chunk_size` trajectories whatever `n` is.

    **Arguments:**

    - `scene`, `y0`, `t1`, `t0`, `ts`, `solver`, `rtol`, `atol`, `dt0`, `max_steps`, `events`:
      as for [`jaxdyn.simulate`][], per trajectory.
    - `n`: number of trajectories (default: the rows of the batched inputs).
    - `key`: a `jax.random.key` or an integer seed.
    - `vary`: name -> distribution ([`jaxdyn.Normal`][], [`jaxdyn.Uniform`][],
      [`jaxdyn.LogNormal`][], [`jaxdyn.Fixed`][]); names are parameters (`"inertia"`,
      `"rotor.momentum"`) or initial values (`"omega"`), optionally one component
      (`"omega[1]"`).
    - `parameters`: parameter name -> array with a leading axis of length `n`.
    - `observe`: `Trajectory -> dict of arrays`, applied to each run (default
      [`jaxdyn.final_state`][]: the outputs at the final time, `t_final` and event flags).
    - `keep`: which observations to return per trajectory (`True`: all, `False`: none, only
      their statistics, or a list of names).
    - `mode`: `"adaptive"` (each trajectory takes its own steps; the default), `"lockstep"`
      (one step size for the whole batch), or `"vmap"` (`jax.vmap` over `simulate`: any diffrax
      solver, and effects that switch such as [`jaxdyn.Thrusters`][], at a fraction of the
      speed). The first two need an explicit Runge-Kutta solver with an error estimate; hybrid
      bodies such as [`jaxdyn.RoughFloorRod`][] run in them too, each trajectory locating its
      own mode switches.
    - `chunk_size`: trajectories per compiled call, rounded up to a multiple of the number of
      devices (default: `n` split into equal chunks of at most 16384, with a multiple of 8
      per device; a size of your own runs fastest as a multiple of 8 per device too).
    - `devices`: devices to shard each chunk across (default: all local devices). JAX gives a
      CPU one device however many cores it has; `jax.config.update("jax_num_cpu_devices", k)`
      before the first computation makes `k` (one per core is usually fastest; `jaxdyn
      montecarlo` does this itself).
    - `out`: a directory for chunk files: each finished chunk is written atomically, and a run
      started again with the same settings resumes where it stopped. Needed when several
      processes share a run (`jax.distributed`): each computes its share of the chunks.
    - `progress`: show a progress bar (tqdm).

    **Returns:**

    An [`jaxdyn.Ensemble`][]. A trajectory that fails (an invalid sample, a step budget that runs
    out) is marked in `status` and leaves the others running.
    """
    inputs = _resolve(scene, y0, t1, n=n, key=key, vary=vary, parameters=parameters, t0=t0,
                      ts=ts, observe=observe, keep=keep, solver=solver, rtol=rtol, atol=atol,
                      dt0=dt0, max_steps=max_steps, mode=mode, events=events)
    plan = _plan(inputs, chunk_size, devices, out)
    store = None if out is None else ChunkStore(out, plan.fingerprint, inputs.n,
                                                plan.chunk_size)
    chunks = _Chunks(inputs, plan, store)
    results, computed, run_s, resumed = _run_chunks(chunks, plan, store, progress)
    in_order = [results[c] for c in range(plan.chunks)]
    timing = {"compile_s": round(chunks.compile_s, 4), "run_s": round(run_s, 4),
              "trajectories_per_s": (computed / run_s) if run_s > 0 else None}
    return Ensemble(
        drawn=_varied(inputs, chunks.draws), n=inputs.n,
        status=np.concatenate([r["status"] for r in in_order]).astype(np.int8),
        values=_kept_values(in_order, inputs.keep), moments=_moments_by_name(in_order),
        steps=np.concatenate([r["steps"] for r in in_order]),
        reasons=_reasons(in_order, plan.chunk_size, inputs.messages), mode=inputs.mode,
        chunk_size=plan.chunk_size, devices=len(plan.devices), timing=timing,
        resumed_chunks=resumed,
        recomputed_chunks=tuple(store.recomputed) if store is not None else (),
    )


class _UnknownReasons:
    """Chunk files written before they held the reasons' texts."""

    def __getitem__(self, code: int) -> str:
        return f"invalid input (reason {code}; its text is not in the chunk files)"


def read_ensemble(directory: str | os.PathLike) -> "Ensemble":
    """The [`jaxdyn.Ensemble`][] of a run written to `directory` (`jaxdyn montecarlo --out
    DIR` or `jd.ensemble(..., out=DIR)`): its statuses, steps, kept observations, statistics
    and, for chunks written by this version, the values each trajectory ran with
    (`varied()`), so that `to_dataframe()` and `to_xarray()` work as on the run itself. Every
    chunk file is checked (fingerprint, checksum); a run that has not finished is refused,
    naming the missing chunks."""
    store = ChunkStore.existing(directory)
    chunks = -(-store.n // store.chunk_size)
    results, missing = [], []
    for c in range(chunks):
        arrays = store.read(c)
        if arrays is None:
            missing.append(c)
        results.append(arrays)
    if missing:
        raise ParameterError(
            f"{str(directory)!r}: chunk(s) {missing[:5]} of {chunks} are missing or failed "
            "their checks: the run has not finished (run the same command again to resume)")
    messages = list(results[0].get("messages", []))
    varied = {}
    if all(any(k.startswith("varied/") for k in r) for r in results):
        names = [k for k in results[0] if k.startswith("varied/")]
        varied = {k[len("varied/"):]: np.concatenate([r[k] for r in results]) for k in names}
    settings = store.settings if isinstance(store.settings, dict) else {}
    return Ensemble(
        drawn=lambda: dict(varied), n=store.n,
        status=np.concatenate([r["status"] for r in results]).astype(np.int8),
        values=_kept_values(results, None), moments=_moments_by_name(results),
        steps=np.concatenate([r["steps"] for r in results]),
        reasons=_reasons(results, store.chunk_size, messages or _UnknownReasons()),
        mode=str(settings.get("mode", "unknown")), chunk_size=store.chunk_size,
        devices=int(settings.get("devices", 1)), timing={},
    )


def _wait_for_chunks(store, missing, timeout: float = 24 * 3600.0, poll: float = 0.5):
    """Chunks written by other processes of a shared run, as they appear."""
    got = {}
    deadline = time.monotonic() + timeout
    while missing:
        for c in list(missing):
            arrays = store.read(c) if store.exists(c) else None
            if arrays is not None:
                got[c] = arrays
                missing.remove(c)
        if missing:
            if time.monotonic() > deadline:
                raise RuntimeError(f"chunks {missing[:5]} were not written by the other "
                                   "processes in time")
            time.sleep(poll)
    return got


