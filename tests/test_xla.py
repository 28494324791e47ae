"""XLA's compiler flag for the command (`jaxdyn._xla`): added only where the user has not
chosen and where this XLA knows it (XLA aborts on an unknown flag), and the command and a
program compiled with it give the same numbers to round-off."""

import json
import os
import subprocess
import sys

import pytest

from jaxdyn import _xla


def test_an_unknown_flag_is_not_known():
    assert not _xla.known("xla_cpu_no_such_flag_in_any_xla")


def test_the_users_choice_is_kept(monkeypatch):
    for value in ("--xla_cpu_use_fusion_emitters=true", "--xla_cpu_use_fusion_emitters"):
        monkeypatch.setenv("XLA_FLAGS", value)
        assert _xla.prefer_fast_compilation() is False
        assert os.environ["XLA_FLAGS"] == value


def test_added_where_known_and_the_users_other_flags_kept(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    added = _xla.prefer_fast_compilation()
    assert added == _xla.known(_xla.FLAG)
    expected = "--xla_force_host_platform_device_count=2" + (f" {_xla.SETTING}" if added else "")
    assert os.environ["XLA_FLAGS"] == expected
    monkeypatch.delenv("XLA_FLAGS")
    assert _xla.prefer_fast_compilation() == added
    assert os.environ.get("XLA_FLAGS", "") == (_xla.SETTING if added else "")


@pytest.mark.skipif(not _xla.known(_xla.FLAG), reason="this jaxlib's XLA lacks the flag")
def test_the_command_gives_the_same_numbers_with_either_emitters(tmp_path):
    """`jaxdyn run --json` (the falling rod) with XLA's default emitters and with the
    command's: the same results to round-off, both against the energy integral's reference."""
    outs = []
    for flags in ("--xla_cpu_use_fusion_emitters=true", ""):
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
