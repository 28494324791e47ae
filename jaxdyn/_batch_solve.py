"""Batched explicit Runge-Kutta integration: the engine behind [`jaxdyn.ensemble`][].

`jax.vmap` over `diffrax.diffeqsolve` is general but slow on a batch: every Runge-Kutta stage
of diffrax's step is a separate small kernel, so on a CPU a step over 4096 trajectories costs
about thirty times the arithmetic it does. This engine takes the same diffrax solver (its Butcher
tableau, its error estimate and its dense interpolant), unrolls the stages, and advances a whole
structure-of-arrays batch per loop iteration, so XLA fuses each stage into one pass over memory.
The step size is chosen as diffrax's `PIDController` (its defaults) chooses it: on the same
tableau and problem a trajectory takes the steps that `diffrax.diffeqsolve` takes (its step-size
factors, computed without the C library's `pow`, agree to about 1e-5), and its values agree to
about 1e-9 relative at `rtol = 1e-6` (tests/test_batch_solve.py).

Two ways to choose the step:

- per trajectory (the default): each trajectory has its own time and step size, accepted or
  rejected on its own error; the loop runs until the slowest trajectory is done;
- lock-step: one step size for the whole batch, the smallest that every trajectory accepts.

Terminating events are per trajectory: a trajectory whose event function changes sign in a step
stops there, and the event time is located afterwards, for all such trajectories at once, by
bracketed root finding (Illinois) on the step's dense interpolant.

Failures are per trajectory too (status codes below): an invalid sample, a step budget that
runs out or a step size that underflows marks that trajectory and leaves the others running.
"""

from collections.abc import Callable
from functools import partial
from typing import Any, NamedTuple

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np

from ._fastmath import with_vectorised_trig
from ._outcome import MESSAGES, NAMES, SUCCESS, Outcome
from ._tolerance import underflow_step
from ._validation import ParameterError

STATUS = NAMES
"""Status codes of batched runs, by index: the codes of `jaxdyn.Outcome`."""

STATUS_HELP = {o.name: MESSAGES[o] for o in Outcome if o not in SUCCESS}

_SAFETY, _FACTOR_MIN, _FACTOR_MAX = 0.9, 0.2, 10.0
_RUNNING = -1  # the status of a trajectory still being integrated
_HELD = 1e6  # the value of a held event (as `jaxdyn._hybrid` holds them): finite, for Illinois
_EVENT = STATUS.index("event")

COMPACT_ROWS = 1024
"""The default of `batch_solve`'s `compact_rows` in ensembles. Per-trajectory stepping compacts
the batch: once at most half of it is still running, those trajectories move to a batch of half
the size, down to this many rows. The loop then costs what the running trajectories cost, not
what the slowest one in the chunk costs. Each size is another copy of the loop to compile (about
0.9 s for the torque-free body, 1.4 s for the falling rod): on 2 cores, 1024 ran 4 to 10% faster
than 2048, and 256 at most 2% faster than 1024 for twice the extra compile time."""


SWITCH_ROWS = 64
"""Rows of a batch whose mode switches are located and applied together (hybrid scenes in the
engine): a step in which some trajectories switch gathers them, this many at a time."""


class Tableau(NamedTuple):
    a: tuple[tuple[float, ...], ...]
    b: tuple[float, ...]
    e: tuple[float, ...]
    c: tuple[float, ...]
    order: int


def tableau(solver: Any) -> Tableau:
    """The Butcher tableau of an explicit diffrax Runge-Kutta solver with an error estimate."""
    tab = getattr(solver, "tableau", None)
    if (not isinstance(solver, dfx.AbstractERK) or tab is None or tab.b_error is None
            or tab.implicit):
        raise ParameterError(
            f"solver {type(solver).__name__}: batched ensembles need an explicit Runge-Kutta "
            "solver with an error estimate (diffrax.Tsit5, Dopri5, Dopri8, Bosh3, Heun); "
            "use mode='vmap' for other solvers"
        )
    return Tableau(
        a=tuple(tuple(float(v) for v in row) for row in tab.a_lower),
        b=tuple(float(v) for v in tab.b_sol),
        e=tuple(float(v) for v in tab.b_error),
        c=tuple(float(v) for v in tab.c),
        order=int(solver.order(None)),
    )


def _combine(y, h, coefs, fs):
    """`y + h * sum_j coefs[j] * fs[j]` leaf by leaf, skipping zero coefficients."""
    def leaf(y_leaf, *f_leaves):
        acc = None
        for c, f in zip(coefs, f_leaves):
            if c != 0.0:
                acc = c * f if acc is None else acc + c * f
        if acc is None:
            return y_leaf if y is not None else jnp.zeros_like(f_leaves[0])
        acc = h * acc  # h: (n,), the batch axis is last
        return acc if y is None else y_leaf + acc

    if y is None:
        return jax.tree.map(lambda *fl: leaf(None, *fl), *fs[: len(coefs)])
    return jax.tree.map(leaf, y, *fs[: len(coefs)])


def _inv_root(x, p: int, iterations: int = 3):
    """`x ** (-1 / p)` for `x` in `[1e-12, 1e12]`, to about 1e-5 (p <= 8), by Newton's method
    from a guess read off the float32 exponent (five iterations give it to round-off, for about
    5% more time per step on the torque-free body).

    A few dozen vectorised operations; `x ** y` would call the C library's scalar `pow` once per
    element, which on a CPU cost a third of a step. (The guess is made in float32, whose
    integer conversions vectorise everywhere.)"""
    x32 = x.astype(jnp.float32)
    one = jax.lax.bitcast_convert_type(jnp.float32(1), jnp.int32)
    bits = jax.lax.bitcast_convert_type(x32, jnp.int32)
    guess = one - ((bits - one).astype(jnp.float32) * (1.0 / p)).astype(jnp.int32)
    y = jax.lax.bitcast_convert_type(guess, jnp.float32).astype(x.dtype)
    for _ in range(iterations):
        y = y * ((p + 1) - x * y**p) * (1.0 / p)
    return y


def pack_pairs(rows):
    """Rows two by two into complex rows (an odd last row stays as it is).

    XLA computes every element of a fused loop's output on its own: rows that share a long
    computation (the stages of a Runge-Kutta step) each compute it again, and a complex row
    computes it once for both of its parts."""
    pairs = tuple(jax.lax.complex(rows[i], rows[i + 1]) for i in range(0, len(rows) - 1, 2))
    return pairs + tuple(rows[len(rows) - len(rows) % 2:])


def unpack_pairs(packed):
    """The rows of `pack_pairs`."""
    rows = []
    for x in packed:
        rows += [jnp.real(x), jnp.imag(x)] if jnp.iscomplexobj(x) else [x]
    return tuple(rows)


def _where(mask, a, b):
    return jax.tree.map(lambda x, z: jnp.where(mask, x, z), a, b)


def _rms(rows):
    """Root mean square over a tuple of rows."""
    return jnp.sqrt(sum(x * x for x in rows) / len(rows))


def _last(tree):
    return jax.tree.map(lambda x: jnp.moveaxis(x, 0, -1), tree)


def _first(tree):
    return jax.tree.map(lambda x: jnp.moveaxis(x, -1, 0), tree)


class BatchRun(NamedTuple):
    t_final: jax.Array
    y_final: Any
    ys: Any  # (n, len(ts), ...) or None
    event: dict[str, jax.Array]
    status: jax.Array
    reason: jax.Array  # index of the violated check for invalid_input
    steps: jax.Array
    rejected: jax.Array
    switches: jax.Array


class Switching(NamedTuple):
    """How a hybrid scene's trajectories switch mode (see `jaxdyn._hybrid`), each a function of
    one trajectory (parameters `p`):

    - `switch(p, t, y, hit) -> (y, stop, ended_by)`: at a segment's end where `hit`, the state
      in its next mode, whether the run ends, and the events that end it (`(n_events,)`);
    - `rescale(p, t, y) -> (atol, time_scale)`: the error floors and time scale of a segment
      starting from `(t, y)` (each segment's error control in its own start's natural scales);
    - `ended_at_start`: `(n, n_events)` booleans, the events that ended the run at `t0`;
    - `max_switches`: the most switches a run may take (one more is a failure).
    """

    switch: Callable
    rescale: Callable
    ended_at_start: Any
    max_switches: int


class _Rows:
    """The batch's state as a tuple of rows: one `(..., m)` array per scalar component, the
    batch along the last axis, so that every Runge-Kutta stage is a handful of fused passes
    over contiguous memory."""

    def __init__(self, y0):  # leaves (n, *shape)
        self.treedef = jax.tree.structure(y0)
        self.shapes = [x.shape[1:] for x in jax.tree.leaves(y0)]

    def of(self, tree) -> tuple:
        """Leaves `(..., *shape, m)` to rows `(..., m)`."""
        out = []
        for x, shape in zip(jax.tree.leaves(tree), self.shapes):
            lead = x.shape[: x.ndim - len(shape) - 1]
            x = x.reshape(lead + (-1, x.shape[-1]))
            out += [x[..., i, :] for i in range(x.shape[-2])]
        return tuple(out)

    def tree(self, rows):
        """Rows `(..., m)` to leaves `(..., *shape, m)`."""
        leaves, i = [], 0
        for shape in self.shapes:
            size = int(np.prod(shape))
            x = jnp.stack(rows[i: i + size], axis=-2)
            leaves.append(x.reshape(x.shape[:-2] + tuple(shape) + x.shape[-1:]))
            i += size
        return jax.tree.unflatten(self.treedef, leaves)


ROLL_EQUATIONS = 250
"""Vector fields of more operations than this (counted in their jaxpr, the jaxprs it calls
included) have their Runge-Kutta stages evaluated in a loop (`rk_step`) rather than unrolled.
Measured on 2 cores with `jaxdyn montecarlo SCENE --n 256 --no-cache` (29 Nov 2026), looped
against unrolled: the B-dot scene (606 operations) compiled in 6.4-7.4 s against 13.1-13.9 s
and ran in 0.40-0.43 s against 0.65-0.70 s; gravity-gradient (612) 6.7-7.2 s against
12.8-13.4 s, running in 0.08-0.09 s against 0.13-0.17 s; reaction-wheels (333) 6.4-8.2 s
against 11.3-14.9 s (at n = 8192: 21 s against 46 s, running in 1.8 s against 4.7 s). Below
the bound, unrolled runs faster: Explorer 1's damper (125) ran twice as long looped, the
rough-floor rod (208) 2.4 times as long at n = 8192 (for 33 s of compilation against 42 s);
the free body (50), dual spinner (82) and falling rod (83) gain nothing looped."""


def _equations(jaxpr) -> int:
    """The operations of a jaxpr, those of the jaxprs in their parameters included (the
    bodies of calls, loops and branches)."""
    def inner(value):
        if hasattr(value, "eqns"):  # a Jaxpr
            return [value]
        if hasattr(value, "jaxpr") and hasattr(value.jaxpr, "eqns"):  # a ClosedJaxpr
            return [value.jaxpr]
        if isinstance(value, tuple | list):
            return [j for v in value for j in inner(v)]
        return []

    return sum(1 + sum(_equations(j) for v in eqn.params.values() for j in inner(v))
               for eqn in jaxpr.eqns)


def _rolled(f, p, t, y) -> bool:
    """Whether `rk_step` evaluates the stages of `f` in a loop: where `f` is large."""
    return _equations(jax.make_jaxpr(f)(p, t, y).jaxpr) > ROLL_EQUATIONS


def rk_step(tab: Tableau, f: Callable, p, t, y: tuple, h, looped: bool | None = None):
    """One explicit Runge-Kutta step of size `h` over rows: the stage derivatives, `y1` and
    the error estimate.

    The first stage is evaluated again even for solvers whose last stage is the next step's
    first (FSAL): carrying it from step to step costs a pass over memory per state component,
    which on a CPU is more than the evaluation (the torque-free body and the falling rod both
    ran about 4% faster without).

    The stages are unrolled, so that XLA fuses each into one pass over memory, unless the
    vector field is large (`ROLL_EQUATIONS`): then they are evaluated in a loop whose body
    holds one copy of the field instead of one per stage (a step appears several times in an
    ensemble's program, each stage a copy of the field when unrolled). The loop forms the
    same sums in the same order; XLA compiles the two forms apart, so a stage can differ in
    its last bit (tests/test_batch_solve.py). `looped`: the decision, where the caller has
    made it already (`_Loop.rk_step`); `None` to decide here."""
    fs = [f(p, t, y)]
    if looped is None:
        looped = _rolled(f, p, t, y)
    if len(tab.a) > 1 and looped:
        fs = _stages_in_a_loop(tab, f, p, t, y, h, fs[0])
    else:
        for row, ci in zip(tab.a, tab.c):
            fs.append(f(p, t + ci * h, _combine(y, h, row, fs)))
    return fs, _combine(y, h, tab.b, fs), _combine(None, h, tab.e, fs)


def _stages_in_a_loop(tab: Tableau, f: Callable, p, t, y: tuple, h, f0):
    """The stage derivatives of `rk_step` from a `fori_loop` over the stages after the first:
    stage `i + 1` from `y + h * sum_j a[i][j] * f_j` over every earlier stage `j` (the
    zero coefficients of the tableau add exact zeros; only where a stage is not finite does
    a zero coefficient carry it on, as NaN, into the later stages)."""
    stages = len(tab.a) + 1
    dtype = h.dtype
    a = np.zeros((stages - 1, stages - 1))
    for i, row in enumerate(tab.a):
        a[i, :len(row)] = row
    a, c = jnp.asarray(a, dtype), jnp.asarray(tab.c, dtype)
    buf = tuple(jnp.zeros((stages,) + v.shape, v.dtype).at[0].set(v) for v in f0)

    def body(i, buf):
        coef = a[i]

        def combine(y_leaf, b):
            acc = coef[0] * b[0]
            for j in range(1, stages - 1):
                acc = acc + coef[j] * b[j]
            return y_leaf + h * acc

        fi = f(p, t + c[i] * h, tuple(combine(v, b) for v, b in zip(y, buf)))
        return tuple(b.at[i + 1].set(v) for b, v in zip(buf, fi))

    buf = jax.lax.fori_loop(0, stages - 1, body, buf)
    return [tuple(b[j] for b in buf) for j in range(stages)]


def initial_step(f, p, t0, y0, f0, rtol, atol, time_scale, error_order):
    """Hairer, Norsett & Wanner's starting step, as diffrax's `PIDController` chooses it, in
    units of each trajectory's time scale (as `ScaledPIDController` does)."""
    T = time_scale
    scale = tuple(a + rtol * jnp.abs(y) for a, y in zip(atol, y0))
    d0 = _rms(tuple(y / s for y, s in zip(y0, scale)))
    d1 = _rms(tuple(k / s for k, s in zip(f0, scale))) * T
    h0 = jnp.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / d1)
    f_euler = f(p, t0 + h0 * T, tuple(y + h0 * T * k for y, k in zip(y0, f0)))
    d2 = _rms(tuple((a - b) / s for a, b, s in zip(f_euler, f0, scale))) * T / h0
    dmax = jnp.maximum(d1, d2)
    h1 = jnp.where(dmax <= 1e-15, jnp.maximum(1e-6, h0 * 1e-3),
                   (0.01 / dmax) ** (1.0 / error_order))
    dt = jnp.minimum(100 * h0, h1) * T
    return jnp.where(jnp.isfinite(dt) & (dt > 0), dt, 1e-6 * T)


def step_factor(norm, accept, error_order: int):
    """The next step size over this one, as diffrax's `PIDController` (integral control, its
    defaults) decides it (to about 1e-5, see `_inv_root`): `0.9 norm^(-1/error_order)`, within
    `[1, 10]` after an accepted step and `[0.2, 0.9]` after a rejected one; `0.2` after a step
    that was not finite."""
    factor = _SAFETY * _inv_root(jnp.clip(norm, 1e-12, 1e12), error_order)
    factor = jnp.where(norm == 0, _FACTOR_MAX, factor)
    factor = jnp.where(jnp.isfinite(norm), factor, _FACTOR_MIN)
    return jnp.where(accept, jnp.clip(factor, 1.0, _FACTOR_MAX),
                     jnp.clip(factor, _FACTOR_MIN, _SAFETY))


def _interpolant_weights(interp_cls, n_stages: int, dtype):
    """`theta -> (w_y0, w_y1, w_k)`: the solver's dense interpolant at `theta` in [0, 1] as
    the weights of `y0`, `y1` and each stage increment `h * f_i` (it is linear in them), for
    one trajectory.

    Read off as the interpolant's gradient, so that the interpolation is a few fused
    multiply-adds per row: `vmap` of diffrax's `evaluate` would be a batched dot, a library
    call that costs as much as a whole Runge-Kutta step on a CPU."""
    def weights(theta):
        def evaluate(y0, y1, k):
            return interp_cls(t0=0.0, t1=1.0, y0=y0, y1=y1, k=k).evaluate(theta)
        zero = jnp.zeros((), dtype)
        _, pullback = jax.vjp(evaluate, zero, zero, jnp.zeros((n_stages,), dtype))
        return pullback(jnp.ones((), dtype))

    return weights


def _interpolate(weights, ta, tb, ya, yb, fs, h, s):
    """The dense interpolant of the steps `[ta, tb]` (stage derivatives `fs`, step `h`) at
    times `s`, row by row."""
    same = ta == tb  # (as diffrax rescales time: a step of zero length gives its start)
    theta = jnp.where(same, 0.0, s - ta) / jnp.where(same, 1.0, tb - ta)
    wa, wb, wk = jax.vmap(weights, out_axes=(0, 0, -1))(theta)
    out = []
    for j, (a, b) in enumerate(zip(ya, yb)):
        acc = None
        for i, f in enumerate(fs):
            acc = wk[i] * f[j] if acc is None else acc + wk[i] * f[j]
        out.append(wa * a + wb * b + h * acc)
    return tuple(out)


def _save(ts, saved, nxt, active, bound, value_at):
    """Save the states at every save time `<= bound` not saved yet, for `active` rows.
    `saved`: rows `(S, n)`; `nxt`: each row's next save time (index into `ts`)."""
    if ts is None:
        return saved, nxt
    S = ts.shape[0]
    rows = jnp.arange(nxt.shape[0])

    def pending(nxt):
        return active & (nxt < S) & (ts[jnp.minimum(nxt, S - 1)] <= bound)

    def body(c):
        saved, nxt = c
        m = pending(nxt)
        col = jnp.minimum(nxt, S - 1)
        val = value_at(ts[col])
        saved = tuple(a.at[col, rows].set(jnp.where(m, v, a[col, rows]))
                      for a, v in zip(saved, val))
        return saved, nxt + m.astype(nxt.dtype)

    return jax.lax.while_loop(lambda c: jnp.any(pending(c[1])), body, (saved, nxt))


def illinois(g, ta, tb, iterations: int):
    """The root of `g` (a function of `(n,)` times, one per row, positive at `ta`) in each
    row's bracket `[ta, tb]`: the end point, within a few ulp, where `g <= 0`.

    Illinois: regula falsi that halves the weight of an end point kept twice; it converges
    superlinearly, in about ten iterations. Rows whose `g(tb)` is positive keep `tb`."""
    eps = jnp.finfo(ta.dtype).eps
    ga, gb = g(ta), g(tb)

    def unsettled(a, b, gb):
        """Rows whose bracket is wider than a few ulp and does not end on an exact zero."""
        wide = jnp.abs(b - a) > 4 * eps * jnp.maximum(jnp.abs(a), jnp.abs(b))
        return wide & (gb != 0)

    def iterate(c):
        a, b, ga, gb, side, go, i = c  # go: the rows not settled yet
        denom = jnp.where(gb != ga, gb - ga, 1.0)
        x = jnp.where(gb != ga, b - gb * (b - a) / denom, 0.5 * (a + b))
        x = jnp.clip(x, jnp.minimum(a, b), jnp.maximum(a, b))
        gx = g(x)
        left = gx > 0  # the root lies in [x, b]
        ga_new = jnp.where(left, gx, jnp.where(side == 1, 0.5 * ga, ga))
        gb_new = jnp.where(left, jnp.where(side == -1, 0.5 * gb, gb), gx)
        a_new = jnp.where(left, x, a)
        b_new = jnp.where(left, b, x)
        side_new = jnp.where(left, -1, 1).astype(jnp.int32)
        # A settled row stays as it is: each row's result is independent of the others
        # (and so of how a batch is sharded or compacted).
        a, b = jnp.where(go, a_new, a), jnp.where(go, b_new, b)
        ga, gb = jnp.where(go, ga_new, ga), jnp.where(go, gb_new, gb)
        side = jnp.where(go, side_new, side)
        return a, b, ga, gb, side, unsettled(a, b, gb), i + 1

    side = jnp.zeros(ta.shape, jnp.int32)
    _, b, _, _, _, _, _ = jax.lax.while_loop(
        lambda c: (c[6] < iterations) & jnp.any(c[5]), iterate,
        (ta, tb, ga, gb, side, unsettled(ta, tb, gb), 0))
    # b: the bracket end where the events have fired (rows where they had not at `tb` keep it)
    return jnp.where(gb <= 0, b, tb)


class _Loop:
    """The stepping loop of one `batch_solve` call over rows: what it integrates and how, and
    its steps as functions of the carry (a dict whose arrays all have the batch as their last
    axis, so that the batch can be compacted by one gather)."""

    def __init__(self, tab, f, G, weights, *, t1, ts, rtol, max_steps, lockstep, axis_name,
                 switching=None, values=None, dt0=None):
        self.tab, self.f, self.G, self.weights = tab, f, G, weights
        # Hybrid scenes: `switching` (batched over rows) and the events' values `(k, n)`.
        self.switching, self.values, self.dt0 = switching, values, dt0
        self.t1, self.ts, self.rtol, self.max_steps = t1, ts, rtol, max_steps
        self.lockstep, self.axis_name = lockstep, axis_name
        self.eps = jnp.finfo(t1.dtype).eps
        self.looped = None  # whether `rk_step` loops over the stages (decided at its first call)

    def rk_step(self, p, t, y, h):
        """`rk_step` of this loop's tableau and field, whether its stages are looped decided
        once (a trace of the field) for every step of the program."""
        if self.looped is None:
            self.looped = _rolled(self.f, p, t, y)
        return rk_step(self.tab, self.f, p, t, y, h, looped=self.looped)

    def bmin(self, x):
        """The smallest element over the batch (every shard of it)."""
        m = jnp.min(x)
        return m if self.axis_name is None else jax.lax.pmin(m, self.axis_name)

    def bany(self, x):
        m = jnp.any(x)
        if self.axis_name is None:
            return m
        return jax.lax.psum(m.astype(jnp.int32), self.axis_name) > 0

    def start(self, p, y0, t0, invalid, dt0, atol, time_scale):
        """The carry at `t0`: rows with invalid inputs marked, those whose events have fired
        already ended (also returned, as `at_start`), the first step sizes, and the states
        saved at the save times at `t0`."""
        n, dtype = y0[0].shape[0], y0[0].dtype
        status = jnp.where(invalid, STATUS.index("invalid_input"), _RUNNING).astype(jnp.int32)
        tvec = jnp.full((n,), t0)
        at_start = jnp.zeros((n,), bool)
        if self.G is not None and self.switching is None:
            at_start = (self.G(p, tvec, y0) <= 0) & ~invalid
            status = jnp.where(at_start, _EVENT, status)
        if dt0 is None:
            dt = initial_step(self.f, p, tvec, y0, self.f(p, tvec, y0), self.rtol, atol,
                              time_scale, self.tab.order)
        else:
            dt = jnp.full((n,), jnp.asarray(dt0, dtype))
        dt = jnp.minimum(dt, self.t1 - t0).astype(dtype)
        if self.lockstep:
            dt = jnp.full((n,), self.bmin(jnp.where(status == _RUNNING, dt, jnp.inf)))
        saved = None if self.ts is None else tuple(
            jnp.full((self.ts.shape[0], n), jnp.inf, dtype) for _ in y0)
        saved, nxt = _save(self.ts, saved, jnp.zeros((n,), jnp.int32), ~invalid, t0,
                           lambda s: y0)
        zeros = jnp.zeros((n,), jnp.int32)
        c = dict(t=tvec, y=y0, dt=dt, status=status, nacc=zeros, nrej=zeros, p=p,
                 saved=saved, nxt=nxt, atol=atol, T=time_scale, switches=zeros)
        if self.switching is not None:
            ended = self.switching.ended_at_start.T & ~invalid
            c.update(status=jnp.where(jnp.any(ended, axis=0), _EVENT, status), ended_by=ended,
                     t_seg=tvec, held=self.values(p, tvec, y0) <= 0)
        return c, at_start

    def condition(self, c, t, y):
        """The earliest of the events at `(t, y)`: the run (or its segment) goes on while it
        is positive. For a hybrid scene, the events at zero when the segment started are held
        (as `jaxdyn._hybrid.Watch.condition` holds them)."""
        if self.switching is None:
            return self.G(c["p"], t, y)
        v = self.values(c["p"], t, y)
        held = c["held"] & ((t <= c["t_seg"]) | (v == 0))
        return jnp.min(jnp.where(held, _HELD, v), axis=0)

    # Each iteration decides on the attempt the one before it computed, then computes the next:
    # the attempt (`h`, and `y1` with the error norm packed by `pack_pairs`, so that the stages
    # are computed once for two rows) is carried from one iteration to the next, where XLA
    # cannot unpack it back into the computation (about 12% faster on the torque-free body).
    def prepare(self, c):
        """The next attempt of every row: its step size and its packed `(y1, norm)`."""
        t, y, dt, status, p = c["t"], c["y"], c["dt"], c["status"], c["p"]
        alive = status == _RUNNING
        h = jnp.where(alive, jnp.minimum(dt, self.t1 - t), 0.0)
        if self.lockstep:
            h = jnp.where(alive, self.bmin(jnp.where(alive, h, jnp.inf)), 0.0)
        _, y1, err = self.rk_step(p, t, y, h)
        norm = _rms(tuple(e / (floor + self.rtol * jnp.maximum(jnp.abs(a), jnp.abs(b)))
                          for e, a, b, floor in zip(err, y, y1, c["atol"])))
        return dict(c, h=h, attempt=pack_pairs(tuple(y1) + (norm,)))

    def step(self, c):
        """Decide on the carried attempt (accept or reject, the next step size, an event, the
        end), save what it passed, and prepare the next attempt."""
        t, y, dt, status, p, h = c["t"], c["y"], c["dt"], c["status"], c["p"], c["h"]
        alive = status == _RUNNING
        *y1, norm = unpack_pairs(c["attempt"])
        y1 = tuple(y1)
        ok = norm < 1.0
        if self.lockstep:
            ok = jnp.full(ok.shape, ~self.bany(alive & ~ok))
        accept = alive & ok
        dt_new = jnp.where(alive, h * step_factor(norm, ok, self.tab.order), dt)
        if self.lockstep:
            dt_new = jnp.where(alive, self.bmin(jnp.where(alive, dt_new, jnp.inf)), dt)
        reached = accept & (t + h >= self.t1)
        t_new = jnp.where(reached, self.t1, jnp.where(accept, t + h, t))
        hit = jnp.zeros(alive.shape, bool)
        if self.switching is not None:
            # A trajectory whose event fires in this step (the last one too) stays at the
            # step's start, with the step size in `dt`: the event is located, and the mode
            # switched, below.
            hit = accept & (self.condition(c, t_new, y1) <= 0)
            reached = reached & ~hit
            dt_new = jnp.where(hit, h, dt_new)
        elif self.G is not None:
            # A trajectory whose event fires in this step (the one that reaches `t1` too)
            # stays at the step's start, with the step size in `dt`: the step is taken again
            # after the loop to locate the event, so the loop carries nothing for it.
            hit = accept & (self.G(p, t_new, y1) <= 0)
            reached = reached & ~hit
            dt_new = jnp.where(hit, h, dt_new)
        advance = accept & ~hit
        # Save the states at the save times passed in this step (for a step that ends in an
        # event, after the event has been located), from the stages again (once per step).
        saved, nxt = c["saved"], c["nxt"]
        if self.ts is not None:
            fs = self.rk_step(p, t, y, h)[0]
            saved, nxt = _save(self.ts, saved, nxt, advance, t_new, lambda s: _interpolate(
                self.weights, t, t_new, y, y1, fs, h, jnp.full(t.shape, s)))
        nacc = c["nacc"] + accept.astype(jnp.int32)
        nrej = c["nrej"] + (alive & ~accept).astype(jnp.int32)
        underflow = alive & ~accept & (dt_new <= underflow_step(t, c["T"], self.eps))
        out_of_steps = alive & ~reached & ~hit & (nacc + nrej >= self.max_steps)
        # (nested selects: jnp.select would reduce over the stacked conditions)
        ended = hit if self.switching is None else jnp.zeros_like(hit)
        status = jnp.where(reached, STATUS.index("completed"), jnp.where(
            ended, _EVENT, jnp.where(out_of_steps, STATUS.index("max_steps_reached"), jnp.where(
                underflow, jnp.where(jnp.isfinite(norm), STATUS.index("step_size_underflow"),
                                     STATUS.index("non_finite")), status))))
        c = dict(c, t=jnp.where(hit, t, t_new), y=_where(advance, y1, y), dt=dt_new,
                 status=status, nacc=nacc, nrej=nrej, saved=saved, nxt=nxt)
        if self.switching is not None:
            c = jax.lax.cond(jnp.any(hit), partial(self.switch_rows, hit=hit), lambda c: c, c)
        return self.prepare({k: v for k, v in c.items() if k not in ("h", "attempt")})

    def switch_rows(self, c, hit):
        """`switch` for the `hit` rows, gathered `SWITCH_ROWS` at a time: a step in which a few
        trajectories switch costs what locating their events costs, not what locating them
        over the whole batch would (each row's result is its own either way)."""
        n = hit.shape[0]
        k = min(n, SWITCH_ROWS)

        def some(state):
            c, pending = state
            # The pending rows first, then the others, each in their order (as `run` orders
            # the running ones): the first `k` are distinct rows, the pending among them.
            pos = jnp.where(pending, jnp.cumsum(pending) - 1,
                            jnp.sum(pending) + jnp.cumsum(~pending) - 1)
            rows = jnp.zeros((n,), jnp.int32).at[pos].set(
                jnp.arange(n, dtype=jnp.int32), unique_indices=True)[:k]
            sub = self.switch(jax.tree.map(lambda x: x[..., rows], c), pending[rows])
            c = jax.tree.map(lambda x, s: x.at[..., rows].set(s), c, sub)
            return c, pending.at[rows].set(False)

        return jax.lax.while_loop(lambda state: jnp.any(state[1]), some, (c, hit))[0]

    def switch(self, c, hit):
        """The `hit` rows moved to their event (located as `_locate_events` locates a
        terminating one), switched into their next mode, and started on a new segment: its
        held events, error floors, time scale and first step, as `jaxdyn._hybrid` starts one."""
        p, t = c["p"], c["t"]
        t_ev, y_ev, saved, nxt = _locate_events(self, hit, p, t, c["y"], c["dt"], c["saved"],
                                                c["nxt"], lambda s, y: self.condition(c, s, y))
        y_sw, stop, ended = self.switching.switch(p, t_ev, y_ev, hit)
        switches = c["switches"] + (hit & ~stop).astype(jnp.int32)
        new = hit & ~stop & (switches <= self.switching.max_switches)
        status = jnp.where(hit & stop, _EVENT, jnp.where(
            hit & ~stop & ~new, STATUS.index("max_steps_reached"),
            jnp.where(new & (t_ev >= self.t1), STATUS.index("completed"), c["status"])))
        atol, T = self.switching.rescale(p, t_ev, y_sw)
        if self.dt0 is None:
            dt = initial_step(self.f, p, t_ev, y_sw, self.f(p, t_ev, y_sw), self.rtol, atol, T,
                              self.tab.order)
        else:
            dt = jnp.full(t.shape, self.dt0, t.dtype)
        dt = jnp.minimum(dt, self.t1 - t_ev)
        return dict(
            c, t=t_ev, y=_where(hit, y_sw, c["y"]), saved=saved, nxt=nxt, status=status,
            switches=switches, ended_by=jnp.where(hit & stop, ended, c["ended_by"]),
            dt=jnp.where(new, dt, c["dt"]), atol=_where(new, atol, c["atol"]),
            T=jnp.where(new, T, c["T"]), t_seg=jnp.where(new, t_ev, c["t_seg"]),
            held=jnp.where(new, self.values(p, t_ev, y_sw) <= 0, c["held"]))

    def run(self, c, m: int, compact_rows: int | None):
        """Step until every trajectory of this (sub-)batch of `m` rows has finished."""
        def running(c):
            return c["status"] == _RUNNING

        if self.lockstep:  # one step size for every shard: they stop together
            return jax.lax.while_loop(lambda c: self.bany(running(c)), self.step, c)
        # Per-trajectory steps need nothing from other trajectories (nor other shards): each
        # shard stops when its own trajectories are done, and the running ones can move to a
        # smaller batch.
        # Half the rows, rounded up to a multiple of 8: XLA's CPU loops vectorise only over
        # those, and a batch of 3572 rows costs twice what one of 3576 does.
        half = -(-m // 16) * 8
        if compact_rows is None or m < 2 * max(compact_rows, 1) or half >= m:
            return jax.lax.while_loop(lambda c: jnp.any(running(c)), self.step, c)
        c = jax.lax.while_loop(lambda c: jnp.sum(running(c)) > half, self.step, c)
        # The running rows (at most `half`) first, then finished ones, each in their order: a
        # partition by prefix sums, linear in `m` (a sort of the flags cost a dozen steps).
        run = running(c)
        pos = jnp.where(run, jnp.cumsum(run) - 1, jnp.sum(run) + jnp.cumsum(~run) - 1)
        order = jnp.zeros((m,), jnp.int32).at[pos].set(
            jnp.arange(m, dtype=jnp.int32), unique_indices=True)[:half]
        sub = self.run(jax.tree.map(lambda x: x[..., order], c), half, compact_rows)
        return jax.tree.map(lambda x, s: x.at[..., order].set(s), c, sub)


def batch_solve(
    field: Callable, conditions: Callable | None, event_names: tuple[str, ...],
    flags, params, y0, t0, t1, ts, *, solver, rtol, atol, max_steps: int,
    lockstep: bool, dt0=None, axis_name: str | None = None,
    compact_rows: int | None = None, time_scale=None, switching: Switching | None = None,
) -> BatchRun:
    """Integrate a batch of `n` trajectories from `t0` to `t1`.

    **Arguments:**

    - `field`: `(p, t, y) -> dy` for one trajectory with parameters `p`.
    - `conditions`: `(p, t, y) -> (n_events,)` event functions, positive while a run goes on;
      `None` for scenes without events.
    - `flags`: `(n, n_checks)` booleans, true where a check of the inputs fails.
    - `params`, `y0`: per-trajectory parameters and initial states, leading axis `n`.
    - `ts`: save times (1-D, increasing, within `[t0, t1]`), or `None`.
    - `rtol`, `atol`: a step is accepted where the RMS norm of `err / (atol + rtol |y|)` is
      below 1. `atol` is a scalar, or a pytree like `y0` with one value per trajectory and
      variable (leaves `(n,)`): jaxdyn's ensembles pass `rtol` times each variable's natural
      scale, as `ScaledPIDController` does for single runs.
    - `time_scale`: `(n,)` time scales of the trajectories (default 1), in whose units the
      starting step is chosen, so that it does not depend on the units of time.
    - `lockstep`: one step size for the whole batch (the smallest any trajectory needs).
    - `axis_name`: the mesh axis when the batch is one shard of a larger batch; lock-step
      reductions then span every shard, so that sharded and unsharded runs agree.
    - `compact_rows`: per-trajectory stepping moves the running trajectories to a batch of half
      the size whenever at most half are running, down to this many rows (`None`: never).
      Every trajectory's arithmetic is the same either way.
    - `switching`: for hybrid scenes (`conditions` then gives every event of the scene), how
      the trajectories switch mode: each locates its own events, in the step in which they
      fire, and goes on in its next mode (see `Switching`).
    """
    tab = tableau(solver)
    n = jax.tree.leaves(y0)[0].shape[0]
    rows = _Rows(y0)
    atol = rows.of(_last(jax.tree.map(lambda a, x: jnp.broadcast_to(
        a.reshape((n,) + (1,) * (x.ndim - 1)), x.shape), _per_trajectory(atol, y0), y0)))
    y0, params = rows.of(_last(y0)), _last(params)
    dtype = y0[0].dtype
    # (sines and cosines in arithmetic that XLA vectorises: on a CPU, the C library's scalar
    # calls were most of a step of the falling rod)
    batched_field = with_vectorised_trig(jax.vmap(field, in_axes=(-1, 0, -1), out_axes=-1))

    def f(p, t, y):
        return rows.of(batched_field(p, t, rows.tree(y)))

    G = batched_c = None
    if conditions is not None:
        batched_c = with_vectorised_trig(jax.vmap(conditions, in_axes=(-1, 0, -1), out_axes=0))

        def G(p, t, y):  # the earliest of the events: the run goes on while it is positive
            return jnp.min(batched_c(p, t, rows.tree(y)), axis=1)

    values = None
    if switching is not None:
        def values(p, t, y):  # every event, (k, n)
            return batched_c(p, t, rows.tree(y)).T

        switching = _batched_switching(switching, rows)
    t0, t1 = jnp.asarray(t0, dtype), jnp.asarray(t1, dtype)
    weights = _interpolant_weights(solver.interpolation_cls, len(tab.c) + 1, dtype)
    loop = _Loop(tab, f, G, weights, t1=t1, ts=ts, rtol=rtol, max_steps=max_steps,
                 lockstep=lockstep, axis_name=axis_name, switching=switching, values=values,
                 dt0=dt0)
    time_scale = jnp.ones((n,), dtype) if time_scale is None else time_scale

    invalid = jnp.any(flags, axis=1)
    carry, at_start = loop.start(params, y0, t0, invalid, dt0, atol, time_scale)
    carry = loop.run(loop.prepare(carry), n, compact_rows)
    t, y, status, p = carry["t"], carry["y"], carry["status"], carry["p"]
    saved, nxt = carry["saved"], carry["nxt"]
    event = {}
    if switching is not None:
        event = dict(zip(event_names, carry["ended_by"]))
    elif G is not None:
        crossed = (status == _EVENT) & ~at_start
        t, y, saved, nxt = _locate_events(loop, crossed, p, t, y, carry["dt"], saved, nxt)
        values = batched_c(p, t, rows.tree(y))
        first = jnp.argmin(values, axis=1)
        for j, name in enumerate(event_names):
            event[name] = (crossed & (first == j)) | (at_start & (values[:, j] <= 0))
    if saved is not None:  # rows (S, n) -> leaves (n, S, ...)
        saved = jax.tree.map(lambda a: jnp.moveaxis(a, -1, 0), rows.tree(saved))
    return BatchRun(t_final=t, y_final=_first(rows.tree(y)), ys=saved, event=event,
                    status=status, reason=jnp.argmax(flags, axis=1).astype(jnp.int32),
                    steps=carry["nacc"], rejected=carry["nrej"], switches=carry["switches"])


def _batched_switching(switching: Switching, rows: _Rows) -> Switching:
    """`switching`'s functions of one trajectory, over the rows of the batch."""
    switch = with_vectorised_trig(jax.vmap(switching.switch, in_axes=(-1, 0, -1, 0),
                                           out_axes=(-1, 0, -1)))
    rescale = with_vectorised_trig(jax.vmap(switching.rescale, in_axes=(-1, 0, -1),
                                            out_axes=(-1, 0)))

    def switch_rows(p, t, y, hit):
        y, stop, ended = switch(p, t, rows.tree(y), hit)
        return rows.of(y), stop, ended

    def rescale_rows(p, t, y):
        atol, time_scale = rescale(p, t, rows.tree(y))
        return rows.of(atol), time_scale

    return switching._replace(switch=switch_rows, rescale=rescale_rows)


def _per_trajectory(atol, y0):
    """`atol` as a pytree like `y0` with one value per trajectory and variable (leaves `(n,)`),
    from a scalar or from such a pytree."""
    if isinstance(atol, dict | tuple | list):
        return atol
    return jax.tree.map(lambda x: jnp.full(x.shape[:1], atol, x.dtype), y0)


def _locate_events(loop: _Loop, crossed, p, t, y, dt, saved, nxt, condition=None):
    """The `crossed` rows moved to their event: the step in which it fired, of size `dt`, taken
    again from where the trajectory stopped, and the event time found on its dense interpolant
    (`illinois`, on `condition(t, y)`: by default the earliest of the events); the save times
    before it are saved."""
    condition = (lambda s, y: loop.G(p, s, y)) if condition is None else condition
    h = jnp.where(crossed, dt, 0.0)
    ta, ya = t, y
    fs, yb, _ = loop.rk_step(p, ta, ya, h)
    tb = ta + h

    def interpolate(s):
        return _interpolate(loop.weights, ta, tb, ya, yb, fs, h, s)

    # Until every bracket has settled: at most 60 iterations in float64 (30 in float32).
    iterations = 60 if t.dtype == jnp.float64 else 30
    t_event = illinois(lambda s: condition(s, interpolate(s)), ta, tb, iterations)
    saved, nxt = _save(loop.ts, saved, nxt, crossed, t_event,
                       lambda s: interpolate(jnp.full(t.shape, s)))
    return (jnp.where(crossed, t_event, t), _where(crossed, interpolate(t_event), y), saved,
            nxt)
