"""`jaxdyn accuracy`: work-precision studies (error against time for every method)."""

import time

from ._common import check_output_file, emit, enable_x64

HELP = "work-precision study: what each digit of accuracy costs in time, per method"


def add_arguments(parser) -> None:
    parser.add_argument("--scene", action="append", default=None, metavar="PROBLEM",
                        help="a problem to study (repeatable): falling-rod, free-body, "
                             "near-separatrix, long-horizon (default: all)")
    parser.add_argument("--repeats", type=int, default=3,
                        help="timed repeats after compilation; the median is reported (default 3)")
    parser.add_argument("--quick", action="store_true",
                        help="three settings per method and one repeat (a smoke test)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--plot", metavar="FILE",
                        help="write the work-precision diagram to FILE (PNG) and the drift "
                             "diagram beside it (FILE with _drift before the suffix)")


def run(args) -> int:
    enable_x64()
    import dataclasses

    from .._accuracy import (
        builtin_problems,
        default_methods,
        drift_series,
        speed_comparison,
        study as run_study,
    )
    from .._validation import ParameterError

    problems = builtin_problems()
    names = args.scene or list(problems)
    unknown = [n for n in names if n not in problems]
    if unknown:
        raise ParameterError(f"--scene {unknown[0]!r}: allowed are {sorted(problems)}")
    if args.repeats < 1:
        raise ParameterError(f"--repeats={args.repeats}: must be at least 1")
    check_output_file("--plot", args.plot)
    t0 = time.perf_counter()
    results, speed = {}, {}
    for name in names:
        problem = problems[name]
        methods = default_methods(problem)
        repeats = args.repeats
        if args.quick:
            methods = [dataclasses.replace(m, tolerances=m.tolerances[:3:2] + m.tolerances[5:6],
                                           steps=m.steps[:2]) for m in methods]
            repeats = 1
        results[name] = run_study(problem, methods, repeats=repeats)
        if "scipy" in results[name]:
            speed[name] = speed_comparison(results[name])
    out = {"problems": results, "speed_vs_scipy": speed,
           "wall_s": time.perf_counter() - t0}
    if args.plot:
        from .._plot import plot_accuracy

        drift = drift_series(problems["long-horizon"]) if "long-horizon" in names else None
        out["plots"] = plot_accuracy(results, drift, args.plot)
    if args.json:
        emit(out, True)
    else:
        for name, result in results.items():
            print(f"{name}: {result['description']} (reference: {result['reference']})")
            for method, points in result["methods"].items():
                best = min(points, key=lambda p: p["error"])
                compile_s = points[0]["compile_time"]
                print(f"  {method:<10} best error {best['error']:.1e} in "
                      f"{best['wall_time'] * 1e3:.2f} ms (compile {compile_s:.1f} s)")
            for method, reason in result["skipped"].items():
                print(f"  {method:<10} skipped: {reason}")
        for name, rows in speed.items():
            print(f"{name}: speed-up over scipy's best at each accuracy level")
            for row in rows:
                ratio = "n/a" if row["speedup"] is None else f"{row['speedup']:.1f}x"
                print(f"  {row['level']:.0e}: {ratio} ({row['jaxdyn_method']} vs "
                      f"{row['scipy_method']})")
    return 0
