import os
import tempfile

# The suite's time goes to compiling (most programs run for milliseconds): XLA's CPU backend
# compiles them without LLVM's expensive optimisations (about half the compile time; the same
# operations, so the same results to round-off). Set before JAX starts its backend, for the
# workers and for the notebook kernels and commands the tests start (they inherit it);
# JAXDYN_TEST_XLA_FLAGS=... chooses other flags (empty: XLA's defaults).
_FAST_COMPILE = "--xla_backend_optimization_level=0"
os.environ["XLA_FLAGS"] = " ".join(
    filter(None, (os.environ.get("XLA_FLAGS", ""),
                  os.environ.get("JAXDYN_TEST_XLA_FLAGS", _FAST_COMPILE))))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

# One persistent compilation cache for the whole run, shared by the workers, by the notebook
# kernels and by the commands the tests start (never the user's own ~/.cache): a program that
# one process compiled is loaded by the others, and a second run of the suite loads them all.
os.environ.setdefault("JAXDYN_CACHE_DIR", os.path.join(tempfile.gettempdir(),
                                                       f"jaxdyn-test-cache-{os.getuid()}"))
from jaxdyn._cache import enable_compilation_cache  # noqa: E402

enable_compilation_cache()

# The longest tests first (measured with --durations; each is mostly compilation), so that the
# workers finish together instead of one running a long test alone at the end.
SLOW_FIRST = (
    "test_notebooks.py::test_notebook_executes[09",
    "test_identify.py::test_wheel_telemetry_fixes_the_inertia_scale",
    "test_hard_cases.py::test_gradients",
    "test_free_body_attitude.py::test_gradients_match_finite_differences",
    "test_identify.py::test_cli_gyro_bias_and_star_tracker",
    "test_free_body_attitude.py::test_reverse_mode_is_finite_at_special_points",
    "test_identify.py::test_cli_fit_programs_are_cached_on_the_second_run",
    "test_readme.py::test_readme_examples_run",
    "test_hard_cases.py::test_float32_reach",
    "test_rough_rod.py::test_gradients_through_events_and_switches",
    "test_notebooks.py::test_notebook_executes",
    "test_identify.py",
    "test_outcomes.py::test_hybrid_outcomes",
    "test_magnetorquers.py::test_residual_dipole_identified_from_gyro_rates",
)


def pytest_collection_modifyitems(config, items):
    def rank(item):
        where = item.nodeid.split("/")[-1]
        return next((i for i, p in enumerate(SLOW_FIRST) if where.startswith(p)),
                    len(SLOW_FIRST))

    items.sort(key=rank)  # stable: the order within a rank (and of the rest) is kept
