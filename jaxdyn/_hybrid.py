r"""The one integration driver: a run as a sequence of segments separated by mode switches.

Every scene runs here. A scene with switches has a body with modes (one with
`max_switches > 0`, such as [`jaxdyn.RoughFloorRod`][], the current mode being part of its
state) or an effect that switches (thrusters turning on and off, [`jaxdyn.Thrusters`][]); a
single-mode scene is one with no switches, and its run is one segment. The scene's `events` are
functions of `(t, y)`, positive while the current mode lasts (each scaled to order one; an event
that does not apply to the current mode returns a large positive constant). A run is

1. `y = scene.start_mode(t0, y0)`: the initial state mapped into a consistent mode (or the end;
   for a body without modes, a terminating event already reached ends the run at once);
2. a segment: `diffrax.diffeqsolve` from the current time until one of the events reaches zero,
   located by root finding (optimistix bisection) on the dense interpolant;
3. `y = scene.switch_mode(t, y, fired)`: the state mapped into the next mode, or the end of the
   run (only a body's events end it; a body without modes ends at any of its events);

repeated, up to the scene's `max_switches` switches, until `t1` or the end. The whole run is
one traced computation: it compiles once, parameters stay array leaves, and `jax.jit` and
`jax.vmap` work. One segment is one call; more are a `jax.lax.scan` over `max_switches + 1`
segments (those after the end are skipped by `lax.cond`), so `jax.grad` works too, through the
event times by the implicit function theorem in the root finder. With `dense=True` a switching
run is a `lax.while_loop` (no iterations after the end), which JAX cannot differentiate in
reverse mode; its segments write their accepted steps into one table (`Table`).

**Event location, one method for every scene.** The events are watched as one condition, their
minimum, so that the root finder locates the *earliest* zero crossing of any of them (diffrax,
given several conditions, locates the first one listed that changed sign in the step, not the
earliest), and the root is located by bisection in the step where the sign changed. Bisection
was chosen over Newton's method (which the single-mode path used before): it cannot leave the
bracket, where Newton can fail where two roots lie close, at a shallow dip, and at the step in
the condition where a held event is released; it costs a few dozen evaluations of the
interpolant once per event, nothing beside a step's cost. An event already at zero when a
segment starts (the one whose root just ended the previous segment, such as a sliding velocity
that starts from rest) is held at a large value at that instant, and wherever it is exactly zero
(an equilibrium), so it fires only once it crosses zero. Events at zero together within a
tolerance of their scaled values (`1e-8` in float64) are all reported as fired, and
`switch_mode` sets their priority.

**Time on the unit interval.** Under jaxdyn's own error control (`ScaledPIDController`) with a
Runge-Kutta solver, each segment from `t_s` to `t_stop` is integrated in `tau = (t - t_s) /
(t_stop - t_s)`, from the constant 0 to the constant 1 (`Unit`): the vector field is multiplied
by the span, and times handed in and out (events, samples, dense output, the end) are mapped.
The steps are those taken in `t` (a Runge-Kutta step and the error control are invariant under
an affine change of time; the first step is chosen in units of the time scale either way), up
to round-off. What it buys is a smaller program: diffrax computes the point 100 ULPs below the
end of its interval at the start of every solve (100 `nextafter`s, about 1400 of the 2000
operations of XLA's cost estimate of a small solve); on constant ends XLA folds them away, and
XLA:CPU runs a program estimated below 1000 operations on the calling thread instead of
handing it to a worker thread and waking the caller when it is done (about 40 us a call on a
busy 2-core machine: most of what a short `simulate` cost beyond a hand-written `jax.jit` of
`diffeqsolve`, whose runtime error check, a host callback, also runs it on the calling thread).

Limitation (of any event detection that looks at the signs at step ends): an event function
that dips below zero and comes back within one step is missed. This matters only near a
tangency (a friction ratio whose peak just touches `mu_s`); tighter tolerances resolve it.
"""

import math
from typing import Any

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array

from ._outcome import MESSAGES, Outcome, from_diffrax, is_success
from ._solution import MergedInterpolation, Trajectory, too_many_switches
from ._solvers._accepted import Reporting, Writing
from ._solvers._fixed import FixedStep, with_root_finder_tolerances
from ._solvers._recorded import Table, empty_table
from ._solvers._sampled import Samples
from ._solvers._wrapped import TracedOnce
from ._tolerance import ScaledPIDController

# The loop of a run whose results nothing differentiates (a call with concrete values, an
# ensemble): diffrax's plain `lax.while_loop` and stage scan. `RecursiveCheckpointAdjoint`'s
# checkpointed loop takes the same steps but traces the step several times over (the falling
# rod's program: 0.55 s of tracing against 0.40 s).
FORWARD = dfx.ForwardMode()
# The Runge-Kutta stage loop that `diffrax.diffeqsolve` picks for these adjoints where the
# solver leaves it open (its forward-mode and `DirectAdjoint` special cases).
_STAGE_LOOPS = {dfx.ForwardMode: "lax", dfx.DirectAdjoint: "bounded"}  # (by `isinstance`)

# Stands in for the events of the other group in each condition's minimum.
_BIG = 1e6


def finite(y) -> jax.Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(y)]))


class Unit(eqx.Module):
    """A segment from `start` to `stop` on the unit interval: `tau = (t - start) / span`
    (module docstring). A segment of zero span (a batch member that ended, under `vmap`) stays
    where it is: its vector field is zero."""

    start: Array
    stop: Array

    @property
    def span(self):
        return self.stop - self.start

    def safe_span(self):  # (a divisor)
        return jnp.where(self.span > 0, self.span, jnp.ones_like(self.span))

    def time(self, tau):
        """`t` at `tau`: exactly `stop` at 1, never past it before."""
        t = self.start + tau * self.span
        return jnp.where(tau == 1, self.stop, jnp.where(tau < 1, jnp.minimum(t, self.stop), t))

    def tau(self, t):
        return (t - self.start) / self.safe_span()

    def vector_field(self, vector_field):
        """`vector_field(t, y, args)` as a function of `tau`."""
        return _OnUnit(vector_field, self.start, self.span)


class _OnUnit(eqx.Module):
    vector_field: Any
    start: Array
    span: Array

    def __call__(self, tau, y, args):
        dy = self.vector_field(self.start + tau * self.span, y, args)
        return jax.tree.map(lambda d: d * self.span.astype(d.dtype), dy)


class Watch:
    """A scene's events as one condition: their values, the condition of a segment, and which
    fired where it reached zero (traced inside the run; the same in the batch engine)."""

    def __init__(self, scene, time_scale, dtype):
        self.scene, self.fns = scene, scene.events()
        self.names = tuple(self.fns)
        self.time_scale, self.dtype = time_scale, dtype
        f64 = dtype == jnp.float64
        self.root_tol = 1e-12 if f64 else 1e-6
        self.fire_tol = 1e-8 if f64 else 1e-3

    def values(self, t, y):
        return jnp.stack([jnp.asarray(self.fns[n](t, y), self.dtype) for n in self.names])

    def condition(self, t_s, zero, unit=None):
        """The segment's condition: the earliest zero of any event. An event at zero when the
        segment starts (it just ended the previous one) is held at `_BIG` at that instant and
        wherever it is exactly zero (an equilibrium: the upright rod on a floor without
        friction), so that the condition starts positive and that event fires only once it
        crosses zero. In units of the scene's time scale, so that the root finder's tolerance
        (the same on the time and on the condition) is relative to it in both. (diffrax
        compares the condition with a Python float: it is returned in the default float.)"""
        ret = jnp.result_type(float)
        scale = self.scale(unit)

        def cond(t, y, args, **kwargs):
            t = t if unit is None else unit.time(t)
            v = self.values(t, y)
            held = zero & ((t <= t_s) | (v == 0))
            return (scale * jnp.min(jnp.where(held, _BIG, v))).astype(ret)

        return cond

    def scale(self, unit):
        """The time scale in the segment's own time (`unit`: on the unit interval)."""
        return self.time_scale if unit is None else self.time_scale / unit.safe_span()

    def event(self, t_s, y_s, unit=None) -> dfx.Event:
        return dfx.Event(
            cond_fn=self.condition(t_s, self.values(t_s, y_s) <= 0, unit),
            # Bracketed by the step in which the sign changed (module docstring). The condition
            # falls through zero across it (flip=True: decreasing), which also serves batch
            # members without an event under `vmap` (diffrax hands them the distance to the
            # end of the step, zero at its upper end).
            root_finder=optx.Bisection(rtol=self.root_tol,
                                       atol=self.root_tol * self.scale(unit), flip=True),
            direction=False,
        )

    def fired(self, hit, t, y):
        """At a segment's end where `hit`: the event at the minimum, and any other at zero
        within tolerance there (coincident events)."""
        v = self.values(t, y)
        return hit & ((v <= self.fire_tol) | (jnp.arange(len(self.names)) == jnp.argmin(v)))

    def at_event(self, t, y, hit):
        """At a segment's end where `hit`: the state in its next mode, whether the run ends,
        and the events that end it."""
        fired = self.fired(hit, t, y)
        y_next, stop = self.scene.switch_mode(t, y, dict(zip(self.names, fired)))
        return y_next, stop, self.ending(t, y, fired)

    def ending(self, t, y, fired):
        """Of the events `fired` that end the run together, those that end it by themselves."""
        alone = jnp.stack([
            self.scene.switch_mode(t, y, {m: jnp.asarray(m == name) for m in self.names})[1]
            for name in self.names
        ])
        return jnp.where(jnp.any(fired & alone), fired & alone, fired)

    def start(self, t0, y0):
        """The state mapped into its first mode, whether the run ends at once, and the events
        that end it. A body without modes ends at once where one of its events has already
        reached zero."""
        y, stop = self.scene.start_mode(t0, y0)
        reached = self.values(t0, y) <= 0
        if not self.scene.body.max_switches:
            body = jnp.asarray([n in self.scene.body.events() for n in self.names])
            stop = stop | jnp.any(reached & body)
        return y, stop, stop & self.ending(t0, y, reached)


class _Run:
    """One run's settings (static while tracing) and its segment, as a function of the carry
    (a dict: the time and state, whether the run is done, counts, saved states, the dense
    table)."""

    def __init__(self, scene, t0, t1, ts, *, solver, controller, dt0, max_steps, adjoint, meter,
                 dense, watch, solver_saves):
        self.scene, self.t0, self.t1, self.ts = scene, t0, t1, ts
        self.controller, self.dt0, self.max_steps = controller, dt0, max_steps
        self.adjoint, self.meter, self.watch = adjoint, meter, watch
        self.term = dfx.ODETerm(scene.vector_field)
        self.segments = scene.max_switches + 1 if watch is not None else 1
        # Several segments keep their dense output in one table (`Table`); one keeps
        # diffrax's own.
        self.record = dense and self.segments > 1
        self.diffrax_dense = dense and not self.record
        # Sample times saved from each accepted step (`Samples`): `SaveAt(ts)` of traced times
        # carries diffrax's runtime check of them, a host callback.
        self.sampled = solver_saves and ts is not None
        kind = next((k for a, k in _STAGE_LOOPS.items() if isinstance(adjoint, a)), None)
        if kind is not None and getattr(solver, "scan_kind", "") is None \
                and isinstance(solver, (dfx.AbstractRungeKutta, dfx.AbstractSRK)):
            # What diffrax does for these adjoints, done before wrapping (its check of the
            # solver's kind sees through one wrapper, not `TracedOnce(Reporting(...))`).
            solver = eqx.tree_at(lambda s: s.scan_kind, solver, kind,
                                 is_leaf=lambda x: x is None)
        self.solver = solver
        # Segments on the unit interval (module docstring), where the solver sees time only
        # through the vector field.
        self.unit = (isinstance(controller, ScaledPIDController)
                     and isinstance(solver, dfx.AbstractRungeKutta))

    def start(self, y0):
        """The carry at `t0`."""
        if self.watch is None:
            y, stop, ended_by = y0, jnp.asarray(False), jnp.zeros(0, bool)
        else:
            y, stop, ended_by = self.watch.start(self.t0, y0)
        zero = jnp.asarray(0)
        c = {"t": self.t0, "y": y, "done": stop, "ended_by": ended_by, "switches": zero,
             "steps": zero, "accepted": zero, "rejected": zero,
             "result": dfx.RESULTS.successful}
        if self.sampled:  # buffers for the whole run, written in place (`Samples`)
            c["samples"] = Samples(self.ts).start(self.t0, y, stop)
        elif self.ts is not None:
            c["ts_taken"] = jnp.zeros(self.ts.shape, bool)
            c["ys"] = jax.tree.map(lambda a: jnp.zeros(self.ts.shape + a.shape, a.dtype), y)
        if self.record:
            solver = self.solver
            if isinstance(solver, dfx.AbstractImplicitSolver):  # (its step, for the table's
                solver = with_root_finder_tolerances(solver, self.controller)  # shapes)
            c["table"] = empty_table(solver, self.term, self.t0, self.t1, y, self.scene,
                                     self.max_steps)
        return c

    def solve(self, c, t_stop):
        """`diffrax.diffeqsolve` over one segment from the carry's time and state; the segment's
        end, its samples (`Samples`' buffers and count, or diffrax's), its dense table."""
        t_s, y_s, ts = c["t"], c["y"], self.ts
        solver, controller, term, dt0 = self.solver, self.controller, self.term, self.dt0
        # (The ends as values of the run, never folded into constants, as the tolerances in
        # `ScaledPIDController.bind`: a call under the caller's `jit` takes the same steps to
        # the bit as a concrete call.)
        unit = Unit(*jax.lax.optimization_barrier((t_s, t_stop))) if self.unit else None
        if isinstance(controller, ScaledPIDController):  # error control in the segment's own
            controller = controller.bind(self.scene, t_s, t_stop, y_s)  # natural scales
        if unit is None:
            start, stop, times = t_s, t_stop, lambda t: t
        else:
            controller = controller.on_unit_interval(unit)
            term = dfx.ODETerm(unit.vector_field(self.scene.vector_field))
            start, stop, times = jnp.zeros_like(t_s), 1.0, unit.tau
            dt0 = None if dt0 is None else dt0 / unit.safe_span()
        # Written from each accepted step into buffers in the controller's state (see
        # `_accepted`): the samples at `ts`, the dense table.
        writers = {}
        subs = [dfx.SubSaveAt(t1=True)]
        if self.sampled:
            writers["samples"] = Samples(self.ts, unit, c["samples"])
        elif ts is not None:
            subs.insert(0, dfx.SubSaveAt(ts=times(jnp.clip(ts, t_s, t_stop))))
        if self.record:
            writers["table"] = Table(c["table"], unit)
        # The step (or first step) held by the controller: `diffeqsolve` checks the sign of a
        # traced `dt0` with a host callback (see `_solvers._fixed`).
        if dt0 is not None and type(controller) is dfx.ConstantStepSize:
            controller, dt0 = FixedStep(dt0), None
        elif dt0 is not None and isinstance(controller, ScaledPIDController):
            controller = eqx.tree_at(lambda c: c.first_step, controller, dt0,
                                     is_leaf=lambda x: x is None)
            dt0 = None
        if isinstance(solver, dfx.AbstractImplicitSolver):  # (what diffeqsolve does, done
            solver = with_root_finder_tolerances(solver, controller)  # before the wrappers)
        if writers:
            controller = Writing(controller, writers, solver.interpolation_cls)
            solver = Reporting(solver)
        event = None if self.watch is None else self.watch.event(t_s, y_s, unit)
        y_start, unravel = y_s, None
        if (not writers and not self.diffrax_dense and isinstance(controller, ScaledPIDController)
                and isinstance(solver, dfx.AbstractRungeKutta) and _ravels(y_s)):
            # A state of several leaves integrated as one array: every state operation of the
            # stages and of the error norm is one kernel, not one per variable (the falling
            # rod's two scalars: 40 kernels per step against 27).
            unravel = _Unravel.like(y_s)
            y_start = _ravel(y_s)
            term = dfx.ODETerm(_Raveled(term.vector_field, unravel))
            scales = jax.tree.map(lambda s, y: jnp.broadcast_to(s, jnp.shape(y)),
                                  controller.scales, y_s)  # (one scale per variable)
            controller = eqx.tree_at(lambda c: c.scales, controller, _ravel(scales))
            if event is not None:
                event = eqx.tree_at(lambda e: e.cond_fn, event,
                                    _Raveled(event.cond_fn, unravel, output=False))
        solver = TracedOnce(solver)  # (its step traced once, not four times)
        sol = dfx.diffeqsolve(
            term, solver, start, stop, dt0, y_start,
            args=self.scene,  # solvers that exploit the scene's structure (splittings) read it
            saveat=dfx.SaveAt(subs=subs, dense=self.diffrax_dense,
                              controller_state=bool(writers)),
            stepsize_controller=controller, max_steps=self.max_steps, adjoint=self.adjoint,
            event=event, progress_meter=self.meter, throw=False,
        )
        if unravel is not None:
            sol = eqx.tree_at(lambda s: s.ys, sol, [jax.vmap(unravel)(y) for y in sol.ys])
        written = sol.controller_state[1] if writers else {}
        saved = written["samples"] if self.sampled else None if ts is None else sol.ys[0]
        t_e = sol.ts[-1][0]
        interpolation = sol.interpolation
        if unit is not None:
            t_e = unit.time(t_e)
            if interpolation is not None:  # (its dense information is per step: unchanged)
                interpolation = eqx.tree_at(lambda i: (i.ts, i.t0_if_trivial), interpolation,
                                            (unit.time(interpolation.ts), t_s))
        return sol, t_e, interpolation, saved, written.get("table")

    def segment(self, c):
        """One segment: integrate to the next event (or `t1`), switch, save, count."""
        live = ~c["done"]  # False only for batch members that ended, under `vmap`
        sol, t_e, interpolation, saved, table = self.solve(c, jnp.where(live, self.t1, c["t"]))
        y_e = jax.tree.map(lambda a: a[0], sol.ys[-1])
        ok = (sol.result == dfx.RESULTS.successful) | (sol.result == dfx.RESULTS.event_occurred)
        new = dict(c, t=t_e, y=y_e, done=jnp.asarray(True))
        if self.watch is not None:
            hit = live & ok & sol.event_mask
            y_sw, stop, ended = self.watch.at_event(t_e, y_e, hit)
            new["y"] = jax.tree.map(lambda a, b: jnp.where(hit, a, b), y_sw, y_e)
            new["done"] = c["done"] | ~hit | stop
            new["ended_by"] = jnp.where(hit & stop, ended, c["ended_by"])
            new["switches"] = c["switches"] + jnp.where(hit & ~stop, 1, 0)
        for key, stat in (("steps", "num_steps"), ("accepted", "num_accepted_steps"),
                          ("rejected", "num_rejected_steps")):
            new[key] = c[key] + jnp.where(live, sol.stats[stat], 0).astype(c[key].dtype)
        new["result"] = dfx.RESULTS.where(live & ~ok, sol.result, c["result"])
        if self.sampled:
            # Samples past the end, written from the last step (past an event), are not kept:
            # the next segment writes them.
            new["samples"] = Samples(self.ts).keep_until(saved, t_e)
        elif self.ts is not None:
            take = live & ~c["ts_taken"] & (self.ts <= t_e)
            new["ts_taken"] = c["ts_taken"] | take
            new["ys"] = jax.tree.map(lambda acc, seg: jnp.where(_expand(take, acc), seg, acc),
                                     c["ys"], saved)
        if self.record:
            new["table"] = table
        if self.diffrax_dense:
            new["interpolation"] = interpolation
        return new

    def loop(self, c):
        """Every segment of the run."""
        if self.segments == 1:
            if self.watch is None:  # nothing can end the run before it starts
                return self.segment(c)
            if self.diffrax_dense:  # (its interpolation exists only once the segment ran)
                return self.segment(c)
            return jax.lax.cond(c["done"], lambda c: c, self.segment, c)
        if self.record or self.sampled:
            # A while loop: no iterations after the end, and the dense table and the samples
            # are updated in place. JAX cannot reverse-mode differentiate it: gradients need
            # dense=False (the samples are written thus only where none are taken).
            def step(c):
                return {**self.segment(c), "n": c["n"] + 1}

            return jax.lax.while_loop(lambda c: ~c["done"] & (c["n"] < self.segments), step,
                                      {**c, "n": jnp.asarray(0)})

        def scan_step(c, _):
            # Segments after the end are skipped (under `vmap` both branches run: the segment
            # then has zero length for the members that ended, and its results are masked).
            return jax.lax.cond(c["done"], lambda c: c, self.segment, c), None

        return jax.lax.scan(scan_step, c, None, length=self.segments)[0]

    def outcome(self, c, y_final, checks):
        """diffrax's result and the outcome code of the run, and `y_final` with a runtime
        error attached where it failed (`checks`)."""
        result = c["result"]
        if self.segments > 1:
            if checks:
                y_final = eqx.error_if(y_final, ~c["done"], too_many_switches(self.scene))
            result = dfx.RESULTS.where((c["steps"] > self.max_steps) | ~c["done"],
                                       dfx.RESULTS.max_steps_reached, result)
        result = dfx.RESULTS.where(
            result != dfx.RESULTS.successful, result,
            dfx.RESULTS.where(jnp.any(c["ended_by"]), dfx.RESULTS.event_occurred,
                              dfx.RESULTS.successful))
        code = from_diffrax(result, finite(y_final))
        if checks:
            y_final = eqx.branched_error_if(y_final, ~is_success(code), code,
                                            [MESSAGES[o] for o in Outcome])
        return result, code, y_final

    def trajectory(self, c, y_start, checks) -> Trajectory:
        """The run's `Trajectory`: saved states, final state, events, outcome, statistics and
        dense output."""
        t_final = c["t"]
        result, code, y_final = self.outcome(c, c["y"], checks)
        if self.ts is None:
            ts_out = jnp.stack([self.t0, t_final])
            ys_out = jax.tree.map(lambda a, b: jnp.stack([a, b]), y_start, y_final)
        else:
            if self.sampled:  # (`inf` where not reached, as diffrax's)
                ys_out, ts_out, _ = c["samples"]
            else:
                taken, ys = c["ts_taken"], c["ys"]
                ts_out = jnp.where(taken, self.ts, jnp.inf)
                ys_out = jax.tree.map(lambda a: jnp.where(_expand(taken, a), a, jnp.inf), ys)
        stats = {"num_steps": c["steps"], "num_accepted_steps": c["accepted"],
                 "num_rejected_steps": c["rejected"], "max_steps": self.max_steps}
        if self.segments > 1:
            stats["num_switches"] = c["switches"]
        names = () if self.watch is None else self.watch.names
        return Trajectory(
            scene=self.scene, ts=ts_out, ys=ys_out, t_final=t_final, y_final=y_final,
            event=dict(zip(names, c["ended_by"])), result=result, outcome=code, stats=stats,
            interpolation=c.get("interpolation", self.merged(c, t_final, y_final)),
        )

    def merged(self, c, t_final, y_final):
        """The dense output of a run of several segments, from its table of steps."""
        if not self.record:
            return None
        table = c["table"]
        r = jnp.arange(self.max_steps)
        bounds = jnp.where(r < table["rows"], table["t_lo"],
                           jnp.where(r == table["rows"], t_final, jnp.inf))
        return MergedInterpolation(
            t0=self.t0, t1=t_final, bounds=bounds, t_lo=table["t_lo"], t_hi=table["t_hi"],
            infos=table["infos"], rows=table["rows"], y_end=y_final,
            interpolation_cls=self.solver.interpolation_cls)


def integrate(scene, y0, t0, t1, ts, *, solver, controller, dt0, max_steps, adjoint, meter,
              dense, events, checks, solver_saves) -> Trajectory:
    """A run of `scene` from `y0` (traced inside `simulate`'s program): every segment between
    switches, then its `Trajectory`. `checks=False` leaves failures in `Trajectory.outcome`;
    `solver_saves`: `ts` saved from each accepted step (see `Samples`), not by diffrax's
    `SaveAt(ts)`."""
    if checks:
        y0 = scene.check(y0)
        if dt0 is not None:  # (checked on the host where it is known: `_prepare_run`)
            dt0 = eqx.error_if(dt0, ~(jnp.isfinite(dt0) & (dt0 > 0)),
                               "dt0: must be a positive finite step (s)")
    if isinstance(controller, ScaledPIDController):
        time_scale = controller.bind(scene, t0, t1, y0).time_scale
    else:  # a controller of the user's: the time scale is still the events'
        time_scale = scene.natural_scales(t0, t1, y0)[1]
    watch = Watch(scene, time_scale, t0.dtype) if events and scene.events() else None
    run = _Run(scene, t0, t1, ts, solver=solver, controller=controller, dt0=dt0,
               max_steps=max_steps, adjoint=adjoint, meter=meter, dense=dense, watch=watch,
               solver_saves=solver_saves)
    c = run.start(y0)
    return run.trajectory(run.loop(c), c["y"], checks)


def _ravels(y) -> bool:
    """Whether a state is integrated as one array: several leaves of one floating dtype."""
    leaves = jax.tree.leaves(y)
    return len(leaves) > 1 and len({jnp.result_type(a) for a in leaves}) == 1


def _ravel(y):
    return jnp.concatenate([jnp.ravel(a) for a in jax.tree.leaves(y)])


class _Unravel(eqx.Module):
    """The inverse of `_ravel` for states shaped as a given one (static)."""

    treedef: Any = eqx.field(static=True)
    shapes: tuple = eqx.field(static=True)

    @staticmethod
    def like(y) -> "_Unravel":
        leaves, treedef = jax.tree.flatten(y)
        return _Unravel(treedef, tuple(tuple(jnp.shape(a)) for a in leaves))

    def __call__(self, flat):
        parts, at = [], 0
        for shape in self.shapes:
            size = math.prod(shape)
            parts.append(flat[at:at + size].reshape(shape))
            at += size
        return jax.tree.unflatten(self.treedef, parts)


class _Raveled(eqx.Module):
    """`fn(t, y, args, ...)` of a state pytree as a function of the raveled state (its output
    raveled too where `output`): a module, so that adjoints see the parameters it holds."""

    fn: Any
    unravel: _Unravel
    output: bool = eqx.field(static=True, default=True)

    def __call__(self, t, y, args, **kwargs):
        out = self.fn(t, self.unravel(y), args, **kwargs)
        return _ravel(out) if self.output else out


def _expand(mask, like):
    """`mask` with trailing axes to broadcast against `like`."""
    return mask.reshape(mask.shape + (1,) * (like.ndim - mask.ndim))
