"""Scale-free numerics: the same physics in other units gives the same relative accuracy at the
default settings (issue 17). References come from independent routes: the Jacobi-elliptic
closed form for the free body, the fall-time quadrature for the rod, the analytic critical
rotor momenta `h = (I_i - I_K) W`."""

import json

import diffrax as dfx
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import DEFAULT_RTOL, WITHIN_RTOL
from hypothesis import HealthCheck, given, settings, strategies as st
from test_cli import run_cli

import jaxdyn as jd

INERTIA = np.array([1.0, 2.0, 3.0])
OMEGA = np.array([0.3, 1.0, 0.2])
FREE = jd.Scene(jd.RigidBody(INERTIA))


def free_error(inertia, omega0, t1, **kwargs):
    """Relative error of the final rates at the defaults, against the closed form."""
    scene = FREE.replace(inertia=jnp.asarray(inertia))
    traj = jd.simulate(scene, scene.state(omega=omega0), t1, **kwargs)
    exact = np.asarray(jd.torque_free_omega(inertia, omega0, t1))
    err = np.max(np.abs(np.asarray(traj.y_final["omega"]) - exact)) / np.max(np.abs(omega0))
    return float(err), int(traj.stats["num_accepted_steps"])


@pytest.mark.parametrize("s", [1e-9, 1e-6, 1e-3, 1.0, 1e3, 1e6, 1e9])
def test_rate_sweep(s):
    """Rates scaled by s and time by 1/s: same steps, same relative error, within 10x rtol."""
    base_err, base_steps = free_error(INERTIA, OMEGA, 20.0)
    err, steps = free_error(INERTIA, OMEGA * s, 20.0 / s)
    assert err < WITHIN_RTOL * DEFAULT_RTOL
    assert steps == base_steps
    assert err == pytest.approx(base_err, rel=1e-3)


@pytest.mark.parametrize("k", [1e-20, 1e-10, 1e10, 1e20])
def test_inertia_sweep(k):
    base_err, base_steps = free_error(INERTIA, OMEGA, 20.0)
    err, steps = free_error(INERTIA * k, OMEGA, 20.0)
    assert err < WITHIN_RTOL * DEFAULT_RTOL and steps == base_steps


def test_fixed_atol_is_a_floor():
    """A user's atol is kept: an absurd floor for slow rates costs accuracy (the old default's
    failure mode), and 0 is pure natural-scale control."""
    err_floor, _ = free_error(INERTIA, OMEGA * 1e-6, 20.0 / 1e-6, atol=1e-10)
    err_zero, _ = free_error(INERTIA, OMEGA * 1e-6, 20.0 / 1e-6, atol=0.0)
    assert err_floor > 100 * err_zero


def rod_fall(theta0, theta_dot0=0.0, length=1.0, g=9.81):
    rod = jd.FallingRod(length=length, mass=1.0, g=g)
    scene = jd.Scene(rod)
    t_ref = float(rod.fall_time(theta0, theta_dot0))
    traj = jd.simulate(scene, scene.state(theta=theta0, theta_dot=theta_dot0), 2 * t_ref)
    assert bool(traj.event["flat"])
    return abs(float(traj.t_final) - t_ref) / t_ref


@pytest.mark.parametrize("theta0", [1e-15, 1e-12, 1e-9, 1e-6, 1e-3, 0.1, 1.0, 1.5])
@pytest.mark.parametrize("length, g", [(1.0, 9.81), (1e-6, 9.81), (1e6, 9.81), (1.0, 1e-6),
                                       (1.0, 1e6)])
def test_rod_start_and_units(theta0, length, g):
    assert rod_fall(theta0, 0.0, length, g) < WITHIN_RTOL * DEFAULT_RTOL


@pytest.mark.parametrize("theta0, rate", [(0.0, 0.3), (1e-12, 1e-9), (0.2, -1.0), (-0.5, 2.0)])
@pytest.mark.parametrize("length", [1e-6, 1.0, 1e6])
def test_rod_with_a_rate(theta0, rate, length):
    w = np.sqrt(9.81 / length)  # rates in units of the rod's own
    assert rod_fall(theta0, rate * w, length) < WITHIN_RTOL * DEFAULT_RTOL


@pytest.mark.parametrize("length", [1e-6, 1.0, 1e6])
def test_rod_upright_stays(length):
    rod = jd.FallingRod(length=length)
    scene = jd.Scene(rod)
    traj = jd.simulate(scene, scene.state(theta=0.0), 100.0)
    assert float(traj.y_final["theta"]) == 0.0 and not bool(traj.event["flat"])


@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(
    a=st.floats(0.2, 1.0), b=st.floats(0.2, 1.0),
    w=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
    rate_exp=st.integers(-9, 9), inertia_exp=st.integers(-20, 20),
)
def test_property_free_body_units(a, b, w, rate_exp, inertia_exp):
    """Random bodies (triangle inequality by construction), rates and unit scalings: the
    relative results agree with the unscaled run."""
    inertia = np.sort([1.0, 1.0 + a, 1.0 + a * b])
    inertia[2] = min(inertia[2], inertia[0] + inertia[1])
    omega = np.asarray(w) + np.array([0.0, 0.0, 1.5])  # never at rest
    s, k = 10.0**rate_exp, 10.0**inertia_exp
    base = jd.simulate(FREE.replace(inertia=jnp.asarray(inertia)), {"omega": jnp.asarray(omega)},
                       10.0)
    scaled = jd.simulate(FREE.replace(inertia=jnp.asarray(inertia * k)),
                         {"omega": jnp.asarray(omega * s)}, 10.0 / s)
    w_base = np.asarray(base.y_final["omega"])
    w_scaled = np.asarray(scaled.y_final["omega"]) / s
    assert np.max(np.abs(w_scaled - w_base)) <= WITHIN_RTOL * DEFAULT_RTOL * np.max(np.abs(omega))


@settings(max_examples=25, deadline=None, derandomize=True)
@given(exp=st.floats(-15.0, np.log10(1.5)), length_exp=st.floats(-6.0, 6.0),
       g_exp=st.floats(-6.0, 6.0))
def test_property_rod_against_quadrature(exp, length_exp, g_exp):
    assert rod_fall(10.0**exp, 0.0, 10.0**length_exp, 10.0**g_exp) < \
        WITHIN_RTOL * DEFAULT_RTOL


@pytest.mark.parametrize("mode", ["adaptive", "vmap"])
def test_ensemble_units(mode):
    """Ensembles control error in the natural scales too: the same relative errors at rates
    of 1e-6 and 1e6 as at 1."""
    rows = OMEGA[None] + np.linspace(-0.1, 0.1, 8)[:, None] * np.array([1.0, 0.0, 0.5])
    errors = []
    for s in (1e-6, 1.0, 1e6):
        res = jd.ensemble(FREE, {"omega": jnp.asarray(rows * s)}, 20.0 / s, mode=mode)
        w = np.asarray(res.values["omega"])
        exact = np.stack([np.asarray(jd.torque_free_omega(INERTIA, r * s, 20.0 / s))
                          for r in rows])
        errors.append(np.max(np.abs(w - exact)) / s)
    assert max(errors) < WITHIN_RTOL * DEFAULT_RTOL
    assert max(errors) / min(errors) < 1.5


@pytest.mark.parametrize("k, momentum", [(1.0, 1.0), (1e20, 1.0), (1e-20, 1.0), (1.0, 1e-300),
                                         (1e20, 1e20), (1.0, 1e200)])
def test_separatrix_extremes(k, momentum):
    scene = jd.Scene(jd.RigidBody(np.array([1.0, 2.0, 2.5]) * k))
    eq = jd.find_equilibria(scene, momentum)
    assert len(eq) == 6 and eq.kind.count("saddle") == 2
    # centres at +-H / I_k on the major and minor axes, saddles on the intermediate one
    expected = sorted(momentum / (np.array([1.0, 2.0, 2.5]) * k))
    rates = sorted(set(np.round(np.max(np.abs(np.asarray(eq.omega)), axis=1) / expected[0],
                                9)))
    assert np.allclose(np.array(rates) * expected[0], expected, rtol=1e-12)


@pytest.mark.parametrize("rate", [1e-200, 1.0, -3.0, 1e160])
def test_critical_momenta_extremes(rate):
    inertia = np.array([1.0, 2.0, 2.5])
    roots = np.asarray(jd.critical_rotor_momenta(inertia, 1, rate))
    expected = np.sort([(inertia[0] - inertia[1]) * rate, (inertia[2] - inertia[1]) * rate])
    np.testing.assert_allclose(roots, expected, rtol=1e-10)


def test_separatrix_says_when_equilibria_are_missing(monkeypatch):
    import jaxdyn._separatrix as sep

    real = sep._solve_all

    def lose_some(scene, momentum, directions):  # as if Newton found only the centres
        out = list(real(scene, momentum, directions))
        eig = np.asarray(out[4])
        out[1] = np.asarray(out[1]) & (eig < 0)
        return tuple(out)

    monkeypatch.setattr(sep, "_solve_all", lose_some)
    with pytest.raises(RuntimeError, match="missed"):
        jd.find_equilibria(jd.Scene(jd.RigidBody([1.0, 2.0, 2.5])), 1.0)


@pytest.mark.parametrize("kwargs, match", [
    ({"rtol": 10.0}, "rtol=10: must be positive"),
    ({"rtol": 1.0}, "rtol=1: must be positive"),
    ({"rtol": 0.0}, "rtol=0: must be positive"),
    ({"rtol": 1e-17}, "below what float64 can reach"),
    ({"atol": -1e-3}, "atol=-0.001: must be within"),
    ({"atol": 1.0}, "atol=1: must be within"),
    ({"atol": float("inf")}, "atol=inf: must be within"),
])
def test_nonsense_tolerances_refused(kwargs, match):
    with pytest.raises(jd.ParameterError, match=match):
        jd.simulate(FREE, FREE.state(omega=OMEGA), 1.0, **kwargs)
    with pytest.raises(jd.ParameterError, match=match):
        jd.ensemble(FREE, FREE.state(omega=OMEGA), 1.0, n=2, **kwargs)
    ts = jnp.linspace(0.0, 1.0, 20)
    with pytest.raises(jd.ParameterError, match=match):
        jd.fit(FREE, ts, {"omega": jnp.ones((20, 3))}, parameters={"inertia": jd.ValidInertia()},
               **kwargs)


def test_tiny_span_refused():
    with pytest.raises(jd.ParameterError, match="t1 - t0"):
        jd.simulate(FREE, FREE.state(omega=OMEGA), 5e-324)


def test_overflow_safe_normalisation():
    scene = jd.Scene(jd.RigidBody(INERTIA), attitude=True)
    for q in ([1e200, 0, 0, 0], [1e-200, 1e-200, 0, 0]):
        unit = np.asarray(scene.state(omega=OMEGA, quaternion=q)["quaternion"])
        assert np.isclose(np.linalg.norm(unit), 1.0, rtol=1e-15)
    with pytest.raises(jd.ParameterError, match="quaternion=.*nonzero"):
        scene.state(omega=OMEGA, quaternion=[0.0, 0.0, 0.0, 0.0])
    wheels = jd.Wheels(axes=[[1e200, 0, 0], [0, 1e-200, 1e-200]], inertia=[1.0, 1.0])
    np.testing.assert_allclose(np.linalg.norm(np.asarray(wheels.axes), axis=1), 1.0)
    with pytest.raises(jd.ParameterError, match="wheels.axes"):
        jd.Wheels(axes=[[0.0, 0.0, 0.0]], inertia=[1.0])
    assert float(jd.safe_norm(jnp.array([3e200, 4e200]))) == pytest.approx(5e200)
    assert float(jd.safe_norm(jnp.array([3e-200, 4e-200]))) == pytest.approx(5e-200)


def test_float32_runs_at_its_defaults():
    scene = jd.Scene(jd.RigidBody(jnp.asarray(INERTIA, jnp.float32)))
    for s in (1e-3, 1e3):
        traj = jd.simulate(scene, scene.state(omega=jnp.asarray(OMEGA * s, jnp.float32)),
                           20.0 / s, rtol=1e-6)
        exact = np.asarray(jd.torque_free_omega(INERTIA, OMEGA * s, 20.0 / s))
        assert traj.y_final["omega"].dtype == jnp.float32
        assert np.max(np.abs(np.asarray(traj.y_final["omega"]) - exact)) / s < 1e-4


def test_implicit_solver_in_natural_scales():
    """Kvaerno5's nonlinear solves take an absolute tolerance in the state's units from the
    natural scales: a slow body (rates 1e-6) is as accurate as a fast one."""
    errs = [free_error(INERTIA, OMEGA * s, 5.0 / s, solver=dfx.Kvaerno5())[0] for s in (1e-6, 1)]
    assert max(errs) < WITHIN_RTOL * DEFAULT_RTOL


def test_cli_rod_at_1e_12_reports_and_agrees(capsys):
    status, text, err = run_cli(capsys, "run", "falling-rod", "--set", "theta0=1e-12", "--json")
    assert status == 0, err
    out = json.loads(text)
    assert out["relative_difference"]["impact_time"] < 1e-9
    assert abs(out["impact_time"] / out["reference"]["impact_time"] - 1) < 1e-9
    assert "warning" not in err


def test_cli_rod_that_has_not_landed_by_t1_says_so(capsys):
    # A rod 1000 m long lands after the scene's t1 = 10 s: the run has no impact to print
    # beside the reference's, and says so on stderr instead of printing None beside it.
    status, text, err = run_cli(capsys, "run", "falling-rod", "--set", "length=1000", "--json")
    assert status == 0, err
    out = json.loads(text)
    assert out["impact_time"] is None and out["t_final"] == out["t1"] == 10
    assert out["reference"]["impact_time"] > 10
    assert ("impact_rate, impact_time: not reached by this run (it ended at t_final=10)"
            in err)
    assert err.count("\n") == 1


def test_a_rod_that_never_falls_has_no_reference_to_miss():
    # Upright at rest the rod stays there: no impact, and no reference impact (time or rate)
    # for the command to call "not reached".
    rod = jd.Scene(jd.FallingRod())
    report = jd.simulate(rod, rod.state(theta=0.0), 2.0).report()
    assert report["impact_time"] is None and report["reference"] == {
        "impact_time": None, "impact_rate": None}
    from jaxdyn._commands._common import warn_on_disagreement

    assert warn_on_disagreement(report, 1e-10, 2.0) == []


def test_cli_free_body_reports_its_closed_form(capsys):
    status, text, err = run_cli(capsys, "run", "torque-free", "--json", "--set", "rtol=1e-3")
    assert status == 0, err
    out = json.loads(text)
    ref = np.asarray(out["reference"]["omega_final"])
    diff = np.max(np.abs(np.asarray(out["omega_final"]) - ref)) / np.max(np.abs(ref))
    assert out["relative_difference"]["omega_final"] == pytest.approx(diff, rel=1e-6)
    # a loose run beside its reference: warned about on stderr when past what rtol promises
    assert ("warning: omega_final differs" in err) == (diff > 100 * 1e-3)


def test_warning_names_the_value():
    from jaxdyn._commands._common import warn_on_disagreement

    lines = warn_on_disagreement({"relative_difference": {"impact_time": 3e-4,
                                                          "impact_rate": None}}, 1e-10)
    assert len(lines) == 1 and "impact_time" in lines[0] and "0.0003" in lines[0]
    # a value with a reference but none of its own: not reached, and named with its reference
    lines = warn_on_disagreement({"impact_time": None, "reference": {"impact_time": 21.5},
                                  "relative_difference": {"impact_time": None}}, 1e-10, 10.0)
    assert len(lines) == 1 and "impact_time: not reached" in lines[0] and "21.5" in lines[0]
    assert warn_on_disagreement({"impact_time": 21.5, "reference": {"impact_time": 21.5},
                                 "relative_difference": {"impact_time": 0.0}}, 1e-10, 30.0) == []
