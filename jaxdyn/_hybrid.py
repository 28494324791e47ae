r"""Hybrid simulation: a run as a sequence of segments separated by mode switches.

A *hybrid* scene has switches: its body has modes with different equations of motion (one with
`max_switches > 0`, such as [`jaxdyn.RoughFloorRod`][], the current mode being part of its
state), or an effect switches (thrusters turning on and off, [`jaxdyn.Thrusters`][]). The
scene's `events` are functions of `(t, y)`, positive while the current mode lasts (each scaled
to order one; an event that does not apply to the current mode returns a large positive
constant). A run is

1. `y = scene.start_mode(t0, y0)`: the initial state mapped into a consistent mode (or the end);
2. a segment: `diffrax.diffeqsolve` from the current time until one of the events reaches zero,
   located by root finding (optimistix bisection) on the dense interpolant;
3. `y = scene.switch_mode(t, y, fired)`: the state mapped into the next mode, or the end of the
   run (only a body's events end it);

repeated, up to the scene's `max_switches` switches, until `t1` or the end. The whole run is
one traced computation: it compiles once, parameters stay array leaves, and `jax.jit` and
`jax.vmap` work.
Without dense output the loop is a `jax.lax.scan` over `max_switches + 1` segments (those after
the end are skipped by `lax.cond`), so `jax.grad` works too, through the event times by the
implicit function theorem in the root finder. With `dense=True` it is a `lax.while_loop` (a
scan would carry the merged dense table through every remaining iteration), which JAX cannot
differentiate in reverse mode.

The events are watched as one condition, their minimum, so that the root finder locates the
*earliest* zero crossing of any of them (diffrax, given several conditions, locates the first
one listed that changed sign in the step, not the earliest). An event already at zero when a
segment starts (the one whose root just ended the previous segment, such as a sliding velocity
that starts from rest) is held at a large value at that instant, and wherever it is exactly zero
(an equilibrium), so it fires only once it crosses zero. The root is located by bisection in
the step where the sign changed. Events at zero together within a tolerance of their scaled
values (`1e-8` in float64) are all reported as fired, and `switch_mode` sets their priority.

Limitation (of any event detection that looks at the signs at step ends): an event function
that dips below zero and comes back within one step is missed. This matters only near a
tangency (a friction ratio whose peak just touches `mu_s`); tighter tolerances resolve it.
"""


import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array

from ._custom_types import State

# Stands in for the events of the other group in each condition's minimum.
_BIG = 1e6


class HybridInterpolation(eqx.Module):
    """Dense output of a hybrid run: the solver's local interpolants of every segment, merged
    into one table of steps (the same interface as `diffrax.DenseInterpolation.evaluate`).

    Times within a run are looked up among the step boundaries, where the last step of each
    segment ends at its event time; at a switch time the state before the switch is returned.
    """

    t0: Array
    t1: Array
    bounds: Array  # step start times, then the end of the run, then inf
    t_lo: Array  # each step's own interval, for its interpolant
    t_hi: Array
    infos: dict
    rows: Array  # number of steps
    y_end: State
    interpolation_cls: type = eqx.field(static=True)

    def evaluate(self, t, t1=None, left: bool = True) -> State:
        """The state at time `t` (nan outside the run)."""
        t = jnp.asarray(t, self.t0.dtype)
        i = jnp.searchsorted(self.bounds, t, side="left" if left else "right")
        i = jnp.clip(i.astype(self.rows.dtype) - 1, 0, jnp.maximum(self.rows - 1, 0))
        info = jax.tree.map(lambda a: a[i], self.infos)
        y = self.interpolation_cls(t0=self.t_lo[i], t1=self.t_hi[i], **info).evaluate(t)
        outside = (t < self.t0) | (t > self.t1)
        return jax.tree.map(
            lambda a, b: jnp.where(outside, jnp.nan, jnp.where(self.rows == 0, b, a)),
            y, self.y_end,
        )


def simulate_hybrid(scene, y0, t0, t1, ts, *, solver, controller, dt0, max_steps, adjoint,
                    meter, dense, time_scale, checks=True):
    """The body of `jaxdyn.simulate` for hybrid bodies (traced inside its `jit`)."""
    from ._outcome import MESSAGES, Outcome, from_diffrax
    from ._simulate import Trajectory, _check_result, _finite
    from ._tolerance import ScaledPIDController

    fns = scene.events()
    names = tuple(fns)
    n_events = len(names)
    dtype = t0.dtype
    f64 = dtype == jnp.float64
    root_tol = 1e-12 if f64 else 1e-6
    fire_tol = 1e-8 if f64 else 1e-3
    ret = jnp.result_type(float)  # diffrax compares event values with a Python float

    def values(t, y):
        return jnp.stack([jnp.asarray(fns[n](t, y), dtype) for n in names])

    def condition(t_s, zero):
        # The earliest zero of any event. An event at zero when the segment starts (it just
        # ended the previous one) is held at _BIG at that instant and wherever it is exactly
        # zero (an equilibrium: the upright rod on a floor without friction), so that the
        # condition starts positive and that event fires only once it crosses zero.
        def cond(t, y, args, **kwargs):
            v = values(t, y)
            held = zero & ((t <= t_s) | (v == 0))
            # In units of the scene's time scale, so that the root finder's tolerance (the
            # same on the time and on the condition) is relative to it in both.
            return (time_scale * jnp.min(jnp.where(held, _BIG, v))).astype(ret)

        return cond

    def ending(t, y, fired):
        """Of the events `fired` that end the run together, those that end it by themselves."""
        alone = jnp.stack([
            scene.switch_mode(t, y, {m: jnp.asarray(m == name) for m in names})[1]
            for name in names
        ])
        return jnp.where(jnp.any(fired & alone), fired & alone, fired)

    term = dfx.ODETerm(scene.vector_field)
    y_start, stop0 = scene.start_mode(t0, y0)
    fired0 = stop0 & ending(t0, y_start, values(t0, y_start) <= 0)

    carry = {
        "t": t0,
        "y": y_start,
        "done": jnp.asarray(stop0),
        "ended_by": fired0,
        "switches": jnp.asarray(0),
        "steps": jnp.asarray(0),
        "accepted": jnp.asarray(0),
        "rejected": jnp.asarray(0),
        "result": dfx.RESULTS.successful,
    }
    if ts is not None:
        carry["ts_taken"] = jnp.zeros(ts.shape, bool)
        carry["ys"] = jax.tree.map(lambda a: jnp.zeros(ts.shape + a.shape, a.dtype), y_start)
    if dense:
        info_shape = jax.eval_shape(
            lambda: solver.step(term, t0, t1, y_start, scene,
                                solver.init(term, t0, t1, y_start, scene), False)[2]
        )
        carry["infos"] = jax.tree.map(
            lambda s: jnp.zeros((2 * max_steps, *s.shape), s.dtype), info_shape
        )
        carry["t_lo"] = jnp.zeros(2 * max_steps, dtype)
        carry["t_hi"] = jnp.zeros(2 * max_steps, dtype)
        carry["rows"] = jnp.asarray(0)

    def advance(c):
        """One segment: integrate to the next event (or t1), switch, save, merge dense output."""
        live = ~c["done"]  # False only for batch members that ended, under `vmap`
        t_s, y_s = c["t"], c["y"]
        t_stop = jnp.where(live, t1, t_s)
        zero = values(t_s, y_s) <= 0
        event = dfx.Event(
            cond_fn=condition(t_s, zero),
            # Bracketed by the step in which the sign changed: bisection cannot leave the
            # bracket (Newton can fail where two roots lie close, at a shallow dip, and at the
            # step in the condition where a held event is released).
            # The condition falls through zero across it (flip=True: decreasing), which also
            # serves batch members without an event under `vmap` (diffrax hands them the
            # distance to the end of the step, zero at its upper end).
            root_finder=optx.Bisection(rtol=root_tol, atol=root_tol * time_scale, flip=True),
            direction=False,
        )
        subs = [] if ts is None else [dfx.SubSaveAt(ts=jnp.clip(ts, t_s, t_stop))]
        sol = dfx.diffeqsolve(
            term, solver, t_s, t_stop, dt0, y_s,
            args=scene,
            saveat=dfx.SaveAt(subs=[*subs, dfx.SubSaveAt(t1=True)], dense=dense),
            # each segment's error control in its own start's natural scales
            stepsize_controller=(controller.bind(scene, t_s, t_stop, y_s)
                                 if isinstance(controller, ScaledPIDController) else controller),
            max_steps=max_steps,
            adjoint=adjoint,
            event=event,
            progress_meter=meter,
            throw=False,
        )
        t_e = sol.ts[-1][0]
        y_e = jax.tree.map(lambda a: a[0], sol.ys[-1])
        ok = (sol.result == dfx.RESULTS.successful) | (sol.result == dfx.RESULTS.event_occurred)
        hit = live & ok & sol.event_mask

        # Which events fired: the one at the minimum, and any other at zero within tolerance
        # there (coincident events).
        v = values(t_e, y_e)
        fired = hit & ((v <= fire_tol) | (jnp.arange(n_events) == jnp.argmin(v)))
        y_sw, stop = scene.switch_mode(t_e, y_e, dict(zip(names, fired)))

        new = dict(c)
        new["t"] = t_e
        new["y"] = jax.tree.map(lambda a, b: jnp.where(hit, a, b), y_sw, y_e)
        new["done"] = c["done"] | ~hit | stop
        new["ended_by"] = jnp.where(hit & stop, ending(t_e, y_e, fired), c["ended_by"])
        new["switches"] = c["switches"] + jnp.where(hit & ~stop, 1, 0)
        for key, stat in (("steps", "num_steps"), ("accepted", "num_accepted_steps"),
                          ("rejected", "num_rejected_steps")):
            new[key] = c[key] + jnp.where(live, sol.stats[stat], 0).astype(c[key].dtype)
        new["result"] = dfx.RESULTS.where(live & ~ok, sol.result, c["result"])
        if ts is not None:
            take = live & ~c["ts_taken"] & (ts <= t_e)
            new["ts_taken"] = c["ts_taken"] | take
            new["ys"] = jax.tree.map(
                lambda acc, seg: jnp.where(_expand(take, acc), seg, acc), c["ys"], sol.ys[0]
            )
        if dense:
            # Append this segment's steps to the merged table (twice `max_steps` long, so that a
            # whole segment's table fits at any offset; what lies beyond `rows` is unused).
            interp = sol.interpolation
            at = c["rows"]
            new["infos"] = jax.tree.map(
                lambda acc, seg: jax.lax.dynamic_update_slice_in_dim(acc, seg, at, 0),
                c["infos"], interp.infos,
            )
            new["t_lo"] = jax.lax.dynamic_update_slice_in_dim(c["t_lo"], interp.ts[:-1], at, 0)
            new["t_hi"] = jax.lax.dynamic_update_slice_in_dim(c["t_hi"], interp.ts[1:], at, 0)
            new["rows"] = at + jnp.where(live, interp.ts_size - 1, 0).astype(at.dtype)
        return new

    if dense:
        # A while loop: no iterations after the end, and the merged table is updated in place
        # (a scan would carry it through every remaining iteration). JAX cannot reverse-mode
        # differentiate a while loop: gradients need dense=False (forward mode works).
        carry["segments"] = jnp.asarray(0)

        def step(c):
            c = advance(c)
            return {**c, "segments": c["segments"] + 1}

        c = jax.lax.while_loop(
            lambda c: ~c["done"] & (c["segments"] <= scene.max_switches), step, carry
        )
    else:
        def segment(c, _):
            # Segments after the end are skipped (under `vmap` both branches run: the segment
            # then has zero length for the members that ended, and its results are masked).
            return jax.lax.cond(c["done"], lambda c: c, advance, c), None

        c, _ = jax.lax.scan(segment, carry, None, length=scene.max_switches + 1)

    t_final = c["t"]
    y_final = c["y"]
    if checks:
        y_final, _ = _check_result(c["result"], y_final)
        y_final = eqx.error_if(y_final, c["steps"] > max_steps,
                               MESSAGES[Outcome.max_steps_reached])
        y_final = eqx.error_if(
            y_final, ~c["done"],
            _too_many_switches(scene),
        )
    else:
        c["result"] = dfx.RESULTS.where((c["steps"] > max_steps) | ~c["done"],
                                        dfx.RESULTS.max_steps_reached, c["result"])
    if ts is None:
        ts_out = jnp.stack([t0, t_final])
        ys_out = jax.tree.map(lambda a, b: jnp.stack([a, b]), y_start, y_final)
    else:
        taken = c["ts_taken"]
        ts_out = jnp.where(taken, ts, jnp.inf)
        ys_out = jax.tree.map(lambda a: jnp.where(_expand(taken, a), a, jnp.inf), c["ys"])
    interpolation = None
    if dense:
        r = jnp.arange(2 * max_steps)
        bounds = jnp.where(r < c["rows"], c["t_lo"], jnp.where(r == c["rows"], t_final, jnp.inf))
        interpolation = HybridInterpolation(
            t0=t0, t1=t_final, bounds=bounds, t_lo=c["t_lo"], t_hi=c["t_hi"], infos=c["infos"],
            rows=c["rows"], y_end=y_final, interpolation_cls=solver.interpolation_cls,
        )
    ended = jnp.any(c["ended_by"])
    result = dfx.RESULTS.where(
        c["result"] != dfx.RESULTS.successful, c["result"],
        dfx.RESULTS.where(ended, dfx.RESULTS.event_occurred, dfx.RESULTS.successful),
    )
    return Trajectory(
        scene=scene,
        ts=ts_out,
        ys=ys_out,
        t_final=t_final,
        y_final=y_final,
        event=dict(zip(names, c["ended_by"])),
        result=result,
        outcome=from_diffrax(result, _finite(y_final)),
        stats={
            "num_steps": c["steps"],
            "num_accepted_steps": c["accepted"],
            "num_rejected_steps": c["rejected"],
            "max_steps": max_steps,
            "num_switches": c["switches"],
        },
        interpolation=interpolation,
    )


def _too_many_switches(scene) -> str:
    """The message of a run that needed more switches than its scene allows."""
    whose = [f"a {scene.body.kind}"] if scene.body.max_switches else []
    whose += [f"{label} {e.max_switches}" for label, e in zip(scene.labels, scene.effects)
              if e.max_switches]
    return (f"the run needed more than {scene.max_switches} mode switches before t1 (the most "
            f"{', '.join(whose)} allows): shorten t1"
            + ("" if scene.body.max_switches else " or raise max_switches"))


def _expand(mask, like):
    """`mask` with trailing axes to broadcast against `like`."""
    return mask.reshape(mask.shape + (1,) * (like.ndim - mask.ndim))
