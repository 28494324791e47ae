"""XLA:CPU's compiler options for the `jaxdyn` command and the test suite.

XLA:CPU emits each fusion by its MLIR-based fusion emitters by default; its earlier
(LLVM IR) emitters compile jaxdyn's programs in about 0.6 of the time and run them as fast
(`benchmarks/latency.py`: the compilation of a cold `jaxdyn run`, `jaxdyn fit`; the run of an
ensemble the same or faster). The command therefore starts XLA with
`--xla_cpu_use_fusion_emitters=false`, unless `XLA_FLAGS` already says which emitters to use.
From Python, set it yourself before JAX starts its backend:
`XLA_FLAGS=--xla_cpu_use_fusion_emitters=false python ...` (nothing in jaxdyn changes
a process-wide setting behind a user's back).

XLA aborts the process on a flag it does not know, so the flag is added only where this
jaxlib's XLA has it: its name is looked for in jaxlib's compiled libraries (about 30 ms).
"""

import importlib.util
import mmap
import os
from pathlib import Path

FLAG = "xla_cpu_use_fusion_emitters"
SETTING = f"--{FLAG}=false"
_SUFFIXES = (".so", ".pyd", ".dll", ".dylib")


def known(flag: str) -> bool:
    """Whether the installed jaxlib's XLA defines `flag` (its name in jaxlib's libraries)."""
    spec = importlib.util.find_spec("jaxlib")  # (finds it without importing it)
    if spec is None or not spec.submodule_search_locations:
        return False
    needle = flag.encode()
    for directory in spec.submodule_search_locations:
        paths = [p for p in Path(directory).iterdir() if p.suffix in _SUFFIXES]
        for path in sorted(paths, key=lambda p: -p.stat().st_size):  # XLA's is the largest
            try:
                with open(path, "rb") as f, mmap.mmap(f.fileno(), 0,
                                                      access=mmap.ACCESS_READ) as m:
                    if m.find(needle) >= 0:
                        return True
            except (OSError, ValueError):  # unreadable, or empty
                continue
    return False


def prefer_fast_compilation() -> bool:
    """Add `--xla_cpu_use_fusion_emitters=false` to `XLA_FLAGS` (read when JAX starts its
    backend) where the user has not chosen the emitters and this XLA knows the flag. Returns
    whether it was added."""
    flags = os.environ.get("XLA_FLAGS", "")
    if FLAG in flags or not known(FLAG):
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {SETTING}".strip()
    return True
