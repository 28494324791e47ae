"""The `jaxdyn` command: run scenes, list them. JSON on stdout with `--json`."""

import argparse
import json
import re
import sys
import time
from typing import Any, NoReturn


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # one line, exit status 2
        self.exit(2, f"jaxdyn: error: {message} (see 'jaxdyn --help')\n")


def _build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="jaxdyn", description="Differentiable rigid-body dynamics in JAX.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    run = sub.add_parser("run", help="simulate a scene and summarise it")
    run.add_argument("scene", nargs="?", default="falling-rod",
                     help="a built-in scene name (see 'jaxdyn scenes') or a TOML scene file "
                          "(default: falling-rod)")
    run.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                     help="override a parameter, e.g. --set theta0=0.1 or "
                          "--set inertia=1,2,3 (repeatable)")
    run.add_argument("--t1", type=float, help="final time (s)")
    run.add_argument("--samples", type=int, default=2001,
                     help="number of saved samples (default 2001)")
    run.add_argument("--max-steps", type=int, default=100_000,
                     help="solver step budget; exceeding it is an error (default 100000)")
    run.add_argument("--json", action="store_true", help="print one JSON object")
    run.add_argument("--plot", metavar="FILE", help="write a PNG figure")
    scenes = sub.add_parser("scenes", help="list the built-in scenes")
    scenes.add_argument("--json", action="store_true", help="print one JSON object")
    return p


def _fail(message: str, status: int = 2) -> NoReturn:
    sys.stderr.write(f"jaxdyn: error: {message}\n")
    raise SystemExit(status)


def _parse_sets(items: list[str]) -> dict[str, Any]:
    from ._scenefile import parse_value
    from ._validation import ParameterError

    out = {}
    for item in items:
        if "=" not in item:
            raise ParameterError(f"--set {item!r}: expected NAME=VALUE")
        name, text = item.split("=", 1)
        out[name.strip()] = parse_value(name.strip(), text)
    return out


def _cmd_scenes(args) -> int:
    from ._scenefile import builtin_scenes

    scenes = builtin_scenes()
    if args.json:
        print(json.dumps(scenes, indent=2))
    else:
        width = max(map(len, scenes))
        for name, description in scenes.items():
            print(f"{name:<{width}}  {description}")
    return 0


def _cmd_run(args, t_start: float) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    from ._scenefile import load_scene
    from ._simulate import simulate
    from ._validation import ParameterError

    overrides = _parse_sets(args.set)
    if args.t1 is not None:
        overrides["t1"] = args.t1
    if args.samples < 2:
        raise ParameterError(f"--samples={args.samples}: must be at least 2")
    spec = load_scene(args.scene, overrides)

    def go():
        traj = simulate(spec.scene, spec.y0, spec.t1, rtol=spec.rtol, atol=spec.atol,
                        max_steps=args.max_steps, dense=True)
        # Samples span the run as it happened (up to the event time if one ended it).
        traj = traj.resample(args.samples)
        jax.block_until_ready(traj)
        return traj

    t0 = time.perf_counter()
    go()
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    traj = go()
    run_s = time.perf_counter() - t0
    report = traj.report()
    out: dict[str, Any] = {
        "scene": spec.name,
        "body": spec.scene.body.kind,
        "effects": list(spec.scene.labels),
        "parameters": {k: v for k, v in spec.values.items() if k not in ("t1", "rtol", "atol")},
        "t1": spec.t1,
        "rtol": spec.rtol,
        "atol": spec.atol,
        "t_final": float(traj.t_final),
        "event": next((k for k, v in traj.event.items() if bool(v)), None),
        "steps": int(traj.stats["num_steps"]),
        **report,
    }
    if args.plot:
        from ._plot import plot_trajectory

        plot_trajectory(traj, args.plot, title=f"{spec.name}: {spec.description}")
        out["plot"] = args.plot
    out["timing"] = {
        "compile_s": max(first - run_s, 0.0),
        "run_s": run_s,
        "wall_s": time.perf_counter() - t_start,
    }
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"{spec.name}: {spec.description}")
        for key, value in out.items():
            if key in ("scene",):
                continue
            print(f"  {key}: {_fmt(value)}")
    return 0


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.10g}"
    if isinstance(value, dict):
        return ", ".join(f"{k}={_fmt(v)}" for k, v in value.items())
    if isinstance(value, list):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return str(value)


def _runtime_message(error: RuntimeError) -> str:
    """The message of an `eqx.error_if` failure, without equinox's debugging advice."""
    text = str(error)
    match = re.search(r"EquinoxRuntimeError: (.*)", text)
    line = match.group(1) if match else next(
        (ln.strip() for ln in text.splitlines() if ln.strip()), type(error).__name__)
    return line.replace("`max_steps`", "--max-steps")


def main(argv: list[str] | None = None) -> int:
    t_start = time.perf_counter()
    args = _build_parser().parse_args(argv)
    from ._validation import ParameterError

    try:
        if args.command == "scenes":
            return _cmd_scenes(args)
        return _cmd_run(args, t_start)
    except ParameterError as e:
        _fail(str(e), 2)
    except RuntimeError as e:  # runtime checks inside jit (eqx.error_if), solver failures
        _fail(f"simulation failed: {_runtime_message(e)}", 1)
    except ModuleNotFoundError as e:
        if e.name == "matplotlib":
            _fail("--plot needs matplotlib: pip install 'jaxdyn[plot]'", 2)
        raise


if __name__ == "__main__":
    raise SystemExit(main())
