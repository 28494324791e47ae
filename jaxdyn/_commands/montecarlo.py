"""`jaxdyn montecarlo`: run a scene over many sampled parameters and initial values."""

import time

from ._common import (
    add_scene_arguments,
    bounded_int,
    check_output_file,
    emit,
    enable_x64,
    parse_sets,
)

HELP = "Monte Carlo ensemble of a scene: statistics of its outputs"


def add_arguments(p) -> None:
    from .._distributions import DISTRIBUTION_SYNTAX

    add_scene_arguments(p)
    p.add_argument("--n", type=bounded_int("--n", 1, 2**31 - 1), required=True,
                   help="number of trajectories")
    p.add_argument("--vary", action="append", default=[], metavar="NAME=DIST",
                   help=f"a varied quantity (repeatable): {DISTRIBUTION_SYNTAX}; e.g. "
                        "--vary 'omega[0]+=normal(0, 0.01)' --vary 'inertia*=lognormal(1, 0.01)'")
    p.add_argument("--seed", type=bounded_int("--seed", 0, 2**63 - 1), default=0,
                   help="random seed (default 0)")
    p.add_argument("--mode", choices=("adaptive", "lockstep", "vmap"), default="adaptive",
                   help="per-trajectory steps (default), one step size for the batch, or "
                        "jax.vmap over simulate (any scene)")
    p.add_argument("--chunk", type=bounded_int("--chunk", 1, 2**31 - 1),
                   help="trajectories per compiled call (default: equal chunks of at most 16384)")
    p.add_argument("--out", metavar="DIR",
                   help="write each finished chunk here; run again to resume")
    p.add_argument("--progress", action="store_true", help="show a progress bar")
    p.add_argument("--export", metavar="FILE",
                   help="write one row per trajectory (status, steps, varied and observed "
                        "values): FILE.csv or FILE.nc (NetCDF); needs pip install "
                        "'jaxdyn[data]'")
    p.add_argument("--devices", type=bounded_int("--devices", 1, 4096), default=None,
                   help="CPU devices to shard each chunk across (default: one per core)")


def cpu_devices(count: int | None) -> None:
    """Expose `count` JAX CPU devices (default: one per core), so that a chunk is sharded
    across every core. Left alone where XLA_FLAGS already chooses, or where JAX has started."""
    import os

    import jax

    if count is not None and count <= 0:
        from .._validation import ParameterError

        raise ParameterError(f"--devices={count}: must be a positive integer")
    if "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return
    try:
        jax.config.update("jax_num_cpu_devices", count or os.cpu_count() or 1)
    except RuntimeError:  # backends already initialised (main() called in-process)
        pass


def run(args) -> int:
    enable_x64()
    cpu_devices(args.devices)
    import numpy as np

    from .._distributions import parse_vary, split_name
    from .._ensemble import ensemble
    from .._scenefile import load_scene
    from .._validation import ParameterError

    check_output_file("--export", args.export, (".csv", ".nc"))
    overrides = parse_sets(args.set)
    if args.t1 is not None:
        overrides["t1"] = args.t1
    if args.n <= 0:
        raise ParameterError(f"--n={args.n}: must be a positive integer")
    spec = load_scene(args.scene, overrides)
    scene, y0 = spec.scene, spec.y0
    params = scene.parameters()
    vary = {}
    for text in args.vary:
        name, op, dist = parse_vary(text)
        if op != "=":
            base, index = split_name(name)
            nominal = y0[base] if base in y0 else params.get(base)
            if nominal is None:
                raise ParameterError(
                    f"--vary {text!r}: unknown name {base!r}: parameters {sorted(params)}, "
                    f"initial values {sorted(y0)}")
            nominal = np.asarray(nominal, float)
            nominal = nominal if index is None else nominal[index]
            dist = dist.shifted(nominal) if op == "+=" else dist.scaled(nominal)
        if name in vary:
            raise ParameterError(f"--vary {text!r}: {name} is varied twice")
        vary[name] = dist
    res = ensemble(scene, y0, spec.t1, n=args.n, key=args.seed, vary=vary, rtol=spec.rtol,
                   atol=spec.atol, max_steps=args.max_steps, mode=args.mode,
                   chunk_size=args.chunk, out=args.out, progress=args.progress, keep=True)
    out = {"scene": spec.name, "t1": spec.t1, "vary": args.vary, "seed": args.seed,
           **res.report()}
    if args.export:
        from .._export import write

        write(res, args.export)
        out["export"] = args.export
    out["timing"]["wall_s"] = time.perf_counter() - args.t_start
    if args.out:
        out["out"] = args.out
    emit(out, args.json, title=f"{spec.name}: Monte Carlo, n={args.n}")
    return 0
