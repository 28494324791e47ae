"""The slow sweeps: the parameter values of the suite's checks that it leaves out.

The test suite checks each solver, outcome and ensemble mode at least once; the further
parameter values of those checks (every explicit tableau on the free body as well as on the
driven pendulum, every outcome in every ensemble mode) are marked `pytest.mark.sweep` and left
out of `python -m pytest` to keep the suite short. This script runs them, in one pytest run
with `--sweeps -m sweep` (the suite's own configuration: workers, compilation cache), and
prints one JSON object: how many passed and failed, the wall time, and each test's time.

Usage: `python benchmarks/sweeps.py [-- extra pytest arguments]`. It exits non-zero if a sweep
fails.
"""

import json
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(extra: list[str]) -> int:
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "sweeps.xml"
        t0 = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-m", "pytest", "--sweeps", "-m", "sweep", "-q",
             "-p", "no:cacheprovider", f"--junitxml={report}", *extra],
            cwd=ROOT, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        tests = []
        if report.exists():
            for case in ET.parse(report).getroot().iter("testcase"):
                failed = case.find("failure") is not None or case.find("error") is not None
                skipped = case.find("skipped") is not None
                tests.append({"test": f"{case.get('classname')}::{case.get('name')}",
                              "s": float(case.get("time", 0.0)),
                              "outcome": "failed" if failed
                              else "skipped" if skipped else "passed"})
    counts = {k: sum(t["outcome"] == k for t in tests) for k in ("passed", "failed", "skipped")}
    out = {"command": "pytest --sweeps -m sweep", "returncode": proc.returncode,
           **counts, "wall_s": wall, "tests": sorted(tests, key=lambda t: -t["s"])}
    if proc.returncode != 0:
        out["output_tail"] = (proc.stdout + proc.stderr)[-3000:]
    print(json.dumps(out, indent=2))
    return 0 if proc.returncode == 0 and counts["passed"] > 0 else 1


if __name__ == "__main__":
    args = sys.argv[1:]
    sys.exit(main(args[1:] if args[:1] == ["--"] else args))
