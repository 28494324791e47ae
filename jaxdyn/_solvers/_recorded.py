"""Recording every accepted step's dense output into a table carried from call to call, so that
a run of many segments (one `diffrax.diffeqsolve` each) keeps one dense output of its own size.

`diffrax.diffeqsolve(..., SaveAt(dense=True))` sizes each call's dense output by its whole step
budget: a run of a thousand segments (thrusters switching) would allocate and merge a thousand
tables of `max_steps` rows. `Recorded` wraps a solver and writes each accepted step's interval
and dense information into the table it is given, at the row after the last one written; the
caller reads the table back from the final solver state (`SaveAt(solver_state=True)`) and gives
it to the next segment's solver. diffrax discards the solver state of a rejected step, so only
accepted steps are written.
"""

from typing import Any

import diffrax as dfx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from ._wrapped import AbstractDelegatingSolver


class Recorded(AbstractDelegatingSolver):
    """`solver`, also writing each accepted step into `table`: a dict with `t_lo`, `t_hi`
    (`(rows,)`, each step's interval), `infos` (the solver's dense information, leaves
    `(rows, ...)`) and `rows` (the number written). Its solver state is `(inner, table)`."""

    solver: dfx.AbstractSolver
    table: dict[str, Any]

    def init(self, terms, t0, t1, y0, args) -> tuple[Any, dict[str, Any]]:
        return self.solver.init(terms, t0, t1, y0, args), self.table

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        inner, table = solver_state
        y1, y_error, dense_info, inner, result = self.solver.step(
            terms, t0, t1, y0, args, inner, made_jump)
        at = table["rows"]
        table = {
            "t_lo": table["t_lo"].at[at].set(t0),
            "t_hi": table["t_hi"].at[at].set(t1),
            "infos": jax.tree.map(lambda a, b: a.at[at].set(b), table["infos"], dense_info),
            "rows": at + 1,
        }
        return y1, y_error, dense_info, (inner, table), result


def empty_table(solver, term, t0, t1, y0, args, rows: int) -> dict[str, Array]:
    """A table of `rows` steps for `Recorded(solver, table)`, none written."""
    info = jax.eval_shape(lambda: solver.step(term, t0, t1, y0, args,
                                              solver.init(term, t0, t1, y0, args), False)[2])
    return {"t_lo": jnp.zeros(rows, t0.dtype), "t_hi": jnp.zeros(rows, t0.dtype),
            "infos": jax.tree.map(lambda s: jnp.zeros((rows, *s.shape), s.dtype), info),
            "rows": jnp.asarray(0)}
