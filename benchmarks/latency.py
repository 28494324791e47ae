"""Latency: what a notebook or command-line user waits for.

- **Imports**: `python -c "import jax"`, `"import jaxdyn"` (public names load on first use)
  and `"import jaxdyn._simulate"` (the integration stack: diffrax, equinox...), medians of
  fresh interpreters.
- **Commands**: each command in a fresh process, cold (an empty persistent compilation cache)
  and warm (the same cache, second invocation): wall time from outside, and the command's own
  split into trace, lower, compile and run where it reports one (`jaxdyn run`).
- **Calls**: `jd.simulate` after compilation against a hand-written `jax.jit(diffeqsolve)` of
  the same problem (the vector field written out, parameters passed as arguments, the same
  tableau and tolerances, saving the start and the end), on the free body and on the falling
  rod (with its impact event); the call against jaxdyn's own compiled program; a derived
  output (`traj.omega`, `traj.normal_force`) against its compiled program. Medians of repeats;
  the steps and the final states of both are compared.

Prints one JSON object. Run: `python benchmarks/latency.py [--quick]`.
"""

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time


def _wall(argv, env=None, repeats=1):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        proc = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=900)
        times.append(time.perf_counter() - t0)
        if proc.returncode != 0:
            raise RuntimeError(f"{argv}: {proc.stderr[-500:]}")
        out = proc.stdout
    return statistics.median(times), out


def imports(repeats):
    py = sys.executable
    out = {}
    for name, code in (("jax", "import jax"), ("jaxdyn", "import jaxdyn"),
                       ("jaxdyn_integration", "import jaxdyn._simulate"),
                       ("python", "pass")):
        out[name + "_s"] = _wall([py, "-c", code], repeats=repeats)[0]
    out["jaxdyn_over_jax"] = out["jaxdyn_s"] / out["jax_s"]
    out["integration_over_jax"] = out["jaxdyn_integration_s"] / out["jax_s"]
    return out


def _fit_data(path):
    import numpy as np
    from scipy.integrate import solve_ivp

    inertia = np.array([1.0, 2.0, 3.0])

    def f(t, w):
        return [(inertia[1] - inertia[2]) / inertia[0] * w[1] * w[2],
                (inertia[2] - inertia[0]) / inertia[1] * w[2] * w[0],
                (inertia[0] - inertia[1]) / inertia[2] * w[0] * w[1]]

    ts = np.linspace(0.0, 20.0, 201)
    sol = solve_ivp(f, (0, 20), [0.3, 1.0, 0.2], t_eval=ts, rtol=1e-12, atol=1e-14,
                    method="DOP853")
    rows = ["t,wx,wy,wz"] + [f"{t:.17g},{a:.17g},{b:.17g},{c:.17g}" for t, (a, b, c) in
                             zip(ts, sol.y.T)]
    path.write_text("\n".join(rows) + "\n")


def commands(quick):
    from pathlib import Path

    tmp = Path(tempfile.mkdtemp(prefix="jaxdyn-latency-"))
    data = tmp / "rates.csv"
    _fit_data(data)
    cases = {
        "run": ["run", "--json"],
        "run_torque_free": ["run", "torque-free", "--json"],
        "fit": ["fit", str(data), "--json"],
        "montecarlo": ["montecarlo", "intermediate-axis", "--n", "1000", "--json",
                       "--vary", "omega[0]+=normal(0, 1e-3)"],
        "separatrix": ["separatrix", "--inertia", "1,2,3", "--json"],
        "scenes": ["scenes"],
    }
    if quick:
        cases = {k: cases[k] for k in ("run", "scenes")}
    out = {}
    for name, args in cases.items():
        cache = tmp / f"cache-{name}"
        env = {**os.environ, "JAXDYN_CACHE_DIR": str(cache)}
        argv = [sys.executable, "-m", "jaxdyn._cli", *args]
        cold, text = _wall(argv, env)
        warm, text_warm = _wall(argv, env, repeats=1 if quick else 3)
        row = {"cold_s": cold, "warm_s": warm, "warm_over_cold": warm / cold}
        if "--json" in args and name.startswith("run"):
            row["cold_split"] = json.loads(text)["timing"]
            row["warm_split"] = json.loads(text_warm)["timing"]
        out[name] = row
    return out


def _median_us(fn, repeats):
    import jax

    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e6


def calls(repeats):
    import diffrax as dfx
    import jax
    import jax.numpy as jnp
    import numpy as np
    import optimistix as optx

    import jaxdyn as jd
    from jaxdyn import _simulate

    jax.config.update("jax_enable_x64", True)
    rtol, atol = 1e-8, 1e-10
    out = {}

    # Free body.
    inertia = jnp.array([1.0, 2.0, 3.0])
    scene = jd.Scene(jd.RigidBody(inertia))
    y0 = scene.state(omega=[0.3, 1.0, 0.2])

    def euler(t, w, i):
        return jnp.stack([(i[1] - i[2]) / i[0] * w[1] * w[2], (i[2] - i[0]) / i[1] * w[2] * w[0],
                          (i[0] - i[1]) / i[2] * w[0] * w[1]])

    @jax.jit
    def hand_free(w0, i, t1):
        return dfx.diffeqsolve(dfx.ODETerm(euler), dfx.Tsit5(), 0.0, t1, None, w0, args=i,
                               stepsize_controller=dfx.PIDController(rtol=rtol, atol=atol),
                               saveat=dfx.SaveAt(t0=True, t1=True), max_steps=100_000)

    # Falling rod, to impact.
    rod = jd.FallingRod(length=1.0, mass=1.0, g=9.81)
    rscene = jd.Scene(rod)
    r0 = rscene.state(theta=0.1)

    def rod_vf(t, y, p):
        length, g = p
        th, om = y
        s, c = jnp.sin(th), jnp.cos(th)
        acc = 3 * s * (2 * g - length * om**2 * c) / (length * (1 + 3 * s**2))
        return jnp.stack([om, acc])

    @jax.jit
    def hand_rod(y, p, t1):
        event = dfx.Event(lambda t, y, args, **kw: jnp.pi / 2 - jnp.abs(y[0]),
                          root_finder=optx.Newton(rtol=1e-12, atol=1e-12))
        return dfx.diffeqsolve(dfx.ODETerm(rod_vf), dfx.Tsit5(), 0.0, t1, None, y, args=p,
                               stepsize_controller=dfx.PIDController(rtol=rtol, atol=atol),
                               saveat=dfx.SaveAt(t0=True, t1=True), max_steps=100_000,
                               event=event)

    cases = {
        "free_body": (scene, y0, 20.0, lambda: hand_free(y0["omega"], inertia, 20.0), "omega"),
        "falling_rod": (rscene, r0, 10.0,
                        lambda: hand_rod(jnp.stack([r0["theta"], r0["theta_dot"]]),
                                         (rod.length, rod.g), 10.0), "normal_force"),
    }
    for name, (sc, y, t1, hand, output) in cases.items():
        sim_us = _median_us(lambda sc=sc, y=y, t1=t1: jd.simulate(sc, y, t1, rtol=rtol),
                            repeats)
        hand_us = _median_us(hand, repeats)
        traj = jd.simulate(sc, y, t1, rtol=rtol)
        sol = hand()
        # jaxdyn's own compiled program, called directly (no host checks, no Trajectory).
        leaves, treedef = jax.tree_util.tree_flatten(sc)
        key = next(k for k in _simulate._PROGRAMS if k[:2] == ("simulate", treedef))
        prog = _simulate._PROGRAMS[key]
        args = (leaves, y, np.asarray(0.0), np.asarray(t1), None, np.asarray(rtol),
                np.asarray(0.0))
        prog_us = _median_us(lambda prog=prog, args=args: prog(*args), repeats)
        outputs_program = jax.jit(jax.vmap(sc.outputs))
        out_prog_us = _median_us(lambda traj=traj: outputs_program(traj.ts, traj.ys), repeats)
        out_us = _median_us(lambda traj=traj, output=output: getattr(traj, output), repeats)
        final_ours = np.concatenate([np.ravel(v) for v in traj.y_final.values()])
        final_hand = np.ravel(np.asarray(sol.ys)[-1])
        out[name] = {
            "simulate_us": sim_us, "hand_jit_diffeqsolve_us": hand_us,
            "simulate_over_hand": sim_us / hand_us,
            "jaxdyn_program_us": prog_us, "simulate_over_program": sim_us / prog_us,
            "steps": int(traj.stats["num_steps"]), "hand_steps": int(sol.stats["num_steps"]),
            "final_state_difference": float(np.max(np.abs(final_ours[:final_hand.size]
                                                          - final_hand))),
            f"{output}_us": out_us, "outputs_program_us": out_prog_us,
            "output_over_program": out_us / out_prog_us,
        }
    return out


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    t0 = time.perf_counter()
    result = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "imports": imports(3 if args.quick else 7),
        "commands": commands(args.quick),
        "calls": calls(100 if args.quick else 500),
    }
    result["wall_s"] = time.perf_counter() - t0
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
