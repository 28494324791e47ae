"""`jaxdyn fit` on spacecraft telemetry with reaction wheels: gyro rates (biased, noisy),
star-tracker attitudes (either sign), tachometers and the commanded motor torques, read from
CSV columns that the wheels declare (`wheel{i}_speed`, `wheel{i}_torque`).

The data come from an independent route: the gyrostat equations with attitude kinematics,
`I w' = (I w + h) x w - u`, `h_i' = u_i`, `q' = q (x) (0, w) / 2`, integrated by SciPy
(DOP853) piece by piece between commands. The commanded torques, known in N m, make the
inertia's scale identifiable: the command reports the absolute tensor.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from test_cli import run_cli
from test_identify import sorted_axes, write_csv

TENSOR = np.array([[2.1, 0.08, -0.05], [0.08, 2.6, 0.12], [-0.05, 0.12, 3.3]])  # kg m^2
WHEEL_J = 0.01  # kg m^2
COMMAND_TIMES = np.arange(0.0, 30.0, 5.0)
COMMANDS = 8e-3 * np.array([[1, 0, 0], [0, -1, 0], [0, 0, 1], [-1, 1, 0], [0, 0, -1],
                            [0, 1, 1]], float)  # N m
SCENE = Path(__file__).with_name("spacecraft_estimate.toml")  # shared with the benchmark


def _qmul(a, b):
    a0, av, b0, bv = a[0], a[1:], b[0], b[1:]
    return np.concatenate([[a0 * b0 - av @ bv], a0 * bv + b0 * av + np.cross(av, bv)])


def telemetry(ts, rng):
    """True rates, attitudes and wheel speeds at `ts` (SciPy), and the torque at each
    sample (the command held since the last command time)."""
    inv = np.linalg.inv(TENSOR)

    def field(t, y):
        w, q, h = y[:3], y[3:7], y[7:]
        u = COMMANDS[np.searchsorted(COMMAND_TIMES, t, side="right") - 1]
        return np.concatenate([inv @ (np.cross(TENSOR @ w + h, w) - u),
                               0.5 * _qmul(q, np.concatenate([[0.0], w])), u])

    w0 = np.array([0.01, -0.02, 0.015])
    q0 = np.array([0.8, 0.2, -0.4, 0.4])
    y = np.concatenate([w0, q0, WHEEL_J * (np.array([40.0, -30.0, 20.0]) + w0)])
    states = [y]
    ends = list(COMMAND_TIMES[1:]) + [ts[-1]]
    for a, b in zip(COMMAND_TIMES, ends):  # one piece per held command
        inside = ts[(ts > a) & (ts <= b)]
        sol = solve_ivp(field, (a, b), y, t_eval=inside, method="DOP853", rtol=1e-12,
                        atol=1e-14, first_step=1e-3)
        y = sol.y[:, -1]
        states.extend(sol.y.T)
    states = np.array(states)
    w, q, h = states[:, :3], states[:, 3:7], states[:, 7:]
    torques = COMMANDS[np.searchsorted(COMMAND_TIMES, ts, side="right") - 1]
    return w, q, h / WHEEL_J - w, torques


def _csv(tmp_path, rng, ts, columns=None):
    w, q, speed, torques = telemetry(ts, rng)
    bias, s_gyro, s_star, s_tach = np.array([4e-4, -2.5e-4, 1.5e-4]), 2e-5, 5e-5, 5e-3
    gyro = w + bias + s_gyro * rng.normal(size=w.shape)
    star = []
    for qk in q:
        e = s_star * rng.normal(size=3)  # a small rotation error, then a random sign
        star.append(_qmul(qk, np.concatenate([[1.0], e / 2])) * rng.choice([-1.0, 1.0]))
    star = np.array(star) / np.linalg.norm(star, axis=1, keepdims=True)
    tach = speed + s_tach * rng.normal(size=speed.shape)
    header = ("t,wx,wy,wz,q0,q1,q2,q3,wheel1_speed,wheel2_speed,wheel3_speed,"
              "wheel1_torque,wheel2_torque,wheel3_torque")
    cols = [ts, gyro, star, tach, torques]
    return write_csv(tmp_path / "telemetry.csv", header, cols), bias


@pytest.fixture(scope="module")
def scene_file():
    return str(SCENE)


def test_fit_reads_wheel_columns_and_recovers_the_absolute_inertia(capsys, tmp_path,
                                                                    scene_file):
    rng = np.random.default_rng(2020)
    ts = np.round(np.arange(0.0, 30.0, 0.2), 10)  # 150 rows at 5 Hz
    path, bias = _csv(tmp_path, rng, ts)
    status, out, err = run_cli(capsys, "fit", path, "--scene", scene_file, "--bias", "omega",
                               "--restarts", "1", "--set", "rtol=1e-8", "--json")
    assert status == 0, err
    out = json.loads(out)
    assert out["converged"]
    # The torques in N m fix the scale: absolute moments (kg m^2), said so.
    assert out["scale_identified"] and out["identifiable"]["inertia.scale"]
    assert "inertia.scale" not in out["not_identifiable"]
    moments, axes = sorted_axes(TENSOR)
    m, sd = np.array(out["principal_moments"]), np.array(out["std"])
    assert np.all(np.abs(m - moments) <= 4 * sd), (m, moments, sd)
    assert np.all(sd < 0.01 * moments)
    # Axes (columns, under the documented sign convention) within 4 reported sigmas.
    a, sa = np.array(out["principal_axes"]), np.array(out["principal_axes_std"])
    assert np.all(np.abs(a - axes) <= 4 * sa + 1e-12), (a, axes, sa)
    assert np.all(sa < 0.01)
    assert np.allclose(np.array(out["inertia"]), TENSOR, atol=4 * sd.max())
    b, sb = np.array(out["bias.omega"]), np.array(out["bias.omega_std"])
    assert np.all(np.abs(b - bias) <= 4 * sb), (b, bias, sb)
    assert set(out["residual_rms_by_output"]) == {"omega", "quaternion", "wheels.speed"}
    assert out["residual_rms_by_output"]["wheels.speed"] == pytest.approx(5e-3, rel=0.2)
    assert np.shape(out["wheels.momentum"]) == (3,)


@pytest.mark.parametrize("change, message", [
    (lambda h: h.replace(",wheel3_torque", ""), r"missing column\(s\) \['wheel3_torque'\]"),
    (lambda h: h + ",wheel4_torque", r"unknown column\(s\) \['wheel4_torque'\]"),
])
def test_wheel_columns_bad_input_exits_2_naming_the_column(capsys, tmp_path, scene_file,
                                                           change, message):
    ts = np.arange(0.0, 2.0, 0.2)
    header = ("t,wx,wy,wz,wheel1_speed,wheel2_speed,wheel3_speed,wheel1_torque,"
              "wheel2_torque,wheel3_torque")
    header = change(header)
    table = np.ones((ts.size, len(header.split(",")) - 1))
    path = write_csv(tmp_path / "bad.csv", header, [ts, table])
    status, _, err = run_cli(capsys, "fit", path, "--scene", scene_file)
    assert status == 2
    assert len(err.strip().splitlines()) == 1
    assert __import__("re").search(message, err), err


def test_wheel_columns_nan_and_missing_scene(capsys, tmp_path, scene_file):
    ts = np.arange(0.0, 2.0, 0.2)
    header = "t,wx,wy,wz,wheel1_speed,wheel2_speed,wheel3_speed"
    table = np.ones((ts.size, 6))
    table[3, 4] = np.nan
    path = write_csv(tmp_path / "nan.csv", header, [ts, table])
    status, _, err = run_cli(capsys, "fit", path, "--scene", scene_file)
    assert status == 2 and "column wheel2_speed=nan" in err, err
    table[3, 4] = 1.0
    path = write_csv(tmp_path / "noscene.csv", header, [ts, table])
    status, _, err = run_cli(capsys, "fit", path)  # the body's own scene has no wheels
    assert status == 2 and "wheel1_speed is a column of the effect 'wheels'" in err, err
