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

The command's processes also load LAPACK for JAX without importing `scipy.linalg`
(`lapack_without_scipy_linalg`): JAX's CPU kernels for LU, QR, Cholesky and the like take
LAPACK's routines from SciPy's two Cython modules, `scipy.linalg.cython_blas` and
`cython_lapack`, and importing them runs `scipy.linalg`'s package, 0.2-0.27 s of a `jaxdyn fit`
or `jaxdyn separatrix` (measured on 7 Dec 2026, SciPy 1.17), against 20-35 ms to load the two
modules alone. Only the command does this, in processes that run no code of the user's (the
function says why it is not for a user's process).
"""

import importlib.machinery
import importlib.util
import mmap
import os
import sys
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


_CYTHON = ("cython_blas", "cython_lapack")


def lapack_without_scipy_linalg() -> bool:
    """Load SciPy's `scipy.linalg.cython_blas` and `cython_lapack` (where JAX's LAPACK kernels
    find their routines) without running `scipy.linalg`'s package: that package is put in
    `sys.modules` first, to be run when first used (`importlib.util.LazyLoader`), and each
    module is registered under its name and as the package's attribute as it is loaded.
    Nothing where `scipy.linalg` is imported already, or SciPy's files are not found (JAX
    then imports it as usual). Returns whether both were loaded this way.

    For the command's processes only: the imports of SciPy that jaxdyn's commands make later
    (`scipy.integrate`, the package itself, a module by `import ... as`) find what an ordinary
    import gives (`tests/test_xla.py`), but Python 3.11's lazy loading is not safe for a user's
    code in general: threads that first touch the package at once can see it half run, a
    module of the package imported before the package itself runs twice (two classes of one
    name), and an error while the package runs is not raised again on a second import."""
    if "scipy.linalg" in sys.modules:
        return False
    try:
        spec = importlib.util.find_spec("scipy")  # (finds it without importing it)
        if spec is None or not spec.submodule_search_locations:
            return False
        base = Path(spec.submodule_search_locations[0]) / "linalg"
        # (The finder picks the file built for this interpreter, as an import would.)
        specs = {name: importlib.machinery.PathFinder.find_spec(f"scipy.linalg.{name}",
                                                                [str(base)])
                 for name in _CYTHON}
        if None in specs.values() or not (base / "__init__.py").exists():
            return False
        import scipy

        if "scipy.linalg" in sys.modules:
            return False
        package = importlib.util.spec_from_file_location(
            "scipy.linalg", base / "__init__.py", submodule_search_locations=[str(base)])
        lazy = importlib.util.LazyLoader(package.loader)
        package.loader = lazy
        linalg = importlib.util.module_from_spec(package)
    except Exception:  # (any surprise: JAX imports SciPy's modules itself)
        return False
    sys.modules["scipy.linalg"] = linalg
    lazy.exec_module(linalg)  # (run when an attribute is first read)
    scipy.linalg = linalg
    try:
        for name, module_spec in specs.items():
            full = f"scipy.linalg.{name}"
            module = importlib.util.module_from_spec(module_spec)
            sys.modules[full] = module
            try:
                module_spec.loader.exec_module(module)
            except BaseException:
                del sys.modules[full]
                raise
            setattr(linalg, name, module)  # (kept when the package runs)
    except Exception:  # (the rest is imported as usual, through the package)
        return False
    return True
