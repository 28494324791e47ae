"""Latency: what a notebook or command-line user waits for.

- **Imports**: `python -c "import jax"`, `"import jaxdyn"` (public names load on first use),
  `"import jaxdyn._simulate"` (the integration stack: diffrax, equinox...) and `"import
  ml_dtypes"` (JAX's dtypes, part of `import jax`: 0.6-0.9 s in version 0.7.0, 5 ms in
  0.6.0), medians of fresh interpreters, and the versions of the libraries imported.
- **Commands**: each command in a fresh process, cold (an empty persistent compilation cache)
  and warm (the same cache, second invocation): wall time from outside, and the command's own
  split into trace, lower, compile and run where it reports one (`jaxdyn run`). With
  `--baseline PYTHON`, the same commands run with another interpreter's jaxdyn (the code
  before issue 19, say), alternating with this code over `--rounds` rounds, and each row
  gives the ratios to it.
- **Calls**: `jd.simulate` after compilation against a hand-written `jax.jit(diffeqsolve)` of
  the same problem (the vector field written out, parameters passed as arguments, the same
  tableau and tolerances, saving the start and the end), on the free body and on the falling
  rod (with its impact event), as written (diffrax's runtime check on: a host callback, which
  makes XLA:CPU run the program on the calling thread) and without that check (as jaxdyn's
  programs, which hold no host callback: XLA:CPU then runs a program on a worker thread unless
  its cost estimate, also reported, is under 1000 operations); the call against jaxdyn's own
  compiled program; a derived
  output (`traj.omega`, `traj.normal_force`) against its compiled program, accessed again on
  one trajectory and first accessed on each of many new runs of the same scene; the dense
  output (`traj.evaluate` at 200 times, `traj.resample(200)`) against a hand-written
  `jax.jit` of the same interpolation over the trajectory's arrays; `jd.torque_free_omega`
  and `jd.torque_free_attitude` (NumPy inputs, 200 times) against their compiled programs
  (and the attitude program's compile time). Medians of
  repeats,
  taken in rounds that call each of the compared functions in turn (so that a slower phase of
  the machine weighs on all of them alike); the steps and the final states of both are
  compared.
- **Again**: each public entry point (`simulate`, a derived output, `ensemble` in both
  modes, `fit`, `find_equilibria`, `trace_separatrices`, `torque_free_attitude`) called once,
  then on the same structure with other values: the second call's traces, compilations and
  programs read from jaxdyn's store (which emit neither event), which issue 19 asks to be
  none, and its wall time.
- **Samples**: `jd.simulate(..., ts=...)` of the free body over 100 s (681 steps)
  against the number of sample times (1e2 to 1e5; 1e6 without `--quick`), after compilation,
  against a hand-written `jax.jit(diffeqsolve)` with diffrax's `SaveAt(ts)` and against the
  way jaxdyn saved before (the sample buffer in the solver state, which diffrax copies at
  every step: `O(samples x steps)`; up to 1e4 samples), in the same process.

- **Loops**: `jd.simulate` of each built-in scene after compilation, saving its start and end
  and at 500 times, in two child processes that differ only in XLA:CPU's small-loop threshold:
  XLA's default (1 KiB) and the command's setting (`jaxdyn._xla`: a while loop touching less
  than 64 KiB per iteration compiled as one function). Medians of repeats in each child,
  the children alternating over `--rounds` rounds (a process-wide setting: no one process can
  hold both); per scene the median of the rounds, the ratio default / setting, and each
  child's compile time of its first calls.

- **Targets**: issue 19's targets that the sections run measured, each with its value, its
  bound and whether it is met (`targets`): `simulate` (start and end; and with 1e2, 1e3 and
  1e4 saved times) and derived outputs against their references, the warm `jaxdyn run`
  against importing what it needs (`import jaxdyn` itself loads its names on first use, so
  the bound is the import of the integration stack), the
  warm `jaxdyn fit` under 3 s, `import jaxdyn` against `import jax`, and with `--baseline`
  each cold command against the code before. All ratios come from this one run.

Prints one JSON object. Run: `python benchmarks/latency.py [--quick]`; the commands against
the code before issue 19 (ebc494a, its own virtual environment):
`python benchmarks/latency.py --only commands --rounds 3 --baseline /path/to/venv/bin/python`.
"""

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time


def _wall(argv, env=None, repeats=1, cwd=None):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        proc = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=900,
                              cwd=cwd)
        times.append(time.perf_counter() - t0)
        if proc.returncode != 0:
            raise RuntimeError(f"{argv}: {proc.stderr[-500:]}")
        out = proc.stdout
    return statistics.median(times), out


# Where an interpreter's jaxdyn is, and the versions of what importing it loads: JAX's
# import time depends on them (ml_dtypes 0.7.0 alone takes 0.6-0.9 s, 0.6.0 5 ms).
_VERSIONS = ("import json, importlib.metadata as m, jaxdyn; print(json.dumps({'jaxdyn': "
             "jaxdyn.__file__, **{p: m.version(p) for p in ('jax', 'jaxlib', 'ml_dtypes', "
             "'numpy', 'diffrax', 'equinox')}}))")


def imports(repeats):
    py = sys.executable
    out = {"versions": json.loads(_wall([py, "-c", _VERSIONS])[1])}
    for name, code in (("jax", "import jax"), ("jaxdyn", "import jaxdyn"),
                       ("jaxdyn_integration", "import jaxdyn._simulate"),
                       ("ml_dtypes", "import ml_dtypes"), ("python", "pass")):
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


def commands(quick, baseline=None, rounds=1):
    """Each command cold and warm in fresh processes; with `baseline` (a Python interpreter
    whose `jaxdyn` is other code, such as a virtual environment holding the commit before
    issue 19), the same commands with that code too, the two alternating in each of `rounds`
    rounds so that a phase of the machine weighs on both alike; medians over the rounds."""
    from pathlib import Path

    # (The cold starts' caches and the fit's data, removed afterwards.)
    with tempfile.TemporaryDirectory(prefix="jaxdyn-latency-") as folder:
        return _commands_in(Path(folder), quick, baseline, rounds)


def _commands_in(tmp, quick, baseline, rounds):
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
    codes = {"now": sys.executable}
    if baseline:
        codes["baseline"] = baseline
    # The commands run in the temporary folder: from a source checkout, `python -m` would
    # import the checkout's jaxdyn whatever the interpreter. Each code's jaxdyn is reported,
    # with the versions of the libraries its imports load (`_VERSIONS`).
    where = {code: json.loads(_wall([python, "-c", _VERSIONS], cwd=tmp)[1])
             for code, python in codes.items()}
    runs = {(name, code): {"cold": [], "warm": []} for name in cases for code in codes}
    splits = {}
    for r in range(rounds):
        for name, args in cases.items():
            for code, python in codes.items():
                cache = tmp / f"cache-{name}-{code}-{r}"  # empty: a cold start
                env = {**os.environ, "JAXDYN_CACHE_DIR": str(cache)}
                argv = [python, "-m", "jaxdyn._cli", *args]
                cold, text = _wall(argv, env, cwd=tmp)
                warm, text_warm = _wall(argv, env, repeats=1 if quick else 3, cwd=tmp)
                runs[name, code]["cold"].append(cold)
                runs[name, code]["warm"].append(warm)
                if code == "now" and "--json" in args and name.startswith("run"):  # last round's
                    splits[name] = {"cold_split": json.loads(text)["timing"],
                                    "warm_split": json.loads(text_warm)["timing"]}
    out = {}
    for name in cases:
        now = runs[name, "now"]
        row = {"cold_s": statistics.median(now["cold"]),
               "warm_s": statistics.median(now["warm"])}
        row["warm_over_cold"] = row["warm_s"] / row["cold_s"]
        if baseline:
            base = runs[name, "baseline"]
            row["baseline_cold_s"] = statistics.median(base["cold"])
            row["baseline_warm_s"] = statistics.median(base["warm"])
            row["cold_over_baseline_cold"] = row["cold_s"] / row["baseline_cold_s"]
            row["warm_over_baseline_warm"] = row["warm_s"] / row["baseline_warm_s"]
            row["rounds"] = {code: runs[name, code] for code in codes}
        out[name] = {**row, **splits.get(name, {})}
    out["jaxdyn"] = where
    return out


def _new_length_s(fn, t_end):
    """The median time of `fn(t)` over five numbers of times not seen before (201-220, evenly
    spaced from 0 to `t_end`), after a call at 200: the first call at each new length."""
    import jax
    import numpy as np

    times = []
    for n in (201, 205, 210, 215, 220):
        t = np.linspace(0.0, t_end, n)
        start = time.perf_counter()
        jax.block_until_ready(fn(t))
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _median_us(fn, repeats):
    return _medians_us([fn], repeats)[0]


def _medians_us(fns, repeats):
    """The median time of each of `fns` (microseconds) over `repeats` rounds, each round
    calling every one in turn: a slower phase of the machine (another process, the clock)
    then weighs on all of them alike, and their ratios hold across runs."""
    import jax

    for fn in fns:
        jax.block_until_ready(fn())
    times = [[] for _ in fns]
    for _ in range(repeats):
        for fn, t in zip(fns, times):
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            t.append(time.perf_counter() - t0)
    return [statistics.median(t) * 1e6 for t in times]


def _free_body():
    """The free body of `calls` and `samples` (float64 enabled first): its inertia, scene,
    initial state, and Euler's equations written out for the hand-written programs."""
    import jax.numpy as jnp

    import jaxdyn as jd

    inertia = jnp.array([1.0, 2.0, 3.0])
    scene = jd.Scene(jd.RigidBody(inertia))

    def euler(t, w, i):
        return jnp.stack([(i[1] - i[2]) / i[0] * w[1] * w[2], (i[2] - i[0]) / i[1] * w[2] * w[0],
                          (i[0] - i[1]) / i[2] * w[0] * w[1]])

    return inertia, scene, scene.state(omega=[0.3, 1.0, 0.2]), euler


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

    inertia, scene, y0, euler = _free_body()

    def hand_free(w0, i, t1, throw=True):
        return dfx.diffeqsolve(dfx.ODETerm(euler), dfx.Tsit5(), 0.0, t1, None, w0, args=i,
                               stepsize_controller=dfx.PIDController(rtol=rtol, atol=atol),
                               saveat=dfx.SaveAt(t0=True, t1=True), max_steps=100_000,
                               throw=throw)

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

    def hand_rod(y, p, t1, throw=True):
        event = dfx.Event(lambda t, y, args, **kw: jnp.pi / 2 - jnp.abs(y[0]),
                          root_finder=optx.Newton(rtol=1e-12, atol=1e-12))
        return dfx.diffeqsolve(dfx.ODETerm(rod_vf), dfx.Tsit5(), 0.0, t1, None, y, args=p,
                               stepsize_controller=dfx.PIDController(rtol=rtol, atol=atol),
                               saveat=dfx.SaveAt(t0=True, t1=True), max_steps=100_000,
                               event=event, throw=throw)

    # The hand-written programs as written (`throw=True`: diffrax's runtime check, a host
    # callback, which also makes XLA:CPU run the program on the calling thread), and without
    # the check (`throw=False`, as jaxdyn's programs: a program XLA estimates at 1000
    # operations or more then runs on a worker thread).
    def hands(fn, *args):
        return tuple(jax.jit(lambda *a, throw=throw: fn(*a, throw=throw)) for throw in
                     (True, False)), args

    cases = {
        "free_body": (scene, y0, 20.0, hands(hand_free, y0["omega"], inertia, 20.0), "omega"),
        "falling_rod": (rscene, r0, 10.0,
                        hands(hand_rod, jnp.stack([r0["theta"], r0["theta_dot"]]),
                              (rod.length, rod.g), 10.0), "normal_force"),
    }
    for name, (sc, y, t1, ((hand_jit, quiet_jit), hand_args), output) in cases.items():
        def hand(hand_jit=hand_jit, hand_args=hand_args):
            return hand_jit(*hand_args)

        # Each call timed until its saved states are ready (blocking on the whole result
        # would also time the flattening of its tree: 10-20 us for a `Trajectory`, which
        # holds its scene; `jd.simulate` has read the run's outcome, so its result is ready
        # when it returns). The whole result is timed too (`simulate_whole_result_us`).
        traj = jd.simulate(sc, y, t1, rtol=rtol)
        sol = hand()
        # jaxdyn's own compiled program, called directly (no host checks, no Trajectory).
        leaves, treedef = jax.tree_util.tree_flatten(sc)
        key = next(k for k in _simulate._PROGRAMS if k[:2] == ("simulate", treedef))
        prog = _simulate._PROGRAMS[key]
        args = (leaves, y, np.array([0.0, t1, rtol, 0.0]), None)  # (t0, t1, rtol, atol)
        # Timed in turn, round by round (`_medians_us`).
        sim_us, sim_whole_us, hand_us, quiet_us, prog_us = _medians_us([
            lambda sc=sc, y=y, t1=t1: jd.simulate(sc, y, t1, rtol=rtol).ys,
            lambda sc=sc, y=y, t1=t1: jd.simulate(sc, y, t1, rtol=rtol),
            lambda: hand().ys,
            lambda q=quiet_jit, a=hand_args: q(*a).ys,
            lambda prog=prog, args=args: prog(*args)[1],  # ys
        ], repeats)
        cost = prog.jitted.lower(*args).compile().cost_analysis()
        hand_cost = quiet_jit.lower(*hand_args).compile().cost_analysis()
        cost, hand_cost = (c[0] if isinstance(c, list) else c for c in (cost, hand_cost))
        outputs_program = jax.jit(jax.vmap(sc.outputs))
        out_prog_us, out_us = _medians_us([
            lambda traj=traj: outputs_program(traj.ts, traj.ys),
            lambda traj=traj, output=output: getattr(traj, output)], repeats)
        # The first access on each of `repeats` new runs of the same scene object (the
        # repeated access above reuses the last access's program call; a new run needs its
        # own), in turn with the program on the same run, which of the two goes first
        # alternating from one run to the next.
        fresh = [jd.simulate(sc, y, t1, rtol=rtol) for _ in range(repeats)]
        first, program_first = [], []
        for i, tr in enumerate(fresh):
            pair = [(lambda: getattr(tr, output), first),
                    (lambda: outputs_program(tr.ts, tr.ys), program_first)]
            for fn, times in pair[::1 if i % 2 else -1]:
                t0 = time.perf_counter()
                jax.block_until_ready(fn())
                times.append(time.perf_counter() - t0)
        first_us = statistics.median(first) * 1e6
        program_first_us = statistics.median(program_first) * 1e6
        # The dense output: `traj.evaluate` at 200 times and `traj.resample(200)`, against
        # the same computation as a hand-written `jax.jit` over the trajectory's arrays.
        dense = jd.simulate(sc, y, t1, rtol=rtol, dense=True)
        t_eval = np.linspace(0.0, float(dense.t_final), 200)
        d_leaves, d_tree = jax.tree_util.tree_flatten(dense)

        def hand_samples(leaves, t=None):
            tr = jax.tree_util.tree_unflatten(d_tree, leaves)
            if t is None:
                t = jnp.linspace(tr.interpolation.t0, tr.t_final, 200)
            return jax.vmap(tr.interpolation.evaluate)(t)

        hand = jax.jit(hand_samples)  # (one program for each: with and without `t`)
        ev_us, ev_hand_us, rs_us, rs_hand_us = _medians_us([
            lambda: dense.evaluate(t_eval), lambda: hand(d_leaves, t_eval),
            lambda: dense.resample(200).ys, lambda: hand(d_leaves)], repeats)
        # `traj.evaluate` at a number of times not seen before (201-220 share the padded
        # length of 200: only the small program that cuts the padding off is new).
        new_length_s = _new_length_s(dense.evaluate, float(dense.t_final))
        final_ours = np.concatenate([np.ravel(v) for v in traj.y_final.values()])
        final_hand = np.ravel(np.asarray(sol.ys)[-1])
        out[name] = {
            "simulate_us": sim_us, "simulate_whole_result_us": sim_whole_us,
            "hand_jit_diffeqsolve_us": hand_us,
            "simulate_over_hand": sim_us / hand_us,
            "hand_without_check_us": quiet_us, "simulate_over_hand_without_check":
                sim_us / quiet_us,
            "jaxdyn_program_flops": cost.get("flops"),
            "hand_without_check_flops": hand_cost.get("flops"),
            "jaxdyn_program_us": prog_us, "simulate_over_program": sim_us / prog_us,
            "steps": int(traj.stats["num_steps"]), "hand_steps": int(sol.stats["num_steps"]),
            "final_state_difference": float(np.max(np.abs(final_ours[:final_hand.size]
                                                          - final_hand))),
            f"{output}_us": out_us, "outputs_program_us": out_prog_us,
            "output_over_program": out_us / out_prog_us,
            f"new_trajectory_{output}_us": first_us,
            "new_trajectory_output_over_program": first_us / program_first_us,
            "evaluate_200_us": ev_us, "hand_jit_evaluate_us": ev_hand_us,
            "evaluate_over_hand": ev_us / ev_hand_us,
            "evaluate_new_length_s": new_length_s,
            "resample_200_us": rs_us, "hand_jit_resample_us": rs_hand_us,
            "resample_over_hand": rs_us / rs_hand_us,
        }
    # The closed form of the free body's rates (`jd.torque_free_omega`, inputs given as NumPy
    # arrays, as from a notebook) at 200 times, against its own compiled program called with
    # JAX arrays (no checks, no conversions).
    from jaxdyn._free_body import _torque_free_omega

    host = (np.array([1.0, 2.0, 3.0]), np.array([0.3, 1.0, 0.2]), np.linspace(0.0, 20.0, 200))
    device = tuple(jnp.asarray(a) for a in host)
    closed_us, closed_program_us = _medians_us([lambda: jd.torque_free_omega(*host),
                                                lambda: _torque_free_omega(*device)], repeats)
    out["torque_free_omega"] = {"call_us": closed_us, "program_us": closed_program_us,
                                "call_over_program": closed_us / closed_program_us}
    # The closed-form attitude (`jd.torque_free_attitude`) likewise, and its program's compile
    # time (a fresh `jax.jit` of the same function: no persistent cache in this process).
    from jaxdyn._free_body_attitude import _torque_free_attitude

    q0 = np.array([1.0, 0.2, -0.1, 0.3])
    host = (*host[:2], q0, host[2])
    device = tuple(jnp.asarray(a) for a in host)
    fresh = jax.jit(_torque_free_attitude.__wrapped__)
    start = time.perf_counter()
    fresh.lower(*device).compile()
    compile_s = time.perf_counter() - start
    attitude_us, attitude_program_us = _medians_us(
        [lambda: jd.torque_free_attitude(*host), lambda: _torque_free_attitude(*device)],
        repeats)
    out["torque_free_attitude"] = {"call_us": attitude_us, "program_us": attitude_program_us,
                                   "call_over_program": attitude_us / attitude_program_us,
                                   "compile_s": compile_s}
    # A number of times not seen before (a notebook's slider over the time span): the times
    # are padded to one of a few lengths (201-224 share the program of 200), so only the small
    # program that cuts the padding off is new. Medians over five new lengths each.
    for name, fn in (("torque_free_omega", lambda t: jd.torque_free_omega(*host[:2], t)),
                     ("torque_free_attitude", lambda t: jd.torque_free_attitude(*host[:3], t))):
        out[name]["new_length_s"] = _new_length_s(fn, 20.0)
    out["torque_free_attitude"]["new_length_over_compile"] = (
        out["torque_free_attitude"]["new_length_s"] / compile_s)
    return out


def again():
    """Issue 19's "no per-call tracing": each public entry point called once, then again on
    the same structure with other values (other moments, rates, data, momenta, keys); the
    second call's traces and compilations (JAX's monitoring events) and its wall time."""
    import jax
    import numpy as np

    import jaxdyn as jd

    jax.config.update("jax_enable_x64", True)
    events = []

    def listen(event, duration, **kwargs):
        if event in ("/jax/core/compile/jaxpr_trace_duration",
                     "/jax/core/compile/backend_compile_duration"):
            events.append((event.rsplit("/", 1)[1], kwargs.get("fun_name", "")))

    # (Bodies away from the flat plate, I1 + I2 = I3, where a fit's shape logits run to
    # infinity and its iterations are many.)
    free = [jd.Scene(jd.RigidBody(i)) for i in ([1.0, 2.0, 2.5], [2.0, 2.5, 4.0])]
    rods = [jd.Scene(jd.FallingRod(length=x)) for x in (1.0, 2.5)]
    rates = ([0.3, 1.0, 0.2], [-0.1, 0.5, 0.7])
    ts = np.linspace(0.0, 5.0, 41)
    truth = jd.simulate(free[0], free[0].state(omega=rates[0]), 5.0, ts=ts)
    rng = np.random.default_rng(0)
    data = [{"omega": np.asarray(truth.ys["omega"]) + 1e-4 * rng.normal(size=(41, 3))}
            for _ in range(2)]
    gyrostat = [jd.Scene(jd.RigidBody([1.0, 2.0, 3.0]), (jd.Rotor(momentum=[0.0, 0.0, h]),))
                for h in (0.2, 0.5)]
    cases = {
        "simulate": lambda k: jd.simulate(free[k], free[k].state(omega=rates[k]), 5.0, ts=ts),
        "simulate_rod": lambda k: jd.simulate(rods[k], rods[k].state(theta=0.1 + 0.1 * k),
                                              10.0),
        "derived_output": lambda k: jd.simulate(free[k], free[k].state(omega=rates[k]), 5.0,
                                                ts=ts).kinetic_energy,
        "ensemble": lambda k: jd.ensemble(free[k], free[k].state(omega=rates[k]), 5.0, n=64,
                                          vary={"omega": jd.Normal(rates[k], 0.01)}, key=k),
        "ensemble_vmap": lambda k: jd.ensemble(rods[k], rods[k].state(theta=0.1), 10.0, n=64,
                                               vary={"theta": jd.Uniform(0.05, 0.2)}, key=k,
                                               mode="vmap"),
        "fit": lambda k: jd.fit(free[0], ts, data[k], parameters={"inertia": jd.ValidInertia()},
                                initial=["omega"]),
        "find_equilibria": lambda k: jd.find_equilibria(gyrostat[k], 1.0 + k),
        "trace_separatrices": lambda k: jd.trace_separatrices(free[k], 1.0 + k),
        "torque_free_attitude": lambda k: jd.torque_free_attitude(
            [1.0, 2.0, 2.5 + 0.4 * k], rates[k], [1.0, 0.0, 0.0, 0.0], ts),
    }
    # A program jaxdyn reads from its own store emits neither event: its stored programs'
    # resolutions of a signature not seen before in this process are counted as well.
    from jaxdyn import _programs

    resolved = []
    load = _programs.StoredProgram._load

    def counted_load(self, *args, **kwargs):
        resolved.append(self)
        return load(self, *args, **kwargs)

    out = {}
    jax.monitoring.register_event_duration_secs_listener(listen)
    _programs.StoredProgram._load = counted_load
    try:
        for name, call in cases.items():
            jax.block_until_ready(jax.tree.leaves(call(0)))
            # (The listener hears every thread: what the first call left preparing on the
            # other core is finished before the second call is counted.)
            for thread in threading.enumerate():
                if thread.name == "jaxdyn-prepare":
                    thread.join()
            events.clear()
            resolved.clear()
            start = time.perf_counter()
            jax.block_until_ready(jax.tree.leaves(call(1)))
            wall = time.perf_counter() - start
            traced = [n for e, n in events if e == "jaxpr_trace_duration"]
            out[name] = {"traces": len(traced), "compilations": len(events) - len(traced),
                         "stored_programs_resolved": len(resolved),
                         "traced": sorted(set(traced)), "second_call_ms": 1e3 * wall}
    finally:
        _programs.StoredProgram._load = load
        jax.monitoring.unregister_event_duration_listener(listen)
    return out


def samples(quick):
    import diffrax as dfx
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxdyn as jd
    from jaxdyn._solvers._wrapped import AbstractDelegatingSolver

    jax.config.update("jax_enable_x64", True)
    rtol, t1 = 1e-8, 100.0
    inertia, scene, y0, euler = _free_body()

    class BufferInSolverState(AbstractDelegatingSolver):  # jaxdyn's `Sampled` at 6d3d62c
        solver: dfx.AbstractSolver
        ts: jax.Array

        def init(self, terms, t0, t1, y0, args):
            ys = jnp.full(self.ts.shape + y0.shape, jnp.inf)
            return self.solver.init(terms, t0, t1, y0, args), ys, jnp.asarray(0)

        def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
            inner, ys, index = solver_state
            y1, err, info, inner, result = self.solver.step(terms, t0, t1, y0, args, inner,
                                                            made_jump)
            interp = self.solver.interpolation_cls(t0=t0, t1=t1, **info)
            ts, n = self.ts, self.ts.size
            ys, index = jax.lax.while_loop(
                lambda c: (c[1] < n) & (ts[jnp.minimum(c[1], n - 1)] <= t1),
                lambda c: (c[0].at[c[1]].set(interp.evaluate(ts[c[1]])), c[1] + 1), (ys, index))
            return y1, err, info, (inner, ys, index), result

    controller = dfx.PIDController(rtol=rtol, atol=1e-10)

    @jax.jit
    def hand_saveat(w0, ts):
        return dfx.diffeqsolve(dfx.ODETerm(euler), dfx.Tsit5(), 0.0, t1, None, w0, args=inertia,
                               stepsize_controller=controller, saveat=dfx.SaveAt(ts=ts),
                               max_steps=100_000).ys

    @jax.jit
    def hand_before(w0, ts):
        sol = dfx.diffeqsolve(dfx.ODETerm(euler), BufferInSolverState(dfx.Tsit5(), ts), 0.0, t1,
                              None, w0, args=inertia, stepsize_controller=controller,
                              saveat=dfx.SaveAt(solver_state=True), max_steps=100_000)
        return sol.solver_state[1]

    out = {}
    sizes = [100, 1_000, 10_000, 100_000] + ([] if quick else [1_000_000])
    for n in sizes:
        ts = np.linspace(0.0, t1, n)
        repeats = (10 if quick else 40) if n <= 10_000 else (3 if quick else 9)
        t0 = time.perf_counter()
        traj = jd.simulate(scene, y0, t1, ts=ts, rtol=rtol)
        first = time.perf_counter() - t0
        fns = [lambda: jd.simulate(scene, y0, t1, ts=ts, rtol=rtol).ys,
               lambda: hand_saveat(y0["omega"], ts)]
        if n <= 10_000:
            fns.append(lambda: hand_before(y0["omega"], ts))
        # (Alternating: their ratios hold across the machine's phases.)
        times_us = _medians_us(fns, repeats)
        row = {"simulate_ms": times_us[0] / 1e3, "first_call_s": first,
               "steps": int(traj.stats["num_steps"]), "hand_saveat_ms": times_us[1] / 1e3}
        row["simulate_over_hand_saveat"] = row["simulate_ms"] / row["hand_saveat_ms"]
        if n <= 10_000:
            row["before_ms"] = times_us[2] / 1e3
            row["before_over_simulate"] = row["before_ms"] / row["simulate_ms"]
        out[str(n)] = row
    return out


LOOP_SCENES = ("falling-rod", "torque-free", "intermediate-axis", "gyrostat", "dual-spinner",
               "explorer-1", "gravity-gradient", "reaction-wheels", "wheels-with-dumping",
               "thruster-despin", "bdot-detumble", "rough-floor-rod")


def _loops_child(repeats):
    """One child of `loops`: per scene, the median call of `jd.simulate` (start and end; 500
    saved times), and the first calls' time (compilation), as JSON on stdout."""
    import jax
    import numpy as np

    import jaxdyn as jd

    jax.config.update("jax_enable_x64", True)
    out = {}
    for name in LOOP_SCENES:
        s = jd.load_scene(name)
        ts = np.linspace(0.0, s.t1, 500)
        start = time.perf_counter()
        jax.block_until_ready(jd.simulate(s.scene, s.y0, s.t1).ys)
        jax.block_until_ready(jd.simulate(s.scene, s.y0, s.t1, ts=ts).ys)
        first = time.perf_counter() - start
        ends, sampled = _medians_us([
            lambda s=s: jd.simulate(s.scene, s.y0, s.t1).ys,
            lambda s=s, ts=ts: jd.simulate(s.scene, s.y0, s.t1, ts=ts).ys], repeats)
        out[name] = {"ends_ms": ends / 1e3, "ts500_ms": sampled / 1e3, "first_calls_s": first}
    print(json.dumps(out))


def loops(rounds, repeats):
    """`_loops_child` with XLA's default small-loop threshold and with the command's, the
    two alternating over `rounds` rounds (both with the command's other setting)."""
    from jaxdyn import _xla

    default = f"--{_xla.EXTRA}={_xla.LOOP_OPTION}=1024"
    flags = {"default": f"{_xla.SETTING} {default}",
             "setting": f"{_xla.SETTING} {_xla.LOOP_SETTING}"}
    runs = {k: [] for k in flags}
    for _ in range(rounds):
        for key, xla_flags in flags.items():
            env = {**os.environ, "XLA_FLAGS": xla_flags, "JAXDYN_CACHE_DIR": "off"}
            _, stdout = _wall([sys.executable, __file__, "--loops-child", str(repeats)], env)
            runs[key].append(json.loads(stdout))
    out = {"flags": flags, "rounds": rounds, "scenes": {}}
    for name in LOOP_SCENES:
        row = {}
        for key in flags:
            for field in ("ends_ms", "ts500_ms", "first_calls_s"):
                row[f"{field}_{key}"] = statistics.median(r[name][field] for r in runs[key])
        for field in ("ends_ms", "ts500_ms"):
            row[f"{field}_default_over_setting"] = (row[f"{field}_default"]
                                                    / row[f"{field}_setting"])
        out["scenes"][name] = row
    return out


def targets(result: dict) -> dict:
    """Issue 19's targets measured by the sections in `result`: value, bound, met."""
    out = {}

    def target(name, value, bound, below=True):
        out[name] = {"value": value, "bound": bound,
                     "met": bool(value <= bound if below else value >= bound)}

    calls = result.get("calls", {})
    for problem in ("free_body", "falling_rod"):
        if problem in calls:
            target(f"simulate_call_over_hand_jit_{problem}",
                   calls[problem]["simulate_over_hand"], 1.5)
            target(f"derived_output_over_program_{problem}",
                   calls[problem]["output_over_program"], 2.0)
    samples = result.get("samples", {})
    for n in ("100", "1000", "10000"):  # (the call with saved times, XLA's defaults)
        if n in samples:
            target(f"simulate_{n}_samples_over_hand_saveat",
                   samples[n]["simulate_over_hand_saveat"], 1.5)
    for name, row in result.get("again", {}).items():
        target(f"traces_on_second_call_{name}", row["traces"], 0)
        target(f"programs_made_or_read_on_second_call_{name}",
               row["compilations"] + row["stored_programs_resolved"], 0)
    imports, commands = result.get("imports", {}), result.get("commands", {})
    if imports:
        target("import_jaxdyn_over_import_jax", imports["jaxdyn_over_jax"], 1.5)
    if imports and "run" in commands:
        target("warm_run_over_import_of_integration_stack",
               commands["run"]["warm_s"] / imports["jaxdyn_integration_s"], 1.5)
    if "fit" in commands:
        target("warm_fit_s", commands["fit"]["warm_s"], 3.0)
    for name, row in commands.items():
        if isinstance(row, dict) and "cold_over_baseline_cold" in row:
            target(f"cold_{name}_over_before", row["cold_over_baseline_cold"], 0.5)
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help="fewer repeats, the quick commands, samples up to 1e5")
    parser.add_argument("--baseline", metavar="PYTHON",
                        help="commands: also time them with this interpreter's jaxdyn (for "
                             "example a virtual environment holding the code before issue "
                             "19), alternating with this code, and report the ratios")
    parser.add_argument("--rounds", type=int, default=1,
                        help="commands: rounds of cold and warm runs (medians over them); "
                             "loops: rounds of the two children (at least 3)")
    parser.add_argument("--only",
                        choices=("imports", "commands", "calls", "again", "samples", "loops"),
                        help="one section alone")
    parser.add_argument("--loops-child", type=int, metavar="REPEATS", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.loops_child is not None:
        return _loops_child(max(args.loops_child, 1))
    t0 = time.perf_counter()
    sections = {
        "imports": lambda: imports(3 if args.quick else 7),
        "commands": lambda: commands(args.quick, args.baseline, args.rounds),
        "calls": lambda: calls(100 if args.quick else 500),
        "again": again,
        "samples": lambda: samples(args.quick),
        "loops": lambda: loops(max(args.rounds, 3), 5 if args.quick else 15),
    }
    result = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version()}}
    for name, section in sections.items():
        if args.only in (None, name):
            result[name] = section()
    result["targets"] = targets(result)
    result["wall_s"] = time.perf_counter() - t0
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
