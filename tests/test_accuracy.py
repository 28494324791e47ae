"""Work-precision studies: the points carry what the issue asks for, errors fall with the
tolerance, references are independent, methods that do not apply are skipped with a reason."""

import dataclasses

import diffrax as dfx
import numpy as np
from test_cli import run_json

import jaxdyn as jd
import jaxdyn.accuracy as acc


def test_study_points_and_monotone_error():
    problem = acc.builtin_problems()["free-body"]
    methods = [acc.Method("Dopri8", dfx.Dopri8(), tolerances=(1e-4, 1e-7, 1e-10)),
               acc.Method("Splitting4", jd.RotationSplitting(4), steps=(0.2, 0.1))]
    result = acc.study(problem, methods, repeats=1)
    assert result["reference"] == "exact"
    points = result["methods"]["Dopri8"]
    for p in points:
        assert {"tolerance", "error", "wall_time", "compile_time", "evaluations", "drift"} <= set(p)
    errors = [p["error"] for p in points]
    assert errors[0] > errors[1] > errors[2] and errors[2] < 1e-9
    split = result["methods"]["Splitting4"]
    assert split[0]["error"] / split[1]["error"] > 8  # fourth order: 16x per halving
    assert split[0]["drift"]["momentum"] < 1e-12
    assert {"RK45", "DOP853"} == set(result["scipy"])
    rows = acc.speed_comparison(result, levels=(1e-3, 1e-6))
    assert all(r["speedup"] is not None for r in rows)


def test_rod_reference_and_skipped_splitting():
    problem = acc.builtin_problems()["falling-rod"]
    t_ref, y_ref, source = acc.reference(problem)
    assert source == "exact"
    assert np.isclose(float(t_ref), float(jd.FallingRod().fall_time(0.1)), rtol=1e-15)
    methods = [acc.Method("Tsit5", dfx.Tsit5(), tolerances=(1e-6, 1e-10)),
               acc.Method("Splitting2", jd.RotationSplitting(2), steps=(0.01,))]
    result = acc.study(problem, methods, repeats=1, scipy=False)
    assert "has no rotation splitting" in result["skipped"]["Splitting2"]
    assert result["methods"]["Tsit5"][1]["error"] < 1e-8


def test_reference_falls_back_to_a_tight_integration():
    scene = jd.Scene(jd.RigidBody([1.0, 2.0, 3.0]), (jd.Rotor([0.0, 0.5, 0.0]),))
    problem = acc.Problem("gyrostat", "a gyrostat", scene, scene.state(omega=[0.3, 0.2, 1.0]),
                          5.0, 0.1)
    assert acc.reference(problem)[2].startswith("Dopri8")


def test_command_quick(capsys, tmp_path):
    png = tmp_path / "wp.png"
    out = run_json(capsys, "accuracy", "--scene", "falling-rod", "--quick", "--plot", str(png))
    points = out["problems"]["falling-rod"]["methods"]["Tsit5"]
    assert {"tolerance", "error", "wall_time", "compile_time", "evaluations"} <= set(points[0])
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert out["speed_vs_scipy"]["falling-rod"][0]["scipy_method"] is not None


def test_method_list_covers_the_issue():
    names = [m.name for m in acc.default_methods(acc.builtin_problems()["free-body"])]
    assert {"Tsit5", "Dopri5", "Dopri8", "RK4", "Kvaerno5", "Splitting2", "Splitting4"} == set(
        names)
    assert dataclasses.is_dataclass(acc.Method)


def test_exact_reference_with_attitude():
    # Scenes that integrate attitude get the exact attitude (elliptic integral of the third kind)
    # as their reference; it agrees with a tight integration.
    scene = jd.Scene(jd.RigidBody([1.0, 2.0, 3.0]), attitude=True)
    y0 = scene.state(omega=[0.3, 0.2, 1.0], quaternion=[0.9, 0.1, -0.3, 0.2])
    problem = acc.Problem("attitude", "free body with attitude", scene, y0, 30.0, 0.1)
    t_ref, y_ref, source = acc.reference(problem)
    assert source == "exact"
    traj = jd.simulate(scene, y0, 30.0, rtol=1e-13, atol=1e-14)
    for key in ("omega", "quaternion"):
        assert np.max(np.abs(np.asarray(traj.y_final[key] - y_ref[key]))) < 1e-11
