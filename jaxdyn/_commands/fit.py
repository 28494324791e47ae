"""`jaxdyn fit`: identify a scene's parameters and initial state from a CSV of samples."""

import argparse
import csv
import math
import sys
import time
import warnings
from pathlib import Path
from typing import Any

from ._common import emit, enable_x64, parse_sets

HELP = "fit a scene's parameters and initial state to sampled data (CSV)"
LAPACK = True  # (its programs solve linear systems: `jaxdyn._xla`)



def _columns_help() -> str:
    """The data files' columns, from the bodies' declarations (see `_identify/_presets.py`)."""
    from .._identify._presets import fit_specs

    parts = []
    for kind, spec in fit_specs().items():
        cols = ",".join(c for cs in spec.columns.values() for c in cs)
        extra = ",".join(c for cs in spec.optional_columns.values() for c in cs)
        parts.append(f"t,{cols} for a {kind}" + (f" (optionally {extra})" if extra else ""))
    from .._identify._presets import effect_columns_help

    return "; ".join(parts + effect_columns_help())


def _progress(flag) -> bool:
    """`--progress`/`--no-progress`, else a bar only where standard error is a terminal."""
    return bool(flag) if flag is not None else sys.stderr.isatty()


def add_arguments(parser) -> None:
    parser.add_argument("data", metavar="DATA.csv",
                        help=f"samples with a header row (t in s): {_columns_help()}; units "
                             "as in 'jaxdyn scenes --parameters'")
    parser.add_argument("--scene",
                        help="a built-in scene or a TOML scene file (any scene of a body "
                             "that can be fitted); by default chosen from the columns")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="fix a known parameter or initial value instead of fitting it, "
                             "e.g. --set g=9.81, --set theta_dot0=0, --set rotor.momentum=0,3,0 "
                             "(repeatable); rtol and atol set the integration tolerances")
    parser.add_argument("--bias", action="append", default=[], metavar="OUTPUT",
                        help="fit a constant sensor bias of this output (a gyro's: "
                             "--bias omega), reported as bias.OUTPUT with its interval "
                             "(repeatable)")
    parser.add_argument("--restarts", type=int, default=8,
                        help="most starting points (default 8; the fit stops once two agree)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random restarts")
    parser.add_argument("--method", choices=("lm", "lbfgs"), default="lm",
                        help="lm: Levenberg-Marquardt (default); lbfgs: Adam then L-BFGS")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="show a progress bar on standard error (default: when standard "
                             "error is a terminal)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def _read_csv(path: str):
    """The header and the samples (an array): numpy's C reader first (a million rows in about
    a second); where it refuses the file, the line-by-line reader below names the line and
    column at fault."""
    import numpy as np

    from .._validation import ParameterError

    p = Path(path)
    if not p.is_file():
        raise ParameterError(f"data={path!r}: no such file")
    try:
        with p.open(encoding="utf-8-sig") as f, warnings.catch_warnings():
            warnings.simplefilter("ignore")  # an empty table: the slow reader says so
            header = [h.strip() for h in next(csv.reader([f.readline()]), [])]
            table = np.loadtxt(f, delimiter=",", ndmin=2, dtype=float)
    except (OSError, UnicodeDecodeError, ValueError, StopIteration):
        pass
    else:
        if (header and table.shape[1:] == (len(header),) and len(set(header)) == len(header)
                and np.all(np.isfinite(table))):
            return header, table
    return _read_csv_slowly(p, path)


def _read_csv_slowly(p: Path, path: str) -> tuple[list[str], list[list[float]]]:
    from .._validation import ParameterError

    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise ParameterError(f"data={path!r}: cannot be read as text ({e})") from None
    lines = [(i + 1, row) for i, row in enumerate(csv.reader(text.splitlines())) if row]
    if not lines:
        raise ParameterError(f"data={path!r}: empty; expected a header row, then samples")
    header = [h.strip() for h in lines[0][1]]
    duplicates = sorted({h for h in header if header.count(h) > 1})
    if duplicates:
        raise ParameterError(f"{path}: column(s) {duplicates} appear more than once")
    rows = []
    for lineno, row in lines[1:]:
        if len(row) != len(header):
            raise ParameterError(
                f"{path} line {lineno}: {len(row)} values, expected {len(header)} "
                f"(columns {','.join(header)})"
            )
        values = []
        for name, text_value in zip(header, row):
            try:
                v = float(text_value)
            except ValueError:
                raise ParameterError(
                    f"{path} line {lineno}, column {name}={text_value.strip()!r}: "
                    "expected a number"
                ) from None
            if not math.isfinite(v):
                raise ParameterError(
                    f"{path} line {lineno}, column {name}={text_value.strip()}: must be finite"
                )
            values.append(v)
        rows.append(values)
    return header, rows


def _choose_scene(header: list[str], path: str) -> str:
    from .._identify._presets import fit_specs
    from .._validation import ParameterError

    specs = {k: s for k, s in fit_specs().items() if s.scene is not None}
    for spec in specs.values():
        if all(c in header for cols in spec.columns.values() for c in cols):
            return spec.scene
    expected = "; ".join(
        f"{s.scene}: t," + ",".join(c for cols in s.columns.values() for c in cols)
        for s in specs.values()
    )
    raise ParameterError(f"{path}: columns {','.join(header)} match no scene; expected "
                         f"{expected} (or pass --scene)")


def _other_effects(unknown: list[str]) -> str:
    """A hint where an unknown column is one of an effect that the scene lacks."""
    from .._identify._presets import effect_of_column

    for c in unknown:
        kind = effect_of_column(c)
        if kind is not None:
            return (f"; {c} is a column of the effect {kind!r}, which this scene lacks: pass "
                    f"--scene with a scene that has it")
    return ""


def _continuous_quaternions(q):
    """Flip signs so that successive samples are on the same side (q and -q are one
    attitude; the integrated quaternion is continuous)."""
    import numpy as np

    q = np.array(q, dtype=float)
    for i in range(1, len(q)):
        if np.dot(q[i], q[i - 1]) < 0:
            q[i] = -q[i]
    return q


def _number(x) -> Any:
    import numpy as np

    a = np.asarray(x)
    if a.ndim == 0:
        v = float(a)
        return v if math.isfinite(v) else None
    return [_number(v) for v in a]


def run(args) -> int:
    enable_x64()
    import numpy as np

    from .._identify import fit
    from .._identify._presets import effect_columns, fit_specs, hold
    from .._scenefile import load_scene
    from .._validation import ParameterError

    sets = parse_sets(args.set)
    if "t1" in sets:
        raise ParameterError("--set t1: not used by fit; the sample times set the time span")
    if args.restarts < 1:
        raise ParameterError(f"--restarts={args.restarts}: must be a positive integer")
    header, rows = _read_csv(args.data)
    scene_name = args.scene or _choose_scene(header, args.data)

    # A first load finds the body kind and the effects (and checks the --set names).
    first = load_scene(scene_name, sets).scene
    kind = first.body.kind
    specs = fit_specs()
    if kind not in specs:
        raise ParameterError(f"--scene {scene_name}: a {kind} cannot be fitted; fit supports "
                             f"{sorted(specs)}")
    spec = specs[kind]
    effects = effect_columns(first)
    outputs = dict(spec.columns)
    optional = {k: v for k, v in spec.optional_columns.items() if any(c in header for c in v)}
    outputs.update(optional)
    required = ["t"] + [c for cols in spec.columns.values() for c in cols]
    extra = [c for cols in spec.optional_columns.values() for c in cols]
    groups = {name: cols for e in effects for name, cols in {**e.measured, **e.held}.items()}
    extra += [c for cols in groups.values() for c in cols]
    allowed = required + extra
    wanted = required + [c for cols in optional.values() for c in cols]
    # An effect's columns come as a group: all of them (one per wheel), or none.
    given = {name: cols for name, cols in groups.items() if any(c in header for c in cols)}
    wanted += [c for cols in given.values() for c in cols]
    missing = [c for c in wanted if c not in header]
    if missing:
        also = f" (optionally also {','.join(extra)})" if extra else ""
        raise ParameterError(f"{args.data}: missing column(s) {missing}: a {kind} needs "
                             f"columns {','.join(required)}{also}")
    unknown = [c for c in header if c not in allowed]
    if unknown:
        raise ParameterError(f"{args.data}: unknown column(s) {unknown}: allowed are "
                             f"{','.join(allowed)}{_other_effects(unknown)}")
    if len(rows) < 3:
        raise ParameterError(f"{args.data}: {len(rows)} data row(s): at least 3 are needed "
                             "(and more values than unknowns)")
    table = np.array(rows)
    col = {name: table[:, i] for i, name in enumerate(header)}
    ts = col["t"]
    steps = np.diff(ts)
    if np.any(steps <= 0):
        i = int(np.argmax(steps <= 0)) + 1
        raise ParameterError(f"{args.data} row {i + 1}, column t={ts[i]:g}: times must be "
                             f"strictly increasing (previous {ts[i - 1]:g})")
    outputs.update({n: c for e in effects for n, c in e.measured.items() if n in given})
    data = {name: np.stack([col[c] for c in cols], axis=-1) if len(cols) > 1 else col[cols[0]]
            for name, cols in outputs.items()}
    if "quaternion" in data:
        data["quaternion"] = _continuous_quaternions(data["quaternion"])
    held = {name: (ts, np.stack([col[c] for c in cols], axis=-1))
            for e in effects for name, cols in e.held.items() if name in given}

    # Starting initial values from the first sample, unless given.
    state_to_file = {v: k for k, v in spec.initial_names.items()}
    for e in effects:
        state_to_file.update({v: k for k, v in e.initial_names.items()})
    overrides = dict(sets)
    for name in data:
        file_name = state_to_file.get(name)
        if file_name is not None and file_name not in sets:
            value = data[name][0]
            overrides[file_name] = value.tolist() if np.ndim(value) else float(value)
    if "quaternion" in data:
        overrides["attitude"] = True
    loaded = load_scene(scene_name, overrides)
    scene, y0 = loaded.scene, loaded.y0
    if held:
        # Known inputs (commanded torques) in place of the scene's laws: a new state layout
        # (a motor's work), so the initial state is built again from the same values.
        scene = hold(scene, held)
        y0 = scene.state(**loaded.initial)

    parameters = {k: m for k, m in spec.parameters.items() if k not in sets}
    initial = {**spec.initial, **{k: m for k, m in spec.optional_initial.items() if k in data}}
    initial = {k: m for k, m in initial.items() if state_to_file.get(k) not in sets}
    # An effect's measured output: its state is fitted (a wheel's momentum, from its speed).
    fitted_state = {}
    for e in effects:
        for output, (state, how) in e.fitted.items():
            if output in data and state_to_file.get(output) not in sets:
                initial[state] = how
                fitted_state[state] = output
    if not parameters and not initial:
        raise ParameterError("--set fixes everything that could be fitted: nothing to fit")
    tolerances = {k: float(sets[k]) for k in ("rtol", "atol") if k in sets}
    unknown_bias = [b for b in args.bias if b not in data]
    if unknown_bias:
        raise ParameterError(f"--bias {unknown_bias[0]}: not among the data's outputs "
                             f"{sorted(data)}")

    t0 = time.perf_counter()
    # Rates and attitude have different units: each is weighted by its own residual scale.
    result = fit(scene, ts, data, parameters=parameters, initial=initial, y0=y0,
                 bias=list(dict.fromkeys(args.bias)), notes=spec.notes,
                 restarts=args.restarts, key=args.seed, method=args.method,
                 reweight=True, progress=_progress(args.progress), **tolerances)
    fit_s = time.perf_counter() - t0

    v, s = result.values, result.std
    out: dict[str, Any] = {"scene": scene_name, "body": kind, "samples": int(ts.size)}
    if "inertia" in parameters:
        scale = result.identifiable["inertia.scale"]
        out.update({
            "principal_moments": _number(v["inertia.principal_moments"]),
            "principal_axes": _number(v["inertia.principal_axes"]),
            "std": _number(s["inertia.principal_moments"]),
            "principal_axes_std": _number(s["inertia.principal_axes"]),
            "scale_identified": scale,
        })
        if scale:
            out["inertia"] = _number(v["inertia"])
    def determined(name):
        return any(ok for c, ok in result.identifiable.items()
                   if c == name or c.startswith((name + ".", name + "[")))

    for name in parameters:
        if name != "inertia":
            # A parameter that the data do not determine has no value (null), only a note.
            out[name] = _number(v[name]) if determined(name) else None
            out[f"{name}_std"] = _number(s[name]) if determined(name) else None
    for name in dict.fromkeys(args.bias):
        out[f"bias.{name}"] = _number(v[f"bias.{name}"])
        out[f"bias.{name}_std"] = _number(s[f"bias.{name}"])
    for name in initial:
        file_name = name if name in fitted_state else state_to_file.get(name, name)
        out[file_name] = _number(v[name])
        out[f"{file_name}_std"] = _number(s[name])
    # In the units of the first output (rad/s, or rad for the rod); all outputs listed apart.
    rms = result.residual_rms_by_output
    out["residual_rms"] = rms[next(iter(spec.columns))]
    if len(rms) > 1:
        out["residual_rms_by_output"] = rms
    known = {k: _number(val) for k, val in scene.parameters().items()
             if k not in parameters and not callable(val)}
    if known:
        out["known"] = known
    out["identifiable"] = result.identifiable
    out["not_identifiable"] = [c for c, ok in result.identifiable.items() if not ok]
    out["notes"] = list(result.notes)
    if "inertia" in parameters and result.identifiable["inertia.scale"]:
        out["notes"].append("inertia.scale is determined by the data: known torques or "
                            "momenta in the scene (commanded motor torques, wheel momenta) "
                            "fix the absolute inertia, reported in kg m^2")
    out["converged"] = result.converged
    out["optimiser_converged"] = result.optimiser_converged
    out["residual_autocorrelation"] = {k: _number(v)
                                       for k, v in result.residual_autocorrelation.items()}
    out["systematic_residuals"] = list(result.systematic)
    out["iterations"] = result.iterations
    out["starts"] = int(result.restart_losses.size)
    out["timing"] = {"fit_s": fit_s, "wall_s": time.perf_counter() - args.t_start}
    emit(out, args.json, title=f"fit {scene_name} to {args.data}")
    if result.systematic:
        # The one-line hint, on standard error whatever the format (the note says more).
        print(f"jaxdyn: warning: the fit is not trustworthy: residuals of "
              f"{', '.join(result.systematic)} are not white noise (a local minimum, or a "
              "sensor bias or torque the scene lacks); see notes", file=sys.stderr)
    return 0
