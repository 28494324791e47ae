import gc
import os
import tempfile

import pytest

# XLA:CPU's flags for the whole run, set before JAX starts its backend (inherited by the
# notebook kernels and the commands the tests start). The command's own choice first
# (`jaxdyn._xla`: XLA's earlier fusion emitters, and small loops compiled whole, each where
# this XLA has it, unless XLA_FLAGS names it): the emitters halve the suite's compilation
# (1034 s -> 528 s of XLA time in the workers, 1091 s -> 772 s of wall time on 2 cores,
# 28 Nov 2026) and run the programs as fast; a single run's step loop, compiled whole, runs
# 1.1-12x faster (`benchmarks/latency.py --only loops`, s44 and s45). Then any of
# JAXDYN_TEST_XLA_FLAGS, added to them.
#
# Most tests spend their time in XLA compiling programs that then run for milliseconds, so XLA
# compiles them with most optimisations off (JAX's `jax_disable_most_optimizations`: LLVM at
# -O0 without its expensive passes), in the workers and in the processes they start (notebook
# kernels, commands), unless JAX_DISABLE_MOST_OPTIMIZATIONS chooses (`=0`: every test compiled
# as a user's programs are). Tests marked `optimized` compile as a user's programs do (the
# `_optimisation` fixture below): those whose time is running (a posterior's sampling: 1.6-3.4x
# slower otherwise), and those that compare two programs bit for bit or bound the round-off of
# the code a user runs; the longest notebooks' kernels likewise (`test_notebooks.py`).
# Fresh-cache runs of the suite on 2 cores, one after the other (6 Dec 2026): 613-642 s with
# every test optimised, 562 s with none (six comparisons failing), 504 s so.
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
from jaxdyn._xla import add_settings  # noqa: E402

add_settings()
if os.environ.get("JAXDYN_TEST_XLA_FLAGS"):
    os.environ["XLA_FLAGS"] = " ".join(
        filter(None, (os.environ.get("XLA_FLAGS", ""), os.environ["JAXDYN_TEST_XLA_FLAGS"])))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

# One persistent compilation cache for the whole run, shared by the workers, by the notebook
# kernels and by the commands the tests start (never the user's own ~/.cache): a program that
# one process compiled is loaded by the others, and a second run of the suite loads them all.
os.environ.setdefault("JAXDYN_CACHE_DIR", os.path.join(tempfile.gettempdir(),
                                                       f"jaxdyn-test-cache-{os.getuid()}"))
from jaxdyn import _programs  # noqa: E402
from jaxdyn._cache import enable_compilation_cache  # noqa: E402

enable_compilation_cache()

# No full garbage collections in the workers, as in the command's process (the command's
# own setting): each walks the whole heap, which JAX's caches of thousands of programs make
# large. Three test modules (test_rod, test_outcomes, test_hard_cases) made 25
# of 0.3 s each in 121 s (6 %), at the same peak memory without them (7 Dec 2026). The
# younger generations are collected as usual, and `_bounded_memory_mappings` below collects
# fully where the compiled programs' mappings grow.
from jaxdyn._cli import _defer_full_collections  # noqa: E402

_defer_full_collections()

# The longest tests first, so that the workers finish together instead of one running a long
# test alone at the end (with `--dist loadscope`, pyproject.toml, each module goes whole to
# one worker, in the order of its first test here). Ordered by `--durations` of a
# fresh-cache `pytest -n 2` run (loaded machine, 24 Nov 2026); each is mostly compilation.
SLOW_FIRST = (
    "test_posterior.py::test_posterior_agrees_with_gauss_newton_where_it_holds",
    "test_magnetorquers.py::test_residual_dipole_identified_from_gyro_rates",
    "test_notebooks.py::test_notebook_executes[09",
    "test_free_body_attitude.py::test_gradients_match_finite_differences",
    "test_fit_consistency.py::test_a_missing_bias_is_flagged_and_not_reported_as_converged",
    "test_posterior.py",
    "test_fit_consistency.py::test_cli_flags_a_missing_bias",
    "test_rough_rod.py::test_gradients_through_events_and_switches",
    "test_identify.py::test_cli_gyro_bias_and_star_tracker",
    "test_shooting.py::test_multiple_shooting_gives_the_single_shooting_estimate_and_intervals",
    "test_identify.py::test_long_noise_free_record_converges_from_the_default_start",
    "test_identify.py::test_cli_fit_programs_are_cached_on_the_second_run",
    "test_free_body_attitude.py::test_reverse_mode_is_finite_at_special_points",
    "test_readme.py::test_readme_examples_run",
    "test_rough_rod.py::test_ensemble_engine_switches_per_trajectory",
    "test_hard_cases.py::test_gradients",
    "test_identify.py::test_wheel_telemetry_fixes_the_inertia_scale",
    "test_fit_wheels_cli.py::test_fit_reads_wheel_columns_and_recovers_the_absolute_inertia",
    "test_long_records.py::test_switching_scene_with_many_samples_and_its_dense_table",
    "test_notebooks.py::test_notebook_executes",
    "test_cli.py::test_cache_can_be_moved_or_turned_off",
    "test_chunkstore.py::test_two_writers_one_killed_lose_nothing",
    "test_cli.py::test_torque_free_with_full_tensor",
    "test_identify.py",
    "test_chunkstore.py::test_the_fingerprint_covers_the_devices",
    "test_ensemble.py::test_processes_joined_by_jax_distributed_share_a_run",
    "test_hard_cases.py::test_float32_reach",
    "test_outcomes.py::test_hybrid_outcomes",
)


_LESS_OPTIMISED = jax.config.values["jax_disable_most_optimizations"]
_HELD = {"less optimised": False}  # whether this worker's caches may hold such programs


@pytest.fixture(autouse=True)
def _optimisation(request, monkeypatch):
    """An `optimized` test compiles its programs, and the processes it starts theirs, as a
    user's are compiled (see above), after this worker's programs compiled otherwise are
    forgotten (`jax.jit`'s, and jaxdyn's stored programs: neither is keyed by the setting)."""
    if not _LESS_OPTIMISED or request.node.get_closest_marker("optimized") is None:
        _HELD["less optimised"] = _LESS_OPTIMISED
        yield
        return
    if _HELD["less optimised"]:
        jax.clear_caches()
        _programs.clear_loaded()
        _HELD["less optimised"] = False
    monkeypatch.setenv("JAX_DISABLE_MOST_OPTIMIZATIONS", "0")
    jax.config.update("jax_disable_most_optimizations", False)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", True)


# Slow sweeps: the parameter values of a check beyond the representatives that the suite runs
# (every solver, outcome or mode is still checked at least once). They are marked
# `pytest.mark.sweep` and left out unless `--sweeps` is given; `python benchmarks/sweeps.py`
# runs them all and prints one JSON object.
def pytest_addoption(parser):
    parser.addoption("--sweeps", action="store_true",
                     help="also run the slow sweeps (tests marked `sweep`; "
                          "benchmarks/sweeps.py runs them)")


def pytest_configure(config):
    config.addinivalue_line("markers", "sweep: a further parameter value of a check the suite "
                                       "already runs; left out unless --sweeps is given")
    config.addinivalue_line("markers", "optimized: compiled with XLA's optimisations, as a "
                                       "user's programs are (the others: most of them off)")


def pytest_collection_modifyitems(config, items):
    if not config.getoption("--sweeps"):
        swept = [item for item in items if item.get_closest_marker("sweep")]
        if swept:
            config.hook.pytest_deselected(items=swept)
            items[:] = [item for item in items if item not in swept]

    def rank(item):
        where = item.nodeid.split("/")[-1]
        return next((i for i, p in enumerate(SLOW_FIRST) if where.startswith(p)),
                    len(SLOW_FIRST))

    items.sort(key=rank)  # stable: the order within a rank (and of the rest) is kept


# Every program XLA:CPU compiles keeps its machine code in memory mappings of its own (about
# 200 for a simulation), and JAX's caches keep the programs, so a worker that compiles
# thousands of them reaches the kernel's limit on mappings per process (vm.max_map_count,
# 65530 by default). There the next compilation fails to map memory ("LLVM compilation
# error: Cannot allocate memory"), and the C++ exception that reports it crashes the process
# (a segmentation fault while unwinding, inside jaxlib): the tests of one worker of a
# fresh-cache `pytest -n 2` run, replayed in one process, died so at 65216 mappings. Past half
# the limit, the caches are dropped after the test (their programs are reloaded from the
# persistent cache where needed); the same replay then peaked at 32975 and passed.
def _mapping_limit():
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            return int(f.read())
    except (OSError, ValueError):
        return None  # not Linux: no such limit to watch


_MAPPING_LIMIT = _mapping_limit()


@pytest.fixture(autouse=True)
def _bounded_memory_mappings():
    yield
    if _MAPPING_LIMIT:
        with open("/proc/self/maps") as f:
            mappings = sum(1 for _ in f)
        if mappings > _MAPPING_LIMIT // 2:
            jax.clear_caches()
            _programs.clear_loaded()
            gc.collect()
