"""The `jaxdyn` command: results against independent references, and bad input."""

import json
import os
import re
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxdyn as jd
from jaxdyn._cli import main


def run_cli(capsys, *argv):
    try:
        status = main(list(argv))
    except SystemExit as e:
        status = e.code
    out, err = capsys.readouterr()
    return status, out, err


def run_json(capsys, *argv):
    status, out, err = run_cli(capsys, *argv, "--json")
    assert status == 0, err
    return json.loads(out)


def assert_frictionless_rod_summary(out):
    """A run's JSON against the frictionless rod's energy integral and quadrature (unit rod)."""
    rod = jd.FallingRod(length=1.0, mass=1.0, g=9.81)
    theta0 = out["parameters"]["theta0"]
    assert np.isclose(out["impact_time"], rod.fall_time(theta0), rtol=1e-9)
    assert np.isclose(out["impact_rate"], rod.rate(np.pi / 2, theta0), rtol=1e-9)
    # Minimum of N / (m g) over the fall, from the energy integral on a fine grid of angles.
    theta = np.linspace(theta0, np.pi / 2, 20001)
    n_min = float(np.min(rod.normal_force_energy(theta, theta0))) / 9.81
    assert np.isclose(out["min_normal_force_over_weight"], n_min, rtol=1e-4)
    return theta0


def test_default_run_is_the_falling_rod(capsys):
    out = run_json(capsys, "run")
    assert out["scene"] == "falling-rod"
    assert_frictionless_rod_summary(out)
    assert out["energy_rel_error"] < 1e-8
    assert out["timing"]["run_s"] > 0


def test_rod_parameters_by_set(capsys):
    out = run_json(capsys, "run", "--set", "length=2.0", "--set", "g=3.7",
                   "--set", "theta0=0.2", "--set", "theta_dot0=0.1")
    rod = jd.FallingRod(length=2.0, g=3.7)
    assert np.isclose(out["impact_time"], rod.fall_time(0.2, 0.1), rtol=1e-9)


def test_rod_that_never_falls_reports_null(capsys):
    out = run_json(capsys, "run", "--set", "theta0=0", "--t1", "2")
    assert out["impact_time"] is None and out["event"] is None


def test_torque_free_against_scipy(capsys):
    inertia, omega0, t1 = [2.0, 1.0, 2.5], [0.4, -1.1, 0.3], 17.0
    out = run_json(capsys, "run", "torque-free", "--set", "inertia=2,1,2.5",
                   "--set", "omega0=0.4,-1.1,0.3", "--t1", "17")
    inertia = np.array(inertia)
    ref = solve_ivp(lambda t, w: np.cross(inertia * w, w) / inertia, (0, t1), omega0,
                    rtol=1e-13, atol=1e-14, method="DOP853").y[:, -1]
    assert np.allclose(out["omega_final"], ref, atol=1e-8)
    assert out["energy_rel_error"] < 1e-9 and out["momentum_rel_error"] < 1e-9


def test_torque_free_with_full_tensor(capsys):
    out = run_json(capsys, "run", "torque-free", "--set", "inertia=2,0.1,0,0.1,1.5,0.2,0,0.2,1",
                   "--set", "omega0=0.4,-1.1,0.3", "--t1", "5")
    tensor = np.array([[2, 0.1, 0], [0.1, 1.5, 0.2], [0, 0.2, 1]])
    exact = jd.RigidBody(tensor).exact_omega(jnp.array([0.4, -1.1, 0.3]), 5.0)
    assert np.allclose(out["omega_final"], exact, atol=1e-8)


def test_scenes_listing(capsys):
    status, out, _ = run_cli(capsys, "scenes", "--json")
    assert status == 0
    names = json.loads(out)
    assert {"falling-rod", "torque-free", "intermediate-axis", "gyrostat",
            "gravity-gradient"} <= set(names)


@pytest.mark.parametrize("scene", ["falling-rod", "torque-free"])
def test_plot(capsys, tmp_path, scene):
    png = tmp_path / "out.png"
    status, _, err = run_cli(capsys, "run", scene, "--t1", "3", "--plot", str(png))
    assert status == 0, err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_scene_file_with_effects(capsys, tmp_path):
    path = tmp_path / "spinner.toml"
    path.write_text(
        'body = "rigid-body"\nt1 = 5.0\n[parameters]\ninertia = [1.0, 2.0, 3.0]\n'
        'omega0 = [0.001, 2.0, 0.001]\n[[effects]]\ntype = "rotor"\nmomentum = [0.0, 3.0, 0.0]\n'
    )
    out = run_json(capsys, "run", str(path), "--set", "rotor.momentum=0,2.5,0")
    assert out["effects"] == ["rotor"]
    assert out["parameters"]["rotor.momentum"] == [0.0, 2.5, 0.0]
    assert out["energy_rel_error"] < 1e-9 and out["momentum_rel_error"] < 1e-9


def test_console_script_fails_cleanly_without_traceback():
    proc = subprocess.run(
        [sys.executable, "-m", "jaxdyn._cli", "run", "--set", "length=0"],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip() == "jaxdyn: error: length=0: expected a positive finite number (m)"


def test_the_command_ends_as_a_normal_exit_would(tmp_path, capsys):
    """The console script skips the interpreter's teardown (`jaxdyn._cli._end`), but not what
    a normal exit does: its status, its output in full when written to a pipe (buffered),
    the exit handlers, and a thread that is not a daemon finishing its work."""
    late = tmp_path / "late"
    script = tmp_path / "console.py"
    script.write_text(
        "import atexit, sys, threading, time\n"
        "from jaxdyn._cli import console\n"
        "atexit.register(lambda: print('exit handler ran'))\n"
        "def work():\n"
        "    time.sleep(0.3)\n"
        f"    open({str(late)!r}, 'w').write('done')\n"
        "threading.Thread(target=work).start()\n"
        "import concurrent.futures\n"  # an idle pool, never shut down: woken at the exit
        "pool = concurrent.futures.ThreadPoolExecutor(1)\n"
        "pool.submit(lambda: None).result()\n"
        "sys.argv = ['jaxdyn', *sys.argv[1:]]\n"
        "console()\n")
    listing = run_cli(capsys, "scenes")[1]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}  # (buffered)
    for argv, status in ((["scenes"], 0), (["run", "--t1", "-1"], 2), (["--help"], 0),
                         (["no-such-command"], 2)):
        late.unlink(missing_ok=True)
        proc = subprocess.run([sys.executable, str(script), *argv], capture_output=True,
                              text=True, timeout=120, env=env)
        assert proc.returncode == status, (argv, proc.stderr)
        assert proc.stdout.endswith("exit handler ran\n"), (argv, proc.stdout[-200:])
        assert late.read_text() == "done", argv
        if argv == ["scenes"]:
            assert proc.stdout == listing + "exit handler ran\n"
        if status == 2:
            assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr
    # A reader that goes away before the output is written (`jaxdyn ... | true`): no message.
    proc = subprocess.run(["bash", "-c", f"{sys.executable} -m jaxdyn scenes | true; "
                           "exit ${PIPESTATUS[0]}"], capture_output=True, text=True, timeout=120,
                          env=env)
    assert (proc.returncode, proc.stderr) == (1, "")
    # With the output closed (`jaxdyn scenes >&-`): no traceback for want of a stream.
    proc = subprocess.run(["bash", "-c", f"{sys.executable} -m jaxdyn scenes >&-"],
                          capture_output=True, text=True, timeout=120, env=env)
    assert "Traceback" not in proc.stderr, proc.stderr[-500:]


def test_step_budget_exhaustion_is_an_error_not_a_truncation(capsys):
    status, out, err = run_cli(capsys, "run", "torque-free", "--max-steps", "20")
    assert status == 1 and out == ""
    assert err.startswith("jaxdyn: error: simulation failed: the step budget --max-steps ran "
                          "out before t1: increase --max-steps")
    assert len(err.strip().splitlines()) == 1


def test_every_program_of_a_command_is_cached_on_the_second_run(tmp_path):
    """JAX's own log: the second invocation compiles nothing (none of the first's programs is
    refused for holding a host callback; the simulation's compiled program is loaded as
    stored, `jaxdyn._programs`, and whatever else runs is read from JAX's persistent cache)."""
    env = {**os.environ, "JAX_LOGGING_LEVEL": "DEBUG", "JAXDYN_CACHE_DIR": str(tmp_path)}
    logs, timings = [], []
    for _ in range(2):
        proc = subprocess.run([sys.executable, "-m", "jaxdyn._cli", "run", "--json"],
                              capture_output=True, text=True, timeout=300, env=env)
        assert proc.returncode == 0, proc.stderr[-2000:]
        logs.append(proc.stderr)
        timings.append(json.loads(proc.stdout)["timing"])
    first, second = logs
    assert "host callback" not in first
    assert re.search(r"Writing .* to persistent compilation cache", first)
    assert list((tmp_path / "jaxdyn-programs").glob("*.exe"))  # this machine's programs
    assert not re.search(r"Writing .* to persistent compilation cache", second)
    assert not re.search(r"Not writing persistent cache entry .* host callbacks", first)
    assert not re.search(r"Not writing persistent cache entry", second)
    compiled = re.findall(r"Compiling (jit\([^)]*\))", second)
    hits = re.findall(r"Persistent compilation cache hit for '([^']+)'", second)
    assert len(hits) == len(compiled), (compiled, hits)
    assert not any("simulate" in c for c in compiled), compiled
    assert timings[0]["load_s"] == 0 < timings[1]["load_s"]
    assert timings[1]["compile_s"] == 0 and timings[0]["compile_s"] > 0


def test_cache_can_be_moved_or_turned_off(tmp_path):
    moved = tmp_path / "elsewhere"
    env = {**os.environ, "JAXDYN_CACHE_DIR": "off"}
    proc = subprocess.run([sys.executable, "-m", "jaxdyn._cli", "scenes"], env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0
    proc = subprocess.run([sys.executable, "-m", "jaxdyn._cli", "run", "--t1", "0.1",
                           "--cache-dir", str(moved), "--json"], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0 and any(moved.iterdir())
    off = tmp_path / "off"
    proc = subprocess.run([sys.executable, "-m", "jaxdyn._cli", "run", "--t1", "0.1",
                           "--no-cache", "--cache-dir", str(off), "--json"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and not off.exists()


@pytest.mark.parametrize("scene", ["bdot-detumble", "wheels-with-dumping", "thruster-despin"])
def test_recovery_scenes_run_from_the_command(capsys, scene):
    """The recovery devices' built-in scenes run from `jaxdyn run` and end where they should:
    detumbled below the orbit rate, the wheels' momentum dumped, the rates in the dead band."""
    out = run_json(capsys, "run", scene, "--samples", "50")
    w = np.abs(np.asarray(out["omega_final"]))
    if scene == "thruster-despin":
        assert np.all(w <= 0.002 + 1e-12)  # the scene's dead band
    else:
        assert np.all(w < 1e-3)
    assert out["t_final"] == out["t1"]


def test_a_warning_is_one_line_naming_what_happened(capsys, tmp_path):
    # A warning of the command (here: a foreign chunk file in the run's folder, recomputed)
    # is one line on stderr, like its errors: no source location, no warning class.
    out = tmp_path / "mc"
    argv = ("montecarlo", "torque-free", "--n", "8", "--chunk", "4", "--t1", "1", "--out",
            str(out))
    first = run_json(capsys, *argv)
    np.savez(out / "chunk-000001.npz", meta=np.frombuffer(b"[1, 2]", np.uint8),
             **{"data/x": np.zeros(3)})
    status, stdout, err = run_cli(capsys, *argv, "--json")
    assert status == 0, err
    lines = err.strip().splitlines()
    assert lines == [f"jaxdyn: warning: chunk file {out / 'chunk-000001.npz'} is not a "
                     "jaxdyn chunk file (its meta is not a record): computing the chunk "
                     "again"], err
    again = json.loads(stdout)
    assert again["recomputed_chunks"] == [1]
    runs = ("timing", "recomputed_chunks", "resumed_chunks")
    assert {k: v for k, v in again.items() if k not in runs} == \
        {k: v for k, v in first.items() if k not in runs}
