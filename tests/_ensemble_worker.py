"""Run one small ensemble in a fresh process and print its per-trajectory results as JSON.

Used by tests/test_ensemble.py for what needs a process of its own: several simulated host
devices (`XLA_FLAGS=--xla_force_host_platform_device_count=N`, set before JAX starts) and
several processes joined by `jax.distributed`.

    python tests/_ensemble_worker.py MODE [--devices K] [--chunk C] [--out DIR]
                                          [--process I --processes P --port PORT]
                                          [--then-devices K2]

With `--then-devices`, the same ensemble is run again on K2 devices in the same process (one
start and one import for both) and a JSON list of the two results is printed.
"""

import argparse
import json

import jax


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("mode")
    parser.add_argument("--devices", type=int, default=None)
    parser.add_argument("--out", default=None)
    parser.add_argument("--process", type=int, default=None)
    parser.add_argument("--processes", type=int, default=None)
    parser.add_argument("--port", type=int, default=None)
    parser.add_argument("--chunk", type=int, default=32)
    parser.add_argument("--then-devices", type=int, default=None)
    args = parser.parse_args()
    if args.process is not None:
        jax.distributed.initialize(coordinator_address=f"127.0.0.1:{args.port}",
                                   num_processes=args.processes, process_id=args.process)
    jax.config.update("jax_enable_x64", True)
    import jaxdyn as jd
    from jaxdyn import _ensemble

    scene = jd.Scene(jd.RigidBody(inertia=[1.0, 2.0, 2.5]))

    def run(count):
        before = set(_ensemble._COMPILED)
        devices = None if count is None else jax.local_devices()[:count]
        res = jd.ensemble(scene, scene.state(omega=[0.1, 1.0, 0.1]), 5.0, n=100, key=3,
                          vary={"omega": jd.Normal([0.1, 1.0, 0.1], 0.05),
                                "inertia[0]": jd.Uniform(0.9, 1.1)},
                          mode=args.mode, chunk_size=args.chunk, devices=devices, out=args.out)
        # How each chunk program this run compiled was compiled: one per device, or one over
        # every device.
        programs = sorted("per_device" if where == "per_device" else "one"
                          for key, (_, where) in _ensemble._COMPILED.items()
                          if key not in before)
        return {"devices": res.devices, "process_count": jax.process_count(),
                "programs": programs, "local_devices": len(jax.local_devices()),
                "omega": res.values["omega"].tolist(),
                "status": res.status.tolist(), "steps": res.steps.tolist()}

    result = run(args.devices)
    if args.then_devices is not None:
        result = [result, run(args.then_devices)]
    print(json.dumps(result))


if __name__ == "__main__":
    main()
