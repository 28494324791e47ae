"""Saving at sample times from each accepted step, so that the sample times may be traced
without diffrax's runtime check of `SaveAt(ts)`.

`diffrax.diffeqsolve` checks that `SaveAt(ts=...)` is increasing and within `[t0, t1]` with
`equinox.error_if`; where the times are traced values (the sample times of a fit, an argument of
its compiled program) that check is a host callback, and JAX's persistent compilation cache
refuses programs that hold one. `Samples` is a writer (`_accepted.Writing`) that saves the
state at each sample time from the same local interpolant of each accepted step from which
diffrax saves `SaveAt(ts)`, so the states saved are those that `SaveAt(ts)` would give, and the
times are checked on the host by the caller.

**Nothing the size of `ts` outside a loop.** Every operation over the samples (filling the
samples at the start, writing them, taking back those written past the end of a segment) is a
loop over the samples concerned, one sample per iteration, as diffrax's own `SaveAt(ts)` loop;
the buffers start as constants. XLA's cost estimate of a program counts a loop's body once, and
XLA:CPU runs a program whose estimate is under 1000 operations on the calling thread, others on
a worker thread that wakes the caller when done (see `_hybrid`): the free body's program is
estimated at 667 operations whatever the number of samples. (Elementwise operations over `ts`
cost about 16 operations a sample, and a block of 16 interpolations 1600: 201 samples put it
at 5439. A call saving 201 times took 1.4-1.6 ms before against 1.3-1.7 ms after with XLA's
defaults, 520 us against 320-440 us with the command's settings, measured at 3620514, the
first form of this loop; s45 in `benchmarks/latency-log.md`.)
"""

from typing import Any

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


class Samples(eqx.Module):
    """Saves the state at the increasing times `ts` (a run forwards in time) into buffers, from
    the sample `index` on.

    For runs that are not reverse-mode differentiated (its loop over the times in a step has a
    dynamic trip count): concrete runs, and forward-mode Jacobians.

    Its state is `(ys, ts_saved, index)`: `ys` holds the state at each of `ts` (`inf` where not
    yet reached, as diffrax fills `SaveAt(ts)`), `ts_saved` the times saved (`inf` likewise),
    `index` the number of times saved. They are carried from segment to segment of a run:
    `start` makes them at its start, `keep_until` takes back those past a segment's end. `unit`
    maps the run's times to the solver's (`None`: the same).
    """

    ts: Float[Array, " times"]
    unit: Any = None
    state: Any = None

    def _tau(self, t):
        return t if self.unit is None else self.unit.tau(t)

    def start(self, t0, y0, stop):
        """The buffers at the start of a run: the initial state at the times up to `t0`
        (none where the run ends at once, `stop`)."""
        n = self.ts.size
        ys = jax.tree.map(lambda y: jnp.full((n,) + jnp.shape(y), jnp.inf, y.dtype), y0)
        state = ys, jnp.full(n, jnp.inf, self.ts.dtype), jnp.asarray(0)
        return _loop(lambda c: ~stop & self._due(c, lambda t: t <= t0),
                     lambda c: self._put(c, lambda _: y0), state)

    def init(self, t0, y0):
        return self.state

    def write(self, state, t0, t1, dense_info, interpolation, keep):
        return _loop(lambda c: keep & self._due(c, lambda t: self._tau(t) <= t1),
                     lambda c: self._put(c, lambda t: interpolation.evaluate(self._tau(t))),
                     state)

    def keep_until(self, state, t_end):
        """`state` without the samples after `t_end` (written from the last step of a segment
        that an event ended inside it): their rows back to `inf`, for the next segment to
        write."""
        blank = jax.tree.map(lambda a: jnp.full(a.shape[1:], jnp.inf, a.dtype), state[0])

        def drop(c):
            ys, ts_saved, i = c
            i = i - 1
            ys = jax.tree.map(lambda b, a: a.at[i].set(b), blank, ys)
            return ys, ts_saved.at[i].set(jnp.inf), i

        return _loop(lambda c: (c[2] > 0) & (self.ts[jnp.maximum(c[2] - 1, 0)] > t_end),
                     drop, state)

    def _due(self, state, within):
        """Whether a sample remains to be saved and its time is `within(time)`."""
        i, n = state[2], self.ts.size
        return (i < n) & within(self.ts[jnp.minimum(i, n - 1)])

    def _put(self, state, value):
        """`state` with the sample `index` saved as `value(its time)`."""
        ys, ts_saved, i = state
        t = self.ts[i]
        ys = jax.tree.map(lambda b, a: a.at[i].set(b), value(t), ys)
        return ys, ts_saved.at[i].set(t), i + 1


def _loop(cond, body, state):
    """`lax.while_loop` over a state `(ys, ts_saved, index)` whose buffers are written one row
    per iteration (equinox's loop with `buffers`, as diffrax's `SaveAt(ts)` loop): under
    `vmap`, a row is written where the member's loop goes on, not the whole buffer selected
    between the old and the new at every iteration (`O(rows)` an iteration: 8 forward-mode
    Jacobians of a free body saving 2000 times took 289 ms so, 44.5 ms now). A row may be
    written again by a later loop (`keep_until`, then the next segment): safe for
    `kind="lax"`, which is not reverse-mode differentiated; equinox's other kinds assume each
    row written once."""
    return eqxi.while_loop(cond, body, state, buffers=lambda c: (c[0], c[1]), kind="lax")
