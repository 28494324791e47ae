"""Identification: parameters recovered from synthetic data made by an independent integrator.

Reference data come from SciPy's DOP853 at rtol=1e-12 (never from jaxdyn), with Gaussian
noise. Cases are seeded random bodies and rods that were not used while developing the fitter.
Every fit here uses 64 samples (one padded length) and the same scene structures as the command
line, so that all of them share a handful of compilations.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import FINITE_DIFF, ROUNDOFF, central_difference, tol
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

import jaxdyn as jd
from jaxdyn._identify import _fit

SAMPLES = 64


# -- independent data ---------------------------------------------------------------------------


def random_body(rng):
    """A random physical body (distinct moments) and unit rates away from the separatrix,
    where the motion is so sensitive that no fit over many periods is well posed."""
    while True:
        moments = rng.uniform(0.3, 1.0, 3)
        m = np.sort(moments)
        if m[2] > m[0] + m[1] or m[0] > 0.85 * m[1] or m[1] > 0.85 * m[2]:
            continue
        axes = Rotation.random(random_state=rng).as_matrix()
        w0 = rng.normal(size=3)
        w0 /= np.linalg.norm(w0)
        wp = axes.T @ w0
        two_t, h2 = np.sum(moments * wp**2), np.sum((moments * wp) ** 2)
        if abs(h2 - two_t * np.median(moments)) > 0.1 * h2:
            return axes @ np.diag(moments) @ axes.T, w0


def euler_rates(tensor, w0, ts, rotor=None):
    """Rates from `I w' = (I w + h) x w` by DOP853 at rtol=1e-12."""
    h = np.zeros(3) if rotor is None else np.asarray(rotor)
    inv = np.linalg.inv(tensor)
    sol = solve_ivp(lambda t, w: inv @ np.cross(tensor @ w + h, w), (ts[0], ts[-1]), w0,
                    t_eval=ts, method="DOP853", rtol=1e-12, atol=1e-12)
    return sol.y.T


def rod_field(length, g):
    """The rod's equation of motion (physics.md, section 1), written out in NumPy."""

    def f(t, y):
        th, w = y
        s, c = np.sin(th), np.cos(th)
        return [w, 3 * s * (2 * g - length * w**2 * c) / (length * (1 + 3 * s**2))]

    return f


def rod_angles(length, g, theta0, theta_dot0, ts):
    sol = solve_ivp(rod_field(length, g), (ts[0], ts[-1]), [theta0, theta_dot0], t_eval=ts,
                    method="DOP853", rtol=1e-12, atol=1e-12)
    return sol.y[0]


def rod_case(rng, g=9.81):
    """A random rod, sampled until 90 % of its fall time (found by a SciPy event)."""
    length = rng.uniform(0.5, 2.0)
    theta0, theta_dot0 = rng.uniform(0.05, 0.3), rng.uniform(0.0, 0.3)

    def flat(t, y):
        return np.cos(y[0])

    flat.terminal = True
    fall = solve_ivp(rod_field(length, g), (0.0, 100.0), [theta0, theta_dot0], events=flat,
                     rtol=1e-10, atol=1e-12).t_events[0][0]
    ts = np.linspace(0.0, 0.9 * fall, SAMPLES)
    return length, theta0, theta_dot0, ts, rod_angles(length, g, theta0, theta_dot0, ts)


def sorted_axes(tensor):
    """Ascending moments, and axes under jaxdyn's documented sign convention (each column's
    largest component positive, then the last column flipped for a proper rotation),
    written out here in NumPy."""
    moments, axes = np.linalg.eigh(tensor)
    idx = np.argmax(np.abs(axes), axis=0)
    axes = axes * np.sign(axes[idx, np.arange(3)])
    axes[:, 2] *= np.sign(np.linalg.det(axes))
    return moments, axes


FIT_BODY = dict(parameters={"inertia": jd.ValidInertia()}, initial=["omega"])
# The scene structure that `jaxdyn fit --scene torque-free` builds (principal moments given).
GUESS = [0.6, 0.8, 1.0]


# -- the parameterisation -----------------------------------------------------------------------


def test_valid_inertia_is_physical_for_any_vector():
    m = jd.ValidInertia()
    us = jax.random.normal(jax.random.PRNGKey(3), (200, 6)) * 3.0
    tensors = np.asarray(jax.jit(jax.vmap(m))(us))
    assert np.allclose(tensors, np.swapaxes(tensors, 1, 2), atol=1e-14)
    moments = np.linalg.eigvalsh(tensors)
    assert np.all(moments > 0)
    assert np.all(moments[:, 2] <= moments[:, 0] + moments[:, 1])


def test_valid_inertia_round_trip():
    rng = np.random.default_rng(11)
    m = jd.ValidInertia()
    round_trip = jax.jit(lambda tensor: m(m.to_unconstrained(tensor)))
    for _ in range(5):
        tensor, _ = random_body(rng)
        assert np.allclose(np.asarray(round_trip(jnp.asarray(tensor))), tensor,
                           atol=10 * tol(ROUNDOFF))


def test_jacobian_against_finite_differences():
    """The fitter's Jacobian (forward mode through the integrator) against central
    differences of its residuals, integrated tightly so that the differences are accurate."""
    rng = np.random.default_rng(12)
    tensor, w0 = random_body(rng)
    ts = np.linspace(0.0, 6.0, SAMPLES)
    data = euler_rates(tensor, w0, ts)
    setup = _fit._setup(jd.Scene(jd.RigidBody(GUESS)), ts, {"omega": data},
                        FIT_BODY["parameters"], FIT_BODY["initial"], None, None,
                        rtol=1e-12, atol=1e-14, max_steps=100_000)
    u = setup.u0 + 0.1 * jax.random.normal(jax.random.PRNGKey(0), setup.u0.shape)
    r, J = _fit._jacobian(setup.problem, u, setup.ts_p, setup.obs_p, setup.weights)
    grad = np.asarray(J.T @ r)

    def loss(u):
        r, _ = _fit._jacobian(setup.problem, u, setup.ts_p, setup.obs_p, setup.weights)
        return 0.5 * jnp.sum(r**2)

    fd = central_difference(loss, u, eps=1e-5)
    scale = np.max(np.abs(fd))
    assert np.allclose(grad, fd, atol=10 * tol(FINITE_DIFF) * scale), (grad, fd)
    # The scale component leaves the rates unchanged: its column is zero.
    assert np.max(np.abs(np.asarray(J[:, 0]))) < 1e-9 * np.max(np.abs(np.asarray(J)))


# -- recovery -----------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [5101, 5102])
def test_torque_free_body_recovered(seed):
    rng = np.random.default_rng(seed)
    tensor, w0 = random_body(rng)
    ts = np.linspace(0.0, 12.0, SAMPLES)
    noise = 0.005
    data = euler_rates(tensor, w0, ts) + noise * rng.normal(size=(SAMPLES, 3))
    res = jd.fit(jd.Scene(jd.RigidBody(GUESS)), ts, {"omega": data}, **FIT_BODY, key=seed)
    truth, axes = sorted_axes(tensor)
    truth = truth / truth[-1]
    moments = np.asarray(res.values["inertia.principal_moments"])
    std = np.asarray(res.std["inertia.principal_moments"])
    assert res.converged
    assert np.all(np.abs(moments - truth) <= 4 * std + 1e-9), (moments, truth, std)
    assert np.max(np.abs(moments - truth)) < 0.02
    assert moments[-1] == pytest.approx(1.0) and std[-1] < 1e-12
    fitted_axes = np.asarray(res.values["inertia.principal_axes"])
    assert np.allclose(fitted_axes, axes, atol=0.02), (fitted_axes, axes)
    # Each axis within 4 sigma of the truth, its sigma (radians) from those of its components.
    angles = np.arccos(np.minimum(1.0, np.sum(fitted_axes * axes, axis=0)))
    axes_sigma = np.linalg.norm(np.asarray(res.std["inertia.principal_axes"]), axis=0)
    assert np.all(angles <= 4 * axes_sigma), (angles, axes_sigma)
    tensor_fit = np.asarray(jd.inertia_tensor(jnp.asarray(moments), jnp.asarray(fitted_axes)))
    assert np.allclose(tensor_fit, tensor / np.max(np.linalg.eigvalsh(tensor)), atol=0.01)
    assert np.allclose(np.asarray(res.values["omega"]), w0, atol=5 * noise)
    assert not res.identifiable["inertia.scale"]
    assert all(v for k, v in res.identifiable.items() if k != "inertia.scale")
    assert any("inertia.scale" in n for n in res.notes)
    assert res.residual_rms == pytest.approx(noise, rel=0.2)
    # The loss never rises within a stage of the fit, and ends at the noise floor
    # (1/2) N sigma^2 for N values with noise sigma, within 3 standard errors of the chi-square
    # (relative standard error sqrt(2 / N)).
    ends = (*res.stages[1:], res.history.size)
    for start, end in zip(res.stages, ends):
        stage = res.history[start:end]
        assert np.all(np.diff(stage) <= 1e-12 * stage[0]), stage
    floor = 0.5 * data.size * noise**2
    assert abs(res.history[-1] / floor - 1) <= 3 * np.sqrt(2 / data.size), res.history[-1] / floor


def test_rotor_fixes_the_scale():
    """A rotor of known momentum breaks the scaling symmetry: absolute moments are fitted."""
    rng = np.random.default_rng(5201)
    tensor, w0 = random_body(rng)
    rotor = np.array([0.0, 0.0, 0.4])
    ts = np.linspace(0.0, 8.0, SAMPLES)
    data = euler_rates(tensor, w0, ts, rotor) + 0.002 * rng.normal(size=(SAMPLES, 3))
    scene = jd.Scene(jd.RigidBody(GUESS), (jd.Rotor(rotor),))
    res = jd.fit(scene, ts, {"omega": data}, **FIT_BODY, key=1)
    truth = np.linalg.eigvalsh(tensor)
    moments = np.asarray(res.values["inertia.principal_moments"])
    std = np.asarray(res.std["inertia.principal_moments"])
    assert all(res.identifiable.values()) and not res.notes
    assert np.all(np.abs(moments - truth) <= 4 * std), (moments, truth, std)
    assert np.allclose(np.asarray(res.values["inertia"]), tensor, atol=0.02)


ROD_FIT = dict(parameters={"length": jd.Positive(), "mass": jd.Positive()},
               initial=["theta", "theta_dot"])


@pytest.mark.parametrize("seed", [5301, 5302])
def test_rod_length_recovered_mass_not_identifiable(seed):
    rng = np.random.default_rng(seed)
    length, theta0, theta_dot0, ts, angles = rod_case(rng)
    data = angles + 0.002 * rng.normal(size=SAMPLES)
    scene = jd.Scene(jd.FallingRod(length=1.0, mass=3.0, g=9.81))
    res = jd.fit(scene, ts, {"theta": data}, **ROD_FIT,
                 notes={"mass": "the mass cancels from the equation of motion"})
    assert res.converged
    assert abs(float(res.values["length"]) - length) <= 4 * float(res.std["length"])
    assert abs(float(res.values["length"]) - length) < 0.02 * length
    assert abs(float(res.values["theta"]) - theta0) <= 4 * float(res.std["theta"])
    assert res.identifiable == {"length": True, "mass": False, "theta": True,
                                "theta_dot": True}
    assert float(res.values["mass"]) == 3.0 and np.isnan(float(res.std["mass"]))
    assert res.notes == ("mass is not identifiable from theta: the mass cancels from the "
                         "equation of motion; kept at its starting value",)


def test_length_and_g_together_are_a_combination():
    """With g fitted as well, only g/L is determined: found by the generic check (a tiny
    singular value of the scaled Jacobian) and reported as a combination."""
    rng = np.random.default_rng(5303)
    length, theta0, theta_dot0, ts, angles = rod_case(rng)
    scene = jd.Scene(jd.FallingRod(length=1.0, mass=1.0, g=9.81))
    res = jd.fit(scene, ts, {"theta": angles + 0.002 * rng.normal(size=SAMPLES)},
                 parameters={"length": jd.Positive(), "g": jd.Positive()},
                 initial=["theta", "theta_dot"], restarts=1)
    assert any("only a combination of length, g" in n for n in res.notes), res.notes
    ratio = float(res.values["g"]) / float(res.values["length"])
    assert ratio == pytest.approx(9.81 / length, rel=0.02)


# -- coverage -----------------------------------------------------------------------------------


def test_intervals_cover_the_truth():
    """Gauss-Newton 1-sigma intervals of the normalised moments cover the truth at ~68 %.

    A small problem (64 samples over 5 s), one body (given in its principal frame, so that the
    scene has the structure used everywhere here), 80 noise seeds; each fit starts at the truth
    and fits the whole record at once (this tests the intervals, not the search: with the
    default growing horizons, one start of seed 13 ends at a degenerate body with twice the
    optimal loss, which the default restarts correct). The fits run one after another through
    one compiled fit (the fitter is a Python-level driver of compiled steps; batching 80 fits
    with `jax.vmap` would cost a second, larger compilation for no gain at this size).
    Tolerance: the two moments of one seed are correlated, so count 80 (not 160) independent
    trials: the binomial standard error is sqrt(0.683 * 0.317 / 80) = 0.052; accept
    0.683 +- 3 standard errors.
    """
    rng = np.random.default_rng(5401)
    tensor, w0 = random_body(rng)
    moments = np.linalg.eigvalsh(tensor)
    ts = np.linspace(0.0, 5.0, SAMPLES)
    clean = euler_rates(np.diag(moments), w0, ts)
    truth = moments / moments[-1]
    scene = jd.Scene(jd.RigidBody(moments))
    hits, z = [], []
    seeds = 80
    noise = 0.01
    for seed in range(seeds):
        data = clean + noise * np.random.default_rng(10_000 + seed).normal(size=clean.shape)
        res = jd.fit(scene, ts, {"omega": data}, **FIT_BODY, restarts=1, horizons=(1.0,),
                     y0={"omega": jnp.asarray(w0)})
        m = np.asarray(res.values["inertia.principal_moments"])[:2]
        s = np.asarray(res.std["inertia.principal_moments"])[:2]
        hits.extend(np.abs(m - truth[:2]) <= s)
        z.extend((m - truth[:2]) / s)
    coverage = float(np.mean(hits))
    se = np.sqrt(0.683 * 0.317 / seeds)
    assert abs(coverage - 0.683) <= 3 * se, (coverage, np.std(z))
    # No gross outliers: P(|z| > 5) ~ 6e-7 for each of 160 Gaussian errors.
    assert np.max(np.abs(z)) <= 5, np.max(np.abs(z))


# -- command line -------------------------------------------------------------------------------


from test_cli import run_cli  # noqa: E402


def write_csv(path, header, columns):
    np.savetxt(path, np.column_stack(columns), delimiter=",", header=header, comments="")
    return str(path)


def test_cli_torque_free(capsys, tmp_path):
    rng = np.random.default_rng(5501)
    tensor, w0 = random_body(rng)
    ts = np.linspace(0.0, 12.0, SAMPLES)
    data = euler_rates(tensor, w0, ts) + 0.005 * rng.normal(size=(SAMPLES, 3))
    path = write_csv(tmp_path / "rates.csv", "t,wx,wy,wz", [ts, data])
    status, out, err = run_cli(capsys, "fit", path, "--scene", "torque-free", "--json")
    assert status == 0, err
    out = json.loads(out)
    truth, axes = sorted_axes(tensor)
    truth = truth / truth[-1]
    moments, std = np.array(out["principal_moments"]), np.array(out["std"])
    assert np.all(np.diff(moments) > 0) and moments[-1] == pytest.approx(1.0)
    assert np.all(np.abs(moments - truth) <= 4 * std + 1e-9), (moments, truth, std)
    assert np.allclose(out["principal_axes"], axes, atol=0.02)
    assert out["scale_identified"] is False
    assert out["residual_rms"] == pytest.approx(0.005, rel=0.25)
    assert out["not_identifiable"] == ["inertia.scale"] and out["converged"]


def test_cli_rod_with_known_g(capsys, tmp_path):
    rng = np.random.default_rng(5502)
    length, theta0, theta_dot0, ts, angles = rod_case(rng, g=3.7)
    path = write_csv(tmp_path / "rod.csv", "t,theta",
                     [ts, angles + 0.002 * rng.normal(size=SAMPLES)])
    status, out, err = run_cli(capsys, "fit", path, "--scene", "falling-rod", "--set", "g=3.7",
                               "--json")
    assert status == 0, err
    out = json.loads(out)
    assert abs(out["length"] - length) <= 4 * out["length_std"], (out["length"], length)
    assert out["not_identifiable"] == ["mass"] and out["mass"] is None
    assert out["known"]["g"] == 3.7 and out["residual_rms"] < 0.003


BAD = [
    ("t,wx,wy\n0,1,2\n", ["--scene", "torque-free"], "missing column(s) ['wz']"),
    ("t,theta\n0,0.1\n0.1,abc\n0.2,0.3\n", [], "column theta='abc': expected a number"),
    ("t,theta\n0,0.1\n0.1,0.2\n", [], "2 data row(s): at least 3 are needed"),
    ("t,theta\n0,0.1\n0.1,0.2\n0.1,0.3\n", [], "column t=0.1: times must be strictly"),
    ("t,theta,x\n0,0.1,1\n", [], "unknown column(s) ['x']"),
    ("t,theta\n0,0.1\n0.1,0.2\n0.2,0.3\n", ["--scene", "spinning-top"],
     "scene='spinning-top': not a built-in scene or a file"),
    ("t,theta\n0,0.1\n0.1,0.2\n0.2,0.3\n", ["--set", "colour=3"],
     "unknown parameter 'colour'"),
    ("a,b\n0,0.1\n", [], "columns a,b match no scene"),
    ("", [], "empty"),
]


@pytest.mark.parametrize("text,extra,message", BAD, ids=[b[2][:24] for b in BAD])
def test_cli_bad_input(capsys, tmp_path, text, extra, message):
    path = tmp_path / "data.csv"
    path.write_text(text)
    status, out, err = run_cli(capsys, "fit", str(path), *extra)
    assert status == 2 and out == ""
    assert len(err.strip().splitlines()) == 1, err
    assert message in err, err


def test_cli_missing_file(capsys, tmp_path):
    status, _, err = run_cli(capsys, "fit", str(tmp_path / "none.csv"))
    assert status == 2 and "no such file" in err


def test_float32_is_kept():
    """A float32 fit of the rod (fewer samples; float32 tolerances) stays in float32."""
    rng = np.random.default_rng(5601)
    length, theta0, theta_dot0, ts, angles = rod_case(rng)
    scene = jd.Scene(jd.FallingRod(length=jnp.float32(1.0), mass=jnp.float32(1.0),
                                   g=jnp.float32(9.81)))
    res = jd.fit(scene, ts.astype(np.float32), {"theta": angles.astype(np.float32)},
                 parameters={"length": jd.Positive()}, initial=["theta", "theta_dot"],
                 restarts=1, rtol=1e-5, atol=1e-7)
    assert res.values["length"].dtype == jnp.float32
    assert float(res.values["length"]) == pytest.approx(length, rel=1e-2)


def test_bad_arguments():
    scene = jd.Scene(jd.FallingRod())
    ts = np.linspace(0, 1, 10)
    data = {"theta": np.zeros(10)}
    with pytest.raises(jd.ParameterError, match="parameters=\\['colour'\\]: not in this scene"):
        jd.fit(scene, ts, data, parameters={"colour": jd.Positive()})
    with pytest.raises(jd.ParameterError, match="data=\\['omega'\\]: not in this scene"):
        jd.fit(scene, ts, {"omega": np.zeros((10, 3))}, parameters={"length": jd.Positive()})
    with pytest.raises(jd.ParameterError, match="has shape \\(9,\\)"):
        jd.fit(scene, ts, {"theta": np.zeros(9)}, parameters={"length": jd.Positive()})
    with pytest.raises(jd.ParameterError, match="more than 4 values are needed to fit 4"):
        jd.fit(scene, ts[:4], {"theta": np.zeros(4)},
               parameters={"length": jd.Positive(), "g": jd.Positive()},
               initial=["theta", "theta_dot"], sigma=None)
    with pytest.raises(jd.ParameterError, match="method='newton'"):
        jd.fit(scene, ts, data, parameters={"length": jd.Positive()}, method="newton")
