"""XLA's compiler settings for the command (`jaxdyn._xla`): each added only where the user has
not chosen it and where this XLA knows it (XLA aborts on an unknown flag), and the command
gives the same numbers to round-off with them as with XLA's defaults."""

import json
import os
import subprocess
import sys

import pytest

import jaxdyn as jd
from jaxdyn import _xla


def test_an_unknown_flag_is_not_known():
    assert not _xla.known("xla_cpu_no_such_flag_in_any_xla")


def test_known_looks_for_every_name():
    assert _xla.known("xla_dump_to")  # (a flag of every XLA: the search finds names)
    assert _xla.known() and not _xla.known(_xla.FLAG, "xla_cpu_no_such_flag_in_any_xla")
    assert _xla.known(_xla.FLAG, _xla.EXTRA) == (_xla.known(_xla.FLAG) and _xla.known(_xla.EXTRA))


def _knows(names):
    return all(_xla.known(name) for name in names)


@pytest.fixture
def before_jax_starts(monkeypatch):
    """As in a process whose JAX backend has not started (this worker's has)."""
    monkeypatch.setattr(_xla, "_backend_started", lambda: False)


def test_the_users_choice_is_kept(monkeypatch, before_jax_starts):
    # Each setting is left out where the user's flags name it; the other is still added.
    for value in ("--xla_cpu_use_fusion_emitters=true", "--xla_cpu_use_fusion_emitters"):
        monkeypatch.setenv("XLA_FLAGS", value)
        loops = _knows(_xla.SETTINGS[1][1])
        assert _xla.prefer_fast_programs() == ((_xla.LOOP_SETTING,) if loops else ())
        assert os.environ["XLA_FLAGS"] == value + (f" {_xla.LOOP_SETTING}" if loops else "")
    mine = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=512"
    monkeypatch.setenv("XLA_FLAGS", mine)
    emitters = _xla.known(_xla.FLAG)
    assert _xla.prefer_fast_programs() == ((_xla.SETTING,) if emitters else ())
    assert os.environ["XLA_FLAGS"] == mine + (f" {_xla.SETTING}" if emitters else "")
    monkeypatch.setenv("XLA_FLAGS", f"{mine} --xla_cpu_use_fusion_emitters=true")
    assert _xla.prefer_fast_programs() == ()


def test_added_where_known_and_the_users_other_flags_kept(monkeypatch, before_jax_starts):
    expected = tuple(setting for setting, names in _xla.SETTINGS if _knows(names))
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    assert _xla.prefer_fast_programs() == expected
    assert os.environ["XLA_FLAGS"] == " ".join(["--xla_force_host_platform_device_count=2",
                                                *expected])
    monkeypatch.delenv("XLA_FLAGS")
    assert _xla.prefer_fast_programs() == expected
    assert os.environ.get("XLA_FLAGS", "") == " ".join(expected)
    assert _xla.prefer_fast_programs() == ()  # (now named: nothing added twice)


def test_an_unknown_setting_is_not_added(monkeypatch, before_jax_starts):
    monkeypatch.setattr(_xla, "SETTINGS", (*_xla.SETTINGS, (
        "--xla_cpu_no_such_flag_in_any_xla=1", ("xla_cpu_no_such_flag_in_any_xla",))))
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert "--xla_cpu_no_such_flag_in_any_xla=1" not in _xla.prefer_fast_programs()
    assert "no_such_flag" not in os.environ.get("XLA_FLAGS", "")


def test_a_flag_is_set_only_by_its_own_name(monkeypatch, before_jax_starts):
    # A path or a value that contains a flag's name does not set it.
    mine = "--xla_dump_to=/tmp/xla_backend_extra_options_and_xla_cpu_use_fusion_emitters"
    monkeypatch.setenv("XLA_FLAGS", mine)
    expected = tuple(setting for setting, names in _xla.SETTINGS if _knows(names))
    assert _xla.prefer_fast_programs() == expected
    assert os.environ["XLA_FLAGS"] == " ".join([mine, *expected])


def test_too_late_once_jax_has_started(monkeypatch):
    # This worker's backend has started: XLA read XLA_FLAGS then, so adding to them would do
    # nothing; said so (with the whole XLA_FLAGS to start Python with), and XLA_FLAGS left as
    # it was. Nothing to add: nothing to say.
    import jax

    jax.devices()  # (starts the backend, where no test before it did)
    assert _xla._backend_started()
    mine = "--xla_force_host_platform_device_count=1"
    monkeypatch.setenv("XLA_FLAGS", mine)
    expected = tuple(setting for setting, names in _xla.SETTINGS if _knows(names))
    assert expected, "this XLA knows neither setting"
    with pytest.raises(RuntimeError, match="before JAX runs anything") as raised:
        jd.prefer_fast_programs()
    assert " ".join([mine, *expected]) in str(raised.value)
    assert os.environ["XLA_FLAGS"] == mine
    monkeypatch.setenv("XLA_FLAGS", " ".join(s for s, _ in _xla.SETTINGS))
    assert jd.prefer_fast_programs() == ()
    # The command's own call adds them without asking (as before this check: a command run
    # from a process whose JAX has started, as benchmarks/identify.py runs `fit`, is not
    # refused; its settings then change nothing).
    monkeypatch.setenv("XLA_FLAGS", mine)
    assert _xla.add_settings() == expected
    assert os.environ["XLA_FLAGS"] == " ".join([mine, *expected])


_HOISTED = r"""
import sys
import jaxdyn as jd
if sys.argv[1] == "prefer":
    print(" ".join(jd.prefer_fast_programs()), file=sys.stderr)
import jax
import jax.numpy as jnp


def loop(x):  # each iteration touches 16 KiB: above XLA's default threshold, below ours
    return jax.lax.while_loop(lambda c: c[0] < 10, lambda c: (c[0] + 1, jnp.sin(c[1])),
                              (0, x))[1]


text = jax.jit(loop).lower(jnp.ones(2048, jnp.float32)).compile().as_text()
print("xla_cpu_small_call" in text)
"""


@pytest.mark.skipif(not _xla.known(_xla.EXTRA, _xla.LOOP_OPTION),
                    reason="this jaxlib's XLA lacks the small-loop option")
def test_a_python_process_gets_small_loops_compiled_whole():
    """`jd.prefer_fast_programs()` first in a fresh process: a loop touching 16 KiB per
    iteration is compiled as one function (XLA's `xla_cpu_small_call`); without it (the
    emitters' setting alone), not."""
    hoisted = {}
    for how in ("prefer", "plain"):
        env = {**os.environ, "XLA_FLAGS": _xla.SETTING}
        proc = subprocess.run([sys.executable, "-c", _HOISTED, how], capture_output=True,
                              text=True, timeout=300, env=env)
        assert proc.returncode == 0, proc.stderr[-2000:]
        hoisted[how] = proc.stdout.strip()
    assert hoisted == {"prefer": "True", "plain": "False"}, hoisted


@pytest.mark.skipif(not _xla.known(_xla.FLAG, _xla.EXTRA),
                    reason="this jaxlib's XLA lacks the flags")
def test_the_command_gives_the_same_numbers_with_xlas_defaults(tmp_path):
    """`jaxdyn run --json` (the falling rod) with XLA's default emitters and small-loop
    threshold (1 KiB), and with the command's settings: the same results to round-off, both
    against the energy integral's reference."""
    defaults = ("--xla_cpu_use_fusion_emitters=true --xla_backend_extra_options="
                "xla_cpu_small_while_loop_byte_threshold=1024")
    outs = []
    for flags in (defaults, ""):
        env = {**os.environ, "XLA_FLAGS": flags, "JAXDYN_CACHE_DIR": "off"}
        proc = subprocess.run([sys.executable, "-m", "jaxdyn._cli", "run", "--json"],
                              capture_output=True, text=True, timeout=600, env=env)
        assert proc.returncode == 0, proc.stderr[-2000:]
        outs.append(json.loads(proc.stdout))
    default, ours = outs
    for key in ("impact_time", "impact_rate", "min_normal_force_over_weight"):
        assert ours[key] == pytest.approx(default[key], rel=1e-12, abs=1e-14), key
    for out in outs:
        assert max(out["relative_difference"].values()) < 1e-9, out["relative_difference"]


_LAPACK_CHECK = r"""
import sys
from jaxdyn._xla import lapack_without_scipy_linalg
loaded = lapack_without_scipy_linalg()
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
a = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]])
b = np.array([1.0, -2.0, 0.5])
x = np.asarray(jnp.linalg.solve(a, b))  # LU: LAPACK's getrf and getrs
w = np.asarray(jnp.linalg.eigh(a)[0])  # syevd
ran = "scipy.linalg._basic" in sys.modules  # scipy.linalg's package run by then?
{mode}
print(loaded, ran, float(np.max(np.abs(a @ x - b))),
      float(np.max(np.abs(w - np.linalg.eigvalsh(a)))))
"""

_LAPACK_MODES = {
    # A later import of SciPy, each the first to touch the package (as jaxdyn's commands
    # meet them), finds what an ordinary import gives.
    "integrate first": (
        "from scipy.integrate import solve_ivp\n"
        "assert abs(solve_ivp(lambda t, y: -y, (0, 1), [1.0], method='Radau', rtol=1e-10,"
        " atol=1e-12).y[0, -1] - np.exp(-1)) < 1e-8\n"
        "import scipy.linalg\n"
        "assert scipy.linalg.cython_blas is sys.modules['scipy.linalg.cython_blas']\n"
        "assert np.allclose(scipy.linalg.solve(a, b), x)"),
    "module first": (
        "import scipy.linalg.cython_lapack as cl\n"
        "assert cl is sys.modules['scipy.linalg.cython_lapack']\n"
        "import scipy.linalg\n"
        "assert np.allclose(scipy.linalg.lu_solve(scipy.linalg.lu_factor(a), b), x)"),
}


@pytest.mark.parametrize("mode", sorted(_LAPACK_MODES))
def test_lapack_is_loaded_without_scipy_linalgs_package(mode):
    """`lapack_without_scipy_linalg`: JAX's LAPACK kernels work (a solve and an eigen-
    decomposition against NumPy's), `scipy.linalg`'s package has not run, and a later import
    of SciPy (`scipy.integrate`, or a module by `import ... as`, then the package) finds what
    an ordinary import gives."""
    script = _LAPACK_CHECK.format(mode=_LAPACK_MODES[mode])
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    loaded, ran, residual, eig = proc.stdout.split()
    assert (loaded, ran) == ("True", "False")
    assert float(residual) < 1e-14 and float(eig) < 1e-13


def test_lapack_loading_leaves_an_imported_scipy_linalg_alone():
    import scipy.linalg as before  # (as here, where the tests import it)

    assert _xla.lapack_without_scipy_linalg() is False
    assert sys.modules["scipy.linalg"] is before and hasattr(before, "lu_factor")


def test_the_commands_that_call_lapack_never_run_scipy_linalgs_package():
    """The commands whose programs call LAPACK declare it (`LAPACK = True`); `jaxdyn
    separatrix` (optimistix's Newton steps: LU) then loads LAPACK's modules and never runs
    `scipy.linalg`'s package, and gives the equilibria of its closed form."""
    from jaxdyn import _cli

    commands = _cli._commands()
    assert [n for n, m in commands.items() if getattr(m, "LAPACK", False)] == [
        "fit", "separatrix"]
    script = (
        "import sys, json, io, contextlib\n"
        "from jaxdyn._cli import main\n"
        "out = io.StringIO()\n"
        "with contextlib.redirect_stdout(out):\n"
        "    status = main(['separatrix', '--inertia', '1,2,3', '--json', '--no-cache'])\n"
        "energies = sorted({round(e['energy'], 12) for e in json.loads(out.getvalue())"
        "['equilibria']})\n"
        "print(status, 'scipy.linalg.cython_lapack' in sys.modules,"
        " 'scipy.linalg._basic' in sys.modules, energies)\n"
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    status, loaded, ran, energies = proc.stdout.split(maxsplit=3)
    assert (status, loaded, ran) == ("0", "True", "False")
    # |H| = 1: an equilibrium about axis k has energy 1 / (2 I_k).
    assert energies.strip() == str([round(1 / 6, 12), 0.25, 0.5])
