"""A pytest plugin for `benchmarks/suite.py`: where each test's time goes in the process that runs
it, from JAX's own monitoring events.

For each test: wall time, the process's CPU time, the CPU time of the processes it started
and waited for (`children_cpu_s`: commands, notebook kernels), and the CPU time JAX spent
tracing, lowering and compiling or loading programs (the phases the commands report,
`trace_s`, `lower_s` and `compile_s`: `jax.jit`'s compilation step, XLA's compilation of a
program or its loading from the persistent cache), the programs so compiled and loaded, and
jaxdyn's stored programs loaded. The phases are timed in CPU time, from the event's start to
its end (JAX reports both on the thread that runs it), so a busy machine does not inflate
them: tracing and lowering in that thread's CPU time (`time.thread_time`: Python's work),
compilation in the process's (`time.process_time`: XLA compiles on threads of its own while
the caller waits; the little that other threads of the process do meanwhile, such as jaxdyn's
background preparation, is counted with it). A compilation on one of jaxdyn's background
threads that ends after its test is counted with the next test.

Each process writes one JSON file into `$JAXDYN_SUITE_PROFILE_DIR` when pytest ends. JAX is
imported only once the suite's `conftest.py` has set its environment (`pytest_configure`): its
configuration is read when it is first imported.
"""

import collections
import json
import os
import resource
import threading
import time

import pytest

PHASES: dict = {}  # JAX's event -> the phase's name, as the commands report them (below)
# One `_REQUESTS` per compilation step, compiled or loaded from the cache (one of `_HITS`).
_REQUESTS = "/jax/core/compile/backend_compile_duration"
_HITS = "/jax/compilation_cache/cache_hits"
_JAXDYN_LOADS = "/jaxdyn/programs/load_duration"
_LOCK = threading.Lock()
_CPU: collections.Counter = collections.Counter()  # event -> CPU seconds (`_clock`)
_COUNTS: collections.Counter = collections.Counter()  # event -> occurrences
_STARTS: dict = {}  # (thread, event) -> `_clock` at the event's start
_TRACE = "/jax/core/compile/jaxpr_trace_duration"
_TRACED: dict = {}  # function's name -> [traces, CPU seconds], within the running test
_UNCACHEABLE: dict = {}  # program's name -> [compiled, seconds], within the running test
_TESTS: dict = {}
_START = time.time()


def _clock(event) -> float:
    return time.process_time() if event == _REQUESTS else time.thread_time()


def _started(event, value, **_):
    if event in PHASES:
        _STARTS.setdefault((threading.get_ident(), event), []).append(_clock(event))


def _ended(event, duration, fun_name=None, **_):
    with _LOCK:
        _COUNTS[event] += 1
        starts = _STARTS.get((threading.get_ident(), event))
        if starts:
            spent = _clock(event) - starts.pop()
            _CPU[event] += spent
            if event == _TRACE and fun_name is not None:
                entry = _TRACED.setdefault(fun_name, [0, 0.0])
                entry[0] += 1
                entry[1] += spent


def _top3(entries: dict) -> dict:
    """The three costliest names of `{name: (count, seconds)}`, with their counts."""
    return {name: n for name, (n, _) in sorted(entries.items(), key=lambda kv: -kv[1][1])[:3]}


def _repeats() -> dict:
    """The running test's repeated work: its functions traced more than once (a new function
    each time, or new shapes or settings; the traces beyond the first, and their CPU time at
    each function's average trace) and the programs it compiled that the persistent cache
    cannot keep (XLA's seconds); each with its three costliest names."""
    with _LOCK:
        again = {name: (n - 1, cpu * (n - 1) / n) for name, (n, cpu) in _TRACED.items()
                 if n > 1}
        uncacheable = {name: tuple(v) for name, v in _UNCACHEABLE.items()}
    out = {}
    for what, entries in (("traced_again", again), ("uncacheable", uncacheable)):
        out[what] = sum(n for n, _ in entries.values())
        out[f"{what}_s"] = sum(t for _, t in entries.values())
        if entries:
            out[f"{what}_names"] = _top3(entries)
    return out


def _event(event, **_):
    with _LOCK:
        _COUNTS[event] += 1


def _children_cpu() -> float:
    """CPU time of the processes this one started and waited for (commands, notebook
    kernels), user and system."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _snapshot() -> dict:
    with _LOCK:
        return {**{name: _CPU[event] for event, name in PHASES.items()},
                "compiled": _COUNTS[_REQUESTS] - _COUNTS[_HITS], "loaded": _COUNTS[_HITS],
                "jaxdyn_loaded": _COUNTS[_JAXDYN_LOADS]}


def pytest_configure(config):
    from jax._src import monitoring  # (after conftest.py: see above)

    from jaxdyn._commands._common import _COMPILE_EVENTS

    PHASES.update({e: name for e, name in _COMPILE_EVENTS.items() if e != _JAXDYN_LOADS})

    # Programs with host callbacks (equinox's runtime checks, `jax.debug`): JAX does not write
    # them to the persistent cache, so each new trace of one compiles it again.
    from jax._src import compiler

    write = compiler._cache_write

    def _cache_write(cache_key, compile_time_secs, module_name, backend, executable,
                     host_callbacks, *args, **kwargs):
        if host_callbacks:
            with _LOCK:
                entry = _UNCACHEABLE.setdefault(module_name, [0, 0.0])
                entry[0] += 1
                entry[1] += compile_time_secs
        return write(cache_key, compile_time_secs, module_name, backend, executable,
                     host_callbacks, *args, **kwargs)

    compiler._cache_write = _cache_write
    monitoring.register_scalar_listener(_started)
    monitoring.register_event_duration_secs_listener(_ended)
    monitoring.register_event_listener(_event)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    before = _snapshot()
    with _LOCK:
        _TRACED.clear()
        _UNCACHEABLE.clear()
    wall, cpu, children = time.perf_counter(), time.process_time(), _children_cpu()
    yield
    after = _snapshot()
    _TESTS[item.nodeid] = {"wall_s": time.perf_counter() - wall,
                           "cpu_s": time.process_time() - cpu,
                           "children_cpu_s": _children_cpu() - children,
                           **{k: after[k] - before[k] for k in after}, **_repeats()}


def pytest_unconfigure(config):
    where = os.environ.get("JAXDYN_SUITE_PROFILE_DIR")
    if not where:
        return
    role = "worker" if hasattr(config, "workerinput") else "main"
    out = {"pid": os.getpid(), "role": role, "wall_s": time.time() - _START,
           "cpu_s": time.process_time(), "totals": _snapshot(), "tests": _TESTS}
    with open(os.path.join(where, f"process-{os.getpid()}.json"), "w") as f:
        json.dump(out, f)
