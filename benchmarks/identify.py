"""Identification of a torque-free body: jaxdyn against SciPy on the same noisy data.

One noisy record of body rates `w(t)` (a seeded random body with a full inertia tensor,
integrated by SciPy's DOP853 at rtol=1e-12, Gaussian noise added) is fitted for the normalised
principal moments, the principal axes and the initial rates, by

- jaxdyn: `jd.fit` (Levenberg--Marquardt from optimistix, exact forward-mode Jacobians through
  the diffrax integrator, compiled), and
- SciPy: `scipy.optimize.least_squares` (trust-region reflective) with finite-difference
  Jacobians (`jac="2-point"`) over `scipy.integrate.solve_ivp` (DOP853).

Both use the same parameterisation (normalised valid inertia from `(a, b)`, axes from modified
Rodrigues parameters, initial rates), the same starting point, the same continuation over the
time span (25 %, 50 %, then 100 % of the samples) with the same tolerances per stage, and the
same integration tolerances (rtol=1e-8, atol=1e-10), from a single start. SciPy's finite
differences use its default step.

Figures: time of each (jaxdyn: median of repeats after compilation, compile time reported
apart; SciPy: median of repeats), the error of the principal moments against the truth, the
1-sigma interval of jaxdyn's fit, the final loss of each (the same optimum), and the ratio of
times. Accuracy counts as equal when the two errors differ by less than 1 % of the 1-sigma
interval (both land on the same least-squares optimum, up to the integration tolerance). Also:
jaxdyn's default multi-start fit (random restarts until two agree) and the optax route (Adam,
then L-BFGS) on the same data, for comparison. Prints one JSON object.

Scaling (`--sizes`): fit time against record length at a fixed sample rate (10 Hz, so a
longer record spans more turns), beside the time of one forward simulation of the same record
(median of 3 after compilation) and, up to 1000 samples, SciPy's fit of the same data; the
error of the moments reached at each size. jaxdyn's fit there is one start with the default
continuation (spans chosen by the record's length); `first_s` includes compilation,
`warm_s` (a second record of the same length, other noise) does not.

Records longer than 40 natural time units are fitted by multiple shooting (`segments` in
each row: the number chosen by the record's length; 1 is single shooting). `peak_rss_mb` is
the process's peak resident memory after the row (monotone over the run: run one size alone,
`--sizes 1000000 --skip-main`, to read the memory of that size).

Coverage of the posterior (`--coverage SEEDS`): a nearly axisymmetric body (principal
moments 1, 1 + 1e-3, 2, axes turned away from the body frame; 64 samples of rates over 8 s,
noise 1e-3, data by SciPy), fitted with `posterior=200, warmup=150` from the truth (one
start) for each seed: how often the truth lies inside the central 90 % credible interval of
each of the two close moments, against the Gauss--Newton 90 % intervals (+-1.645 sigma), with
a binomial bound (the coverage of `2 x SEEDS` intervals is consistent with 90 % when it lies
within 3 binomial standard deviations). Also each seed's diagnostics of its 4 chains
(acceptance, leapfrog steps per draw in warm-up and sampling, divergences, energy BFMI, the
largest split R-hat and smallest effective sample size over the sampled components): a chain
with an acceptance under 0.3 is counted as stuck, a fit with an R-hat over 1.05 as not
converged (`fit` warns); `fit_s_median` is the time of a fit with its posterior after the
first (which compiles).

Spacecraft telemetry (`--wheels SAMPLES`, e.g. 100000): a spacecraft with products of
inertia and three reaction wheels doing slews (commanded torques held 10 s each, in pairs
that return the momentum), sampled at 10 Hz: gyro rates with bias and noise (2e-5 rad/s),
star-tracker attitudes (5e-5 rad, random signs) and tachometers (5e-3 rad/s), with the
commanded torques, written to a CSV and fitted by `jaxdyn fit` itself (`--bias omega
--restarts 1 --set rtol=1e-8`, from a design estimate: the diagonal 30 % high). Figures: the
command's fit time (`fit_s`, a second run that compiles nothing; where the first took over
2 minutes, that first run alone, `warm: false`) against one forward simulation of
the same record (median of 3 after compilation), the error of the moments and axes in
reported sigmas, the segments, and the peak memory.

Run: `python benchmarks/identify.py [--quick] [--sizes 100,1000,10000,100000]
[--scipy-max 1000] [--skip-main] [--coverage 20] [--wheels 100000]`.
"""

import argparse
import json
import platform
import resource
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import jaxdyn as jd  # noqa: E402

HORIZONS = (0.25, 0.5, 1.0)


def make_data(seed: int, samples: int, t1: float, noise: float):
    """A random physical body, rates of order 1 rad/s, away from the separatrix."""
    rng = np.random.default_rng(seed)
    while True:
        moments = rng.uniform(0.2, 1.0, 3)
        if np.any(moments > moments.sum() - moments):
            continue
        axes = Rotation.random(random_state=rng).as_matrix()
        w0 = rng.normal(size=3)
        w0 /= np.linalg.norm(w0)
        m = np.sort(moments)
        wp = axes.T @ w0
        two_t, h2 = np.sum(moments * wp**2), np.sum((moments * wp) ** 2)
        ordered = np.argsort(moments)
        two_t_i2 = two_t * moments[ordered[1]]
        if abs(h2 - two_t_i2) > 0.1 * h2 and m[0] < 0.9 * m[1] and m[1] < 0.9 * m[2]:
            break
    tensor = axes @ np.diag(moments) @ axes.T
    inv = np.linalg.inv(tensor)
    ts = np.linspace(0.0, t1, samples)
    sol = solve_ivp(lambda t, w: inv @ np.cross(tensor @ w, w), (0.0, t1), w0, t_eval=ts,
                    method="DOP853", rtol=1e-12, atol=1e-12)
    data = sol.y.T + noise * rng.normal(size=(samples, 3))
    return tensor, ts, data


def scipy_model(v, ts, rtol, atol):
    """Rates at `ts` for the unconstrained vector `v = (a, b, sigma, w0)` (normalised scale)."""
    logits = np.array([v[0], v[1], 0.0])
    p = np.exp(logits - logits.max())
    x, y, z = p / p.sum()
    moments = np.array([y + z, x + z, x + y])
    axes = Rotation.from_mrp(v[2:5]).as_matrix()
    tensor = axes @ np.diag(moments) @ axes.T
    inv = np.linalg.inv(tensor)
    sol = solve_ivp(lambda t, w: inv @ np.cross(tensor @ w, w), (ts[0], ts[-1]), v[5:8],
                    t_eval=ts, method="DOP853", rtol=rtol, atol=atol)
    return sol.y.T, moments


def scipy_fit(v0, ts, data, rtol=1e-8, atol=1e-10):
    v = np.array(v0, float)
    nfev = 0
    for h in HORIZONS:
        n = int(np.sum(ts <= ts[0] + h * (ts[-1] - ts[0])))

        def residuals(v, n=n):
            return (scipy_model(v, ts[:n], rtol, atol)[0] - data[:n]).ravel()

        tol = 1e-8 if h == 1.0 else 1e-4
        sol = least_squares(residuals, v, jac="2-point", method="trf", xtol=tol, ftol=tol,
                            gtol=tol)
        v = sol.x
        nfev += sol.nfev + sol.njev * v.size
    moments = np.sort(scipy_model(v, ts[:2], rtol, atol)[1])
    return moments / moments[-1], nfev, sol.cost


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats")
    parser.add_argument("--seed", type=int, default=2024)
    parser.add_argument("--sizes", default="100,1000,10000",
                        help="record lengths for the scaling table (comma-separated; '' "
                             "skips it)")
    parser.add_argument("--scipy-max", type=int, default=1000,
                        help="largest record that SciPy fits in the scaling table")
    parser.add_argument("--skip-main", action="store_true",
                        help="only the scaling table (not the 200-sample comparison)")
    parser.add_argument("--coverage", type=int, default=0, metavar="SEEDS",
                        help="only the posterior's coverage over this many seeds on a nearly "
                             "axisymmetric body")
    parser.add_argument("--wheels", type=int, default=0, metavar="SAMPLES",
                        help="only the spacecraft-telemetry row (gyro, star tracker, wheels) "
                             "of this many samples, fitted by `jaxdyn fit`")
    args = parser.parse_args()
    if args.wheels:
        print(json.dumps({"wheels": wheels_row(args.wheels, args.seed)}, indent=2))
        return
    if args.coverage:
        print(json.dumps({"coverage": posterior_coverage(args.coverage)}, indent=2))
        return
    if args.skip_main:
        sizes = [int(float(x)) for x in args.sizes.split(",") if x.strip()]
        scene = jd.Scene(jd.RigidBody([0.6, 0.8, 1.0]))
        print(json.dumps({"scaling": [scaling_row(args.seed, n, scene, args.scipy_max)
                                      for n in sizes]}, indent=2))
        return
    repeats = 3 if args.quick else 7
    samples, t1, noise = 200, 20.0, 0.01

    tensor, ts, data = make_data(args.seed, samples, t1, noise)
    truth = np.linalg.eigvalsh(tensor)
    truth = truth / truth[-1]

    scene = jd.Scene(jd.RigidBody([0.6, 0.8, 1.0]))
    kwargs = dict(parameters={"inertia": jd.ValidInertia()}, initial=["omega"],
                  horizons=HORIZONS)

    def jaxdyn_fit(**extra):
        return jd.fit(scene, ts, {"omega": data}, **kwargs, **extra)

    def timed(fn, n):
        t0 = time.perf_counter()
        fn()
        first_s = time.perf_counter() - t0
        times = []
        for _ in range(n):
            t0 = time.perf_counter()
            out = fn()
            times.append(time.perf_counter() - t0)
        return out, first_s, statistics.median(times)

    def moments_error(m):
        return float(np.max(np.abs(np.asarray(m) - truth)))

    # The same single start for both: the scene's values and the first sample.
    single, first_s, jd_s = timed(lambda: jaxdyn_fit(restarts=1), repeats)
    jd_m = np.asarray(single.values["inertia.principal_moments"])
    u0 = jd.ValidInertia().to_unconstrained(scene.body.inertia)  # (scale, a, b, sigma)
    v0 = np.concatenate([np.asarray(u0)[1:], data[0]])
    (sp_m, nfev, sp_loss), _, sp_s = timed(lambda: scipy_fit(v0, ts, data),
                                           1 if args.quick else 3)

    multi, multi_first_s, multi_s = timed(lambda: jaxdyn_fit(restarts=8), repeats)
    lbfgs, lbfgs_first_s, lbfgs_s = timed(
        lambda: jaxdyn_fit(restarts=1, method="lbfgs", adam_steps=200), max(repeats // 2, 1))

    out = {
        "problem": {
            "samples": samples, "t1": t1, "noise_rad_s": noise, "seed": args.seed,
            "unknowns": 8, "true_principal_moments": truth.tolist(),
        },
        "jaxdyn": {
            "method": "Levenberg-Marquardt (optimistix), forward-mode Jacobian, one start",
            "time_s": jd_s,
            "compile_s": max(first_s - jd_s, 0.0),
            "principal_moments": jd_m.tolist(),
            "std": np.asarray(single.std["inertia.principal_moments"]).tolist(),
            "moments_error": moments_error(jd_m),
            "iterations": single.iterations,
            "residual_rms": single.residual_rms,
            "final_loss": single.loss,
        },
        "scipy": {
            "method": "least_squares trf, 2-point finite differences over solve_ivp DOP853 "
                      "(rtol 1e-8), one start",
            "time_s": sp_s,
            "principal_moments": sp_m.tolist(),
            "moments_error": moments_error(sp_m),
            "ode_solves": nfev,
            "final_loss": float(sp_loss),
        },
        "speedup": sp_s / jd_s,
        "estimates_differ_by": float(np.max(np.abs(jd_m - sp_m))),
        "jaxdyn_multistart": {
            "time_s": multi_s, "compile_s": max(multi_first_s - multi_s, 0.0),
            "starts_run": int(multi.restart_losses.size),
            "moments_error": moments_error(multi.values["inertia.principal_moments"]),
        },
        "jaxdyn_adam_lbfgs": {
            "time_s": lbfgs_s, "compile_s": max(lbfgs_first_s - lbfgs_s, 0.0),
            "iterations": lbfgs.iterations, "converged": lbfgs.converged,
            "moments_error": moments_error(lbfgs.values["inertia.principal_moments"]),
        },
        "machine": {"python": platform.python_version(), "jax": jax.__version__,
                    "device": str(jax.devices()[0])},
    }
    sigma = float(np.max(np.asarray(single.std["inertia.principal_moments"])))
    out["equal_or_better_accuracy"] = bool(
        out["jaxdyn"]["moments_error"] <= out["scipy"]["moments_error"] + 0.01 * sigma)
    out["target_met"] = bool(out["speedup"] >= 10 and out["equal_or_better_accuracy"])
    sizes = [int(float(x)) for x in args.sizes.split(",") if x.strip()]
    out["scaling"] = [scaling_row(args.seed, n, scene, args.scipy_max) for n in sizes]
    print(json.dumps(out, indent=2))


def scaling_row(seed: int, samples: int, scene, scipy_max: int = 1000) -> dict:
    """One row of the scaling table: a record of `samples` at 10 Hz."""
    rate, noise = 10.0, 0.01
    t1 = (samples - 1) / rate
    tensor, ts, data = make_data(seed, samples, t1, noise)
    truth = np.linalg.eigvalsh(tensor)
    truth = truth / truth[-1]
    kwargs = dict(parameters={"inertia": jd.ValidInertia()}, initial=["omega"], restarts=1)

    def fit(d):
        t0 = time.perf_counter()
        res = jd.fit(scene, ts, {"omega": d}, **kwargs)
        return res, time.perf_counter() - t0

    res, first_s = fit(data)
    row = {"samples": samples, "t1": t1, "first_s": first_s, "converged": res.converged,
           "moments_error": float(np.max(np.abs(
               np.asarray(res.values["inertia.principal_moments"]) - truth))),
           "std": float(np.max(np.asarray(res.std["inertia.principal_moments"]))),
           "stages": len(res.stages), "iterations": res.iterations, "segments": res.segments}
    if samples <= 100_000:
        other = data + noise * np.random.default_rng(seed + 1).normal(size=data.shape)
        row["warm_s"] = fit(other)[1]
    body = jd.Scene(jd.RigidBody(tensor))
    y0, grid = body.state(omega=data[0]), jnp.asarray(ts)
    jax.block_until_ready(jd.simulate(body, y0, t1, ts=grid).ys)
    sims = []
    for _ in range(3):
        t0 = time.perf_counter()
        jax.block_until_ready(jd.simulate(body, y0, t1, ts=grid).ys)
        sims.append(time.perf_counter() - t0)
    row["simulate_s"] = statistics.median(sims)
    row["fit_over_simulate"] = row.get("warm_s", first_s) / row["simulate_s"]
    row["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if samples <= scipy_max:
        u0 = jd.ValidInertia().to_unconstrained(scene.body.inertia)
        v0 = np.concatenate([np.asarray(u0)[1:], data[0]])
        t0 = time.perf_counter()
        sp_m = scipy_fit(v0, ts, data)[0]
        row["scipy_s"] = time.perf_counter() - t0
        row["scipy_moments_error"] = float(np.max(np.abs(sp_m - truth)))
    return row


def posterior_coverage(seeds: int, eps: float = 1e-3, samples: int = 64, t1: float = 8.0,
                       noise: float = 1e-3, chains: int = 4) -> dict:
    """Coverage of NUTS's central 90 % intervals and of Gauss--Newton's over `seeds` noise
    draws on a nearly axisymmetric body (see the module's docstring)."""
    moments = np.array([1.0, 1.0 + eps, 2.0])
    axes = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    tensor = axes @ np.diag(moments) @ axes.T
    w0 = np.array([0.7, 0.2, 0.6])
    ts = np.linspace(0.0, t1, samples)
    clean = solve_ivp(lambda t, w: np.linalg.solve(tensor, np.cross(tensor @ w, w)),
                      (0.0, t1), w0, t_eval=ts, method="DOP853", rtol=1e-12,
                      atol=1e-12).y.T
    truth = (moments / moments[-1])[:2]
    scene = jd.Scene(jd.RigidBody(tensor))
    z = 1.6448536269514722  # the 95 % quantile of the standard normal
    rows, gn, post = [], [], []
    for seed in range(seeds):
        data = clean + noise * np.random.default_rng(9000 + seed).normal(size=clean.shape)
        t0 = time.perf_counter()
        res = jd.fit(scene, ts, {"omega": data}, parameters={"inertia": jd.ValidInertia()},
                     initial=["omega"], restarts=1, horizons=(1.0,), posterior=200,
                     warmup=150, chains=chains, key=seed)
        m = np.asarray(res.values["inertia.principal_moments"])[:2]
        sd = np.asarray(res.std["inertia.principal_moments"])[:2]
        lo, hi = np.quantile(res.posterior["inertia.principal_moments"][:, :2], [0.05, 0.95],
                             axis=0)
        gn.extend(np.abs(m - truth) <= z * sd)
        post.extend((lo <= truth) & (truth <= hi))
        diag = res.posterior_diagnostics
        rows.append({"seed": seed, "s": time.perf_counter() - t0,
                     "acceptance": diag["acceptance"], "leapfrogs": diag["leapfrogs"],
                     "warmup_leapfrogs": diag["warmup_leapfrogs"],
                     "divergences": diag["divergences"], "bfmi": diag["bfmi"],
                     "max_rhat": diag["max_rhat"], "min_ess": diag["min_ess"],
                     "gn_covers": [bool(x) for x in gn[-2:]],
                     "posterior_covers": [bool(x) for x in post[-2:]]})
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)  # progress
    n = len(post)
    bound = 3 * np.sqrt(0.9 * 0.1 / n)
    return {"moments": moments.tolist(), "samples": samples, "noise": noise, "seeds": seeds,
            "nominal": 0.9, "binomial_3sd": float(bound),
            "posterior_coverage": float(np.mean(post)),
            "gauss_newton_coverage": float(np.mean(gn)),
            "posterior_consistent": bool(abs(np.mean(post) - 0.9) <= bound),
            "gauss_newton_consistent": bool(abs(np.mean(gn) - 0.9) <= bound),
            "chains": chains, "stuck_chains": sum(a < 0.3 for r in rows for a in r["acceptance"]),
            "fits_rhat_over_1.05": sum(r["max_rhat"] > 1.05 for r in rows),
            "max_rhat": max(r["max_rhat"] for r in rows),
            "min_ess": min(r["min_ess"] for r in rows),
            "divergences": sum(sum(r["divergences"]) for r in rows),
            # The first fit compiles: the median of the others is the time of a fit.
            "fit_s_median": float(np.median([r["s"] for r in rows[1:]] or [rows[0]["s"]])),
            "first_fit_s": rows[0]["s"], "rows": rows}


# The design estimate that the fit starts from (the diagonal 30 % high), shared with the tests.
WHEELS_SCENE = Path(__file__).resolve().parents[1] / "tests" / "spacecraft_estimate.toml"


def wheels_record(samples: int, seed: int) -> dict:
    """The spacecraft-telemetry record of `--wheels` (see the module's docstring): the true
    tensor and initial state, the scene with its commanded torques, and the sensors' readings
    (`gyro`, `star`, `tach`, `held`: the command held at each sample)."""
    rng = np.random.default_rng(seed)
    tensor = np.array([[2.1, 0.08, -0.05], [0.08, 2.6, 0.12], [-0.05, 0.12, 3.3]])
    ts = np.arange(samples) / 10.0
    t1 = float(ts[-1])
    times = np.arange(0.0, t1 + 10.0, 10.0)
    half = 4e-3 * rng.choice([-1.0, 0.0, 1.0], size=((times.size + 1) // 2, 3))
    commands = np.stack([half, -half], axis=1).reshape(-1, 3)[:times.size]
    wheels = jd.Wheels(np.eye(3), [0.01] * 3, motor=jd.CommandedTorques(times, commands))
    truth = jd.Scene(jd.RigidBody(tensor), (wheels,), attitude=True)
    y0 = truth.state(omega=[0.01, -0.02, 0.015], quaternion=[0.8, 0.2, -0.4, 0.4],
                     **{"wheels.speed": [40.0, -30.0, 20.0]})
    grid = jnp.asarray(ts)

    def simulate():
        rec = jd.simulate(truth, y0, t1, ts=grid, rtol=1e-10, max_steps=50 * samples)
        return jax.block_until_ready(rec)

    t0 = time.perf_counter()
    record = simulate()
    first_sim_s = time.perf_counter() - t0
    sims = []
    for _ in range(3):
        t0 = time.perf_counter()
        simulate()
        sims.append(time.perf_counter() - t0)
    out = jax.vmap(truth.outputs)(record.ts, record.ys)
    bias = np.array([4e-4, -2.5e-4, 1.5e-4])
    gyro = np.asarray(out["omega"]) + bias + 2e-5 * rng.normal(size=(samples, 3))
    tach = np.asarray(out["wheels.speed"]) + 5e-3 * rng.normal(size=(samples, 3))
    error = 5e-5 * rng.normal(size=(samples, 3))
    turn = jax.vmap(jd.quat_from_axis_angle)(jnp.asarray(error),
                                             jnp.linalg.norm(error, axis=1))
    star = np.asarray(jax.vmap(jd.quat_multiply)(record.ys["quaternion"], turn))
    star = star * rng.choice([-1.0, 1.0], size=(samples, 1))
    held = commands[np.searchsorted(times, ts, side="right") - 1]
    return {"tensor": tensor, "truth": truth, "y0": y0, "ts": ts, "t1": t1, "bias": bias,
            "gyro": gyro, "star": star, "tach": tach, "held": held, "states": record.ys,
            "simulate_first_s": first_sim_s, "simulate_s": statistics.median(sims)}


def write_wheels_csv(path, rec: dict) -> None:
    """The record's CSV, as `jaxdyn fit` reads it."""
    header = ("t,wx,wy,wz,q0,q1,q2,q3,wheel1_speed,wheel2_speed,wheel3_speed,"
              "wheel1_torque,wheel2_torque,wheel3_torque")
    np.savetxt(path, np.column_stack([rec["ts"], rec["gyro"], rec["star"], rec["tach"],
                                      rec["held"]]),
               delimiter=",", header=header, comments="")


def wheels_row(samples: int, seed: int) -> dict:
    """Spacecraft telemetry of `samples` rows at 10 Hz fitted by `jaxdyn fit` (see the
    module's docstring)."""
    import contextlib
    import io
    import tempfile

    from jaxdyn._cli import main as cli

    rec = wheels_record(samples, seed)
    tensor, t1 = rec["tensor"], rec["t1"]
    with tempfile.TemporaryDirectory() as tmp:
        csv_path = Path(tmp) / "telemetry.csv"
        write_wheels_csv(csv_path, rec)
        argv = ["fit", str(csv_path), "--scene", str(WHEELS_SCENE), "--bias", "omega",
                "--restarts", "1", "--set", "rtol=1e-8", "--no-progress", "--json"]
        runs = []
        for _ in range(2):  # the second run compiles nothing
            printed = io.StringIO()
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(printed):
                status = cli(argv)
            runs.append(time.perf_counter() - t0)
            if status != 0 or runs[0] > 120:  # a long fit: compilation is a small part
                break
        first_s, fit_s = runs[0], runs[-1]
    row = {"samples": samples, "t1": t1, "status": status, "first_fit_s": first_s,
           "fit_s": fit_s, "warm": len(runs) > 1,
           "simulate_first_s": rec["simulate_first_s"], "simulate_s": rec["simulate_s"],
           "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    row["fit_over_simulate"] = fit_s / row["simulate_s"]
    if status != 0:
        return row
    res = json.loads(printed.getvalue())
    moments, axes = np.linalg.eigh(tensor)
    m, sd = np.array(res["principal_moments"]), np.array(res["std"])
    a, sa = np.array(res["principal_axes"]), np.array(res["principal_axes_std"])
    a = a * np.sign(np.sum(a * axes, axis=0))  # each axis's sign, as the truth's
    row.update({"converged": res["converged"], "iterations": res["iterations"],
                "scale_identified": res["scale_identified"],
                "moments_error_sigmas": (np.abs(m - moments) / sd).tolist(),
                "axes_error_sigmas_max": float(np.max(np.abs(a - axes) / sa)),
                "moments_rel_std": (sd / moments).tolist(),
                "systematic_residuals": res["systematic_residuals"],
                "residual_rms_by_output": res["residual_rms_by_output"],
                "fit_timing": res["timing"]})
    return row


if __name__ == "__main__":
    jnp.zeros(())  # initialise the backend before timing
    main()
