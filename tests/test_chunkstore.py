"""Output directories of ensembles that survive concurrent writers and foreign files (issue 18)."""

import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from helpers import host_devices_env

import jaxdyn as jd
from jaxdyn._chunkstore import _HOST, ChunkStore

WORKER = Path(__file__).resolve().parent / "_ensemble_worker.py"


def _cli(*args):
    return [sys.executable, "-m", "jaxdyn", "montecarlo", "falling-rod", "--n", "3000",
            "--chunk", "64", "--vary", "theta=uniform(0.001, 0.2)", "--json", "--mode", "vmap",
            *args]


def test_two_writers_one_killed_lose_nothing(tmp_path):
    out = tmp_path / "run"
    first = subprocess.Popen(_cli("--out", str(out)), stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 240
    while not list(out.glob("chunk-*.npz")) and first.poll() is None:
        assert time.monotonic() < deadline, "no chunk written"
        time.sleep(0.005)
    second = subprocess.Popen(_cli("--out", str(out)), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    # Kill the first while both are writing (it may be in the middle of a chunk file).
    while len(list(out.glob("chunk-*.npz"))) < 4 and first.poll() is None:
        time.sleep(0.002)
    first.send_signal(signal.SIGKILL)
    first.wait()
    stdout, stderr = second.communicate(timeout=600)
    assert second.returncode == 0, stderr[-2000:]
    survivor = json.loads(stdout)
    whole = json.loads(subprocess.run(_cli(), capture_output=True, text=True,
                                      check=True).stdout)
    assert survivor["completed"] == whole["completed"] == 3000
    assert survivor["statistics"] == whole["statistics"]
    assert len(list(out.glob("chunk-*.npz"))) == 47  # ceil(3000 / 64)
    again = subprocess.run(_cli("--out", str(out)), capture_output=True, text=True, check=True)
    resumed = json.loads(again.stdout)
    assert resumed["resumed_chunks"] == 47 and resumed["statistics"] == whole["statistics"]
    assert not list(out.glob(".chunk-*.tmp"))  # the killed writer's temporary is cleared


def _store(path, **kw):
    return ChunkStore(path, {"what": "test"}, n=10, chunk_size=5, **kw)


def test_only_temporaries_of_dead_local_processes_are_removed(tmp_path):
    _store(tmp_path)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    dead_pid = int(dead.stdout)
    names = {
        "alive": f".chunk-000000.npz.{_HOST}.{os.getppid()}.abc.tmp",
        "dead": f".chunk-000001.npz.{_HOST}.{dead_pid}.abc.tmp",
        "other_host": f".chunk-000002.npz.otherhost.{dead_pid}.abc.tmp",
        "foreign": ".chunk-notours.tmp",
    }
    for name in names.values():
        (tmp_path / name).write_bytes(b"partial")
    with pytest.warns(UserWarning, match=f"process {dead_pid}"):
        _store(tmp_path)
    left = {p.name for p in tmp_path.glob(".chunk-*.tmp")}
    assert left == {names["alive"], names["other_host"], names["foreign"]}


def test_foreign_chunk_files_are_reported_and_recomputed(tmp_path):
    scene = jd.Scene(jd.RigidBody([1.0, 2.0, 2.5]))
    kw = dict(n=20, chunk_size=10, vary={"omega[0]": jd.Normal(0.1, 0.01)}, key=2)
    first = jd.ensemble(scene, scene.state(omega=[0.1, 1.0, 0.1]), 2.0, out=tmp_path, **kw)
    np.savez(tmp_path / "chunk-000001.npz", meta=np.frombuffer(b"[1, 2]", np.uint8),
             **{"data/x": np.zeros(3)})
    with pytest.warns(UserWarning, match="not a jaxdyn chunk file") as record:
        again = jd.ensemble(scene, scene.state(omega=[0.1, 1.0, 0.1]), 2.0, out=tmp_path, **kw)
    # Attributed to the caller's line, not to jaxdyn's code.
    assert {Path(w.filename).name for w in record} == {"test_chunkstore.py"}, \
        [w.filename for w in record]
    assert again.recomputed_chunks == (1,)
    assert np.array_equal(again.values["omega"], first.values["omega"])
    (tmp_path / "chunk-000001.npz").unlink()
    (tmp_path / "chunk-000001.npz").mkdir()
    with pytest.raises(jd.ParameterError, match="chunk-000001.npz is not a chunk file"):
        jd.ensemble(scene, scene.state(omega=[0.1, 1.0, 0.1]), 2.0, out=tmp_path, **kw)
    assert (tmp_path / "chunk-000001.npz").is_dir()  # the user's directory is left alone


def test_the_fingerprint_covers_the_devices(tmp_path):
    env = host_devices_env(2)
    out = str(tmp_path / "run")
    two = subprocess.run([sys.executable, str(WORKER), "adaptive", "--devices", "2", "--out",
                          out], capture_output=True, text=True, env=env)
    assert two.returncode == 0, two.stderr[-2000:]
    one = subprocess.run([sys.executable, str(WORKER), "adaptive", "--devices", "1", "--out",
                          out], capture_output=True, text=True, env=env)
    assert one.returncode != 0 and "different run" in one.stderr


def test_a_write_in_progress_is_left_alone(tmp_path):
    """A store opened while another process has a write in progress leaves it alone."""
    _store(tmp_path)
    tmp = tmp_path / f".chunk-000000.npz.{_HOST}.{os.getpid()}.xyz.tmp"
    tmp.write_bytes(b"in progress")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _store(tmp_path)
    assert tmp.exists()
