"""Hard cases: each returns the figures it reaches; the tests assert bounds on them.

`python tests/test_hard_cases.py` prints every figure as one JSON object (the README's table).
References are independent of the code under test: scipy quadrature and integration, the
small-angle closed form, the linearised flow, conservation laws.
"""

import functools
import json

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import scipy_euler
from scipy.integrate import quad
from scipy.optimize import brentq

import jaxdyn as jd

jax.config.update("jax_enable_x64", True)

ROD = jd.FallingRod(length=1.0, mass=1.0, g=9.81)
ROD_SCENE = jd.Scene(ROD)
INERTIA = np.array([1.0, 2.0, 3.0])
FREE = jd.Scene(jd.RigidBody(INERTIA))


# -- 1. the rod released from a tiny angle -------------------------------------------------------


def _fall_time_reference(theta0, theta1=1e-5):
    """Small-angle closed form up to theta1 (theta ~ theta0 cosh(k t), relative error
    ~theta1^2), then scipy quadrature of the energy integral from theta1 to pi/2."""
    L, g = 1.0, 9.81
    k = np.sqrt(6 * g / L)
    head = np.arccosh(theta1 / theta0) / k

    def inv_rate(theta):
        num = 24 * g / L * np.sin((theta - theta0) / 2) * np.sin((theta + theta0) / 2)
        return np.sqrt((1 + 3 * np.sin(theta) ** 2) / num)

    tail = quad(inv_rate, theta1, np.pi / 2, epsabs=0, epsrel=1e-13, limit=200)[0]
    return head + tail


@functools.cache
def case_tiny_angle():
    out = {}
    for theta0 in (1e-12, 1e-15):
        ref = _fall_time_reference(theta0)
        quadrature = float(ROD.fall_time(theta0))
        # Pure relative error control: an absolute tolerance would swamp theta ~ 1e-15.
        traj = jd.simulate(ROD_SCENE, ROD_SCENE.state(theta=theta0), 30.0, rtol=1e-13,
                           atol=1e-30)
        out[f"{theta0:g}"] = {
            "fall_time": quadrature,
            "quadrature_vs_reference": abs(quadrature / ref - 1),
            "simulation_vs_quadrature": abs(float(traj.t_final) / quadrature - 1),
        }
    return out


def test_rod_from_tiny_angles():
    for figures in case_tiny_angle().values():
        assert figures["quadrature_vs_reference"] < 1e-9
        assert figures["simulation_vs_quadrature"] < 1e-8


# -- 2. the rod exactly upright ------------------------------------------------------------------


@functools.cache
def case_upright():
    traj = jd.simulate(ROD_SCENE, ROD_SCENE.state(theta=0.0), 100.0, ts=jnp.linspace(0, 100, 101))
    finite = all(bool(jnp.all(jnp.isfinite(v))) for v in traj.outputs().values())
    return {
        "max_abs_theta": float(jnp.max(jnp.abs(traj.ys["theta"]))),
        "event": bool(traj.event["flat"]),
        "all_outputs_finite": finite,
        "fall_time": float(ROD.fall_time(0.0)),
        "d_fall_time_d_theta0": float(jax.grad(ROD.fall_time)(0.0)),
    }


def test_rod_upright_stays_up():
    f = case_upright()
    assert f["max_abs_theta"] == 0.0 and not f["event"] and f["all_outputs_finite"]
    assert f["fall_time"] == np.inf and f["d_fall_time_d_theta0"] == -np.inf


# -- 3. the rod with a rate, near flat, already flat ---------------------------------------------


@functools.cache
def case_rod_edges():
    out = {}
    for name, theta0, rate in (("initial_rate", 0.1, 2.0), ("towards_upright", 0.1, -4.0),
                               ("near_flat", np.pi / 2 - 1e-6, 0.0),
                               ("already_flat", np.pi / 2, 0.0)):
        traj = jd.simulate(ROD_SCENE, ROD_SCENE.state(theta=theta0, theta_dot=rate), 10.0,
                           rtol=1e-12, atol=1e-14)
        ref = float(ROD.fall_time(theta0, rate))
        err = abs(float(traj.t_final) - ref) / max(ref, 1e-300) if ref else float(traj.t_final)
        out[name] = {"impact_time": float(traj.t_final), "reference": ref,
                     "relative_error": err, "event": bool(traj.event["flat"])}
    return out


def test_rod_edges():
    f = case_rod_edges()
    for name in ("initial_rate", "towards_upright", "near_flat"):
        assert f[name]["event"] and f[name]["relative_error"] < 1e-9
    assert f["already_flat"]["event"] and f["already_flat"]["impact_time"] == 0.0


# -- 4. the intermediate-axis spin -----------------------------------------------------------------


def _first_zero(fn, t_max, n=4000):
    ts = np.linspace(0, t_max, n)
    vals = np.array([fn(t) for t in ts]) if n < 100 else np.asarray(fn(ts))
    i = np.argmax(np.sign(vals[1:]) != np.sign(vals[:-1]))
    return brentq(lambda t: float(np.asarray(fn(np.array([t])))[0]), ts[i], ts[i + 1],
                  xtol=1e-14, rtol=1e-15)


@functools.cache
def case_intermediate_axis():
    out = {}
    rtol = 1e-12
    lam = np.sqrt((3 - 2) * (2 - 1) / (1 * 3)) * 2.0  # growth rate at the saddle
    for eps in (1e-3, 1e-6, 1e-9):
        omega0 = jnp.array([eps, 2.0, eps])
        t_max = 1.2 * float(jd.torque_free_period(INERTIA, omega0)) / 2
        exact = _first_zero(lambda t: jd.torque_free_omega(INERTIA, omega0, t)[..., 1], t_max)
        traj = jd.simulate(FREE, FREE.state(omega=omega0), t_max, rtol=rtol, atol=1e-20,
                           dense=True, max_steps=200_000)
        sim = _first_zero(lambda t: traj.evaluate(jnp.asarray(t))["omega"][:, 1], t_max)
        # Conditioning: a relative state error rtol shifts the flip by ~ rtol |w| / (lam eps).
        bound = rtol * 2.0 / (lam * eps)
        inv = traj.resample(200).outputs()
        out[f"{eps:g}"] = {
            "flip_time": exact,
            "flip_time_error": abs(sim - exact),
            "conditioning_bound": bound,
            "energy_drift": float(jnp.max(jnp.abs(inv["energy"] / inv["energy"][0] - 1))),
            "momentum_drift": float(jnp.max(jnp.abs(inv["momentum"] / inv["momentum"][0] - 1))),
        }
    return out


def test_intermediate_axis_flip_times():
    for f in case_intermediate_axis().values():
        assert f["flip_time_error"] < 10 * f["conditioning_bound"]
        assert f["energy_drift"] < 1e-10 and f["momentum_drift"] < 1e-10


# -- 5. on the separatrix ------------------------------------------------------------------------


@functools.cache
def case_separatrix():
    w1 = 0.5
    w3 = w1 * np.sqrt(1 * (2 - 1) / (3 * (3 - 2)))
    ts = np.linspace(0, 20, 201)
    on = jnp.array([w1, 0.3, w3])
    exact = np.asarray(jd.torque_free_omega(INERTIA, on, ts))
    out = {"m1": float(jd.elliptic_parameter(INERTIA, on)[1]),
           "limit_vs_scipy": float(np.max(np.abs(
               exact - scipy_euler(INERTIA, on, 20, ts, atol=1e-15))))}
    grad = jax.jacfwd(lambda w: jd.torque_free_omega(INERTIA, w, 10.0))
    gaps, finite = [], True
    for delta in (1e-4, 1e-8, 1e-12, -1e-12, -1e-8, -1e-4):
        near = on.at[2].multiply(1 + delta)
        gaps.append(float(np.max(np.abs(np.asarray(jd.torque_free_omega(INERTIA, near, 5.0))
                                        - exact[50]))))
        finite &= bool(jnp.all(jnp.isfinite(grad(near))))
    out["gap_at_t5_for_delta_1e-4_1e-8_1e-12_both_sides"] = gaps
    out["gradients_finite"] = finite
    return out


def test_separatrix_limit():
    f = case_separatrix()
    assert f["m1"] == 0.0 and f["limit_vs_scipy"] < 1e-9 and f["gradients_finite"]
    gaps = f["gap_at_t5_for_delta_1e-4_1e-8_1e-12_both_sides"]
    assert gaps[2] < 1e-10 and gaps[3] < 1e-10  # continuous from both sides
    assert gaps[0] > gaps[1] > gaps[2] and gaps[5] > gaps[4] > gaps[3]


# -- 6. axisymmetric and spherical bodies ----------------------------------------------------------


@functools.cache
def case_symmetric():
    out = {}
    omega0 = np.array([0.3, 0.4, 1.0])
    for inertia in ((1.0, 1.0, 2.0), (1.0, 2.0, 2.0), (2.0, 2.0, 2.0)):
        ts = np.linspace(0, 10, 11)
        exact = jd.torque_free_omega(jnp.asarray(inertia), jnp.asarray(omega0), ts)
        reference = scipy_euler(inertia, omega0, 10, ts, atol=1e-15)
        out[str(inertia)] = float(np.max(np.abs(exact - reference)))
    return out


def test_axisymmetric_and_spherical():
    for err in case_symmetric().values():
        assert err < 1e-11
    with pytest.raises(jd.ParameterError, match="no intermediate axis"):
        jd.separatrix_curves([1.0, 1.0, 2.0])


# -- 7. extreme inertia --------------------------------------------------------------------------


@functools.cache
def case_extreme_inertia():
    out = {}
    for name, inertia in (("flat_plate", (1.0, 1e3, 1001.0)), ("needle", (1e-3, 1.0, 1.0005))):
        scene = jd.Scene(jd.RigidBody(inertia))
        omega0 = jnp.array([0.2, 0.1, 0.05])
        traj = jd.simulate(scene, scene.state(omega=omega0), 10.0, rtol=1e-12, atol=1e-14)
        exact = scipy_euler(inertia, np.asarray(omega0), 10.0, atol=1e-15)[-1]
        out[name] = {"error_vs_scipy": float(np.max(np.abs(traj.y_final["omega"] - exact))),
                     "closed_form_vs_scipy": float(np.max(np.abs(
                         jd.torque_free_omega(jnp.asarray(inertia), omega0, 10.0) - exact)))}
    try:
        jd.RigidBody([1.0, 1e3, 1e6])
        out["1:1e3:1e6"] = "accepted"
    except jd.ParameterError as e:
        out["1:1e3:1e6"] = str(e)
    return out


def test_extreme_inertia():
    f = case_extreme_inertia()
    for name in ("flat_plate", "needle"):
        assert f[name]["error_vs_scipy"] < 1e-9 and f[name]["closed_form_vs_scipy"] < 1e-9
    assert "triangle inequality" in f["1:1e3:1e6"]


# -- 8. a long horizon ---------------------------------------------------------------------------


@functools.cache
def case_long_horizon():
    scene = jd.Scene(jd.RigidBody(INERTIA), attitude=True)
    ts = jnp.linspace(0, 1e6, 20001)  # 50 s apart: about 0.19 rad of rotation
    traj = jd.simulate(scene, scene.state(omega=[1e-3, 2e-3, 3e-3]), 1e6, ts=ts,
                       solver=dfx.Dopri8(), rtol=1e-14, atol=1e-16, max_steps=200_000)
    o = traj.outputs()
    mrp = np.asarray(o["mrp"])
    dcm_mrp = np.asarray(jax.vmap(jd.mrp_to_dcm)(o["mrp"]))
    h = np.asarray(o["momentum_inertial"])
    jumps = np.linalg.norm(np.diff(mrp, axis=0), axis=1) > 1.0  # a switch to the shadow set
    dcm_steps = np.linalg.norm(np.diff(np.asarray(o["dcm"]), axis=0), axis=(1, 2))
    return {
        "horizon": 1e6,
        "steps": int(traj.stats["num_steps"]),
        "quaternion_norm_error": float(np.max(np.abs(np.asarray(o["quaternion_norm"]) - 1))),
        "energy_drift": float(np.max(np.abs(o["energy"] / o["energy"][0] - 1))),
        "momentum_drift": float(np.max(np.abs(o["momentum"] / o["momentum"][0] - 1))),
        "inertial_momentum_drift": float(np.max(np.linalg.norm(h - h[0], axis=1))
                                         / np.linalg.norm(h[0])),
        "mrp_switches": int(np.sum(jumps)),
        "mrp_max_norm": float(np.max(np.linalg.norm(mrp, axis=1))),
        "dcm_from_mrp_vs_quaternion": float(np.max(np.abs(dcm_mrp - np.asarray(o["dcm"])))),
        "dcm_step_at_switches_over_median": float(np.max(dcm_steps[jumps])
                                                  / np.median(dcm_steps)),
    }


def test_long_horizon():
    f = case_long_horizon()
    assert f["quaternion_norm_error"] < 1e-12
    assert f["energy_drift"] < 1e-11 and f["momentum_drift"] < 1e-11
    assert f["inertial_momentum_drift"] < 1e-10
    assert f["mrp_switches"] > 0 and f["mrp_max_norm"] <= 1 + 1e-12
    assert f["dcm_from_mrp_vs_quaternion"] < 1e-11
    assert f["dcm_step_at_switches_over_median"] < 1.5  # the attitude does not jump


# -- 9. gradients ----------------------------------------------------------------------------------


@functools.cache
def case_gradients():
    def impact(x):
        rod = jd.FallingRod(length=x[0], mass=1.0, g=9.81)
        scene = jd.Scene(rod)
        return jd.simulate(scene, scene.state(theta=x[1]), 10.0, rtol=1e-12, atol=1e-14).t_final

    x = jnp.array([1.3, 0.2])
    g = jax.grad(impact)(x)
    g_ref = jax.grad(lambda x: jd.FallingRod(length=x[0], g=9.81).fall_time(x[1]))(x)

    def near_separatrix(inertia):
        s = FREE.replace(inertia=inertia)
        y = jd.simulate(s, s.state(omega=[1e-3, 2.0, 1e-3]), 1e3, rtol=1e-10, atol=1e-12,
                        max_steps=200_000, adjoint=dfx.ForwardMode()).y_final
        return y["omega"][1]

    # Three parameters: forward mode is the cheap direction.
    g_sep = jax.jacfwd(near_separatrix)(jnp.asarray(INERTIA))

    def at_rest(x):
        s = FREE.replace(inertia=x[:3])
        traj = jd.simulate(s, s.state(omega=x[3:]), 5.0)
        o = traj.final_outputs()
        return o["momentum"][0] + o["energy"][0]

    g_rest = jax.grad(at_rest)(jnp.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0]))
    return {
        "impact_gradient_vs_quadrature": float(jnp.max(jnp.abs(g / g_ref - 1))),
        "near_separatrix_gradient_norm": float(jnp.linalg.norm(g_sep)),
        "near_separatrix_gradient_finite": bool(jnp.all(jnp.isfinite(g_sep))),
        "at_rest_gradient_finite": bool(jnp.all(jnp.isfinite(g_rest))),
    }


def test_gradients():
    f = case_gradients()
    assert f["impact_gradient_vs_quadrature"] < 1e-7
    assert f["near_separatrix_gradient_finite"] and f["at_rest_gradient_finite"]


# -- 10. float32 ---------------------------------------------------------------------------------


@functools.cache
def case_float32():
    f32 = np.float32
    out = {}
    rod = jd.FallingRod(f32(1.0), f32(1.0), f32(9.81))
    scene = jd.Scene(rod)
    traj = jd.simulate(scene, scene.state(theta=f32(0.1)), 5.0, rtol=1e-6, atol=1e-7)
    out["falling-rod_impact_time_rel_error"] = abs(float(traj.t_final)
                                                   / float(ROD.fall_time(0.1)) - 1)
    body = jd.RigidBody(np.array([1.0, 2.0, 3.0], f32))
    omega0 = np.array([0.3, 0.2, 1.0], f32)
    for name, effects, attitude in (
        ("torque-free", (), False),
        ("gyrostat", (jd.Rotor(np.zeros(3, f32)),), False),
        ("torque", (jd.ExternalTorque(np.zeros(3, f32)),), False),
        ("attitude", (), True),
        ("gravity-gradient", (jd.GravityGradient(f32(1e-6)),), True),
    ):
        s = jd.Scene(body, effects, attitude=attitude)
        tr = jd.simulate(s, s.state(omega=omega0), 10.0, rtol=1e-6, atol=1e-7)
        exact = jd.torque_free_omega(INERTIA, omega0.astype(np.float64), 10.0)
        assert tr.y_final["omega"].dtype == jnp.float32
        out[f"{name}_omega_error"] = float(np.max(np.abs(np.asarray(tr.y_final["omega"],
                                                                   np.float64) - exact)))
    try:
        jd.simulate(scene, scene.state(theta=f32(0.1)), 5.0, rtol=1e-10)
        out["rtol_1e-10"] = "accepted"
    except jd.ParameterError as e:
        out["rtol_1e-10"] = str(e)
    return out


def test_float32_reach():
    f = case_float32()
    assert f["falling-rod_impact_time_rel_error"] < 1e-5
    for name in ("torque-free", "gyrostat", "torque", "attitude", "gravity-gradient"):
        assert f[f"{name}_omega_error"] < 1e-4
    assert "below what float32 can reach" in f["rtol_1e-10"]


# -- 11. step budget and stiffness -----------------------------------------------------------------


@functools.cache
def case_budget_and_stiffness():
    out = {}

    def message(fn):
        try:
            fn()
            return "completed"
        except jd.SimulationError as e:
            return str(e)

    out["max_steps_exhausted"] = message(
        lambda: jd.simulate(FREE, FREE.state(omega=[0.3, 0.2, 1.0]), 100.0, max_steps=20))
    # A stiff damping law: tau = -c w with c = 1e5, so w decays on a 1e-5 time scale.
    damped = jd.Scene(jd.RigidBody(INERTIA),
                      (jd.ExternalTorque(lambda t, y: -1e5 * y["omega"], feedback=True),))
    y0 = damped.state(omega=[0.3, 0.2, 1.0])
    out["stiff_explicit"] = message(
        lambda: jd.simulate(damped, y0, 10.0, max_steps=2000))
    implicit = jd.simulate(damped, y0, 10.0, solver=dfx.Kvaerno5(), max_steps=2000)
    out["stiff_implicit_steps"] = int(implicit.stats["num_steps"])
    out["stiff_implicit_final_norm"] = float(jnp.linalg.norm(implicit.y_final["omega"]))
    return out


def test_step_budget_and_stiffness():
    f = case_budget_and_stiffness()
    assert "increase max_steps" in f["max_steps_exhausted"]
    assert "stiff" in f["stiff_explicit"] and "Kvaerno5" in f["stiff_explicit"]
    assert f["stiff_implicit_steps"] < 2000 and f["stiff_implicit_final_norm"] < 1e-10



# -- 12. every row at the default settings (issue 17) ----------------------------------------------


@functools.cache
def case_defaults():
    """The rows above with `simulate`'s defaults (rtol 1e-8, error control in the natural
    scales, no atol): what a new user gets without choosing a tolerance."""
    out = {}
    for theta0 in (1e-12, 1e-15):
        traj = jd.simulate(ROD_SCENE, ROD_SCENE.state(theta=theta0), 30.0)
        out[f"rod_{theta0:g}"] = abs(float(traj.t_final) / float(ROD.fall_time(theta0)) - 1)
    traj = jd.simulate(ROD_SCENE, ROD_SCENE.state(theta=0.0), 100.0)
    out["rod_upright_theta"] = float(traj.y_final["theta"])
    for name, theta0, rate in (("initial_rate", 0.1, 2.0), ("towards_upright", 0.1, -4.0),
                               ("near_flat", np.pi / 2 - 1e-6, 0.0)):
        traj = jd.simulate(ROD_SCENE, ROD_SCENE.state(theta=theta0, theta_dot=rate), 10.0)
        out[f"rod_{name}"] = abs(float(traj.t_final) / float(ROD.fall_time(theta0, rate)) - 1)
    lam = np.sqrt((3 - 2) * (2 - 1) / (1 * 3)) * 2.0
    for eps in (1e-3, 1e-6, 1e-9):
        omega0 = jnp.array([eps, 2.0, eps])
        t_max = 1.2 * float(jd.torque_free_period(INERTIA, omega0)) / 2
        exact = _first_zero(lambda t: jd.torque_free_omega(INERTIA, omega0, t)[..., 1], t_max)
        traj = jd.simulate(FREE, FREE.state(omega=omega0), t_max, dense=True)
        sim = _first_zero(lambda t: traj.evaluate(jnp.asarray(t))["omega"][:, 1], t_max)
        out[f"flip_{eps:g}"] = abs(sim - exact)
        out[f"flip_{eps:g}_bound"] = 1e-8 * 2.0 / (lam * eps)
    for name, inertia in (("flat_plate", (1.0, 1e3, 1001.0)), ("needle", (1e-3, 1.0, 1.0005))):
        scene = jd.Scene(jd.RigidBody(inertia))
        omega0 = jnp.array([0.2, 0.1, 0.05])
        traj = jd.simulate(scene, scene.state(omega=omega0), 10.0)
        exact = scipy_euler(inertia, np.asarray(omega0), 10.0, atol=1e-15)[-1]
        out[name] = float(np.max(np.abs(traj.y_final["omega"] - exact)) / 0.2)
    f32 = jnp.float32
    rod32 = jd.FallingRod(length=f32(1.0), mass=f32(1.0), g=f32(9.81))
    traj = jd.simulate(jd.Scene(rod32), jd.Scene(rod32).state(theta=f32(0.1)), 5.0)
    out["float32_rod"] = abs(float(traj.t_final) / float(ROD.fall_time(0.1)) - 1)
    return out


def test_hard_cases_at_the_defaults():
    f = case_defaults()
    target = 10 * 1e-8  # within 10x of the default rtol
    for key in ("rod_1e-12", "rod_1e-15", "rod_initial_rate", "rod_towards_upright",
                "rod_near_flat", "flat_plate", "needle"):
        assert f[key] < target, key
    assert f["rod_upright_theta"] == 0.0
    for eps in ("0.001", "1e-06", "1e-09"):  # ill-conditioned: within the conditioning bound
        assert f[f"flip_{eps}"] < f[f"flip_{eps}_bound"]
    assert f["float32_rod"] < 1e-5

CASES = {
    "1_rod_tiny_angle": case_tiny_angle,
    "2_rod_upright": case_upright,
    "3_rod_edges": case_rod_edges,
    "4_intermediate_axis": case_intermediate_axis,
    "5_separatrix": case_separatrix,
    "6_axisymmetric_spherical": case_symmetric,
    "7_extreme_inertia": case_extreme_inertia,
    "8_long_horizon": case_long_horizon,
    "9_gradients": case_gradients,
    "10_float32": case_float32,
    "11_budget_and_stiffness": case_budget_and_stiffness,
    "12_defaults": case_defaults,
}


if __name__ == "__main__":
    print(json.dumps({name: fn() for name, fn in CASES.items()}, indent=2))
