"""The rod on a rough floor, checked through independent routes: the slip onset against the
contact forces of the pivoting rod in closed form (solved with scipy's brentq); whole hybrid runs
against a second implementation (scipy's solve_ivp, with the contact forces from a linear solve
of the Newton-Euler equations written with the cross product, and scipy's event location); the
frictionless limit against the falling rod's quadrature; a pivot all the way down against its own
quadrature; lift-off and the free flight against the ballistic closed form; and the energy
balance against a quadrature of the friction power over the dense output."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import INTEGRATION, tol
from scipy.integrate import quad, solve_ivp, trapezoid
from scipy.optimize import brentq
from test_cli import assert_frictionless_rod_summary, run_cli, run_json

import jaxdyn as jd
from jaxdyn import _batch_solve

L, M, G = 1.0, 1.0, 9.81
TIGHT = dict(rtol=1e-12, atol=1e-12)
STICK, SLIP, FLIGHT = 0, 1, 2


def _scene(mu_s, mu_k):
    return jd.Scene(jd.RoughFloorRod(length=L, mass=M, g=G, mu_s=mu_s, mu_k=mu_k))


def _run(mu_s, mu_k, theta0, theta_dot0=0.0, t1=5.0, **kw):
    scene = _scene(mu_s, mu_k)
    return jd.simulate(scene, scene.state(theta=theta0, theta_dot=theta_dot0), t1,
                       **{**TIGHT, **kw})


# -- closed form for the pivoting rod -------------------------------------------------------


def pivot_forces(theta, theta0):
    """F and N on a rod pivoting from rest at theta0: energy gives
    theta_dot^2 = (3 g / L)(cos theta0 - cos theta), the pivot theta_ddot = (3 g / 2 L) sin theta,
    and F = m a_cx, N = m g + m a_cy with the CM on a circle about the tip."""
    rate2 = 3 * G / L * (np.cos(theta0) - np.cos(theta))
    acc = 1.5 * G / L * np.sin(theta)
    a_cx = L / 2 * (acc * np.cos(theta) - rate2 * np.sin(theta))
    a_cy = -L / 2 * (acc * np.sin(theta) + rate2 * np.cos(theta))
    return M * a_cx, M * G + M * a_cy


def slip_onset(theta0, mu_s):
    """First angle where |F| = mu_s N, bracketed on a fine grid and polished by brentq."""
    def excess(theta):
        f, n = pivot_forces(theta, theta0)
        return abs(f) - mu_s * n

    grid = np.linspace(theta0, np.pi / 2, 20001)
    i = int(np.argmax([excess(x) > 0 for x in grid]))
    assert i > 0, "slips at once"
    theta = brentq(excess, grid[i - 1], grid[i], xtol=1e-15, rtol=1e-15)
    return theta, pivot_forces(theta, theta0)[0]


@pytest.mark.parametrize("theta0", [0.05, 0.6])
def test_pivot_forces_match_the_closed_form(theta0):
    # `RoughFloorRod.pivot_forces` against F = m a_cx and N = m g + m a_cy with the CM on a circle
    # about the fixed tip (written out above), and against the forms
    # F = (3/4) m g sin(theta) (3 cos(theta) - 2 cos(theta0)),
    # N = (1/4) m g (1 + 9 cos(theta)^2 - 6 cos(theta0) cos(theta)).
    rod = jd.RoughFloorRod(length=L, mass=M, g=G, mu_s=0.5, mu_k=0.4)
    theta = np.linspace(theta0, np.arccos(1 / 3) - 0.02, 2000)
    forces = rod.pivot_forces(theta, theta0)
    f, n = np.asarray(forces["friction_force"]), np.asarray(forces["normal_force"])
    f_ref, n_ref = pivot_forces(theta, theta0)
    assert np.allclose(f, f_ref, rtol=0, atol=1e-12) and np.allclose(n, n_ref, rtol=0, atol=1e-12)
    c, c0 = np.cos(theta), np.cos(theta0)
    assert np.allclose(f, 0.75 * M * G * np.sin(theta) * (3 * c - 2 * c0), rtol=0, atol=1e-12)
    assert np.allclose(n, 0.25 * M * G * (1 + 9 * c**2 - 6 * c0 * c), rtol=0, atol=1e-12)


@pytest.mark.parametrize("mu_s", [0.07, 0.23, 0.31, 0.45, 0.62, 1.3])
def test_slip_onset_matches_pivot_contact_forces(mu_s):
    # mu_s below the peak of F/N in the first phase of the fall (where the floor must push the
    # tip forward, F > 0) slips backward; above it, the rod slips forward after F has changed sign
    # (at cos(theta) = 2 cos(theta0) / 3) and before N vanishes (cos(theta) = 1/3 from upright).
    theta0 = 0.05
    traj = _run(mu_s, 0.7 * mu_s, theta0)
    rep = traj.report()
    theta_slip, friction = slip_onset(theta0, mu_s)
    assert np.isclose(rep["slip_angle"], theta_slip, rtol=tol(INTEGRATION))
    # The tip slides against the friction it needed: backward (-x) where F > 0.
    assert rep["slip_direction"] == ("backward" if friction > 0 else "forward")
    assert rep["liftoff"] is False and rep["impact_time"] is not None
    assert theta_slip < np.arccos(1 / 3)


def test_backward_slips_only_below_the_peak_friction_ratio():
    # From near upright the ratio F/N of the first phase peaks at r_max ~ 0.3715: below it the
    # tip slips backward, above it forward, and the slip angle jumps across it.
    theta0 = 0.05
    grid = np.linspace(theta0, np.arccos(2 * np.cos(theta0) / 3), 200001)
    f, n = pivot_forces(grid, theta0)
    r_max = float(np.max(f / n))
    below, above = _run(r_max - 0.01, 0.0, theta0).report(), _run(r_max + 0.01, 0.0, theta0)
    above = above.report()
    assert below["slip_direction"] == "backward" and above["slip_direction"] == "forward"
    assert below["slip_angle"] < 0.62 < 0.84 < above["slip_angle"]


def test_frictionless_limit_is_the_falling_rod():
    rod = jd.FallingRod(length=L, mass=M, g=G)
    for theta0, theta_dot0 in [(0.05, 0.0), (0.3, 0.5)]:
        traj = _run(0.0, 0.0, theta0, theta_dot0)
        assert bool(traj.event["flat"]) and not bool(traj.event["restick"])
        assert np.isclose(traj.t_final, rod.fall_time(theta0, theta_dot0),
                          rtol=tol(INTEGRATION))
        rate = rod.rate(np.pi / 2, theta0, theta_dot0)
        assert np.isclose(traj.y_final["theta_dot"], rate, rtol=tol(INTEGRATION))
        # No horizontal force: the CM moves at its initial horizontal velocity (the tip starts
        # at rest, so that is (L/2) cos(theta0) theta_dot0; the angle does not depend on it).
        cm_x = traj.final_outputs()["cm_x"][0]
        start = L / 2 * np.sin(theta0)  # the tip starts at x = 0
        drift = L / 2 * np.cos(theta0) * theta_dot0 * float(traj.t_final)
        assert abs(float(cm_x) - start - drift) < 1e-10
        assert float(traj.y_final["friction_work"]) == 0.0


def test_pivot_all_the_way_down():
    # Started at 1.3 rad, N = m g (1 + 9 c^2 - 6 c0 c) / 4 never vanishes and |F| / N stays below
    # 1.7: with mu_s = 10 the rod pivots down to the floor. Fall time by quadrature of
    # dt = d(theta) / theta_dot with theta = theta0 + (pi/2 - theta0) s^2 (no singularity).
    theta0 = 1.3
    traj = _run(10.0, 5.0, theta0)
    assert bool(traj.event["flat"]) and traj.report()["slip_angle"] is None
    a = np.pi / 2 - theta0

    def integrand(s):
        theta = theta0 + a * s**2
        if s == 0:
            return 2 * np.sqrt(a) / np.sqrt(1.5 * G / L * np.sin(theta0))
        return 2 * a * s / np.sqrt(3 * G / L * (np.cos(theta0) - np.cos(theta)))

    t_fall = quad(integrand, 0, 1, epsabs=0, epsrel=1e-13, limit=200)[0]
    assert np.isclose(traj.t_final, t_fall, rtol=tol(INTEGRATION))
    assert np.isclose(traj.y_final["theta_dot"], np.sqrt(3 * G / L * np.cos(theta0)),
                      rtol=tol(INTEGRATION))
    assert float(traj.y_final["tip_x"]) == 0.0


def test_gradients_through_events_and_switches():
    # Reverse mode through the whole hybrid run (stick, slip, flat). The slip angle solves
    # h(theta, mu) = |F| - mu N = 0, so d theta / d mu = N / (d|F|/d theta - mu dN/d theta)
    # (implicit function theorem on the closed form); at fixed mu, theta0 and theta_dot0 = 0 the
    # run is scale-free: the slip angle does not depend on L and every time scales as sqrt(L/g).
    theta0 = 0.05
    y0 = _scene(0.5, 0.4).state(theta=theta0)

    def run(p):
        sc = _scene(p[0], 0.5 * p[0]).replace(length=p[1])
        traj = jd.simulate(sc, y0, 3.0, **TIGHT)
        return jnp.stack([traj.y_final["slip_theta"], traj.t_final])

    jac = jax.jacrev(run)
    for mu in (0.3, 0.6):
        p = jnp.array([mu, 1.3])
        (dtheta_dmu, dtheta_dl), (_, dt_dl) = np.asarray(jac(p))
        theta, t_end = np.asarray(run(p))
        s, c, c0 = np.sin(theta), np.cos(theta), np.cos(theta0)
        f = 0.75 * G * s * (3 * c - 2 * c0)
        n = 0.25 * G * (1 + 9 * c**2 - 6 * c0 * c)
        df = 0.75 * G * (c * (3 * c - 2 * c0) - 3 * s**2)
        dn = 0.25 * G * (-18 * c * s + 6 * c0 * s)
        assert np.isclose(dtheta_dmu, n / (np.sign(f) * df - mu * dn), rtol=1e-8)
        assert abs(dtheta_dl) < 1e-9
        assert np.isclose(dt_dl, t_end / (2 * 1.3), rtol=1e-8)


# -- a second implementation: scipy, Newton-Euler linear solve ------------------------------


def _contact(state, mode, sigma, mu_k):
    """theta_ddot, F, N and the tip's acceleration, from the Newton-Euler equations solved as a
    linear system in (theta_ddot, a_cx, a_cy, F, N)."""
    theta, rate = state[0], state[1]
    s, c = np.sin(theta), np.cos(theta)
    i_c = M * L**2 / 12
    r = np.array([-L / 2 * s, -L / 2 * c])  # tip relative to the CM
    if mode == FLIGHT:
        return 0.0, 0.0, 0.0, L / 2 * s * rate**2, -G + L / 2 * c * rate**2
    a = np.zeros((5, 5))
    b = np.zeros(5)
    a[0, [1, 3]] = M, -1.0  # m a_cx = F
    a[1, [2, 4]] = M, -1.0  # m a_cy = N - m g
    b[1] = -M * G
    # theta turns clockwise (the top to +x), so the z-angle is -theta: -I_c theta_ddot = r x f.
    a[2, 0] = -i_c
    a[2, 3], a[2, 4] = r[1], -r[0]  # -(r_x N - r_y F) moved to the left
    # The tip stays on the floor: y_tip = y_c - (L/2) cos(theta) = 0, twice differentiated.
    a[3, [0, 2]] = L / 2 * s, 1.0
    b[3] = -L / 2 * c * rate**2
    if mode == STICK:  # the tip stays put: x_tip = x_c - (L/2) sin(theta)
        a[4, [0, 1]] = -L / 2 * c, 1.0
        b[4] = -L / 2 * s * rate**2
    else:  # kinetic friction against the sliding velocity
        a[4, [3, 4]] = 1.0, sigma * mu_k
    theta_ddot, a_cx, _, f, n = np.linalg.solve(a, b)
    tip_ax = a_cx - L / 2 * (c * theta_ddot - s * rate**2)
    return theta_ddot, f, n, tip_ax, 0.0


def reference_run(mu_s, mu_k, theta0, theta_dot0=0.0, t1=5.0):
    """A hybrid run with solve_ivp (DOP853) and its event location, modes switched by the same
    Coulomb rules. Returns the final time, state and records."""
    state = np.array([theta0, theta_dot0, 0.0, 0.0, 0.0, 0.0, 0.0])  # ..., friction work
    t, records = 0.0, {"slip_angle": None, "slip_direction": None, "liftoff": False,
                       "switches": 0, "event": None}

    def settle(state):
        _, f, n, _, _ = _contact(state, STICK, 0.0, mu_k)
        if L * state[1] ** 2 * np.cos(state[0]) >= 2 * G:
            return FLIGHT, 0.0
        if n >= 0 and abs(f) <= mu_s * n:
            return STICK, 0.0
        return SLIP, -np.sign(f)

    def enter(mode, sigma):
        if mode == SLIP and records["slip_angle"] is None:
            records["slip_angle"] = state[0]
            lean = np.sign(state[0]) or np.sign(state[1])
            records["slip_direction"] = "forward" if sigma * lean > 0 else "backward"
        if mode == FLIGHT:
            records["liftoff"] = True

    mode, sigma = settle(state)
    enter(mode, sigma)
    while True:
        def rhs(_, y, mode=mode, sigma=sigma):
            theta_ddot, _, n, tip_ax, tip_ay = _contact(y, mode, sigma, mu_k)
            work = mu_k * n * abs(y[3]) if mode == SLIP else 0.0
            return [y[1], theta_ddot, y[3], tip_ax, y[5], tip_ay, work]

        def flat(_, y):
            return np.pi / 2 - abs(y[0])

        def slip(_, y, mode=mode):
            _, f, n, _, _ = _contact(y, STICK, 0.0, mu_k)
            return mu_s * n - abs(f)

        def restick(_, y, sigma=sigma):
            return sigma * y[3]

        def liftoff(_, y, mode=mode, sigma=sigma):
            return _contact(y, SLIP, sigma, mu_k)[2]

        def touchdown(_, y):
            return y[4] + min(0.0, L * np.cos(y[0]))

        events = {STICK: [flat, slip], SLIP: [flat, restick, liftoff], FLIGHT: [touchdown]}[mode]
        for e in events:
            e.terminal, e.direction = True, -1
        sol = solve_ivp(rhs, (t, t1), state, method="DOP853", rtol=1e-13, atol=1e-13,
                        events=events)
        t, state = sol.t[-1], sol.y[:, -1].copy()
        fired = [e.__name__ for e, te in zip(events, sol.t_events) if len(te)]
        if not fired:
            return t, state, records
        name = fired[0]
        if name in ("flat", "touchdown"):
            records["event"] = name
            return t, state, records
        records["switches"] += 1
        if name == "slip":
            mode, sigma = SLIP, -np.sign(_contact(state, STICK, 0.0, mu_k)[1])
        elif name == "restick":
            state[3] = 0.0
            mode, sigma = settle(state)
        else:
            mode, sigma = FLIGHT, 0.0
        enter(mode, sigma)


CASES = {
    # name: (mu_s, mu_k, theta0, theta_dot0), and the switches expected
    "stick, slip forward": ((0.55, 0.4, 0.05, 0.0), 1),
    "slip backward, reverse": ((0.2, 0.1, 0.05, 0.0), 2),
    "slip backward, re-stick, slip forward": ((0.365, 0.3, 0.05, 0.0), 3),
    "slip, re-stick, pivot over the top, slip": ((0.5, 0.4, 0.6, -4.0), 2),
    "slip, lift off, fly, touch down": ((0.5, 0.4, 0.8, -5.0), 1),
    "lift off at once": ((0.5, 0.4, 0.05, 5.0), 0),
}


@pytest.mark.parametrize("case", CASES)
def test_hybrid_run_matches_second_implementation(case):
    (mu_s, mu_k, theta0, theta_dot0), switches = CASES[case]
    t_ref, y_ref, rec = reference_run(mu_s, mu_k, theta0, theta_dot0)
    traj = _run(mu_s, mu_k, theta0, theta_dot0)
    rep = traj.report()
    assert rec["switches"] == switches
    assert int(traj.stats["num_switches"]) == switches
    assert rec["event"] == next(k for k, v in traj.event.items() if bool(v))
    assert np.isclose(traj.t_final, t_ref, rtol=tol(INTEGRATION))
    yf = traj.y_final
    got = [yf[k] for k in ("theta", "theta_dot", "tip_x", "tip_vx", "tip_y", "tip_vy",
                           "friction_work")]
    assert np.allclose(got, y_ref, rtol=1e-8, atol=1e-9), (np.array(got), y_ref)
    for key in ("slip_direction", "liftoff"):
        assert rep[key] == rec[key], key
    if rec["slip_angle"] is None:
        assert rep["slip_angle"] is None
    else:
        assert np.isclose(rep["slip_angle"], rec["slip_angle"], rtol=tol(INTEGRATION))
    assert rep["energy_rel_error"] < 1e-10


def test_liftoff_and_flight_are_ballistic():
    # At lift-off N = 0, i.e. L theta_dot^2 cos(theta) = 2 g; in flight theta_dot is constant and
    # the CM falls freely: the touchdown is where the tip (the lower end) reaches the floor again.
    traj = _run(0.5, 0.4, 0.8, -5.0, dense=True)
    assert traj.report()["liftoff"] and bool(traj.event["touchdown"])
    ts = np.linspace(0.0, float(traj.t_final), 4001)
    ys = {k: np.asarray(v) for k, v in traj.evaluate(ts).items()}
    # The switch: bracketed between samples, then narrowed on finer grids of the dense output.
    lo, hi = 0.0, float(traj.t_final)
    for _ in range(4):
        grid = np.linspace(lo, hi, 4001)
        j = int(np.argmax(np.asarray(traj.evaluate(grid)["mode"]) == FLIGHT))
        lo, hi = grid[j - 1], grid[j]
    y_l = {k: float(v[0]) for k, v in traj.evaluate(jnp.array([lo])).items()}
    assert np.isclose(L * y_l["theta_dot"] ** 2 * np.cos(y_l["theta"]), 2 * G, rtol=1e-8)
    t_l = lo
    cm_x0 = y_l["tip_x"] + L / 2 * np.sin(y_l["theta"])
    cm_y0 = L / 2 * np.cos(y_l["theta"])
    vx0 = y_l["tip_vx"] + L / 2 * np.cos(y_l["theta"]) * y_l["theta_dot"]
    vy0 = -L / 2 * np.sin(y_l["theta"]) * y_l["theta_dot"]

    def tip_height(t):
        dt = t - t_l
        theta = y_l["theta"] + y_l["theta_dot"] * dt
        return cm_y0 + vy0 * dt - G * dt**2 / 2 - L / 2 * abs(np.cos(theta))

    # The tip rises first (it leaves the floor), then comes down.
    grid = np.linspace(t_l + 1e-3, t_l + 2.0, 20001)
    heights = np.array([tip_height(t) for t in grid])
    j = int(np.argmax(heights < 0))
    t_down = brentq(tip_height, grid[j - 1], grid[j], xtol=1e-15)
    assert np.isclose(traj.t_final, t_down, rtol=1e-8)
    dt = t_down - t_l
    assert np.isclose(traj.y_final["tip_x"],
                      cm_x0 + vx0 * dt - L / 2 * np.sin(y_l["theta"] + y_l["theta_dot"] * dt),
                      rtol=1e-8)
    # Along the flight: a constant rate, and the CM on the parabola from the lift-off state.
    flight = ys["mode"] == FLIGHT
    dt = ts[flight] - t_l
    assert np.allclose(ys["theta_dot"][flight], y_l["theta_dot"], rtol=1e-8)
    cm_y = ys["tip_y"][flight] + L / 2 * np.cos(ys["theta"][flight])
    assert np.allclose(cm_y, cm_y0 + vy0 * dt - G * dt**2 / 2, rtol=0, atol=1e-8)
    # The tip rises more than a centimetre and never dips below the floor; the run ends with the
    # rod's lower end (by then its top) on the floor.
    assert np.all(ys["tip_y"] >= -1e-12) and np.max(ys["tip_y"]) > 0.01
    yf = {k: float(v) for k, v in traj.y_final.items()}
    assert abs(min(yf["tip_y"], yf["tip_y"] + L * np.cos(yf["theta"]))) < 1e-9


# -- energy bookkeeping ----------------------------------------------------------------------


def test_energy_balance_with_kinetic_friction():
    # The mechanical energy drops by the work of kinetic friction, the integral of
    # mu_k N |v_tip| dt, here by the trapezoidal rule over the dense output; while the tip sticks
    # the mechanical energy is conserved. A run that slides backward, re-sticks and slides forward.
    mu_k = 0.3
    traj = _run(0.365, mu_k, 0.05, 0.0, rtol=1e-11, atol=1e-12, dense=True)
    t = np.linspace(0.0, float(traj.t_final), 40001)
    y = traj.evaluate(t)
    out = jax.vmap(traj.scene.outputs)(jnp.asarray(t), y)
    mech = np.asarray(out["mechanical_energy"])
    power = np.where(np.asarray(y["mode"]) == SLIP,
                     mu_k * np.asarray(out["normal_force"]) * np.abs(np.asarray(y["tip_vx"])), 0)
    work = np.concatenate([[0.0], np.cumsum(0.5 * (power[1:] + power[:-1]) * np.diff(t))])
    scale = M * G * L / 2
    assert work[-1] > 0.005 * scale
    assert np.max(np.abs(mech[0] - mech - work)) < 1e-7 * scale
    assert np.isclose(float(traj.y_final["friction_work"]), trapezoid(power, t), rtol=1e-7)
    # Stick segments: the last one, between the re-stick and the forward slip.
    mode = np.asarray(y["mode"])
    stuck = (mode == STICK) & (t > t[np.argmax(mode == SLIP)])
    assert stuck.sum() > 100
    assert np.ptp(mech[stuck]) < 1e-9 * scale


# -- the command -------------------------------------------------------------------------------


def test_cli_keys_and_slip_onset(capsys):
    out = run_json(capsys, "run", "rough-floor-rod", "--set", "mu_s=0.3", "--set", "mu_k=0.2")
    assert out["body"] == "rough-floor-rod" and out["event"] == "flat"
    for key in ("impact_time", "impact_rate", "min_normal_force_over_weight",
                "energy_rel_error", "slip_angle", "slip_direction", "liftoff"):
        assert key in out, key
    theta0 = out["parameters"]["theta0"]
    assert np.isclose(out["slip_angle"], slip_onset(theta0, 0.3)[0], rtol=1e-9)
    assert out["slip_direction"] == "backward" and out["liftoff"] is False
    assert out["impact_time"] > 0 and out["energy_rel_error"] < 1e-8
    out = run_json(capsys, "run", "rough-floor-rod", "--set", "mu_s=0.6", "--set", "mu_k=0.5")
    assert out["slip_direction"] == "forward"
    assert np.isclose(out["slip_angle"], slip_onset(theta0, 0.6)[0], rtol=1e-9)


def test_cli_frictionless_and_liftoff(capsys):
    out = run_json(capsys, "run", "rough-floor-rod", "--set", "mu_s=0", "--set", "mu_k=0")
    theta0 = assert_frictionless_rod_summary(out)
    assert out["slip_direction"] == "backward" and np.isclose(out["slip_angle"], theta0)
    out = run_json(capsys, "run", "rough-floor-rod", "--set", "theta0=0.8",
                   "--set", "theta_dot0=-5")
    assert out["liftoff"] is True and out["event"] == "touchdown"
    assert out["impact_time"] is None and out["impact_rate"] is None
    assert out["min_normal_force_over_weight"] == 0.0


def test_cli_scene_listing_and_plot(capsys, tmp_path):
    status, out, _ = run_cli(capsys, "scenes")
    assert status == 0 and "rough-floor-rod" in out
    png = tmp_path / "rough.png"
    status, _, err = run_cli(capsys, "run", "rough-floor-rod", "--set", "mu_s=0.365",
                             "--set", "mu_k=0.3", "--plot", str(png))
    assert status == 0, err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# -- bad input ---------------------------------------------------------------------------------


@pytest.mark.parametrize("make, message", [
    (lambda: jd.RoughFloorRod(mu_s=0.3, mu_k=0.5),
     "mu_k=0.5: must be finite and within [0, mu_s] (kinetic friction cannot exceed static)"),
    (lambda: jd.RoughFloorRod(mu_s=-0.1, mu_k=0.0), "mu_s=-0.1: must be finite and >= 0"),
    (lambda: jd.RoughFloorRod(mu_s=float("nan")), "mu_s=nan: must be finite and >= 0"),
    (lambda: jd.RoughFloorRod(mu_k=-1.0), "mu_k=-1: must be finite and within [0, mu_s]"),
    (lambda: jd.RoughFloorRod(length=0.0), "length=0: must be positive and finite"),
    (lambda: jd.RoughFloorRod(mu_s="rough"), "mu_s='rough': expected a number"),
    (lambda: _scene(0.5, 0.4).state(theta=2.0), "theta=2: must be finite and within"),
    (lambda: _scene(0.5, 0.4).state(theta=0.1, tip=1.0), "unknown state variables ['tip']"),
    (lambda: jd.Scene(jd.RoughFloorRod(), attitude=True), "has no 3-D attitude"),
    (lambda: jd.Scene(jd.RoughFloorRod(), (jd.Rotor([0.0, 0.0, 1.0]),)),
     "cannot act on a rough-floor-rod"),
    (lambda: jd.load_scene("rough-floor-rod", {"mu": 0.3}), "unknown parameter 'mu'"),
])
def test_bad_input_fails_early(make, message):
    with pytest.raises(jd.ParameterError) as info:
        make()
    assert message in str(info.value)


def test_moving_tip_fails_at_run_time():
    scene = _scene(0.5, 0.4)
    y0 = scene.state(theta=0.05)
    moving = {**y0, "tip_vx": jnp.ones_like(y0["tip_vx"])}
    with pytest.raises(jd.ParameterError, match="the tip of a rough-floor rod must start "
                                                "at rest"):
        jd.simulate(scene, moving, 5.0, **TIGHT)
    # Known only inside a trace: the same check, at run time.
    run = jax.jit(lambda y: jd.simulate(scene, y, 5.0, **TIGHT).t_final)
    with pytest.raises(RuntimeError, match="the tip of a rough-floor rod must start at rest"):
        run(moving)


def test_cli_bad_input(capsys):
    status, out, err = run_cli(capsys, "run", "rough-floor-rod", "--set", "mu_k=0.9")
    assert status == 2 and out == ""
    assert err.strip() == ("jaxdyn: error: mu_k=0.9: must be finite and within [0, mu_s] "
                           "(kinetic friction cannot exceed static)")


def test_ensemble_engine_switches_per_trajectory(monkeypatch):
    # The rough-floor rod in the default ensemble mode (the batch engine: each trajectory
    # locates its own switches) against `mode="vmap"` (simulate's driver under `jax.vmap`) and
    # against each member's single run: every case of CASES in one batch, with its own friction.
    # The engine switches two rows at a time here, so that rows switching in the same step
    # are gathered in several passes.
    monkeypatch.setattr(_batch_solve, "SWITCH_ROWS", 2)
    cases = list(CASES.values())
    (mu_s, mu_k, theta0, theta_dot0) = (np.array(x) for x in zip(*(c[0] for c in cases)))
    scene = _scene(0.5, 0.4)
    y0 = scene.state(theta=0.1)
    y0 = {k: np.repeat(np.asarray(v)[None], len(cases), axis=0) for k, v in y0.items()}
    y0.update(theta=theta0, theta_dot=theta_dot0)
    ts = np.linspace(0.0, 1.5, 7)

    def observe(traj):
        return {**{f"y.{k}": v for k, v in traj.y_final.items()}, "t_final": traj.t_final,
                "switches": traj.stats["num_switches"], "theta_ts": traj.ys["theta"],
                **{f"event.{k}": v for k, v in traj.event.items()}}

    options = dict(parameters={"mu_s": mu_s, "mu_k": mu_k}, ts=ts, observe=observe,
                   rtol=1e-10)
    engine = jd.ensemble(scene, y0, 5.0, **options)
    vmap = jd.ensemble(scene, y0, 5.0, mode="vmap", **options)
    assert engine.mode == "adaptive"
    assert np.array_equal(engine.status, vmap.status) and engine.completed == len(cases)
    assert list(engine.values["switches"]) == [c[1] for c in cases]
    assert np.array_equal(engine.values["switches"], vmap.values["switches"])
    for k, v in vmap.values.items():
        scale = np.max(np.abs(v[np.isfinite(v)]), initial=1.0)
        assert np.allclose(engine.values[k], v, rtol=1e-8, atol=1e-8 * scale,
                           equal_nan=True), k
    for i, (params, _) in enumerate(cases):
        single = _run(*params, ts=ts, rtol=1e-10, atol=None)
        assert np.isclose(float(single.t_final), vmap.values["t_final"][i], rtol=1e-12)
        assert int(single.stats["num_switches"]) == vmap.values["switches"][i]
        assert np.allclose(single.ys["theta"], vmap.values["theta_ts"][i], rtol=1e-12)
