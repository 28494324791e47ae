"""Relative equilibria, separatrices and critical rotor momenta, against independent routes:
closed forms for the torque-free body, the gyrostat's equilibrium condition solved as a
polynomial with numpy, stability seen in simulations, and the analytic stability condition of a
spin with a rotor along its axis."""


import jax.numpy as jnp
import numpy as np
import pytest
import test_cli
from helpers import INTEGRATION, ROUNDOFF, tol
from numpy.polynomial import polynomial as P
from scipy.optimize import brentq

import jaxdyn as jd

# The equilibria from numpy's polynomial roots (polished by Newton steps in numpy): a few digits
# short of round-off, as the rates depend on the root through 1 / (mu - I_i).
SEXTIC = 1e-10
# A perturbation of size DELTA off an equilibrium: a saddle's grows past GROWN * DELTA within
# 12 e-folds, a centre's stays below BOUNDED * DELTA (its polhode is a small ellipse whose
# aspect ratio stays well under BOUNDED for these bodies).
DELTA, GROWN, BOUNDED = 1e-7, 1e3, 30.0

RNG_SEED = 20240611


def random_moments(rng):
    # Moments in [1, 1.9): the triangle inequality always holds; random order.
    return rng.uniform(1.0, 1.9, size=3)


def scene_of(inertia, rotor=None):
    body = jd.RigidBody(jnp.asarray(inertia))
    return jd.Scene(body, () if rotor is None else (jd.Rotor(jnp.asarray(rotor)),))


# -- torque-free body: closed form ---------------------------------------------------------


def torque_free_cases():
    rng = np.random.default_rng(RNG_SEED)
    cases = [([1.0, 2.0, 3.0], 1.0), ([3.0, 1.0, 2.5], 2.0)]
    cases += [(random_moments(rng).tolist(), float(rng.uniform(0.5, 3.0))) for _ in range(3)]
    return cases


@pytest.mark.parametrize("inertia, momentum", torque_free_cases())
def test_torque_free_equilibria_closed_form(inertia, momentum):
    inertia = np.asarray(inertia)
    eq = jd.find_equilibria(scene_of(inertia), momentum)
    assert len(eq) == 6 and eq.degenerate.shape == (0, 3)
    order = np.argsort(inertia)
    minor, mid, major = order
    omega = np.asarray(eq.omega)
    rtol = tol(ROUNDOFF)
    for k in range(3):
        # +- H / I_k along each principal axis, a saddle on the intermediate axis only.
        rate = momentum / inertia[k]
        on_axis = np.flatnonzero(np.isclose(np.abs(omega[:, k]), rate, rtol=rtol))
        assert len(on_axis) == 2 and np.allclose(omega[on_axis].sum(axis=0), 0, atol=rtol)
        others = [i for i in range(3) if i != k]
        assert np.allclose(omega[on_axis][:, others], 0, atol=rtol * rate)
        kinds = {eq.kind[i] for i in on_axis}
        assert kinds == ({"saddle"} if k == mid else {"center"})
        # Linearised about a spin at rate W about k:
        # lambda^2 = W^2 (I_k - I_i)(I_j - I_k) / (I_i I_j).
        i, j = others
        lam2 = rate**2 * (inertia[k] - inertia[i]) * (inertia[j] - inertia[k]) / (
            inertia[i] * inertia[j])
        for n in on_axis:
            ev = np.asarray(eq.eigenvalues[n])
            assert np.allclose(np.sort_complex(ev ** 2), [lam2, lam2], rtol=1e-10, atol=1e-14)
            if k == mid:  # the saddle's growth rate lambda
                assert np.isclose(eq.growth_rate[n], np.sqrt(lam2), rtol=rtol)
    energies = np.asarray(eq.energy)
    assert np.allclose(energies, 0.5 * np.sum(inertia * omega**2, axis=1), rtol=rtol)
    assert np.allclose(eq.separatrix_energies, [momentum**2 / (2 * inertia[mid])], rtol=rtol)
    assert {minor, major} == {int(np.argmax(np.abs(omega[n]))) for n in np.flatnonzero(
        ~eq.is_saddle)}


def test_traced_separatrix_of_the_torque_free_body():
    inertia = np.array([2.5, 1.0, 1.8])  # intermediate axis is the third
    momentum = 1.7
    scene = scene_of(inertia)
    eq = jd.find_equilibria(scene, momentum)
    sep = jd.trace_separatrices(scene, eq, num=101)
    assert len(sep) == 4 and sep.omega.shape == (4, 101, 3)
    assert bool(np.all(sep.returned))
    # Heteroclinic: each branch leaves one saddle and arrives at the other.
    assert np.all(np.asarray(sep.end_saddle) != np.asarray(sep.saddle))
    w = np.asarray(sep.omega)
    scale = momentum**2 / inertia.min()  # size of H^2 - 2 T I_2
    cond = np.asarray(jd.separatrix_condition(jnp.asarray(inertia), jnp.asarray(w)))
    assert np.max(np.abs(cond)) < tol(INTEGRATION) * scale
    assert np.allclose(np.linalg.norm(inertia * w, axis=-1), momentum, rtol=tol(INTEGRATION))
    assert np.allclose(np.asarray(sep.angular_momentum), inertia * w, rtol=tol(ROUNDOFF))
    assert np.allclose(sep.energy, momentum**2 / (2 * 1.8), rtol=tol(ROUNDOFF))
    # Each branch spans the separatrix from saddle to saddle: through the plane h_3 = 0 with the
    # largest |h_1| that the separatrix allows (its widest point).
    h = inertia * w
    i1, i2, i3 = 1.0, 1.8, 2.5
    widest = momentum * np.sqrt((1 - i2 / i3) / (i2 / i1 - i2 / i3))
    assert np.allclose(np.max(np.abs(h[..., 1]), axis=1), widest, rtol=1e-3)


def test_equal_moments_are_reported_not_failed():
    eq = jd.find_equilibria(scene_of([1.0, 2.0, 2.0]), 1.0)
    assert eq.continuum and eq.degenerate.shape[0] > 2
    assert len(eq.separatrix_energies) == 0 and not np.any(eq.is_saddle)
    assert np.allclose(np.abs(np.asarray(eq.omega)[:, 0]), 1.0, rtol=tol(ROUNDOFF))
    # The degenerate ones form the circle h_1 = 0 on the sphere.
    d = np.asarray(eq.degenerate)
    assert np.allclose(d[:, 0], 0, atol=1e-12)
    assert np.allclose(np.linalg.norm(2.0 * d, axis=1), 1.0, rtol=tol(ROUNDOFF))
    assert len(jd.trace_separatrices(scene_of([1.0, 2.0, 2.0]), eq)) == 0


def test_full_tensor_body_in_float32():
    # A body whose frame is not principal, in float32 (one compilation for both checks): the
    # finder uses only the scene's vector field and invariants, so it finds the spins about the
    # rotated principal axes, and it keeps the dtype.
    moments = np.array([1.3, 2.1, 2.9])
    axis = np.array([0.3, -0.5, 0.8]) / np.sqrt(0.98)
    q = jd.quat_from_axis_angle(jnp.asarray(axis), 0.7)
    rot = np.asarray(jd.quat_to_dcm(q))
    tensor = (rot @ np.diag(moments) @ rot.T).astype(np.float32)
    eq = jd.find_equilibria(scene_of(tensor), np.float32(1.5))
    assert eq.omega.dtype == jnp.float32 and eq.energy.dtype == jnp.float32
    assert eq.eigenvalues.dtype == jnp.complex64
    assert len(eq) == 6 and eq.kind.count("saddle") == 2
    rtol = 10 * tol(ROUNDOFF, jnp.float32)  # the tensor itself is rounded to float32
    principal = np.asarray(eq.omega) @ rot  # rates in the principal frame
    assert np.allclose(np.sort(np.abs(principal).max(axis=1)),
                       np.sort(np.repeat(1.5 / moments, 2)), rtol=rtol)
    assert {int(np.argmax(np.abs(w))) for w in principal[eq.is_saddle]} == {1}
    assert np.allclose(eq.separatrix_energies, [1.5**2 / (2 * 2.1)], rtol=rtol)
    roots = jd.critical_rotor_momenta(moments.astype(np.float32), 1, np.float32(1.0))
    assert roots.dtype == jnp.float32
    assert np.allclose(roots, [1.3 - 2.1, 2.9 - 2.1], rtol=rtol)


# -- gyrostat: independent routes ---------------------------------------------------------


def sextic_equilibria(inertia, h, momentum):
    """Equilibria of `I w_dot = (I w + h) x w` on `|I w + h| = H`, for `h` with no zero
    component: `I w + h = mu w`, so `L_i = mu h_i / (mu - I_i)` and `sum L_i^2 = H^2` is a
    degree-6 polynomial in `mu`."""
    lin = [np.array([-m, 1.0]) for m in inertia]
    sq = [P.polymul(a, a) for a in lin]
    poly = -momentum**2 * P.polymul(P.polymul(sq[0], sq[1]), sq[2])
    for i in range(3):
        others = [sq[j] for j in range(3) if j != i]
        poly = P.polyadd(poly, P.polymul([0.0, 0.0, h[i] ** 2], P.polymul(*others)))
    roots = P.polyroots(poly)
    real = roots[np.abs(roots.imag) < 1e-9 * np.abs(roots)].real
    # Keep only well-separated, clearly real roots (no case near a bifurcation).
    ambiguous = np.any((np.abs(roots.imag) > 1e-9 * np.abs(roots))
                       & (np.abs(roots.imag) < 1e-3 * np.abs(roots)))
    close = real.size > 1 and np.min(np.diff(np.sort(real))) < 1e-3
    for _ in range(3):  # polish each root by Newton on sum_i L_i(mu)^2 - H^2
        total = real[:, None] * h / (real[:, None] - inertia)
        slope = -inertia * h / (real[:, None] - inertia) ** 2
        real = real - (np.sum(total**2, axis=1) - momentum**2) / np.sum(2 * total * slope, axis=1)
    return np.array([h / (mu - inertia) for mu in real]), bool(ambiguous or close)


def gyrostat_cases(n=3):
    rng = np.random.default_rng(RNG_SEED + 1)
    cases = []
    while len(cases) < n:
        inertia = random_moments(rng)
        h = rng.normal(size=3) * rng.uniform(0.05, 0.6)
        momentum = float(rng.uniform(0.8, 2.0))
        _, bad = sextic_equilibria(inertia, h, momentum)
        if not bad:
            cases.append((inertia, h, momentum))
    return cases


@pytest.fixture(scope="module")
def gyrostats():
    out = []
    for inertia, h, momentum in gyrostat_cases():
        eq = jd.find_equilibria(scene_of(inertia, h), momentum)
        out.append((inertia, h, momentum, eq))
    return out


def test_gyrostat_equilibria_against_the_polynomial(gyrostats):
    for inertia, h, momentum, eq in gyrostats:
        omega = np.asarray(eq.omega)
        expected, _ = sextic_equilibria(inertia, h, momentum)
        assert len(eq) == len(expected) and eq.degenerate.shape == (0, 3)
        for w in expected:
            assert np.min(np.linalg.norm(omega - w, axis=1)) < SEXTIC * np.linalg.norm(w)
        # Directly: I w + h is parallel to w, and on the sphere.
        total = inertia * omega + h
        assert np.allclose(np.cross(total, omega), 0, atol=tol(ROUNDOFF))
        assert np.allclose(np.linalg.norm(total, axis=1), momentum, rtol=tol(ROUNDOFF))
        assert np.allclose(eq.energy, 0.5 * np.sum(inertia * omega**2, axis=1),
                           rtol=tol(ROUNDOFF))


def test_gyrostat_stability_seen_in_simulation(gyrostats):
    rng = np.random.default_rng(RNG_SEED + 2)
    for inertia, h, momentum, eq in gyrostats:
        scene = scene_of(inertia, h)
        for w, kind, ev in zip(np.asarray(eq.omega), eq.kind, np.asarray(eq.eigenvalues)):
            # A random direction tangent to the momentum sphere (normal: I (I w + h)).
            normal = inertia * (inertia * w + h)
            d = rng.normal(size=3)
            d -= d @ normal / (normal @ normal) * normal
            size = DELTA * np.linalg.norm(w)
            w0 = w + size * d / np.linalg.norm(d)
            rate = float(np.max(np.abs(ev)))
            t1 = 12.0 / rate if kind == "saddle" else 4 * 2 * np.pi / rate
            # Same saved times and options as trace_separatrices: one compilation for both.
            traj = jd.simulate(scene, scene.state(omega=w0), t1,
                               ts=jnp.linspace(0.0, t1, 4001), rtol=1e-11, atol=1e-13, dense=True)
            dev = np.max(np.linalg.norm(np.asarray(traj.omega) - w, axis=1)) / size
            assert (dev > GROWN) if kind == "saddle" else (dev < BOUNDED), (kind, dev)


def rotor_on_axis_3_count(inertia, h, momentum):
    """Equilibria of a rotor `h e_3` on `|H| = momentum`, counted by hand: the two spins about
    axis 3, and for i = 1, 2 the pair with `mu = I_i`, `L_3 = I_i h / (I_i - I_3)`, which exists
    while `|L_3| < H`. A spin about axis 3 with `L_3 = +-H` is stable where
    `(L_3 - I_1 w_3)(L_3 - I_2 w_3) > 0`."""
    n = 2 + sum(2 for i in (0, 1) if abs(inertia[i] * h / (inertia[i] - inertia[2])) < momentum)
    stable = {}
    for sign in (1, -1):
        total = sign * momentum
        w3 = (total - h) / inertia[2]
        stable[sign] = (total - inertia[0] * w3) * (total - inertia[1] * w3) > 0
    return n, stable


@pytest.mark.parametrize("h", [0.3, 0.45, 0.7, 2.5])
def test_gyrostat_saddles_move_and_vanish(h):
    inertia, momentum = np.array([1.0, 2.0, 3.0]), 1.0
    scene = scene_of(inertia, [0.0, 0.0, h])
    eq = jd.find_equilibria(scene, momentum)
    n, stable = rotor_on_axis_3_count(inertia, h, momentum)
    assert len(eq) == n
    omega = np.asarray(eq.omega)
    # Directly: I w + h is parallel to w, and on the sphere.
    total = inertia * omega + [0.0, 0.0, h]
    assert np.allclose(np.cross(total, omega), 0, atol=tol(ROUNDOFF))
    assert np.allclose(np.linalg.norm(total, axis=1), momentum, rtol=tol(ROUNDOFF))
    for sign in (1, -1):
        w3 = (sign * momentum - h) / inertia[2]
        k = np.flatnonzero(np.linalg.norm(omega - [0, 0, w3], axis=1) < 1e-10)
        assert len(k) == 1
        assert eq.kind[k[0]] == ("center" if stable[sign] else "saddle")
        # Linearised about the spin: lambda^2 = -(L_3 - I_1 w_3)(L_3 - I_2 w_3) / (I_1 I_2).
        total3 = sign * momentum
        lam2 = -(total3 - inertia[0] * w3) * (total3 - inertia[1] * w3) / (inertia[0] * inertia[1])
        ev = np.asarray(eq.eigenvalues[k[0]])
        assert np.allclose(ev**2, lam2, rtol=1e-10, atol=1e-14)
    # Separatrices: every branch comes back to a saddle, on the sphere and at its energy.
    sep = jd.trace_separatrices(scene, eq, num=64)
    assert len(sep) == 2 * int(np.sum(eq.is_saddle))
    if len(sep):
        assert bool(np.all(sep.returned))
        w = np.asarray(sep.omega)
        energy = 0.5 * np.sum(inertia * w**2, axis=-1)
        assert np.allclose(energy, np.asarray(sep.energy)[:, None], rtol=tol(INTEGRATION))
        total = np.linalg.norm(inertia * w + [0.0, 0.0, h], axis=-1)
        assert np.allclose(total, momentum, rtol=tol(INTEGRATION))


def _crossings_of_h2(scene, omega0, t1):
    """Times of the zero crossings of h_2 = I_2 omega_2 (the rotor is along e_3) after t = 0, on
    the dense output (brentq)."""
    traj = jd.simulate(scene, scene.state(omega=jnp.asarray(omega0)), t1, rtol=1e-12,
                       atol=1e-14, dense=True, max_steps=100_000)

    def h2(t):
        return float(traj.evaluate(jnp.array([t]))["omega"][0, 1])

    grid = np.linspace(0.0, t1, 4001)[1:]
    values = np.asarray(traj.evaluate(jnp.asarray(grid))["omega"][:, 1])
    i = np.flatnonzero(np.sign(values[1:]) != np.sign(values[:-1]))
    return np.array([brentq(h2, grid[k], grid[k + 1], xtol=1e-13, rtol=1e-15) for k in i])


def test_gyrostat_period_diverges_with_one_log_per_saddle_passed():
    # Rotor h e_3 with h = 0.7 (I = (1, 2, 3), H = 1): one saddle, the spin about -e_3, whose
    # separatrix is a figure of eight around the two centres near the minor axis. Near it the
    # period grows like (n / lambda) ln(1 / |T - T_s|), n the saddle passages per period: n = 1
    # inside a lobe (T > T_s), n = 2 outside both (T < T_s). Starts on the h_1 h_3 great circle
    # (h_2 = 0), which every orbit crosses twice per period (the flow is reversible under
    # h_2 -> -h_2), so the second crossing after the start ends one period; lambda from the
    # closed form of the linearisation.
    inertia, momentum, h = np.array([1.0, 2.0, 3.0]), 1.0, 0.7
    scene = scene_of(inertia, [0.0, 0.0, h])
    w3 = (-momentum - h) / inertia[2]
    lam = np.sqrt(-(-momentum - inertia[0] * w3) * (-momentum - inertia[1] * w3)
                  / (inertia[0] * inertia[1]))
    t_sep = 0.5 * inertia[2] * w3**2

    def energy(c):  # h = H (sqrt(1 - c^2), 0, c)
        return 0.5 * ((1 - c**2) * momentum**2 / inertia[0] + (momentum * c - h) ** 2 / inertia[2])

    # The lobe's centre has h_3 = I_1 h / (I_1 - I_3); between it and +e_3 the energy is monotonic.
    c_lobe = inertia[0] * h / (inertia[0] - inertia[2])
    for side, n in ((-1, 2), (1, 1)):
        periods = []
        for offset in (1e-5, 1e-6):
            target = t_sep * (1 + side * offset)
            c = brentq(lambda c, target=target: energy(c) - target, c_lobe, 1.0, xtol=1e-15,
                       rtol=1e-15)
            omega0 = (momentum * np.array([np.sqrt(1 - c**2), 0.0, c]) - [0.0, 0.0, h]) / inertia
            t1 = (n * np.log(1 / offset) + 40.0) / lam
            crossings = _crossings_of_h2(scene, omega0, t1)
            periods.append(crossings[1])
        slope = (periods[1] - periods[0]) / np.log(10)
        assert np.isclose(slope, n / lam, rtol=1e-3), (side, slope, n / lam)


# -- critical rotor momenta ----------------------------------------------------------------


def critical_cases(n=6):
    rng = np.random.default_rng(RNG_SEED + 3)
    return [(random_moments(rng), int(rng.integers(3)),
             float(rng.choice([-1, 1]) * rng.uniform(0.2, 5.0))) for _ in range(n)]


@pytest.mark.parametrize("inertia, axis, rate", critical_cases())
def test_critical_rotor_momenta_against_the_stability_condition(inertia, axis, rate):
    roots = np.asarray(jd.critical_rotor_momenta(jnp.asarray(inertia), axis, rate))
    i, j = [k for k in range(3) if k != axis]
    expected = np.sort([(inertia[i] - inertia[axis]) * rate, (inertia[j] - inertia[axis]) * rate])
    assert np.allclose(roots, expected, rtol=1e-10, atol=1e-12 * abs(rate))

    def stable(hr):  # the analytic condition
        total = inertia[axis] * rate + hr
        return (total - inertia[i] * rate) * (total - inertia[j] * rate) > 0

    eps = 1e-3 * abs(rate)
    for r in roots:
        assert stable(r - eps) != stable(r + eps)


@pytest.mark.parametrize("h", [-1.5, -0.8, 0.0, 0.6, 1.3])
def test_rotor_between_the_critical_momenta_leaves_the_spin_unstable(h):
    # A spin at 1 rad/s about the intermediate axis of I = (1, 2, 3), with a rotor along it and a
    # nudge of 1e-6 rad/s: between the critical rotor momenta it grows by orders of magnitude
    # within 60 s; outside them it stays within a small multiple of the nudge.
    inertia, rate, nudge = jnp.array([1.0, 2.0, 3.0]), 1.0, 1e-6
    low, high = np.asarray(jd.critical_rotor_momenta(inertia, 1, rate))
    scene = scene_of(inertia, [0.0, h, 0.0])
    traj = jd.simulate(scene, scene.state(omega=jnp.array([nudge, rate, 0.0])), 60.0,
                       ts=jnp.linspace(0.0, 60.0, 601), rtol=1e-10, atol=1e-12)
    growth = np.max(np.abs(np.asarray(traj.omega)[:, [0, 2]])) / nudge
    if low < h < high:
        assert growth > 1e3, growth
    else:
        assert growth < 10, growth


def test_critical_rotor_momentum_double_root():
    # Equal transverse moments: lambda^2 touches zero without changing sign; one root.
    roots = np.asarray(jd.critical_rotor_momenta(jnp.array([2.0, 2.0, 3.0]), 2, 1.5))
    assert np.allclose(roots, [(2.0 - 3.0) * 1.5], rtol=1e-6)


# -- bad input -----------------------------------------------------------------------------


def test_scenes_that_are_not_conservative_rotations_are_refused():
    body = jd.RigidBody(jnp.array([1.0, 2.0, 3.0]))
    with pytest.raises(jd.ParameterError, match="integrates attitude"):
        jd.find_equilibria(jd.Scene(body, attitude=True))
    with pytest.raises(jd.ParameterError, match="conservative"):
        jd.find_equilibria(jd.Scene(body, (jd.ExternalTorque(jnp.array([0.0, 0.0, 1.0])),)))
    with pytest.raises(jd.ParameterError, match="body rates"):
        jd.find_equilibria(jd.Scene(jd.FallingRod(length=1.0)))
    with pytest.raises(jd.ParameterError, match="momentum=-1: must be positive"):
        jd.find_equilibria(jd.Scene(body), -1.0)
    with pytest.raises(jd.ParameterError, match="spin_axis=3"):
        jd.critical_rotor_momenta(jnp.array([1.0, 2.0, 3.0]), 3, 1.0)
    with pytest.raises(jd.ParameterError, match="rate=0"):
        jd.critical_rotor_momenta(jnp.array([1.0, 2.0, 3.0]), 1, 0.0)
    with pytest.raises(jd.ParameterError, match="triangle inequality"):
        jd.critical_rotor_momenta(jnp.array([1.0, 2.0, 10.0]), 1, 1.0)


# -- the command ---------------------------------------------------------------------------


def run_cli(capsys, *argv):
    return test_cli.run_cli(capsys, "separatrix", *argv)


def run_json(capsys, *argv):
    return test_cli.run_json(capsys, "separatrix", *argv)


def test_cli_torque_free(capsys):
    rng = np.random.default_rng(RNG_SEED + 4)
    inertia = random_moments(rng)
    text = ",".join(f"{m:.6f}" for m in inertia)
    inertia = np.array([float(t) for t in text.split(",")])
    for extra, momentum in (([], 1.0), (["--momentum", "2.5"], 2.5)):
        out = run_json(capsys, "--inertia", text, *extra)
        mid = np.argsort(inertia)[1]
        assert np.allclose(out["separatrix_energies"], [momentum**2 / (2 * inertia[mid])],
                           rtol=tol(ROUNDOFF))
        eqs = out["equilibria"]
        assert len(eqs) == 6 and [e["kind"] for e in eqs].count("saddle") == 2
        for e in eqs:
            w = np.array(e["omega"])
            assert np.isclose(np.linalg.norm(inertia * w), momentum, rtol=tol(ROUNDOFF))
            assert np.isclose(e["energy"], 0.5 * np.sum(inertia * w**2), rtol=tol(ROUNDOFF))
            k = int(np.argmax(np.abs(w)))
            assert (e["kind"] == "saddle") == (k == mid)


def test_cli_gyrostat(capsys):
    inertia, h, momentum = gyrostat_cases(4)[-1]
    out = run_json(capsys, "--inertia", ",".join(map(repr, inertia.tolist())),
                   "--rotor", ",".join(map(repr, h.tolist())), "--momentum", repr(momentum))
    expected, _ = sextic_equilibria(inertia, h, momentum)
    omega = np.array([e["omega"] for e in out["equilibria"]])
    assert omega.shape == expected.shape
    for w in expected:
        assert np.min(np.linalg.norm(omega - w, axis=1)) < SEXTIC * np.linalg.norm(w)
    saddle_energies = sorted({round(e["energy"], 12) for e in out["equilibria"]
                              if e["kind"] == "saddle"})
    assert np.allclose(out["separatrix_energies"], saddle_energies, rtol=1e-10)


def test_cli_critical_rotor(capsys):
    rng = np.random.default_rng(RNG_SEED + 5)
    inertia = np.round(random_moments(rng), 4)
    axis, rate = int(rng.integers(1, 4)), float(np.round(rng.uniform(-3, 3), 4))
    out = run_json(capsys, "--inertia", ",".join(map(str, inertia)), "--spin-axis", str(axis),
                   "--rate", str(rate), "--critical-rotor")
    k = axis - 1
    expected = sorted((inertia[i] - inertia[k]) * rate for i in range(3) if i != k)
    assert np.allclose(out["critical_rotor_momenta"], expected, rtol=1e-10)


def test_cli_equal_moments_says_so(capsys):
    out = run_json(capsys, "--inertia", "2,1,2")
    assert out["separatrix_energies"] == [] and out["degenerate_equilibria"] > 0
    assert "continuum" in out["note"]


def test_cli_text_output(capsys):
    status, out, err = run_cli(capsys, "--inertia", "1,2,3")
    assert status == 0 and "separatrix_energies: [0.25]" in out


BAD = [
    (["--inertia", "1,2,10"], "triangle inequality"),
    (["--inertia", "1,2"], "--inertia='1,2': expected 3 comma-separated numbers"),
    (["--inertia", "1,a,3"], "--inertia='1,a,3': expected 3 comma-separated numbers"),
    (["--inertia", "1,2,-3"], "must be positive"),
    (["--inertia", "1,2,3", "--rotor", "1,2"], "--rotor='1,2': expected 3"),
    (["--inertia", "1,2,3", "--rotor", "1,inf,2"], "expected finite numbers"),
    (["--inertia", "1,2,3", "--momentum", "0"], "--momentum=0: must be positive"),
    (["--inertia", "1,2,3", "--momentum", "x"], "--momentum='x': expected a number"),
    (["--inertia", "1,2,3", "--spin-axis", "4", "--rate", "1", "--critical-rotor"],
     "--spin-axis='4': must be 1, 2 or 3"),
    (["--inertia", "1,2,3", "--spin-axis", "2", "--critical-rotor"], "--rate is required"),
    (["--inertia", "1,2,3", "--rate", "1", "--critical-rotor"], "--spin-axis is required"),
    (["--inertia", "1,2,3", "--spin-axis", "2", "--rate", "0", "--critical-rotor"],
     "--rate=0: must be nonzero"),
    (["--inertia", "1,2,3", "--spin-axis", "2", "--rate", "1,2", "--critical-rotor"],
     "--rate='1,2': expected a number"),
    (["--inertia", "1,2,3", "--rotor", "0,0,1", "--spin-axis", "2", "--rate", "1",
      "--critical-rotor"], "--rotor: not used with --critical-rotor"),
    (["--inertia", "1,2,3", "--rate", "1"], "--rate: only used with --critical-rotor"),
    (["--rotor", "0,0,1"], "the following arguments are required: --inertia"),
]


@pytest.mark.parametrize("argv, expected", BAD, ids=[" ".join(a) for a, _ in BAD])
def test_cli_bad_input_exits_2_with_one_line(capsys, argv, expected):
    status, out, err = run_cli(capsys, *argv)
    assert status == 2 and out == ""
    assert expected in err, err
    assert len(err.strip().splitlines()) == 1
