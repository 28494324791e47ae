"""A pytest plugin for `benchmarks/suite.py`: where each test's time goes in the process that runs
it (a worker), from JAX's own monitoring events.

For each test: wall time, the process's CPU time, and JAX's tracing, lowering and XLA
compilation time and the programs compiled (persistent-cache misses) and loaded (hits) meanwhile.
Each process writes one JSON file into `$JAXDYN_SUITE_PROFILE_DIR` when pytest ends. JAX is
imported only once the suite's `conftest.py` has set its environment (`pytest_configure`): its
configuration is read when it is first imported.
"""

import collections
import json
import os
import time

import pytest

_TIMES: collections.Counter = collections.Counter()
_COUNTS: collections.Counter = collections.Counter()
_TESTS: dict = {}
_EVENTS = {"trace_s": "/jax/core/compile/jaxpr_trace_duration",
           "lower_s": "/jax/core/compile/jaxpr_to_mlir_module_duration",
           "compile_s": "/jax/core/compile/backend_compile_duration"}
_MISSES, _HITS = "/jax/compilation_cache/cache_misses", "/jax/compilation_cache/cache_hits"
_START = time.time()


def _duration(event, duration, **_):
    _TIMES[event] += duration


def _event(event, **_):
    _COUNTS[event] += 1


def pytest_configure(config):
    from jax._src import monitoring  # (after conftest.py: see above)

    monitoring.register_event_duration_secs_listener(_duration)
    monitoring.register_event_listener(_event)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    before = {k: _TIMES[v] for k, v in _EVENTS.items()}
    misses, hits = _COUNTS[_MISSES], _COUNTS[_HITS]
    wall, cpu = time.perf_counter(), time.process_time()
    yield
    _TESTS[item.nodeid] = {
        "wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu,
        **{k: _TIMES[v] - before[k] for k, v in _EVENTS.items()},
        "compiled": _COUNTS[_MISSES] - misses, "loaded": _COUNTS[_HITS] - hits}


def pytest_unconfigure(config):
    where = os.environ.get("JAXDYN_SUITE_PROFILE_DIR")
    if not where:
        return
    totals = {k: _TIMES[v] for k, v in _EVENTS.items()}
    out = {"pid": os.getpid(), "wall_s": time.time() - _START, "cpu_s": time.process_time(),
           "totals": {**totals, "compiled": _COUNTS[_MISSES], "loaded": _COUNTS[_HITS]},
           "tests": _TESTS}
    with open(os.path.join(where, f"process-{os.getpid()}.json"), "w") as f:
        json.dump(out, f)
