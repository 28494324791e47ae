"""Helpers shared by subcommands."""

import json
import sys
from typing import Any

PROMISE = 100
"""A result more than `PROMISE * rtol` (relative) from its independent reference is reported:
the default error control keeps the local error per step within `rtol` of each variable's
scale, and the global error of a well-conditioned run within a few times that."""


_COMPILE_EVENTS = {  # JAX's monitoring events, by what the report calls them
    "/jax/core/compile/jaxpr_trace_duration": "trace_s",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
    "/jax/core/compile/backend_compile_duration": "compile_s",
    "/jaxdyn/programs/load_duration": "load_s",  # a stored compiled program (`_programs`)
}
_EVENTS: list[tuple[float, str, float]] = []  # (end time, phase, seconds)
_LISTENING: list = []  # the listener, once registered


def compile_clock() -> float:
    """Start listening to JAX's compilation events (once per process); returns the time."""
    import time

    if not _LISTENING:
        import jax

        def listen(event: str, duration: float, **_):
            if event in _COMPILE_EVENTS:
                _EVENTS.append((time.perf_counter(), _COMPILE_EVENTS[event], duration))

        jax.monitoring.register_event_duration_secs_listener(listen)
        _LISTENING.append(listen)
    return time.perf_counter()


def timing_since(t0: float) -> dict[str, float]:
    """Seconds spent since `t0 = compile_clock()` tracing, lowering and compiling (JAX's own
    monitoring events, so a command measures itself without running anything twice; a program
    loaded from the persistent cache costs no compile time), loading stored compiled programs
    (`load_s`, jaxdyn's event), and the rest as `run_s`. Eager
    operations compiled while tracing nest inside the trace: `run_s` subtracts the union of
    the intervals, not their sum. The phases sum the seconds of every thread: where programs
    are prepared on worker threads (a cold `jaxdyn run`), `compile_s` can exceed the wall
    time."""
    import time

    now = time.perf_counter()
    out = {"trace_s": 0.0, "lower_s": 0.0, "compile_s": 0.0, "load_s": 0.0}
    spans = []
    for end, phase, seconds in _EVENTS:
        if end > t0:
            out[phase] += seconds
            spans.append((max(end - seconds, t0), end))
    busy, reach = 0.0, t0
    for start, end in sorted(spans):
        if end > reach:
            busy += end - max(start, reach)
            reach = end
    out["run_s"] = max(now - t0 - busy, 0.0)
    return out


def enable_x64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


def bounded_int(option: str, low: int, high: int):
    """An argparse type: an integer within `[low, high]`, refused by name otherwise."""
    import argparse

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{option}={text!r}: expected an integer within [{low}, {high}]") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(
                f"{option}={value}: must be within [{low}, {high}]")
        return value

    return parse


def check_output_file(option: str, path: str | None, suffixes=(".png",)) -> None:
    """Refuse, before any computation, an output file that cannot be written: a wrong suffix,
    a missing or unwritable folder, or a path that is a folder."""
    import os
    from pathlib import Path

    from .._errors import ParameterError

    if path is None:
        return
    p = Path(path)
    if p.suffix.lower() not in suffixes:
        raise ParameterError(f"{option}={path!r}: expected a file name ending in "
                             f"{' or '.join(suffixes)}")
    if p.is_dir():
        raise ParameterError(f"{option}={path!r}: is a folder; give a file name")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise ParameterError(f"{option}={path!r}: the folder {str(parent)!r} does not exist")
    if not os.access(parent, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise ParameterError(f"{option}={path!r}: not writable")


def add_scene_arguments(p, *, default_scene: str | None = None) -> None:
    """The arguments every simulating command shares: the scene, `--set`, `--t1`, `--max-steps`
    and `--json`."""
    scene_help = "a built-in scene name (see 'jaxdyn scenes') or a TOML scene file"
    if default_scene is None:
        p.add_argument("scene", help=scene_help)
    else:
        p.add_argument("scene", nargs="?", default=default_scene,
                       help=f"{scene_help} (default: {default_scene})")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="override a parameter, e.g. --set theta0=0.1, --set inertia=1,2,3 "
                        "or --set rotor.momentum=0,3,0 (repeatable); 'jaxdyn scenes "
                        "--parameters' lists every name with its unit and range")
    p.add_argument("--t1", type=float, help="final time (s)")
    p.add_argument("--max-steps", type=bounded_int("--max-steps", 1, 2**31 - 1),
                   default=100_000,
                   help="solver step budget per run; exceeding it is an error or, in an "
                        "ensemble, a failed trajectory (default 100000)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def parse_sets(items: list[str]) -> dict[str, Any]:
    """`--set NAME=VALUE` items as a dict of parsed values."""
    from .._scenefile import parse_value
    from .._validation import ParameterError

    out = {}
    for item in items:
        if "=" not in item:
            raise ParameterError(f"--set {item!r}: expected NAME=VALUE")
        name, text = item.split("=", 1)
        out[name.strip()] = parse_value(name.strip(), text)
    return out


def fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.10g}"
    if isinstance(value, dict):
        return ", ".join(f"{k}={fmt(v)}" for k, v in value.items())
    if isinstance(value, list):
        return "[" + ", ".join(fmt(v) for v in value) + "]"
    return str(value)


def emit(out: dict[str, Any], as_json: bool, title: str = "") -> None:
    """Print one JSON object, or a readable `key: value` summary."""
    if as_json:
        print(json.dumps(out, indent=2))
        return
    if title:
        print(title)
    for key, value in out.items():
        print(f"  {key}: {fmt(value)}")


def warn_on_disagreement(report: dict[str, Any], rtol: float,
                         t_final: float | None = None) -> list[str]:
    """Warn on stderr for every value of a run's report that differs from its independent
    reference (`report["relative_difference"]`) by more than the tolerances promise, and for
    every value that has a reference but no value in this run (an impact after the run's end):
    nothing is printed beside its reference without saying how far apart they are."""
    warnings = []
    reference = report.get("reference") or {}
    for key, diff in (report.get("relative_difference") or {}).items():
        if diff is not None and diff > PROMISE * rtol:
            warnings.append(
                f"jaxdyn: warning: {key} differs from its reference by {diff:.2g} (relative), "
                f"more than rtol={rtol:g} promises ({PROMISE} x rtol = {PROMISE * rtol:.2g}): "
                "the run may be ill-conditioned (near a separatrix, a long horizon); tighten "
                "rtol with --set rtol=... to check"
            )
    missing = [k for k, v in reference.items() if v is not None and k in report
               and report[k] is None]
    if missing:
        refs = fmt({k: reference[k] for k in missing})
        warnings.append(
            f"jaxdyn: warning: {', '.join(missing)}: not reached by this run"
            + (f" (it ended at t_final={fmt(t_final)})" if t_final is not None else "")
            + f", while the reference gives {refs} (a reference time after the run's end: a "
            "longer run, --t1, reaches it)"
        )
    for line in warnings:
        print(line, file=sys.stderr)
    return warnings
