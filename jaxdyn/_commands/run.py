"""`jaxdyn run`: simulate a scene and summarise it."""

import time
from typing import Any

from ._common import (
    add_scene_arguments,
    bounded_int,
    check_output_file,
    compile_clock,
    emit,
    enable_x64,
    parse_sets,
    timing_since,
    warn_on_disagreement,
)

HELP = "simulate a scene and summarise it"


def add_arguments(run) -> None:
    add_scene_arguments(run, default_scene="falling-rod")
    run.add_argument("--samples", type=bounded_int("--samples", 2, 10**7), default=2001,
                     help="number of saved samples over the run (default 2001)")
    run.add_argument("--plot", metavar="FILE", help="write a PNG figure")
    run.add_argument("--export", metavar="FILE",
                     help="write the samples: FILE.csv (one row per time) or FILE.nc (NetCDF, "
                          "xarray); needs pandas and xarray (pip install 'jaxdyn[data]')")
    run.add_argument("--animate", metavar="FILE",
                     help="write an animation of the run: FILE.gif, or FILE.mp4 (needs "
                          "ffmpeg); a rigid body's attitude is integrated for it")


def run(args) -> int:
    enable_x64()
    import jax

    from .._scenefile import load_scene
    from .._simulate import simulate, then_prepare
    from .._solution import prepare_report
    from .._validation import ParameterError

    check_output_file("--plot", args.plot)
    check_output_file("--animate", args.animate, (".gif", ".mp4"))
    check_output_file("--export", args.export, (".csv", ".nc"))
    overrides = parse_sets(args.set)
    if args.t1 is not None:
        overrides["t1"] = args.t1
    spec = load_scene(args.scene, overrides)
    if args.animate and any(i.name == "attitude" for i in spec.scene.body.inputs) \
            and not spec.scene.attitude:  # the animation draws the attitude
        spec = load_scene(args.scene, {**overrides, "attitude": True})

    t0 = compile_clock()
    if spec.scene.max_switches > spec.scene.body.max_switches:
        # Effects that switch (thrusters): the samples are saved as the run goes. (Dense output
        # now costs one table of the whole step budget for the run, not one per segment, but
        # that table is still most of a short run: 156 ms against 48 ms for 137 steps.)
        import jax.numpy as jnp

        with then_prepare(prepare_report):
            traj = simulate(spec.scene, spec.y0, spec.t1, rtol=spec.rtol, atol=spec.atol,
                            max_steps=args.max_steps,
                            ts=jnp.linspace(0.0, spec.t1, args.samples))
    else:
        # A run of a new structure is lowered before XLA compiles it: its resampling and
        # summary are then traced and compiled on another core meanwhile.
        with then_prepare(lambda shape: prepare_report(shape, args.samples)):
            traj = simulate(spec.scene, spec.y0, spec.t1, rtol=spec.rtol, atol=spec.atol,
                            max_steps=args.max_steps, dense=True)
        # Samples span the run as it happened (up to the event time if one ended it).
        traj = traj.resample(args.samples)
    traj = jax.block_until_ready(traj)
    report = traj.report()
    timing = timing_since(t0)
    warn_on_disagreement(report, spec.rtol, float(traj.t_final))
    out: dict[str, Any] = {
        "scene": spec.name,
        "body": spec.scene.body.kind,
        "effects": list(spec.scene.labels),
        "parameters": {k: v for k, v in spec.values.items() if k not in ("t1", "rtol", "atol")},
        "t1": spec.t1,
        "rtol": spec.rtol,
        "atol": spec.atol,
        "t_final": float(traj.t_final),
        "event": next((k for k, v in traj.event.items() if bool(v)), None),
        "steps": int(traj.stats["num_steps"]),
        **report,
    }
    if args.export:
        from .._export import write

        write(traj, args.export)
        out["export"] = args.export
    if args.animate:
        from .._animate import animate

        anim = animate(traj, frames=min(args.samples, 150), title=f"{spec.name}")
        if args.animate.lower().endswith(".mp4"):
            from matplotlib import animation

            if not animation.writers.is_available("ffmpeg"):
                raise ParameterError(f"--animate={args.animate}: .mp4 needs ffmpeg; use .gif")
            anim.save(args.animate, writer="ffmpeg", dpi=90)
        else:
            anim.save(args.animate, writer="pillow", dpi=90)
        out["animation"] = args.animate
    if args.plot:
        from .._plot import plot_trajectory

        plot_trajectory(traj, args.plot, title=f"{spec.name}: {spec.description}")
        out["plot"] = args.plot
    out["timing"] = {**timing, "wall_s": time.perf_counter() - args.t_start}
    emit({k: v for k, v in out.items() if args.json or k != "scene"}, args.json,
         title=f"{spec.name}: {spec.description}")
    return 0
