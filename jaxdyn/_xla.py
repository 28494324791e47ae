"""XLA:CPU's compiler options for the `jaxdyn` command and the test suite.

Two settings, each added to `XLA_FLAGS` (read when JAX starts its backend) unless the user's
`XLA_FLAGS` already sets that flag (`prefer_fast_programs`; a user's own
`xla_backend_extra_options`, whatever they hold, are left as they are, not replaced):

- **The earlier fusion emitters.** XLA:CPU emits each fusion by its MLIR-based fusion emitters
  by default; its earlier (LLVM IR) emitters compile jaxdyn's programs in about 0.6 of the
  time and run them as fast (`benchmarks/latency.py`: the compilation of a cold `jaxdyn run`,
  `jaxdyn fit`; the run of an ensemble the same or faster): `--xla_cpu_use_fusion_emitters=false`.
- **Small loops compiled whole.** XLA:CPU runs a program as a sequence of kernels, one per
  fusion or operation, each launched by its runtime (a loop's condition and body are
  launched anew at each iteration); a while loop whose iteration touches less than a
  threshold of memory (1 KiB by default) and calls no library routine is compiled instead as
  one function, loop included (`SmallWhileLoopHoistingPass`). The step loop of a single run
  touches a few KiB (its state, the solver's stages, a buffer of saved samples), so each of
  its steps launched dozens of kernels, most of the run's time. With the threshold at 64 KiB
  (`--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=65536`) the step
  loop and the sample writer inside it are each one function: `jd.simulate` of the built-in
  scenes ran 1.1-12x faster after compilation, their first calls (compiling) took 0.71-1.23x
  as long (s44's and s45's runs), and ensembles ran as fast (their batched loops touch more
  than the threshold): `benchmarks/latency.py --only loops`; the figures of the latest run in
  the README's latency section, earlier ones in `benchmarks/latency-log.md`.
  The arithmetic is the same, compiled into one function instead of several
  (`tests/test_xla.py` compares a command's results with XLA's defaults).

In Python, `jd.prefer_fast_programs()` (this module's function) adds them when called first,
before JAX starts its backend; or start Python with `XLA_FLAGS="--xla_cpu_use_fusion_emitters=false
--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=65536"`. Nothing in
jaxdyn changes a process-wide setting behind a user's back: only the command and the test
suite call it themselves.

XLA aborts the process on a flag it does not know, so a setting is added only where this
jaxlib's XLA has it: its names are looked for in jaxlib's compiled libraries (each library
mapped once and searched for each name: 15-20 ms for the three names, with the files in the
page cache).

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
EXTRA = "xla_backend_extra_options"
LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
LOOP_BYTES = 65536
LOOP_SETTING = f"--{EXTRA}={LOOP_OPTION}={LOOP_BYTES}"
# (the setting; the names XLA must know, the first that of its flag: where `XLA_FLAGS`
# sets that flag, the user chose)
SETTINGS = ((SETTING, (FLAG,)), (LOOP_SETTING, (EXTRA, LOOP_OPTION)))
_SUFFIXES = (".so", ".pyd", ".dll", ".dylib")


def known(*flags: str) -> bool:
    """Whether the installed jaxlib's XLA defines every one of `flags` (their names in
    jaxlib's libraries, each library mapped once)."""
    return not _missing(flags)


def _missing(flags) -> set:
    """Those of `flags` whose names are in none of jaxlib's compiled libraries."""
    missing = set(flags)
    spec = importlib.util.find_spec("jaxlib")  # (finds it without importing it)
    if spec is None or not spec.submodule_search_locations:
        return missing
    for directory in spec.submodule_search_locations:
        paths = [p for p in Path(directory).iterdir() if p.suffix in _SUFFIXES]
        for path in sorted(paths, key=lambda p: -p.stat().st_size):  # XLA's is the largest
            try:
                with open(path, "rb") as f, mmap.mmap(f.fileno(), 0,
                                                      access=mmap.ACCESS_READ) as m:
                    missing = {flag for flag in missing if m.find(flag.encode()) < 0}
            except (OSError, ValueError):  # unreadable, or empty
                continue
            if not missing:
                return missing
    return missing


def prefer_fast_programs() -> tuple[str, ...]:
    """Compile the programs of this process as the `jaxdyn` command compiles its own: XLA's
    earlier fusion emitters, and small loops compiled whole, so that a single run's step loop
    is one function instead of dozens of kernels launched per step (`jd.simulate` of the
    built-in scenes 1.1-12x faster after compilation; the README's latency section).

    Each setting is added to `XLA_FLAGS` unless `XLA_FLAGS` already sets its flag (your own
    `--xla_backend_extra_options` are kept as they are, and the small-loop setting is then
    not added), and only where this jaxlib's XLA knows it (XLA aborts the process on a flag
    it does not know). XLA reads `XLA_FLAGS` once, when JAX starts its backend (the first
    computation, not `import jax`), and the settings hold for every program of the process,
    yours too: call this first, in a notebook's first cell or at the top of a script. jaxdyn
    never calls it in your process.

    **Returns:**

    The settings added (none where each is set already or unknown to this XLA).

    **Raises:**

    `RuntimeError` where a setting would be added but JAX has already started its backend
    (XLA would not read it): `XLA_FLAGS` is then left as it was.
    """
    return _add(refuse_late=True)


def add_settings() -> tuple[str, ...]:
    """`prefer_fast_programs` for the command and the test suite, which call it before they
    import JAX: the settings added to `XLA_FLAGS`, without looking at JAX's backend (where
    the command is run from a process whose JAX has started, as `benchmarks/identify.py`
    does, they then change nothing, as before)."""
    return _add(refuse_late=False)


def _add(refuse_late: bool) -> tuple[str, ...]:
    """Add to `XLA_FLAGS` the settings it does not set yet and this XLA knows; return them.
    `refuse_late`: raise instead where JAX's backend has started (`prefer_fast_programs`)."""
    flags = os.environ.get("XLA_FLAGS", "")
    wanted = [(setting, names) for setting, names in SETTINGS if not _sets(flags, names[0])]
    if not wanted:
        return ()
    missing = _missing({name for _, names in wanted for name in names})
    added = tuple(setting for setting, names in wanted if not missing.intersection(names))
    if not added:
        return ()
    flags = " ".join([flags, *added]).strip()
    if refuse_late and _backend_started():
        raise RuntimeError(
            "prefer_fast_programs: JAX has already started its backend, and XLA read XLA_FLAGS "
            "then; call it before JAX runs anything (first in the notebook or script, after "
            f"a restart of the kernel), or start Python with XLA_FLAGS=\"{flags}\"")
    os.environ["XLA_FLAGS"] = flags
    return added


def _sets(flags: str, name: str) -> bool:
    """Whether the flags `flags` (as in `XLA_FLAGS`) set the flag `name`."""
    return any(token == f"--{name}" or token.startswith(f"--{name}=")
               for token in flags.split())


def _backend_started() -> bool:
    """Whether JAX has started its backend (so that XLA has read `XLA_FLAGS`)."""
    if "jax" not in sys.modules:  # (the command, before it imports JAX)
        return False
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # (another JAX: cannot tell, so as before)
        return False


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
