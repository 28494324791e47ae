"""Monte Carlo ensembles: jaxdyn against plain `jax.vmap`, a SciPy loop and a lean fused kernel.

Two problems, each over the same `n` initial states (drawn once with NumPy, passed to every
method), rtol=1e-8, atol=1e-10:

- torque-free body, rates only: inertia (1, 2, 3), omega0 ~ Normal((0.1, 1, 0.1), 0.05) per
  component, t in [0, 20]; the error is measured against the closed form
  (`jd.torque_free_omega`, Jacobi elliptic functions);
- falling rod: length 1, theta0 ~ Uniform(0.01, 0.2), theta_dot0 ~ Normal(0, 0.01), until it
  lies flat (a terminating event); the error of the fall time is measured against the
  quadrature `FallingRod.fall_time`.

Methods, all in this one run, with every core as a JAX CPU device (`jax_num_cpu_devices`, as
`jaxdyn montecarlo` sets it; `--devices=1` for one):

- jaxdyn: `jd.ensemble` (default mode: per-trajectory adaptive Tsit5 over a batch, sharded
  across the devices; chunks of `--chunk` trajectories, by default its own choice), observing
  what the other methods return (final rates; fall time), and its lock-step mode; also with
  its default observation (every output of the scene at the final time), for comparison;
- plain vmap: `jax.jit(jax.vmap(diffrax.diffeqsolve))` with Tsit5 and a PID controller (and a
  `diffrax.Event` for the rod), as a user would write it (one device);
- SciPy: a loop over `scipy.integrate.solve_ivp` (RK45 and DOP853; the faster is compared) on
  the first `--scipy-n` trajectories, rate extrapolated;
- lean kernel, the practical limit: Tsit5's tableau with a fixed step in a `lax.scan` (rod: a
  `while_loop` until every rod is down, the event located on the cubic Hermite interpolant by
  Newton), over a structure-of-arrays state (one row per component), with the smallest number
  of steps whose largest error over the check subset is no larger than jaxdyn's. It is timed on
  the whole batch at once, in chunks, and in chunks sharded across the devices, for the rod both
  with the C library's sine and cosine and with jaxdyn's vectorised `sincos`, each compiled
  with XLA's default options and with those `jd.ensemble` compiles its chunks with (512-bit
  vectors on a CPU), each with the state as real rows and packed two rows to a complex row
  (the trick `jd.ensemble` uses: XLA then computes a step once for both rows of a pair); the
  fastest is the limit. Chunks are jaxdyn's size and 16384.

The ratio to the lean kernel (`lean_over_jaxdyn`, the target's figure) is measured head to
head: once the fastest variant is chosen, it and jaxdyn run alternately for `--rounds` rounds
and the ratio is the median of the rounds' ratios. The fastest of many variants, each timed
once (`lean_over_jaxdyn_selection`), is biased towards a lucky measurement (its variants move by
up to 20% from run to run), and minutes apart from jaxdyn's timing.

Peak memory: resident set of a fresh process running 1, 4 and 16 chunks of `--chunk` (default
16384) trajectories with nothing kept.

Run: `python benchmarks/montecarlo.py [--quick] [--n N]`. Prints one JSON object.
"""

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from functools import partial

import jax

jax.config.update("jax_enable_x64", True)
# Every core as a JAX CPU device (what `jaxdyn montecarlo` does, and the README recommends for
# Monte Carlo on a CPU): jd.ensemble and the lean kernel shard across them; plain vmap and SciPy
# run as users write them. `--devices 1` for one device.
_devices = next((int(a.split("=")[1]) for a in sys.argv if a.startswith("--devices=")),
                os.cpu_count() or 1)
jax.config.update("jax_num_cpu_devices", _devices)

import diffrax as dfx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402
from diffrax._solver.tsit5 import _tsit5_tableau as TSIT5  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

import jaxdyn as jd  # noqa: E402
from jaxdyn._batch_solve import pack_pairs, unpack_pairs  # noqa: E402
from jaxdyn._ensemble import CPU_COMPILER_OPTIONS, DEFAULT_CHUNK  # noqa: E402
from jaxdyn._fastmath import sincos  # noqa: E402

RTOL, ATOL = 1e-8, 1e-10
INERTIA = (1.0, 2.0, 3.0)
T_FREE = 20.0
T_ROD = 5.0
G, LENGTH = 9.81, 1.0
CHECK = 2000  # trajectories whose error is measured


def timed(fn, repeats):
    """(median seconds after a first call, first-call seconds)."""
    start = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return statistics.median(times), first


# -- the lean kernel ---------------------------------------------------------------------------

A = [tuple(float(v) for v in row) for row in TSIT5.a_lower]
B = tuple(float(v) for v in TSIT5.b_sol)
C = tuple(float(v) for v in TSIT5.c)


def rk_step(f, y, h):
    """One Tsit5 step (no error estimate) on a tuple of rows; returns (y1, f(y0))."""
    ks = [f(y)]
    for row in A:
        yi = tuple(y[j] + h * sum(a * k[j] for a, k in zip(row, ks) if a != 0.0)
                   for j in range(len(y)))
        ks.append(f(yi))
    y1 = tuple(y[j] + h * sum(b * k[j] for b, k in zip(B, ks) if b != 0.0)
               for j in range(len(y)))
    return y1, ks[0]


def euler_rows(w):
    i1, i2, i3 = INERTIA
    w1, w2, w3 = w
    return ((i2 - i3) / i1 * w2 * w3, (i3 - i1) / i2 * w3 * w1, (i1 - i2) / i3 * w1 * w2)


def lean_free(w0, steps, packed=False):
    h = T_FREE / steps
    y = tuple(w0[:, j] for j in range(3))
    if packed:
        y, _ = jax.lax.scan(
            lambda y, _: (pack_pairs(rk_step(euler_rows, unpack_pairs(y), h)[0]), None),
            pack_pairs(y), None, length=steps)
        y = unpack_pairs(y)
    else:
        y, _ = jax.lax.scan(lambda y, _: (rk_step(euler_rows, y, h)[0], None), y, None,
                            length=steps)
    return jnp.stack(y, axis=-1)


def rod_rows(y, trig=None):
    theta, rate = y
    s, c = (jnp.sin(theta), jnp.cos(theta)) if trig is None else trig(theta)
    acc = (6 * G / LENGTH * s - 3 * s * c * rate**2) / (1 + 3 * s**2)
    return (rate, acc)


def lean_rod(y0, h, trig=None, packed=False):
    """Fixed steps until every rod is flat; fall time from the cubic Hermite interpolant."""
    theta, rate = y0[:, 0], y0[:, 1]
    n = theta.shape[0]
    half = jnp.pi / 2
    into, back = (pack_pairs, unpack_pairs) if packed else (tuple, tuple)

    def cond(c):
        return jnp.any(~c[3])

    def body(c):
        t, y, f, done, out = c
        y = back(y)
        y1, _ = rk_step(lambda y: rod_rows(y, trig), y, h)
        f1 = rod_rows(y1, trig)
        hit = ~done & (jnp.abs(y1[0]) >= half)
        # Hermite cubic of theta over the step, root of |theta| = pi/2 by Newton from the secant.
        th0, th1, d0, d1 = y[0], y1[0], f[0] * h, f1[0] * h
        sgn = jnp.sign(th1)
        s = jnp.clip((half - sgn * th0) / (sgn * (th1 - th0)), 0.0, 1.0)
        for _ in range(4):
            h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
            h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
            p = h00 * th0 + h10 * d0 + h01 * th1 + h11 * d1
            dp = ((6 * s**2 - 6 * s) * th0 + (3 * s**2 - 4 * s + 1) * d0
                  + (-6 * s**2 + 6 * s) * th1 + (3 * s**2 - 2 * s) * d1)
            s = jnp.clip(s - (sgn * p - half) / (sgn * dp), 0.0, 1.0)
        out = jnp.where(hit, t + s * h, out)
        return t + h, into(y1), f1, done | hit, out

    y = (theta, rate)
    c = (jnp.zeros(()), into(y), rod_rows(y, trig), jnp.zeros(n, bool), jnp.full(n, jnp.inf))
    return jax.lax.while_loop(cond, body, c)[4]


# -- plain vmap over diffrax ---------------------------------------------------------------------

def plain_free(w0):
    def one(w):
        sol = dfx.diffeqsolve(
            dfx.ODETerm(lambda t, w, i: jnp.cross(i * w, w) / i), dfx.Tsit5(), 0.0, T_FREE,
            None, w, args=jnp.asarray(INERTIA),
            stepsize_controller=dfx.PIDController(rtol=RTOL, atol=ATOL),
            saveat=dfx.SaveAt(t1=True), max_steps=100_000)
        return sol.ys[0]
    return jax.vmap(one)(w0)


def plain_rod(y0):
    def vf(t, y, args):
        return jnp.stack(rod_rows((y[0], y[1])))

    event = dfx.Event(lambda t, y, args, **kw: jnp.pi / 2 - jnp.abs(y[0]),
                      root_finder=optx.Newton(rtol=1e-12, atol=1e-12))

    def one(y):
        sol = dfx.diffeqsolve(dfx.ODETerm(vf), dfx.Tsit5(), 0.0, T_ROD, None, y,
                              stepsize_controller=dfx.PIDController(rtol=RTOL, atol=ATOL),
                              saveat=dfx.SaveAt(t1=True), event=event, max_steps=100_000)
        return sol.ts[0]
    return jax.vmap(one)(y0)


# -- SciPy --------------------------------------------------------------------------------------

def scipy_free(w0, method):
    i1, i2, i3 = INERTIA

    def f(t, w):
        return [(i2 - i3) / i1 * w[1] * w[2], (i3 - i1) / i2 * w[2] * w[0],
                (i1 - i2) / i3 * w[0] * w[1]]
    return np.array([solve_ivp(f, (0.0, T_FREE), w, method=method, rtol=RTOL,
                               atol=ATOL).y[:, -1] for w in w0])


def scipy_rod(y0, method):
    def f(t, y):
        s, c = np.sin(y[0]), np.cos(y[0])
        return [y[1], (6 * G / LENGTH * s - 3 * s * c * y[1] ** 2) / (1 + 3 * s**2)]

    def flat(t, y):
        return np.pi / 2 - abs(y[0])
    flat.terminal = True
    return np.array([solve_ivp(f, (0.0, T_ROD), y, method=method, rtol=RTOL, atol=ATOL,
                               events=flat).t_events[0][0] for y in y0])


def scipy_rate(fn, inputs, ref, err):
    best = None
    for method in ("RK45", "DOP853"):
        start = time.perf_counter()
        out = fn(inputs, method)
        seconds = time.perf_counter() - start
        e = err(out, ref)
        row = {"method": method, "n": len(inputs), "seconds": seconds,
               "trajectories_per_s": len(inputs) / seconds, "max_error": e[0],
               "median_error": e[1]}
        if best is None or row["trajectories_per_s"] > best["trajectories_per_s"]:
            best = row
    return best


def errors(out, ref):
    e = np.abs(np.asarray(out) - np.asarray(ref)).reshape(len(ref), -1).max(axis=1)
    return float(e.max()), float(np.median(e))


def lean_search(run, ref, target, first):
    """Smallest step count (rod: largest step) in a ladder whose max error is <= target."""
    steps = first
    while True:
        e = errors(run(steps), ref)
        if e[0] <= target or steps > 100 * first:
            return steps, e
        steps = int(np.ceil(steps * 1.1))


# -- the two problems ----------------------------------------------------------------------------

def compare(out, ens, observed, ref, inputs, plain_fn, scipy_fn, lean_fn, first_steps, *,
            chunk, repeats, rounds, scipy_n, lean_trigs=(None,)):
    """Every method on one problem: `ens(mode)` runs jaxdyn, `inputs` (n, state) the initial
    states of the others, `lean_fn(inputs, steps)` the fixed-step kernel."""
    n = len(inputs)
    # jaxdyn observing only what the other methods compute (the comparison), and with its
    # default observation (every output of the scene at the final time, kept for each run).
    for name, mode, everything in (("adaptive", "adaptive", False),
                                   ("lockstep", "lockstep", False),
                                   ("adaptive_all_outputs", "adaptive", True)):
        res = ens(mode, everything)
        seconds, _ = timed(lambda: ens(mode, everything).status, repeats)
        e = errors(res.values[observed][:CHECK], ref)
        out[f"jaxdyn_{name}"] = {
            "trajectories_per_s": n / seconds, "seconds": seconds,
            "compile_s": res.timing["compile_s"], "chunk_size": res.chunk_size,
            "failed": res.failed, "mean_steps": float(res.steps.mean()), "max_error": e[0],
            "median_error": e[1]}
    target = out["jaxdyn_adaptive"]["max_error"]
    if chunk is None:
        chunk = out["jaxdyn_adaptive"]["chunk_size"]

    plain = jax.jit(plain_fn)
    x = jnp.asarray(inputs)
    seconds, first = timed(lambda: plain(x), max(1, repeats // 2))
    e = errors(plain(x)[:CHECK], ref)
    out["plain_vmap"] = {"trajectories_per_s": n / seconds, "seconds": seconds,
                         "compile_s": first - seconds, "max_error": e[0], "median_error": e[1]}

    out["scipy_loop"] = scipy_rate(scipy_fn, inputs[:scipy_n], ref[:scipy_n], errors)

    runs = {}

    def lean(steps):
        if steps not in runs:
            runs[steps] = jax.jit(lambda y: lean_fn(y, steps))
        return np.asarray(runs[steps](x[:CHECK]))
    steps, e = lean_search(lean, ref, target, first_steps)

    # The limit: the fastest of the whole batch at once, chunks in a loop, and chunks sharded
    # across the devices (chunks of jaxdyn's size and of 16384), with the C library's sine and
    # cosine and (where there are any) with jaxdyn's vectorised sincos.
    devices = jax.devices()
    k = len(devices)
    mesh = jax.sharding.Mesh(np.asarray(devices), ("b",))
    spec = jax.sharding.PartitionSpec("b")

    def chunked(fn, per):
        def run(y):
            r = jax.lax.map(fn, y.reshape((-1, per) + y.shape[1:]))
            return r.reshape((-1,) + r.shape[2:])
        return run

    rows, compiled = {}, {}
    for trig, packed in [(trig, packed) for trig in lean_trigs for packed in (False, True)]:
        fn = partial(lean_fn, steps=steps, packed=packed)
        if trig is not None:
            fn = partial(fn, trig=trig)
        name = ("libm" if trig is None else "sincos") + ("_packed" if packed else "")
        layouts = {"whole_batch": (fn, n)}
        for size in sorted({chunk, DEFAULT_CHUNK}):
            per = max(size // k, 1)
            m = (n // (per * k)) * per * k  # whole chunks only
            layouts[f"chunked{size}"] = (chunked(fn, per * k), m)
            if k > 1:
                layouts[f"sharded{size}"] = (jax.shard_map(
                    chunked(fn, per), mesh=mesh, in_specs=spec, out_specs=spec,
                    check_vma=False), m)
        for layout, (f, size) in layouts.items():
            # XLA's default, and the options jd.ensemble compiles its chunks with.
            for tag, options in (("", None), ("_vec512", CPU_COMPILER_OPTIONS)):
                start = time.perf_counter()
                c = jax.jit(f).lower(x[:size]).compile(options)
                compile_s = time.perf_counter() - start
                seconds, _ = timed(lambda: c(x[:size]), repeats)
                rows[f"{layout}_{name}{tag}"] = {"trajectories_per_s": size / seconds,
                                                 "compile_s": compile_s}
                compiled[f"{layout}_{name}{tag}"] = (c, size)
    best = max(rows, key=lambda r: rows[r]["trajectories_per_s"])
    out["lean_kernel"] = {"steps": steps, "trajectories_per_s":
                          rows[best]["trajectories_per_s"], "fastest": best,
                          "variants": rows, "max_error": e[0], "median_error": e[1]}

    # The fastest variant and jaxdyn alternately, round by round.
    c, size = compiled[best]
    lean_x = x[:size]
    jaxdyn_rates, lean_rates = [], []
    for _ in range(rounds):
        jaxdyn_rates.append(n / timed(lambda: ens("adaptive", False).status, 1)[0])
        lean_rates.append(size / timed(lambda: c(lean_x), 1)[0])
    out["head_to_head"] = {
        "rounds": rounds, "lean_variant": best,
        "jaxdyn_trajectories_per_s": statistics.median(jaxdyn_rates),
        "lean_trajectories_per_s": statistics.median(lean_rates),
        "lean_over_jaxdyn": statistics.median(
            lean / j for lean, j in zip(lean_rates, jaxdyn_rates)),
        "lean_over_jaxdyn_range": [min(lean / j for lean, j in zip(lean_rates, jaxdyn_rates)),
                                   max(lean / j for lean, j in zip(lean_rates, jaxdyn_rates))]}
    return out


def free_body(n, chunk, repeats, rounds, scipy_n, rng):
    w0 = np.array([0.1, 1.0, 0.1]) + 0.05 * rng.standard_normal((n, 3))
    scene = jd.Scene(jd.RigidBody(inertia=list(INERTIA)))
    ref = np.asarray(jax.jit(jax.vmap(lambda w: jd.torque_free_omega(
        jnp.asarray(INERTIA), w, T_FREE)))(jnp.asarray(w0[:CHECK])))

    def rates(tr):  # one function object, so that jd.ensemble reuses its compiled chunks
        return {"omega": tr.y_final["omega"]}

    def ens(mode, everything):
        observe = None if everything else rates
        return jd.ensemble(scene, {"omega": w0}, T_FREE, rtol=RTOL, mode=mode,
                           chunk_size=chunk, observe=observe)

    out = {"problem": "torque-free body, rates only, t in [0, 20]", "n": n}
    return compare(out, ens, "omega", ref, w0, plain_free, scipy_free, lean_free, 60,
                   chunk=chunk, repeats=repeats, rounds=rounds, scipy_n=scipy_n)


def rod(n, chunk, repeats, rounds, scipy_n, rng):
    theta0 = rng.uniform(0.01, 0.2, n)
    rate0 = 0.01 * rng.standard_normal(n)
    y0 = np.stack([theta0, rate0], axis=1)
    scene = jd.Scene(jd.FallingRod(length=LENGTH, g=G))
    ref = np.array([float(scene.body.fall_time(a, b)) for a, b in y0[:CHECK]])

    def fall_time(tr):  # one function object, so that jd.ensemble reuses its compiled chunks
        return {"t_final": tr.t_final}

    def ens(mode, everything):
        observe = None if everything else fall_time
        return jd.ensemble(scene, {"theta": theta0, "theta_dot": rate0}, T_ROD, rtol=RTOL,
                           mode=mode, chunk_size=chunk, observe=observe)

    out = {"problem": "falling rod to impact (terminating event)", "n": n,
           "lean_steps_are": "steps per unit of simulated time"}
    return compare(out, ens, "t_final", ref, y0, plain_rod, scipy_rod,
                   lambda y, steps, trig=None, packed=False: lean_rod(y, 1.0 / steps, trig,
                                                                      packed), 20,
                   chunk=chunk, repeats=repeats, rounds=rounds, scipy_n=scipy_n,
                   lean_trigs=(None, sincos))


def ratios(block):
    j = block["jaxdyn_adaptive"]["trajectories_per_s"]
    return {
        "vs_plain_vmap": j / block["plain_vmap"]["trajectories_per_s"],
        "vs_scipy_loop": j / block["scipy_loop"]["trajectories_per_s"],
        "lean_over_jaxdyn": block["head_to_head"]["lean_over_jaxdyn"],
        "lean_over_jaxdyn_selection": block["lean_kernel"]["trajectories_per_s"] / j,
        "adaptive_over_lockstep": j / block["jaxdyn_lockstep"]["trajectories_per_s"],
        "targets_met": {
            "10x_plain_vmap": j >= 10 * block["plain_vmap"]["trajectories_per_s"],
            "1000x_scipy": j >= 1000 * block["scipy_loop"]["trajectories_per_s"],
            "within_3x_of_lean": block["head_to_head"]["lean_over_jaxdyn"] <= 3,
        },
    }


def memory_probe(n, chunk):
    scene = jd.Scene(jd.RigidBody(inertia=list(INERTIA)))
    res = jd.ensemble(scene, scene.state(omega=[0.1, 1.0, 0.1]), T_FREE, n=n,
                      vary={"omega": jd.Normal([0.1, 1.0, 0.1], 0.05)}, rtol=RTOL,
                      chunk_size=chunk, keep=False)
    assert res.completed == n
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # MiB on Linux


def memory(chunk):
    chunk = chunk or DEFAULT_CHUNK
    rows = []
    for k in (1, 4, 16):
        n = k * chunk
        proc = subprocess.run([sys.executable, __file__, "--memory-probe", str(n),
                               "--chunk", str(chunk)], capture_output=True, text=True,
                              check=True)
        rows.append({"n": n, "peak_rss_mib": float(proc.stdout.strip().splitlines()[-1])})
    return {"rows": rows, "peak_ratio_16_over_1_chunk":
            rows[-1]["peak_rss_mib"] / rows[0]["peak_rss_mib"]}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=100_000)
    parser.add_argument("--chunk", type=int, default=None,
                        help="trajectories per chunk (default: jaxdyn's own choice)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=9,
                        help="alternate runs of jaxdyn and the fastest lean kernel")
    parser.add_argument("--scipy-n", type=int, default=200)
    parser.add_argument("--quick", action="store_true", help="n = 32768, one repeat")
    parser.add_argument("--devices", type=int, default=_devices,
                        help="JAX CPU devices (default: one per core); give as --devices=K")
    parser.add_argument("--memory-probe", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.memory_probe is not None:
        print(memory_probe(args.memory_probe, args.chunk))
        return
    if args.quick:
        args.n, args.repeats, args.rounds, args.scipy_n = 32768, 1, 3, 50
    rng = np.random.default_rng(2026)
    start = time.perf_counter()
    free = free_body(args.n, args.chunk, args.repeats, args.rounds, args.scipy_n, rng)
    free["ratios"] = ratios(free)
    rod_block = rod(args.n, args.chunk, args.repeats, args.rounds, args.scipy_n, rng)
    rod_block["ratios"] = ratios(rod_block)
    out = {
        "benchmark": "montecarlo",
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "cores": os.cpu_count(), "devices": jax.device_count(),
                    "device": jax.devices()[0].device_kind,
                    "jax": jax.__version__, "jaxdyn": jd.__version__},
        "settings": {"rtol": RTOL, "atol": ATOL, "chunk": args.chunk,
                     "repeats": args.repeats, "rounds": args.rounds, "check_subset": CHECK},
        "torque_free": free,
        "falling_rod": rod_block,
        "memory": memory(args.chunk),
        "wall_s": time.perf_counter() - start,
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
