"""Compiled programs kept between processes: a second `jaxdyn run` skips tracing too.

JAX's persistent compilation cache (`jaxdyn._cache`) skips XLA's compilation in a later
process, but not the Python tracing and lowering that come before it, which for a diffrax
program is most of a warm command (0.9 s of tracing and 0.2 s of lowering for the falling
rod's `simulate`, against 0.25 s to load its compiled code). So where that cache is on, each
program that jaxdyn builds once per scene structure (`_solution._structure_program`) and the
fit's programs (`_stored_jit`) are also kept, compiled for this machine, beside it (in
`<cache>/jaxdyn-programs`, by `jax.experimental.serialize_executable`): a later process loads
the compiled program and calls it, without tracing, lowering or compiling. The first process
traces, lowers and compiles once, as `jax.jit` would, and stores what it compiled. (Until
28 Nov 2026 the first process also exported the program, `jax.export`, and compiled the
export: a second tracing and lowering that cost a cold `jaxdyn run` about 0.45 s, kept only
for another machine sharing the folder, which now compiles afresh.)

A stored program is used only where its key says it is the same program:
- the key holds the program's name and static options, the scene's structure (its classes and
  static fields) and the inputs' shapes and dtypes, the versions of jax, jaxlib, diffrax,
  equinox, optimistix and lineax, a hash of jaxdyn's own source, the machine (`_machine`:
  the processor, the devices and XLA's flags) and JAX's settings that change what XLA
  compiles (`_compile_settings`: `jax_disable_most_optimizations` and the optimisation
  levels and efforts, which JAX's own cache key holds through its compile options);
- a structure that names anything outside these packages (a class defined in a notebook, a
  Python function held by an effect) is never stored: its code could change under the same
  name, so it is traced as usual.
Nothing is stored or read where the compilation cache is off.

A program whose inputs' shapes are known before its inputs are computed can be `prepare`d: it
is then traced and compiled on a worker thread while the caller's thread compiles another
program (XLA:CPU compiles a program on one core and releases Python's lock meanwhile), and a
later call waits for it. A cold `jaxdyn fit` prepares its summaries' program as its
Levenberg-Marquardt program compiles. A program whose inputs' shapes are known only from
another program's outputs is prepared from those outputs' shapes as that program is lowered,
before XLA compiles it (`when_lowered`; `prepare(..., then=...)` for a chain): a cold `jaxdyn
run` prepares its resampling and summary programs as its simulation compiles.

One case keeps the tracing: a program that JAX's persistent cache already holds when it is
first compiled under a key (the same program under another key, or one whose stored file was
removed or could not be written) is used but not stored, since XLA:CPU's executable read from
that cache serialises without its kernels (`_compile_and_store`); a later process traces and
lowers it, and JAX's cache skips its compilation. Files of earlier versions (other keys, and
the `.bin`/`.tree` exports written before 28 Nov 2026) are never read again; the folder is a
cache and may be removed at any time.

A program made `light` is compiled with XLA's cheap settings (those of JAX's
`jax_disable_most_optimizations`: LLVM at -O0, without its expensive passes), where it is
called with concrete inputs: for programs that make one pass over a trajectory or solve one
small problem per call (a trajectory's summary and resampling, the equilibria and critical
rotor momenta of the momentum sphere), whose compilation costs a hundred to a thousand times
their run. A cold `jaxdyn run torque-free` compiled its summary in 0.35 s instead of 0.66 s;
resampling 2e5 points of a dense trajectory ran in 94 ms instead of 56 ms (7 Dec 2026). Under
a trace of the caller's the function is traced into the caller's program, which is compiled
as the caller's.
"""

import contextlib
import copyreg
import functools
import hashlib
import importlib.metadata
import math
import os
import pickle
import platform
import re
import threading
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import ParamSpec, TypeVar

import jax
import numpy as np

_TRUSTED = ("jaxdyn", "builtins", "diffrax", "equinox", "jax", "jaxlib", "optimistix",
            "lineax", "collections", "numpy")
_CLASS = re.compile(r"<class '([\w.]+)'>")
_DIR = "jaxdyn-programs"
P = ParamSpec("P")
R = TypeVar("R")


def _register_sentinels() -> None:
    """Unpickle equinox's `MISSING` sentinel (in the auxiliary data of a module's tree
    definition) as the sentinel itself, so that stored tree definitions compare equal."""
    try:
        from equinox._module._flatten import MISSING  # pyright: ignore
    except ImportError:  # another equinox: tree definitions holding it are not stored
        return
    copyreg.pickle(type(MISSING), lambda _: (_missing, ()))


def _missing():
    from equinox._module._flatten import MISSING  # pyright: ignore

    return MISSING


_VERSION = None


def _version() -> str:
    """The versions of the libraries a program is built from, and a hash of jaxdyn's source."""
    global _VERSION
    if _VERSION is None:
        h = hashlib.sha256()
        for lib in ("jax", "jaxlib", "diffrax", "equinox", "optimistix", "lineax"):
            try:
                h.update(f"{lib}={importlib.metadata.version(lib)};".encode())
            except importlib.metadata.PackageNotFoundError:
                h.update(f"{lib}=?;".encode())
        root = Path(__file__).parent
        for path in sorted(root.rglob("*.py")):
            h.update(str(path.relative_to(root)).encode())
            h.update(path.read_bytes())
        _VERSION = h.hexdigest()
        _register_sentinels()
    return _VERSION


def _directory() -> Path | None:
    where = jax.config.jax_compilation_cache_dir
    return Path(where) / _DIR if where else None


def _trusted(text: str) -> bool:
    """Whether a structure's text names only jaxdyn's and its libraries' classes (and no
    object identified by its address, such as a Python function)."""
    if " at 0x" in text or "<function" in text or "<lambda>" in text:
        return False
    return all(m.split(".")[0] in _TRUSTED for m in _CLASS.findall(text))


def _signature(leaves) -> tuple:
    """The shapes and dtypes of the inputs (what a `jax.jit` program is specialised to)."""
    return tuple((x.shape, x.dtype, getattr(x, "weak_type", False)) if hasattr(x, "dtype")
                 else (np.shape(x), np.result_type(x)) for x in leaves)


class StoredProgram:
    """`jax.jit(fn)` for one program, kept on disk per input signature where the compilation
    cache is on (see the module's docstring). Called with arrays only."""

    def __init__(self, name: str, structure, options, fn, *, light: bool = False):
        self.fn = fn
        self.light = light  # compiled with XLA's cheap settings (see the module's docstring)
        self.jitted = _on_one_device(fn)  # (traced into a caller's program: no settings)
        self.called = _light_call(fn, self.jitted) if light else self.jitted  # concrete inputs
        self.text = f"{name}|{structure}|{options!r}" + ("|light" if light else "")
        self.trusted = _trusted(self.text)
        self.calls: dict = {}
        _LIVE.add(self)

    def __call__(self, *args):
        return self.resolve(*args)(*args)

    def resolve(self, *args):
        """The callable for arguments of this signature (their structure, shapes and dtypes):
        a caller that holds it skips working the signature out on each call."""
        leaves, in_tree = jax.tree_util.tree_flatten(args)
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            # Under the caller's transformation (`jit`, `vmap`, `grad` of a derived output of
            # a traced trajectory): the function itself, traced (a compiled program has no
            # derivative rule and takes concrete inputs only).
            return self.jitted
        key = (in_tree, _signature(leaves))
        call = self.calls.get(key)
        if call is None or isinstance(call, _Pending):  # decided once per signature
            call = self.calls[key] = self._load(args, key)
        return call

    def prepare(self, *args, then=None):
        """Have the program for the signature of `args` (their structure, shapes and dtypes;
        the values do not matter) made ready on a worker thread while this thread next
        compiles another stored program: XLA:CPU compiles a program on one core, without
        Python's lock, so a program whose inputs' shapes are known before they are computed
        (a fit's summaries, known at its start) is traced and compiled on the other core,
        off the caller's path. A call of this signature then waits for it; one that comes
        first makes the program itself. Nothing where the program is stored already (it is
        read when called), not stored at all, or the arguments are traced. The arguments may
        be `jax.ShapeDtypeStruct`s. `then(outputs)`: called on the worker thread with the
        outputs' shapes once the program is lowered (`when_lowered`), to prepare the programs
        that take its outputs."""
        leaves, in_tree = jax.tree_util.tree_flatten(args)
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return
        key = (in_tree, _signature(leaves))
        if key in self.calls:
            return
        path = self._path(key)
        if path is None or path.exists():
            return
        context = _trace_context()
        if context is not None:
            self.calls[key] = _Pending(self, key, args, path, context, then)

    def _path(self, key) -> Path | None:
        """Where the program of this signature is stored, or `None` (not stored)."""
        where = _directory() if self.trusted else None
        if where is None:
            return None
        text = f"{_version()}|{self.text}|{key}|x64={jax.config.jax_enable_x64}|" \
               f"{jax.default_backend()}|{_machine()}|{_compile_settings()}"
        return where / (hashlib.sha256(text.encode()).hexdigest() + ".exe")

    def _load(self, args, key):
        """The program for this signature: this machine's compiled program read from disk, or
        else compiled here and stored for the next process (`jax.jit` alone where the
        compilation cache is off or the structure untrusted); or the one being made ready
        by `prepare`."""
        pending = self.calls.get(key)
        if isinstance(pending, _Pending):
            # Taken out first: a call interrupted while it compiles leaves nothing behind
            # for the next to wait on (a concurrent caller compiles its own).
            self.calls.pop(key, None)
            ready = pending.wait()
            if ready is not None:
                return ready
        path = self._path(key)
        if path is None:
            return self.called
        return self._ready(args, path)

    def _ready(self, args, path: Path):
        loaded = _read_executable(path)
        if loaded is _UNLOADABLE:  # (removed): compiled into JAX's cache, not stored again,
            return self._compiled(args, None)  # so no process compiles it afresh after
        if loaded is None:
            return self._compiled(args, path)
        compiled, out_tree = loaded
        return _checked(compiled, out_tree, path, lambda a: self._compiled(a, None))

    def _compiled(self, args, path: Path | None):
        """The program traced, lowered and compiled for `args` as `jax.jit` would, and its
        compiled form stored at `path` (unless `None`; see `_compile_and_store`)."""
        found = []

        def flat(*a):  # flat outputs: their tree is kept beside the compiled program
            leaves, tree = jax.tree_util.tree_flatten(self.fn(*a))
            found.append(tree)
            return leaves

        # Named with jaxdyn's version: JAX's persistent cache then never holds the program
        # from an earlier version (its executable could not be stored: `_compile_and_store`).
        program = _on_one_device(_named(flat, self.fn, _version()[:10]), self.light)
        compiled = _compile_and_store(path, program, args, found)
        if compiled is None:
            return self.called
        return _checked(compiled, found[0], None, lambda _: self.called)


def _trace_context():
    """The configuration a program is traced under (JAX's own key for it: x64, the default
    device, ...), or `None` where this JAX does not say (then nothing is prepared)."""
    try:
        from jax._src.config import trace_context  # pyright: ignore

        return trace_context()
    except Exception:
        return None


_QUEUE: list = []  # programs to prepare when a compilation next starts (`StoredProgram.prepare`)
_LOCK = threading.Lock()


class _Pending:
    """A program `prepare`d: queued, then made ready on a worker thread once a compilation
    starts (`start_prepared`). Its thread traces only under the caller's configuration
    (settings such as `jax.default_device` are per thread): otherwise it does nothing, and
    the call makes the program itself. The thread is not a daemon: a process that ends while
    it compiles waits for it."""

    def __init__(self, program: "StoredProgram", key, args, path: Path, context, then=None):
        self.program, self.key, self.args = program, key, args
        self.path, self.context, self.then = path, context, then
        self.done = threading.Event()
        self.result = None
        with _LOCK:
            _QUEUE.append(self)
        scope = getattr(_SCOPE, "pending", None)
        if scope is not None:
            scope.append(self)

    def start(self) -> None:
        def work():
            try:
                if _trace_context() == self.context:
                    with when_lowered(self.then):
                        self.result = self.program._ready(self.args, self.path)
            except Exception:  # made again by the call, which raises what it raises
                self.result = None
            finally:
                self.args = self.then = None
                self.done.set()

        try:
            threading.Thread(target=work, name="jaxdyn-prepare").start()
        except Exception:  # no thread to be had (at the interpreter's shutdown): the call
            self.args = self.then = None  # makes it
            self.done.set()

    def cancel(self) -> bool:
        """Take it out of the queue if it has not started (its call, if any, makes it);
        whether it was still queued."""
        with _LOCK:
            if self not in _QUEUE:
                return False
            _QUEUE.remove(self)
            self.done.set()  # (here: an interrupt cannot come between the two)
        self.args = self.then = None
        calls = self.program.calls
        if calls.get(self.key) is self:  # (a later `prepare` of this signature queues anew)
            calls.pop(self.key, None)
        return True

    def wait(self):
        """The program made ready, or `None` (not started, or it failed): the caller makes
        it."""
        if not self.cancel():
            self.done.wait()
        return self.result


def start_prepared() -> None:
    """Start preparing the queued programs (`StoredProgram.prepare`): called as a stored
    program's compilation starts, and by a caller about to compile a program that is not
    stored (a posterior's chain), so that they are made ready on the other core meanwhile."""
    queued: list = []
    started = 0
    try:
        with _LOCK:
            queued = list(_QUEUE)
            _QUEUE.clear()
        for pending in queued:
            pending.start()
            started += 1
    except BaseException:  # (an interrupt, wherever it comes): the rest are left to their
        for rest in queued[started:]:  # calls
            rest.args = rest.then = None
            rest.done.set()
        raise


_SCOPE = threading.local()


@contextlib.contextmanager
def when_lowered(callback):
    """Within: `callback(outputs)`, with the outputs' shapes (`jax.ShapeDtypeStruct`s in the
    outputs' tree), as the next stored program that this thread compiles is lowered, before
    XLA compiles it, so that the programs `callback` `prepare`s from them are traced and
    compiled on another core meanwhile (`None`: nothing). Called at most once; an exception
    it raises is dropped (the programs it would have prepared are made by their calls).
    `None` leaves an enclosing callback in place."""
    if callback is None:
        yield
        return
    with thread_setting(_SCOPE, "lowered", callback):
        yield


@contextlib.contextmanager
def thread_setting(local: threading.local, name: str, value):
    """Within: `local.name` (a per-thread setting) is `value`; the enclosing one after."""
    outer = getattr(local, name, None)
    setattr(local, name, value)
    try:
        yield
    finally:
        setattr(local, name, outer)


def _announce_lowered(program, args, found: list) -> None:
    callback = getattr(_SCOPE, "lowered", None)
    if callback is None:
        return
    _SCOPE.lowered = None  # (once: the program this thread compiles next, not the ones after)
    try:
        # (`eval_shape` reads the tracing just done, and keeps weak types: `Lowered.out_info`
        # drops them, and a weak-typed input is another signature.)
        callback(jax.tree_util.tree_unflatten(found[0], program.eval_shape(*args)))
    except Exception:
        pass


def cancels_unused_preparations(fn: Callable[P, R]) -> Callable[P, R]:
    """`fn` with the programs it `prepare`s on this thread and has not called by the time it
    returns or raises taken out of the queue (an interrupted fit leaves no compilation to be
    started later for nothing)."""
    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        mine: list = []
        try:
            with thread_setting(_SCOPE, "pending", mine):
                return fn(*args, **kwargs)
        finally:
            for pending in mine:
                pending.cancel()

    return wrapper


_LIVE: "weakref.WeakSet[StoredProgram]" = weakref.WeakSet()


_FORGET: list = []  # other modules' compiled programs, and their memories of calls of these


def forgotten_on_clear(forget: Callable[[], None]) -> Callable[[], None]:
    """Register `forget()`, which drops a module's compiled programs or its memory of loaded
    programs' calls, to be called by `clear_loaded`."""
    _FORGET.append(forget)
    return forget


def clear_loaded() -> None:
    """Forget every stored program's compiled form held in this process, the calls of them
    that other modules remember, and the programs other modules compiled themselves (the
    ensemble's chunks): a later call reads the program again, or compiles it. This is
    what `jax.clear_caches()` does for `jax.jit`'s programs, whose memory (XLA:CPU's
    mappings of their machine code) it frees. As with `jax.jit`, a program once compiled in
    a process is otherwise called whatever JAX's settings are later; programs being made
    ready on a worker thread are left to their calls."""
    for program in list(_LIVE):
        program.calls = {k: v for k, v in program.calls.items() if isinstance(v, _Pending)}
    for forget in _FORGET:
        forget()


# JAX's settings that change what XLA compiles from the same program: a program stored under
# one is not read under another (JAX's persistent cache keys them through its compile options).
_COMPILE_SETTINGS = ("jax_disable_most_optimizations", "jax_optimization_level",
                     "jax_exec_time_optimization_effort", "jax_memory_fitting_effort",
                     "jax_memory_fitting_level")


def _compile_settings() -> str:
    values = jax.config.values  # (once per signature: 50 us)
    return ";".join(f"{name}={values.get(name)}" for name in _COMPILE_SETTINGS)


_MACHINE = None


def _machine() -> str:
    """What a compiled program is specific to beyond JAX's versions: the processor (XLA:CPU
    compiles for the host's instruction set), the backend's platform version, the devices
    (their kinds and count, and the one programs run on) and XLA's flags."""
    global _MACHINE
    if _MACHINE is None:
        cpu = ""
        try:
            with open("/proc/cpuinfo") as f:
                cpu = "".join(sorted({line for line in f
                                      if line.startswith(("model name", "flags", "Features",
                                                          "CPU part"))}))
        except OSError:
            cpu = platform.processor()
        devices = jax.devices()
        client = devices[0].client
        _MACHINE = (f"{platform.machine()}|{cpu}|{client.platform}|{client.platform_version}|"
                    f"{[d.device_kind for d in devices]}|{_default_device()}|"
                    f"{os.environ.get('XLA_FLAGS', '')}")
    return _MACHINE


def _checked(compiled, out_tree, path: Path | None, fallback):
    """A compiled program (`jax.stages.Compiled`) called as `jax.jit` would call it, with
    concrete inputs (`resolve` hands traced ones to the function itself): inputs committed to
    another device are moved to the program's; and a program that does not run here (XLA:CPU:
    a kernel missing from it, "NOT_FOUND", raised at the call or, for a program run on a
    worker thread, when its results are read: its first call waits for them) is replaced by
    `fallback(args)`, and its stored file (`path`) removed."""
    device = _default_device()
    checked, replacement = False, None

    def call(*a):
        nonlocal checked, replacement
        if replacement is not None:
            return replacement(*a)
        try:
            try:
                out = compiled(*a)
            except ValueError:  # inputs on another device
                out = compiled(*jax.device_put(a, device))
            if not checked:
                jax.block_until_ready(out)
                checked = True
        except jax.errors.JaxRuntimeError as e:
            if checked or "NOT_FOUND" not in str(e):
                raise
            if path is not None:
                _remove(path)
            replacement = fallback(a)
            return replacement(*a)
        return jax.tree_util.tree_unflatten(out_tree, out)

    return call


_CUSTOM_CALL = re.compile(r"custom_call @(\w+)|call_target_name = \"(\w+)\"")


def _compile_and_store(path: Path | None, program, args, found: list):
    """`program` (flat outputs, whose tree its tracing appends to `found`) compiled for
    `args` (`None` where it cannot be: it is then called as usual), and stored at `path` as
    this machine's compiled program where that is safe (a later process loads it without
    tracing, lowering or compiling: `_read_executable`). Not stored where JAX's persistent
    cache held the program (an earlier process compiled the same one under other
    circumstances, such as a stored program that was since removed): XLA:CPU's executable
    deserialised from that cache serialises without its kernels ("Function ... not found"
    when run; measured with jax 0.10), so only a fresh compilation is stored; nor where it
    calls custom kernels other than LAPACK's (only those are known to be set up on loading,
    below), nor where the outputs' tree does not survive a pickle.

    A program that is stored here is not also written to JAX's persistent cache (its
    executable would be serialised twice, on the caller's path: about 70 ms of a cold
    `jaxdyn run`, measured on 7 Dec 2026); one that is not stored is written there as usual.
    So that no program is compiled afresh by every process, one whose stored file could not
    be loaded (`_UNLOADABLE`) is compiled into JAX's cache and not stored again (`_ready`),
    nothing is kept out of JAX's cache where the folder cannot be written, and one whose
    serialisation or writing fails leaves a marker (`.unstorable`) under which later
    processes compile it into JAX's cache."""
    try:
        lowered = program.lower(*args)
    except Exception:  # called as usual
        return None
    _announce_lowered(program, args, found)
    start_prepared()  # (their tracing runs while XLA compiles this one)
    _listen_for_cache_hits()
    _HITS.count = 0  # (this thread's compilation's, not a prepared one's)
    lapack = None if path is None else _storable(lowered, found[0], path)
    try:
        with contextlib.nullcontext() if lapack is None else _not_in_jax_cache():
            compiled = lowered.compile()
    except Exception:
        return None
    if lapack is None or _HITS.count:
        return compiled
    try:
        from jax.experimental import serialize_executable

        blob = pickle.dumps((serialize_executable.serialize(compiled), found[0], lapack))
    except Exception:  # not serialisable: used, not kept
        blob = None
    if blob is None or not _write(path, blob):  # (nor tried again: the marker)
        _write(_marker(path), b"")
    return compiled


def _marker(path: Path) -> Path:
    """The file that says the program of `path` could not be stored (`_compile_and_store`)."""
    return path.with_suffix(".unstorable")


def _storable(lowered, out_tree, path: Path) -> bool | None:
    """Whether a lowered program calls LAPACK's kernels, if it can be stored at `path`
    (`None`: it calls other custom kernels, its outputs' tree does not survive a pickle, its
    folder cannot be written, or an earlier process could not store it)."""
    if not _writable(path.parent) or _marker(path).exists():
        return None
    targets = {a or b for a, b in _CUSTOM_CALL.findall(lowered.as_text())}
    if not all(t.startswith("lapack_") for t in targets):
        return None
    try:
        if pickle.loads(pickle.dumps(out_tree)) != out_tree:  # (a tree lost in a pickle)
            return None
    except Exception:
        return None
    return bool(targets)


def _writable(directory: Path) -> bool:
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(directory, os.W_OK)


def _not_in_jax_cache():
    """Within (this thread): XLA's compilations are not written to JAX's persistent cache
    (JAX's minimum compile time for an entry set to infinity, a per-thread setting); nothing
    where this JAX has no such setting."""
    try:
        from jax._src.config import persistent_cache_min_compile_time_secs  # pyright: ignore

        return persistent_cache_min_compile_time_secs(math.inf)
    except Exception:
        return contextlib.nullcontext()


_HITS = threading.local()  # JAX's persistent-cache hits of this thread's compilations
_LISTENING: list = []


def _listen_for_cache_hits() -> None:
    """Count JAX's persistent-cache hits per thread (JAX records them on the compiling
    thread); one listener for the process, registered once (registering and removing one per
    compilation raced with another thread's compilation reading the listeners)."""
    if _LISTENING:
        return
    with _LOCK:
        if _LISTENING:
            return

        def listen(event, **kwargs):
            if event == "/jax/compilation_cache/cache_hits":
                _HITS.count = getattr(_HITS, "count", 0) + 1

        jax.monitoring.register_event_listener(listen)
        _LISTENING.append(listen)


_UNLOADABLE = object()  # a stored file that this JAX could not load (`_read_executable`)


def _read_executable(path: Path):
    """The compiled program stored by `_compile_and_store` and the tree of its outputs,
    `None` (not stored, or not readable), or `_UNLOADABLE` (read but not loadable by this
    JAX: removed)."""
    import time

    start = time.perf_counter()
    try:
        blob = path.read_bytes()
    except OSError:
        return None
    try:
        from jax.experimental import serialize_executable

        (payload, in_tree, flat_tree), out_tree, lapack = pickle.loads(blob)
        if lapack:
            # LAPACK's kernels read their routines from scipy, which JAX sets up when it
            # lowers a program that calls them; a loaded program is never lowered.
            from jax._src.lax.linalg import initialize_lapack  # pyright: ignore

            initialize_lapack()
        compiled = serialize_executable.deserialize_and_load(
            payload, in_tree, flat_tree, execution_devices=[_default_device()])
    except Exception:  # unreadable (truncated, another JAX): removed, compiled again
        _remove(path)
        return _UNLOADABLE
    jax.monitoring.record_event_duration_secs("/jaxdyn/programs/load_duration",
                                              time.perf_counter() - start)
    return compiled, out_tree


def _write(path: Path, data: bytes) -> bool:
    """`data` written to `path` atomically (concurrent writers agree); nothing where the
    folder cannot be written (read-only, full: the program is still used, only not kept).
    Whether it was written."""
    # (One temporary file per writer: two threads of a process may store one program.)
    tmp = path.with_suffix(f"{path.suffix}.{os.getpid()}.{threading.get_ident()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError:
        _remove(tmp)
        return False
    return True


def _remove(path: Path) -> None:
    try:
        path.unlink(missing_ok=True)
    except OSError:
        pass


def _default_device():
    """The device jaxdyn's programs run on: JAX's default device (where `jax.jit` puts host
    inputs)."""
    device = jax.config.jax_default_device
    if not isinstance(device, jax.Device):
        device = jax.local_devices(backend=device if isinstance(device, str) else None)[0]
    return device


# XLA's settings for a light program (`StoredProgram(light=True)`): those that JAX's
# `jax_disable_most_optimizations` sets.
_LIGHT = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


def _on_one_device(fn, light: bool = False):
    """`jax.jit(fn)` with every input placed on JAX's default device (and XLA's cheap
    settings where `light`: such a program can only be called, not traced into another).

    Plain `jax.jit` lowers and compiles a program again, under another key of the persistent
    cache, when an input that was a host array (not committed to a device) in one call is a
    device array (committed) in the next: a fit that passes one stage's estimate to the next,
    or `jd.simulate` from `traj.y_final`, compiled each of its programs twice. Naming the
    placement makes every call the same program. (Inputs committed to another device are
    moved to the default one: jaxdyn's programs run on one device.)"""
    return jax.jit(fn, in_shardings=jax.sharding.SingleDeviceSharding(_default_device()),
                   compiler_options=_LIGHT if light else None)


def staged() -> bool:
    """Whether this call is being staged into a program of the caller's (`jax.jit` of a
    function that closes over concrete inputs): new values are then tracers. Where no trace
    is open at all (JAX's own check, 0.3 us) it is not, without making a value (65 us)."""
    if _trace_state_clean():
        return False
    return isinstance(jax.numpy.zeros((), bool), jax.core.Tracer)


def _trace_state_clean() -> bool:
    try:
        from jax._src.core import trace_state_clean  # pyright: ignore
    except ImportError:  # (another JAX: the value is made)
        return False
    return trace_state_clean()


def _light_call(fn, usual):
    """`fn` under `jax.jit` on one device with XLA's cheap settings, or `usual` where the call
    is staged into a program of the caller's (there `jax.jit`, even of concrete inputs, is a
    nested program, which may not carry options of its own)."""
    cheap = _on_one_device(fn, True)

    def call(*args):
        return usual(*args) if staged() else cheap(*args)

    return call


def _named(fn, like, tag=None):
    """`fn` under the name of `like` (JAX's logs and caches name a program after it), with
    `tag` appended."""
    def program(*args):
        return fn(*args)

    name = getattr(like, "__name__", "program")
    program.__name__ = program.__qualname__ = name if tag is None else f"{name}_{tag}"
    return program
