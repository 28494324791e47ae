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

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


class Samples(eqx.Module):
    """Saves the state at the increasing times `ts` (a run forwards in time).

    For runs that are not reverse-mode differentiated (its loop over the times in a step has a
    dynamic trip count): concrete runs, and forward-mode Jacobians.

    Its state is `(ys, index)`: `ys` holds the state at each of `ts` (the initial state at
    times up to the start; `inf` where not yet reached, as diffrax fills `SaveAt(ts)`),
    `index` the number of times saved.
    """

    ts: Float[Array, " times"]

    def init(self, t0, y0):
        reached = self.ts <= t0
        ys = jax.tree.map(
            lambda y: jnp.where(reached.reshape((-1,) + (1,) * jnp.ndim(y)), y,
                                jnp.full((self.ts.size,) + jnp.shape(y), jnp.inf, y.dtype)),
            y0)
        return ys, jnp.sum(reached)

    def write(self, state, t0, t1, dense_info, interpolation, keep):
        ts, n = self.ts, self.ts.size

        def pending(carry):
            _, i = carry
            return keep & (i < n) & (ts[jnp.minimum(i, n - 1)] <= t1)

        def save(carry):
            ys, i = carry
            y = interpolation.evaluate(ts[i])
            return jax.tree.map(lambda a, b: a.at[i].set(b), ys, y), i + 1

        return jax.lax.while_loop(pending, save, state)
