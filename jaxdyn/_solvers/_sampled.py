"""Saving at sample times from inside the solver, so that the sample times may be traced
without diffrax's runtime check of `SaveAt(ts)`.

`diffrax.diffeqsolve` checks that `SaveAt(ts=...)` is increasing and within `[t0, t1]` with
`equinox.error_if`; where the times are traced values (the sample times of a fit, an argument of
its compiled program) that check is a host callback, and JAX's persistent compilation cache
refuses programs that hold one. `Sampled` wraps a solver and writes the state at each sample
time into its own solver state, from the same local interpolant of each accepted step from
which diffrax saves `SaveAt(ts)` (the solver state of a rejected step is discarded by
diffrax), so the states saved are those that `SaveAt(ts)` would give, and the times are checked
on the host by the caller.
"""

from typing import Any

import diffrax as dfx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._wrapped import AbstractDelegatingSolver


class Sampled(AbstractDelegatingSolver):
    """`solver`, also saving the state at the increasing times `ts` (a run forwards in time).

    For runs that are not reverse-mode differentiated (its loop over the times in a step has a
    dynamic trip count): concrete runs, and forward-mode Jacobians.

    Its solver state is `(inner, ys, index)`: `ys` holds the state at each of `ts` (the initial
    state at times up to the start; `inf` where not yet reached, as diffrax fills `SaveAt(ts)`),
    `index` the number of times saved. Read it with `diffrax.SaveAt(solver_state=True)`.
    """

    solver: dfx.AbstractSolver
    ts: Float[Array, " times"]

    def init(self, terms, t0, t1, y0, args) -> tuple[Any, Any, Array]:
        reached = self.ts <= t0
        ys = jax.tree.map(
            lambda y: jnp.where(reached.reshape((-1,) + (1,) * jnp.ndim(y)), y,
                                jnp.full((self.ts.size,) + jnp.shape(y), jnp.inf, y.dtype)),
            y0)
        return self.solver.init(terms, t0, t1, y0, args), ys, jnp.sum(reached)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        inner, ys, index = solver_state
        y1, y_error, dense_info, inner, result = self.solver.step(
            terms, t0, t1, y0, args, inner, made_jump)
        interpolation = self.solver.interpolation_cls(t0=t0, t1=t1, **dense_info)
        ts, n = self.ts, self.ts.size

        def pending(carry):
            _, i = carry
            return (i < n) & (ts[jnp.minimum(i, n - 1)] <= t1)

        def save(carry):
            ys, i = carry
            y = interpolation.evaluate(ts[i])
            return jax.tree.map(lambda a, b: a.at[i].set(b), ys, y), i + 1

        ys, index = jax.lax.while_loop(pending, save, (ys, index))
        return y1, y_error, dense_info, (inner, ys, index), result
