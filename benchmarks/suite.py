"""The test suite's time, and where it goes.

Runs the README's test command (`python -m pytest`: its workers, its configuration) on a fresh
persistent compilation cache of its own (as on a clean machine), with the plugin
`benchmarks/_suite_plugin.py` in every worker, and prints one JSON object:

- the wall time and the CPU time of the whole run (the workers and every process they started and
  waited for: notebook kernels, commands);
- in the workers: the CPU time JAX spent tracing, lowering, and compiling or loading
  programs (`benchmarks/_suite_plugin.py` says how it is timed), the programs XLA compiled and
  those loaded from the persistent cache, jaxdyn's stored programs loaded, and what is left
  (running the programs, Python, pytest); the CPU time of the other processes (those the
  tests started: notebook kernels, commands; and pytest's controller) apart;
- per module and for the tests that cost most CPU, the same split, and the CPU time of the
  processes each started and waited for (`children_cpu_s`; ordered by the two together);
  the functions a test traced more than once (`traced_again`, `traced_again_s`: a new
  function given to `jax.jit` each time, or new shapes or settings), a test's three costliest
  by name (`traced_again_names`); the programs it compiled that JAX's persistent cache
  cannot keep (`uncacheable`, `uncacheable_s`: XLA's seconds; programs with host callbacks,
  such as equinox's runtime checks, compiled again on each new trace); and the tests that
  traced most again, and compiled most such programs, by those times.

Usage: `python benchmarks/suite.py [--top N] [-- extra pytest arguments]` (for example
`-- tests/test_outcomes.py -n 0`). It exits non-zero if the suite fails. The suite is CPU-bound
on 2 cores: compare runs made one after the other on the same idle machine, and compare CPU
seconds and programs compiled (which do not depend on the machine's load) as well as wall time.
"""

import argparse
import collections
import glob
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _suite_plugin import _children_cpu  # (this folder: the script's own)

ROOT = Path(__file__).resolve().parents[1]
_SPLIT = ("trace_s", "lower_s", "compile_s")  # (compile_s: compiling or loading)
_COUNTED = ("compiled", "loaded", "jaxdyn_loaded")


def _add(into: dict, test: dict) -> None:
    for k in ("wall_s", "cpu_s", "children_cpu_s", *_SPLIT, *_COUNTED, "traced_again",
              "traced_again_s", "uncacheable", "uncacheable_s"):
        into[k] = into.get(k, 0) + test[k]


def _costliest_first(item) -> float:  # a test's or module's CPU time, with its processes'
    return -(item[1]["cpu_s"] + item[1]["children_cpu_s"])


def _rounded(d: dict) -> dict:
    return {k: round(v, 2) if isinstance(v, float) else v for k, v in d.items()}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--top", type=int, default=30,
                        help="tests listed (most CPU first, with their processes')")
    parser.add_argument("pytest_args", nargs="*", help="after --: passed to pytest")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        profile, cache = Path(tmp) / "profile", Path(tmp) / "cache"
        profile.mkdir()
        env = {**os.environ, "JAXDYN_SUITE_PROFILE_DIR": str(profile),
               "JAXDYN_CACHE_DIR": str(cache),
               "PYTHONPATH": os.pathsep.join(filter(None, (str(ROOT / "benchmarks"),
                                                           os.environ.get("PYTHONPATH"))))}
        cpu0, t0 = _children_cpu(), time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "_suite_plugin",
             "-p", "no:cacheprovider", *args.pytest_args],
            cwd=ROOT, env=env, capture_output=True, text=True)
        wall, cpu = time.perf_counter() - t0, _children_cpu() - cpu0
        processes = [json.loads(Path(p).read_text())
                     for p in glob.glob(str(profile / "process-*.json"))]
    processes = ([p for p in processes if p["role"] == "worker"]  # (xdist's workers; without
                 or processes)  # xdist, pytest's own process)
    tests = {k: v for p in processes for k, v in p["tests"].items()}
    workers = {"processes": len(processes), "cpu_s": sum(p["cpu_s"] for p in processes)}
    for k in (*_SPLIT, *_COUNTED):
        workers[k] = sum(p["totals"][k] for p in processes)
    workers["other_s"] = workers["cpu_s"] - sum(workers[k] for k in _SPLIT)
    modules: dict = collections.defaultdict(dict)
    for nodeid, test in tests.items():
        _add(modules[nodeid.split("::")[0]], test)
    last = next((line for line in reversed(proc.stdout.splitlines())
                 if re.search(r" in [\d.]+s", line)), "")  # pytest's summary line
    summary = re.findall(r"(\d+) (passed|failed|skipped|deselected|xfailed|xpassed|errors?)",
                         last)
    out = {
        "command": " ".join(["python -m pytest", *args.pytest_args]),
        "returncode": proc.returncode,
        **{word: int(n) for n, word in summary},
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "cores_busy": round(cpu / wall, 2),
        "workers": _rounded(workers),
        "other_processes_cpu_s": round(cpu - workers["cpu_s"], 1),
        "modules": {m: _rounded(v) for m, v in
                    sorted(modules.items(), key=_costliest_first)},
        "tests": {k: _rounded(v) for k, v in
                  sorted(tests.items(), key=_costliest_first)[:args.top]},
        **{what: {k: {n: v[n] for n in (what, f"{what}_s", f"{what}_names") if n in v}
                  for k, v in sorted(tests.items(), key=lambda kv: -kv[1][f"{what}_s"])
                  [:args.top] if v[what]}
           for what in ("traced_again", "uncacheable")},
    }
    if proc.returncode != 0:
        out["output_tail"] = (proc.stdout + proc.stderr)[-3000:]
    print(json.dumps(out, indent=2))
    return 0 if proc.returncode == 0 and processes else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
