"""Error control in the scene's natural scales: the same relative accuracy in any units.

diffrax's `PIDController` accepts a step when `norm(err / (atol + rtol |y|)) < 1`. A fixed
`atol` is a statement about units: `atol = 1e-10` is a loose tolerance for rates of `1e-9` rad/s
and an irrelevant one for rates of `1e3`. jaxdyn instead measures each state variable `y_i`
against its natural scale `s_i` (declared by the body and the effects, see
`Scene.natural_scales`): a step is accepted when

$$\\left\\| \\frac{e_i}{\\max(c\\,\\mathrm{rtol}\\,s_i,\\ \\mathrm{atol})
+ \\mathrm{rtol}\\,|y_i|} \\right\\| < 1, \\qquad c = 0.01,$$

which is diffrax's PID control applied to the dimensionless state `y_i / s_i` with
`atol = c rtol` (`FLOOR`). Rescaling the units of a problem rescales `y` and `s` together, so
the steps taken (in the rescaled time) and the relative errors are the same. A user's `atol`
is kept as a floor in the state's own units.
"""

from collections.abc import Callable
from typing import Any

import diffrax as dfx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import PyTree

_div = lambda a, s: a / s  # noqa: E731

FLOOR = 0.01
"""The absolute floor of each variable, as a fraction of its natural scale. With 1 (the floor
at the scale itself) components that pass through zero, such as the small rates of a spin
near a principal axis, are controlled only to `rtol` times the largest rate, and the error
of an intermediate-axis flip reached 50 `rtol`; with 0.01 it stays near `rtol`, for about
1.5 times the steps (figures in the README's section on tolerances)."""


class ScaledPIDController(dfx.AbstractAdaptiveStepSizeController):
    """diffrax's PID controller on the state divided by its natural scales.

    Built with the tolerances alone, then bound to a run (`bind`), which computes the scales
    once from the scene and the initial state; they are constants of the run (no gradient
    flows through them, as none flows through diffrax's step-size choice).

    **Arguments:**

    - `rtol`: relative tolerance.
    - `atol`: absolute floor in the state's own units (`0`: none, the default).

    Where the scene's torques jump at known times (`Scene.jump_times`: a zero-order hold's
    commands), a step ends just before each jump and the next starts just after it (by
    `underflow_step`, far below any step), as diffrax's `ClipStepSizeController(jump_ts=...)`
    does, but finding the next jump by bisection: a step across a jump would be accepted by
    an error estimate that assumes a smooth vector field, and its error would change
    discontinuously with the parameters (a fit's loss at the integration's resolution).
    """

    rtol: Any
    atol: Any
    norm: Callable[[PyTree], Any] = optx.rms_norm
    scales: dict | None = None
    time_scale: Any = None
    unit: Any = None  # a run on the unit interval (`on_unit_interval`): `jaxdyn._hybrid.Unit`
    jumps: Any = None  # sorted times (in `t`) at which the vector field jumps, or `None`
    # The first step where the run gives one (`dt0`), held here: `diffeqsolve` checks the
    # sign of a traced `dt0` with a host callback (see `_solvers._fixed`).
    first_step: Any = None

    def bind(self, scene, t0, t1, y0) -> "ScaledPIDController":
        """This controller for a run of `scene` from `y0` over `[t0, t1]`: the natural scales
        (no lower than `atol` allows) and the time scale, and `atol` raised to `FLOOR` times
        `rtol` times the smallest scale. That changes no step (no scale lies below it) and
        gives what diffrax hands `atol` to, the nonlinear solves of implicit solvers, an
        absolute tolerance in the state's units."""
        scales, time_scale = scene.natural_scales(t0, t1, y0)
        # The tolerances as values of the run, never folded into the program as constants: a
        # call under the caller's `jit` (constant tolerances) then takes the same steps, to
        # the bit, as a concrete call (tolerances passed to its program), which a spin about
        # the intermediate axis, amplifying round-off 1e8-fold, shows.
        rtol, atol = jax.lax.optimization_barrier((jnp.asarray(self.rtol),
                                                   jnp.asarray(self.atol)))
        floor = jnp.where(rtol > 0, atol / (FLOOR * rtol), 0.0)
        scales = {k: jnp.maximum(s, floor.astype(s.dtype)) for k, s in scales.items()}
        scales, time_scale = jax.lax.stop_gradient((scales, time_scale))
        smallest = jnp.min(jnp.stack([jnp.min(s) for s in scales.values()]))
        jumps = scene.jump_times()
        jumps = None if jumps is None else jax.lax.stop_gradient(jumps.astype(t0.dtype))
        return ScaledPIDController(rtol=rtol, atol=jnp.maximum(atol, FLOOR * rtol * smallest),
                                   norm=self.norm, scales=scales, time_scale=time_scale,
                                   jumps=jumps)

    def on_unit_interval(self, unit) -> "ScaledPIDController":
        """This (bound) controller for the run on the unit interval of `unit` (a
        `jaxdyn._hybrid.Unit`, `tau = (t - start) / span` from 0 to 1): the same steps, their
        underflow still judged in `t`."""
        return ScaledPIDController(rtol=self.rtol, atol=self.atol, norm=self.norm,
                                   scales=self.scales, time_scale=self.time_scale, unit=unit,
                                   jumps=self.jumps)

    def _at_jumps(self, t_start, t_end, t_stop):
        """The next step `[t_start, t_end]` (the solver's time) kept off the jumps before the
        run's end `t_stop`: a start within twice `underflow_step` before a jump moves to that
        step after it (and reports the jump, so that a first-same-as-last solver evaluates the
        vector field anew), an end past the next jump moves to that step before it."""
        J = self.jumps
        to_t = (lambda s: s) if self.unit is None else self.unit.time
        to_s = (lambda t: t) if self.unit is None else self.unit.tau
        eps = jnp.finfo(jnp.result_type(t_start)).eps

        def next_jump(i):
            j = J[jnp.minimum(i, J.shape[0] - 1)]
            return j, underflow_step(j, self.time_scale, eps), i < J.shape[0]

        ts = to_t(t_start)
        i = jnp.searchsorted(J, ts, side="right", method="scan_unrolled")  # the next jump
        j, m, has = next_jump(i)
        # (2: the end of a clipped step, after rounding. A jump within two gaps of the run's
        # end is neither stepped to nor over: a start moved past the end would leave a step
        # of negative length, rejected until the step budget runs out.)
        bump = has & (ts >= j - 2 * m) & (j + 2 * m < to_t(t_stop))
        ts_new = jnp.where(bump, j + m, ts)
        j, m, has = next_jump(jnp.where(bump, i + 1, i))
        te = to_t(t_end) + (ts_new - ts)
        clip = has & (te > j - m) & (j - 2 * m > ts_new) & (j + 2 * m < to_t(t_stop))
        t_start = jnp.where(bump, to_s(ts_new), t_start)
        t_end = jnp.where(clip, to_s(j - m), jnp.where(bump, to_s(te), t_end))
        return t_start, t_end, bump

    def _inner(self) -> dfx.PIDController:
        return dfx.PIDController(rtol=self.rtol, atol=FLOOR * self.rtol, norm=self.norm)

    def wrap(self, direction):
        return self

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        if self.scales is None:
            raise ValueError("ScaledPIDController: bind it to the run first (bind)")
        scales, T = self.scales, self.time_scale
        if self.unit is not None:  # the time scale in units of the span
            T = T / self.unit.safe_span()

        # The first step is chosen as diffrax chooses it (Hairer, Norsett & Wanner), on the
        # dimensionless state and in units of the time scale: their rule mixes powers of time
        # and would otherwise give a first step that depends on the units.
        def scaled_func(terms, tau, z, args):
            y = jax.tree.map(lambda a, s: a * s, z, scales)
            return jax.tree.map(lambda a, s: a * (T / s), func(terms, t0 + tau * T, y, args),
                                scales)

        zero = jnp.zeros_like(T)
        dt0 = self.first_step if dt0 is None else dt0
        tau0 = None if dt0 is None else dt0 / T
        tau1, state = self._inner().init(terms, zero, (t1 - t0) / T,
                                         jax.tree.map(_div, y0, scales), tau0, args,
                                         scaled_func, error_order)
        t_first = t0 + tau1 * T
        if self.jumps is not None:
            _, t_first, _ = self._at_jumps(t0, t_first, t1)
        return t_first, (state, t1)  # (the run's end, for the jumps)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order,
                        controller_state):
        scales = self.scales
        z0, z1, err = (jax.tree.map(_div, x, scales) for x in (y0, y1_candidate, y_error))
        # A step into a region where the vector field is not finite is rejected with the
        # smallest factor (diffrax would carry a NaN step size on to the step budget).
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(e)) & jnp.all(jnp.isfinite(z))
                                    for e, z in zip(jax.tree.leaves(err),
                                                    jax.tree.leaves(z1))]))
        err = jax.tree.map(lambda e: jnp.where(finite, e, jnp.full_like(e, 1e30)), err)
        state, t_stop = controller_state
        keep, t_next, t_after, jump, state, result = self._inner().adapt_step_size(
            t0, t1, z0, z1, args, err, error_order, state)
        # Step-size underflow (as jaxdyn's batch engine decides it): the next step no longer
        # resolves the time, at round-off of `max(|t|, T)`. Reported as `nonfinite` where the
        # rejected step was not finite, as `dt_min_reached` otherwise.
        eps = jnp.finfo(jnp.result_type(t1)).eps
        step, t = t_after - t_next, t1
        if self.unit is not None:
            step, t = step * self.unit.span, self.unit.start + t1 * self.unit.span
        underflow = ~keep & (step <= underflow_step(t, self.time_scale, eps))
        R = dfx.RESULTS
        result = R.where(underflow, R.where(finite, R.dt_min_reached, R.nonfinite), result)
        if self.jumps is not None:
            t_next, t_after, bumped = self._at_jumps(t_next, t_after, t_stop)
            jump = jump | bumped
        return keep, t_next, t_after, jump, (state, t_stop), result


def underflow_step(t, time_scale, eps):
    """The step below which time is not resolved: `16 eps max(|t|, T)`."""
    return 16 * eps * jnp.maximum(jnp.abs(t), time_scale)
