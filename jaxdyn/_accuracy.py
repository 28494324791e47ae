"""Work-precision studies: what each digit of accuracy costs in time, for any scene.

A problem is a scene, an initial state and a horizon; its reference comes from an independent
exact route through the scene protocol (`Scene.exact_final`: closed forms, quadrature) or, where
none is known, from a tight Dopri8 integration. Each method is swept over tolerances (adaptive)
or step sizes (fixed-step); every point reports the error against the reference, the drift of
the conserved invariants, the wall time (median of repeats after compilation), the compile time
and the vector-field evaluations. scipy's `solve_ivp` runs in the same study as the outside
baseline.
"""

import dataclasses
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._custom_types import State
from ._rigid_body import RigidBody
from ._rod import FallingRod
from ._scene import Scene
from ._simulate import check_tolerances, raise_on_failure, simulate, simulate_unchecked
from ._solvers import RK4, RotationSplitting
from ._tolerance import FLOOR, ScaledPIDController
from ._validation import ParameterError


@dataclasses.dataclass(frozen=True)
class Problem:
    """An accuracy problem: `scene`, initial state `y0`, horizon `t1`, the base step of the
    fixed-step sweeps, and optionally a numpy vector field on the flattened state for scipy (in
    the order of `scene.state_shapes()`) with its terminating event."""

    name: str
    description: str
    scene: Scene
    y0: State
    t1: float
    step: float
    numpy_rhs: Callable | None = None
    numpy_event: Callable | None = None
    halvings: int = 6
    min_tolerance: float = 1e-12


@dataclasses.dataclass(frozen=True)
class Method:
    """A method in a study: a diffrax solver swept over `tolerances` (adaptive step) or over
    `steps` (fixed step)."""

    name: str
    solver: Any
    tolerances: tuple[float, ...] = ()
    steps: tuple[float, ...] = ()


TOLERANCES = tuple(10.0**-k for k in range(3, 13))


def default_methods(problem: Problem) -> list[Method]:
    """Tsit5, Dopri5, Dopri8 and Kvaerno5 (implicit) over tolerances 1e-3..1e-12; RK4 and the
    splitting integrators of orders 2 and 4 over steps `problem.step * 2^-k`."""
    steps = tuple(problem.step * 2.0**-k for k in range(problem.halvings))
    tols = tuple(t for t in TOLERANCES if t >= problem.min_tolerance)
    return [
        Method("Tsit5", dfx.Tsit5(), tolerances=tols),
        Method("Dopri5", dfx.Dopri5(), tolerances=tols),
        Method("Dopri8", dfx.Dopri8(), tolerances=tols),
        Method("Kvaerno5", dfx.Kvaerno5(), tolerances=tols[:-2]),
        Method("RK4", RK4(), steps=steps),
        Method("Splitting2", RotationSplitting(2), steps=tuple(s / 4 for s in steps)),
        Method("Splitting4", RotationSplitting(4), steps=steps),
    ]


def _euler_numpy(inertia):
    inertia = np.asarray(inertia, float)
    return lambda t, w: np.cross(inertia * w, w) / inertia


def _rod_numpy(length, g):
    def rhs(t, y):
        theta, rate = y
        s, c = np.sin(theta), np.cos(theta)
        return [rate, 3 * s * (2 * g - length * rate**2 * c) / (length * (1 + 3 * s**2))]

    def flat(t, y):
        return np.pi / 2 - abs(y[0])

    flat.terminal = True
    return rhs, flat


def builtin_problems() -> dict[str, Problem]:
    """The four problems of the standard study: the rod falling to impact; an asymmetric free
    body over ten periods; an intermediate-axis spin near the separatrix; a long horizon (1e4
    time units) where invariant drift dominates."""
    inertia = [1.0, 2.0, 3.0]
    body = Scene(RigidBody(inertia))
    rod = Scene(FallingRod(length=1.0, g=9.81))
    rod_rhs, rod_event = _rod_numpy(1.0, 9.81)
    from ._free_body import torque_free_period

    w_free = jnp.array([0.3, 0.2, 1.0])
    w_sep = jnp.array([1e-4, 2.0, 1e-4])
    return {
        "falling-rod": Problem("falling-rod", "rod from theta0 = 0.1 to impact", rod,
                               rod.state(theta=0.1), 5.0, 0.02, rod_rhs, rod_event),
        "free-body": Problem(
            "free-body", "asymmetric free body over ten polhode periods", body,
            body.state(omega=w_free), 10 * float(torque_free_period(jnp.array(inertia), w_free)),
            0.1, _euler_numpy(inertia)),
        "near-separatrix": Problem(
            "near-separatrix", "intermediate-axis spin perturbed by 1e-4, over three flips",
            body, body.state(omega=w_sep),
            1.5 * float(torque_free_period(jnp.array(inertia), w_sep)), 0.02,
            _euler_numpy(inertia)),
        "long-horizon": Problem(
            "long-horizon", "free body over 1e4 time units: invariant drift dominates",
            body, body.state(omega=w_free), 1e4, 0.2, _euler_numpy(inertia), halvings=3,
            min_tolerance=1e-10),
    }


def _flat(scene: Scene, y: State) -> np.ndarray:
    return np.concatenate([np.ravel(np.asarray(y[k])) for k in scene.state_shapes()])


def _error(problem: Problem, ref, t_final, y_final) -> float:
    t_ref, y_ref = ref
    ref_vec = _flat(problem.scene, y_ref)
    err = np.linalg.norm(_flat(problem.scene, y_final) - ref_vec) / np.linalg.norm(ref_vec)
    if problem.scene.events():
        err = max(err, abs(float(t_final) - float(t_ref)) / abs(float(t_ref)))
    return float(err)


def reference(problem: Problem) -> tuple[Any, State, str]:
    """`(t_final, y_final, source)`: exact where the scene knows it, else a tight Dopri8 run."""
    exact = problem.scene.exact_final(problem.y0, problem.t1)
    if exact is not None:
        return exact[0], exact[1], "exact"
    traj = simulate(problem.scene, problem.y0, problem.t1, solver=dfx.Dopri8(), rtol=1e-13,
                    max_steps=10_000_000)
    return traj.t_final, traj.y_final, "Dopri8 rtol 1e-13"


def _check_setting(problem: Problem, solver, kind: str, value: float):
    """What `simulate` checks of a study's settings, on the host (the solves run in the
    study's own program, where traced values are not checked): the initial state, and a
    tolerance or step that the solver can use. A method that does not apply to the scene (a
    splitting of the rod) is refused when its program is traced. Returns the state's dtype."""
    y0 = problem.scene.check_state(problem.y0)
    for name, v in y0.items():
        if not np.all(np.isfinite(np.asarray(v))):
            raise ParameterError(f"y0[{name!r}]: must be finite")
    dtype = jnp.result_type(*y0.values())
    if kind == "tolerance":
        if not isinstance(solver, dfx.AbstractAdaptiveSolver):
            raise ParameterError(f"solver {type(solver).__name__} takes fixed steps: sweep "
                                 "it over steps, not tolerances")
        check_tolerances(value, None, dtype)
    elif not (np.isfinite(value) and value > 0):
        raise ParameterError(f"step={value!r}: must be positive and finite")
    return dtype


def _solve_program(problem: Problem, solver, kind: str, max_steps: int):
    """One compiled program per method of a study, the swept value (`rtol` or the step) and
    the sample times its arguments: each point of the sweep costs what its solve costs, not
    a call's argument checks (done once per method by `simulate`, which this program then
    matches; its outcome is raised on the host by `raise_on_failure`). The run takes no
    derivative, so it is in forward mode, where the solver saves the samples itself: the
    program holds no host callback and the persistent cache keeps it."""

    @jax.jit
    def solve(scene, y0, value, ts):
        if kind == "tolerance":
            kw = dict(stepsize_controller=ScaledPIDController(rtol=value,
                                                              atol=jnp.zeros_like(value)))
        else:
            kw = dict(stepsize_controller=dfx.ConstantStepSize(), dt0=value)
        return simulate_unchecked(scene, y0, problem.t1, ts=ts, solver=solver,
                                  max_steps=max_steps, adjoint=dfx.ForwardMode(), **kw)

    return solve


def _stages(solver) -> int | None:
    if isinstance(solver, RotationSplitting):
        return 0  # exact rotations, no vector-field evaluations
    tableau = getattr(solver, "tableau", None)
    if tableau is None or not hasattr(tableau, "c"):
        return None
    fsal = bool(getattr(tableau, "fsal", False))
    return len(tableau.c) + 1 - int(fsal)


def _timed(fn, repeats: int):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
        if times[-1] > 2.0:
            break
    return out, first, statistics.median(times)


@eqx.filter_jit
def _invariants_over(scene, ts, ys):
    """The scene's invariants at each sample, as one compiled program (eager under `vmap`,
    each of their operations was a program of its own)."""
    return jax.vmap(scene.invariants)(ts, ys)


@eqx.filter_jit
def _natural_scales(scene, t0, t1, y0):
    """`scene.natural_scales`, as one compiled program."""
    return scene.natural_scales(t0, t1, y0)


def _drift(problem: Problem, traj) -> dict[str, float]:
    valid = np.asarray(traj.valid)
    inv = _invariants_over(problem.scene, traj.ts, traj.ys)
    out = {}
    for name in problem.scene.conserved:
        v = np.asarray(inv[name])[valid]
        v = v if v.ndim == 1 else np.linalg.norm(v, axis=-1)
        out[name] = float(np.max(np.abs(v - v[0])) / max(abs(v[0]), 1e-300))
    return out


def study(problem: Problem, methods: Sequence[Method] | None = None, *, repeats: int = 3,
          samples: int = 101, scipy: bool = True, budget: float = 3.0) -> dict[str, Any]:
    """Sweep every method over its tolerances or steps on one problem.

    **Returns:** a JSON-ready dict: `reference` (its source), `methods` (per method a list of
    points with `tolerance` or `step`, `error`, `drift`, `wall_time`, `compile_time`,
    `evaluations`, `steps`), `skipped` (methods that do not apply, with the reason), and `scipy`
    (RK45 and DOP853 points with `tolerance`, `error`, `wall_time`, `evaluations`). Settings are
    run from cheap to expensive; once one solve takes longer than `budget` seconds the sweep of
    that method stops (`stopped` says where), which keeps a full study to a few minutes.
    """
    methods = default_methods(problem) if methods is None else methods
    t_ref, y_ref, source = reference(problem)
    ts = jnp.linspace(0.0, problem.t1, samples)
    out: dict[str, Any] = {"description": problem.description, "t1": problem.t1,
                           "reference": source, "methods": {}, "skipped": {}, "stopped": {}}
    for method in methods:
        stages = _stages(method.solver)
        points = []
        settings = [("tolerance", v) for v in method.tolerances] + [
            ("step", v) for v in method.steps]
        max_steps = int(problem.t1 / min(method.steps)) + 16 if method.steps else 1_000_000
        compile_time, programs = None, {}
        try:
            for kind, value in settings:
                if kind == "tolerance":
                    # Error control in the natural scales; the samples on the common grid.
                    on = ts
                else:
                    # A step that divides the horizon, and samples on step points: invariants
                    # are measured where the method computed them, not on its linear dense
                    # output between steps.
                    value = problem.t1 / np.ceil(problem.t1 / value)
                    on = jnp.asarray(
                        np.minimum(np.round(np.asarray(ts) / value) * value, problem.t1))
                dtype = _check_setting(problem, method.solver, kind, value)
                if kind not in programs:
                    programs[kind] = _solve_program(problem, method.solver, kind, max_steps)
                arguments = (problem.scene, problem.y0, jnp.asarray(value, dtype),
                             jnp.asarray(on, dtype))
                traj, first, wall = _timed(lambda f=programs[kind], a=arguments: f(*a), repeats)
                raise_on_failure(traj)
                if compile_time is None:
                    compile_time = max(first - wall, 0.0)
                steps = int(traj.stats["num_steps"])
                points.append({
                    kind: value,
                    "error": _error(problem, (t_ref, y_ref), traj.t_final, traj.y_final),
                    "drift": _drift(problem, traj),
                    "wall_time": wall,
                    "compile_time": compile_time,
                    "steps": steps,
                    "evaluations": None if stages is None else steps * stages,
                })
                if wall > budget:
                    out["stopped"][method.name] = f"after {kind} {value:g}: {wall:.1f} s a solve"
                    break
        except ParameterError as e:
            out["skipped"][method.name] = str(e)
            continue
        except RuntimeError as e:  # a point that ran out of steps: keep the others
            out["skipped"][method.name] = str(e).splitlines()[0][:200]
        out["methods"][method.name] = points
    if scipy and problem.numpy_rhs is not None:
        out["scipy"] = _scipy(problem, (t_ref, y_ref), repeats, budget, out["stopped"])
    return out


def _scipy(problem: Problem, ref, repeats: int, budget: float, stopped: dict) -> dict[str, list]:
    from scipy.integrate import solve_ivp

    y0 = _flat(problem.scene, problem.y0)
    shapes = problem.scene.state_shapes()
    # The same error control as jaxdyn's: each component's floor is 1% (FLOOR) of rtol times
    # its natural scale.
    scales, _ = _natural_scales(problem.scene, np.zeros(()), np.asarray(problem.t1),
                                problem.y0)
    scale = _flat(problem.scene, {k: jnp.broadcast_to(v, problem.y0[k].shape)
                                  for k, v in scales.items()})
    out = {}
    for name in ("RK45", "DOP853"):
        points = []
        for tol in TOLERANCES:
            def run(tol=tol):
                return solve_ivp(problem.numpy_rhs, (0.0, problem.t1), y0, method=name,
                                 rtol=tol, atol=FLOOR * tol * scale,
                                 events=problem.numpy_event)

            times = []
            for _ in range(max(repeats, 1)):
                t0 = time.perf_counter()
                sol = run()
                times.append(time.perf_counter() - t0)
                if times[-1] > 2.0:
                    break
            y_end, t_end = sol.y[:, -1], sol.t[-1]
            if problem.numpy_event is not None and len(sol.t_events[0]):
                t_end, y_end = sol.t_events[0][0], sol.y_events[0][0]
            y_final, i = {}, 0
            for k, shape in shapes.items():
                n = int(np.prod(shape))
                y_final[k] = y_end[i:i + n].reshape(shape)
                i += n
            points.append({"tolerance": tol, "error": _error(problem, ref, t_end, y_final),
                           "wall_time": statistics.median(times), "evaluations": int(sol.nfev)})
            if times[0] > budget:
                stopped[f"scipy {name}"] = f"after tolerance {tol:g}: {times[0]:.1f} s a solve"
                break
        out[name] = points
    return out


def speed_comparison(result: dict[str, Any], levels=tuple(10.0**-k for k in range(3, 12))):
    """For each accuracy level: jaxdyn's fastest point reaching it and scipy's, and the ratio."""
    rows = []
    for level in levels:
        def best(groups):
            found = [(p["wall_time"], name) for name, pts in groups.items() for p in pts
                     if p["error"] <= level]
            return min(found) if found else (None, None)

        jd_time, jd_method = best(result["methods"])
        sp_time, sp_method = best(result.get("scipy", {}))
        rows.append({"level": level, "jaxdyn_method": jd_method, "jaxdyn_time": jd_time,
                     "scipy_method": sp_method, "scipy_time": sp_time,
                     "speedup": None if not (jd_time and sp_time) else sp_time / jd_time})
    return rows


def drift_series(problem: Problem, settings: dict[str, tuple[Method, dict]] | None = None,
                 samples: int = 1001) -> dict[str, Any]:
    """Relative drift of each conserved invariant against time, one run per method (for the
    drift diagram). `settings`: name -> (method, simulate keyword arguments)."""
    if settings is None:
        settings = {
            "Tsit5 rtol 1e-8": (Method("Tsit5", dfx.Tsit5()), dict(rtol=1e-8)),
            "Dopri8 rtol 1e-8": (Method("Dopri8", dfx.Dopri8()), dict(rtol=1e-8)),
            "RK4 dt 0.05": (Method("RK4", RK4()), dict(dt0=0.05)),
            "Splitting2 dt 0.05": (Method("Splitting2", RotationSplitting(2)), dict(dt0=0.05)),
            "Splitting4 dt 0.1": (Method("Splitting4", RotationSplitting(4)), dict(dt0=0.1)),
        }
    ts = jnp.linspace(0.0, problem.t1, samples)
    out: dict[str, Any] = {"t": np.asarray(ts).tolist(), "series": {}}
    for name, (method, kw) in settings.items():
        if "dt0" in kw:
            kw = dict(kw, stepsize_controller=dfx.ConstantStepSize(),
                      max_steps=int(problem.t1 / kw["dt0"]) + 16)
        else:
            kw = dict(kw, max_steps=1_000_000)
        try:
            traj = simulate(problem.scene, problem.y0, problem.t1, ts=ts, solver=method.solver,
                            **kw)
        except ParameterError:
            continue
        inv = _invariants_over(problem.scene, traj.ts, traj.ys)
        series = {}
        for key in problem.scene.conserved:
            v = np.asarray(inv[key])
            v = v if v.ndim == 1 else np.linalg.norm(v, axis=-1)
            series[key] = (np.abs(v / v[0] - 1)).tolist()
        out["series"][name] = series
    return out
