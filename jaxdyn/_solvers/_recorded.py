"""Recording every accepted step's dense output into a table carried from call to call, so that
a run of many segments (one `diffrax.diffeqsolve` each) keeps one dense output of its own size.

`diffrax.diffeqsolve(..., SaveAt(dense=True))` sizes each call's dense output by its whole step
budget: a run of a thousand segments (thrusters switching) would allocate and merge a thousand
tables of `max_steps` rows. `Table` is a writer (`_accepted.Writing`) that writes each accepted
step's interval and dense information into the table it is given, at the row after the last
one written; the caller reads the table back from the final controller state and gives it to
the next segment.
"""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array


class Table(eqx.Module):
    """Writes each accepted step into `table`: a dict with `t_lo`, `t_hi` (`(rows,)`, each
    step's interval), `infos` (the solver's dense information, leaves `(rows, ...)`) and
    `rows` (the number written). Its state is the table."""

    table: dict[str, Any]
    unit: Any = None  # a segment on the unit interval (`jaxdyn._hybrid.Unit`): times mapped

    def init(self, t0, y0):
        return self.table

    def write(self, table, t0, t1, dense_info, interpolation, keep):
        if self.unit is not None:  # (the dense information is per step: unchanged)
            t0, t1 = self.unit.time(t0), self.unit.time(t1)
        rows = table["t_lo"].size
        at, fits = jnp.minimum(table["rows"], rows - 1), table["rows"] < rows

        def put(a, b):  # one row, in place (a full table keeps its rows)
            return jax.lax.dynamic_update_index_in_dim(a, jnp.where(keep & fits, b, a[at]), at, 0)

        return {
            "t_lo": put(table["t_lo"], t0),
            "t_hi": put(table["t_hi"], t1),
            "infos": jax.tree.map(put, table["infos"], dense_info),
            "rows": table["rows"] + jnp.where(keep, 1, 0),
        }


def empty_table(solver, term, t0, t1, y0, args, rows: int) -> dict[str, Array]:
    """A table of `rows` steps for `Table`, none written."""
    info = jax.eval_shape(lambda: solver.step(term, t0, t1, y0, args,
                                              solver.init(term, t0, t1, y0, args), False)[2])
    return {"t_lo": jnp.zeros(rows, t0.dtype), "t_hi": jnp.zeros(rows, t0.dtype),
            "infos": jax.tree.map(lambda s: jnp.zeros((rows, *s.shape), s.dtype), info),
            "rows": jnp.asarray(0)}
