"""Saving at sample times from each accepted step, so that the sample times may be traced
without diffrax's runtime check of `SaveAt(ts)`.

`diffrax.diffeqsolve` checks that `SaveAt(ts=...)` is increasing and within `[t0, t1]` with
`equinox.error_if`; where the times are traced values (the sample times of a fit, an argument of
its compiled program) that check is a host callback, and JAX's persistent compilation cache
refuses programs that hold one. `Samples` is a writer (`_accepted.Writing`) that saves the
state at each sample time from the same local interpolant of each accepted step from which
diffrax saves `SaveAt(ts)`, so the states saved are those that `SaveAt(ts)` would give, and the
times are checked on the host by the caller.
"""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

BLOCK = 16
"""Samples written together, from one evaluation of the interpolant at `BLOCK` times: a loop
iteration a sample costs more than the evaluation (several microseconds for a state of many
leaves)."""


class Samples(eqx.Module):
    """Saves the state at the increasing times `ts` (a run forwards in time) into `ys`, from
    the sample `index` on.

    For runs that are not reverse-mode differentiated (its loop over the times in a step has a
    dynamic trip count): concrete runs, and forward-mode Jacobians.

    `ts` is padded with `BLOCK` infinite times (`pad`), `ys` with as many rows, so that a block
    of samples is written in place wherever it starts. Its state is `(ys, index)`: `ys` holds
    the state at each of `ts` (`inf` where not yet reached, as diffrax fills `SaveAt(ts)`),
    `index` the number of times saved. `ys` and `index` are carried from segment to segment of
    a run: `start` makes them at its start.
    """

    ts: Float[Array, " times+BLOCK"]
    ys: Any = None
    index: Any = None

    @staticmethod
    def pad(ts):
        return jnp.concatenate([ts, jnp.full(BLOCK, jnp.inf, ts.dtype)])

    def start(self, t0, y0):
        """The buffer and count at the start of a run: the initial state at times up to it."""
        reached = self.ts <= t0
        ys = jax.tree.map(
            lambda y: jnp.where(_rows(reached, jnp.ndim(y)), y,
                                jnp.full((self.ts.size,) + jnp.shape(y), jnp.inf, y.dtype)),
            y0)
        return ys, jnp.sum(reached)

    def init(self, t0, y0):
        return self.ys, self.index

    def write(self, state, t0, t1, dense_info, interpolation, keep):
        def pending(carry):
            return keep & (self.ts[carry[1]] <= t1)

        def save(carry):
            ys, i = carry
            times = jax.lax.dynamic_slice_in_dim(self.ts, i, BLOCK)
            now = times <= t1  # a prefix: the block's samples within this step
            y = jax.vmap(interpolation.evaluate)(jnp.where(now, times, t1))

            def put(a, b):  # in place; the rows past this step keep what they hold
                old = jax.lax.dynamic_slice_in_dim(a, i, BLOCK)
                new = jnp.where(_rows(now, b.ndim - 1), b, old)
                return jax.lax.dynamic_update_slice_in_dim(a, new, i, 0)

            return jax.tree.map(put, ys, y), i + jnp.sum(now)

        return jax.lax.while_loop(pending, save, state)


def _rows(mask, trailing):
    """`mask` over rows, with `trailing` axes to broadcast."""
    return mask.reshape(mask.shape + (1,) * trailing)
