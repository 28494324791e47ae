"""Property-based fuzzing of the command's input paths (issue 18): whatever a careless user or
an attacker types, the command ends with status 0, 1 or 2 and, on failure, one line on
stderr, never a traceback. Fixed seed, bounded examples."""

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from jaxdyn._cli import main

FUZZ = settings(max_examples=40, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow,
                                       HealthCheck.function_scoped_fixture])

NAMES = ["theta0", "theta_dot0", "length", "mass", "g", "inertia", "omega0", "quaternion0",
         "rotor.momentum", "t1", "rtol", "atol", "mu_s", "wheels.axes", "x", ""]
VALUES = st.one_of(
    st.text(max_size=30),
    st.integers().map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.lists(st.floats(allow_nan=False), max_size=5).map(lambda v: ",".join(map(repr, v))),
    st.sampled_from(["1e400", "-0", "nan", "True", "[1,[2]]", "1" * 400, "\x00", "0x10"]),
)
TOML_VALUES = st.one_of(
    st.sampled_from(['"rigid-body"', '"falling-rod"', '["rigid-body"]', "{x = 1}", "1" * 400,
                     "1e400", "nan", "true", '"\\u0000"', "[[1], [2]]", '"rotor"']),
    st.integers().map(str), st.floats(allow_nan=False).map(repr))


def _run(capsys, argv):
    try:
        status = main(argv)
    except SystemExit as e:
        status = e.code
    out, err = capsys.readouterr()
    assert status in (0, 1, 2), (argv, status, err)
    assert "Traceback" not in err, err
    if status:
        lines = [ln for ln in err.splitlines() if ln.startswith("jaxdyn:")]
        assert len(lines) == 1 and lines[0].startswith("jaxdyn: error:"), err
    return status


@FUZZ
@given(data=st.one_of(st.binary(max_size=300), st.text(max_size=300).map(str.encode)))
def test_any_scene_file_bytes(tmp_path_factory, capsys, data):
    path = tmp_path_factory.mktemp("scene") / "scene.toml"
    path.write_bytes(data)
    _run(capsys, ["run", str(path), "--t1", "0.01"])


@FUZZ
@given(body=TOML_VALUES, key=st.sampled_from(NAMES), value=TOML_VALUES,
       etype=TOML_VALUES, bom=st.booleans())
def test_structured_scene_files(tmp_path_factory, capsys, body, key, value, etype, bom):
    key = key or "k"
    text = (f"body = {body}\nt1 = 0.01\n[parameters]\n\"{key}\" = {value}\n"
            f"[[effects]]\ntype = {etype}\n")
    path = tmp_path_factory.mktemp("scene") / "scene.toml"
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode())
    _run(capsys, ["run", str(path)])


@FUZZ
@given(scene=st.sampled_from(["falling-rod", "torque-free", "gyrostat", "reaction-wheels"]),
       name=st.sampled_from(NAMES), value=VALUES)
def test_set_values(capsys, scene, name, value):
    _run(capsys, ["run", scene, "--t1", "0.01", "--samples", "3", "--set", f"{name}={value}"])


@FUZZ
@given(name=st.sampled_from(["omega[0]", "omega[5]", "omega", "inertia", "theta", "inertia[-1]",
                             "rotor.momentum", "x", "omega[0]+", "omega[True]"]),
       op=st.sampled_from(["=", "+=", "*=", "=="]),
       dist=st.one_of(st.text(max_size=20), st.sampled_from(
           ["normal(0, 1e-3)", "uniform(1, 0)", "lognormal(1, -1)", "normal(0,", "True",
            "normal(1e400, 1)", "uniform(0, nan)", "3", "normal([1,2], 0.1)"])))
def test_vary_values(capsys, name, op, dist):
    _run(capsys, ["montecarlo", "torque-free", "--n", "4", "--t1", "0.01", "--mode", "vmap",
                  "--vary", f"{name}{op}{dist}"])


@pytest.mark.parametrize("argv", [
    ["run", "--plot", "notes.txt"],
    ["run", "--plot", "/nonexistent-folder/figure.png"],
    ["montecarlo", "falling-rod", "--n", "4294967297"],
    ["montecarlo", "falling-rod", "--n", "10", "--seed", str(2**70)],
    ["run", "--max-steps", "1e20"],
    ["run", "/nonexistent/scene.toml"],
])
def test_refused_before_any_work(capsys, argv):
    assert _run(capsys, argv) == 2


def test_silent_acceptances_now_refused(tmp_path, capsys):
    import jaxdyn as jd

    scene = tmp_path / "wheels.toml"
    scene.write_text('body = "rigid-body"\n[parameters]\ninertia = [1.0, 2.0, 3.0]\n'
                     'omega0 = [0.1, 0.2, 0.3]\n[[effects]]\ntype = "wheels"\n'
                     'axes = [[1.0, 0.0, 0.0]]\ninertia = [0.1]\ngain = 0.5\n')
    assert _run(capsys, ["run", str(scene)]) == 2
    assert _run(capsys, ["montecarlo", "torque-free", "--n", "4", "--vary",
                         "omega[0]=True"]) == 2
    for law in (lambda: jd.RateDamping(float("nan")),
                lambda: jd.AttitudeTracking([1.0, 0.0, 0.0, 0.0], kp=-1.0, kd=1.0)):
        with pytest.raises(jd.ParameterError, match="must be finite and non-negative"):
            law()
