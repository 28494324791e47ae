"""Writing each accepted step into buffers that diffrax leaves in place.

diffrax 0.7 keeps or discards the whole solver state after every step
(`jnp.where(keep_step, new, old)` on each leaf), so a buffer held in the solver state (the
sample buffer of `Samples`, the dense table of `Table`) is copied at every step: a run with
`n` samples and `s` steps cost `O(n s)` (3.1 s for 1e6 samples of a free body over 681
steps; 62 ms in s45, as diffrax's own `SaveAt(ts)`). The step-size
controller's state is not selected: the controller decides acceptance itself and returns its
state as it is. So the buffers live there: `Reporting` wraps the solver and hands each step's
dense information to the controller alongside the error estimate (`y_error` becomes the pair
`(y_error, dense_info)`, which diffrax passes on untouched but for mapping NaN to inf), and
`Writing` wraps the controller, asks the controller it wraps whether the step is accepted, and
writes the accepted step into its writers' buffers in place. A run then costs `O(n + s)`.

A writer is an `equinox.Module` with `init(t0, y0) -> state` and
`write(state, t0, t1, dense_info, interpolation, keep) -> state`: the step's interval, its
dense information and local interpolant, and whether it was accepted. It writes only what
`keep` allows, element by element, so that its buffer is updated in place. The final
controller state (`SaveAt(controller_state=True)`) is `(inner, {name: writer state})`.
"""

from collections.abc import Callable
from typing import Any

import diffrax as dfx
import equinox as eqx

from ._wrapped import AbstractDelegatingSolver


class Reporting(AbstractDelegatingSolver):
    """`solver`, reporting each step's dense information to the controller (see above)."""

    solver: dfx.AbstractSolver

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        y1, y_error, dense_info, solver_state, result = self.solver.step(
            terms, t0, t1, y0, args, solver_state, made_jump)
        return y1, (y_error, dense_info), dense_info, solver_state, result


class Writing(dfx.AbstractStepSizeController):
    """`controller`, also writing each accepted step of a `Reporting` solver into `writers`
    (a dict of writers). Its state is `(inner, {name: writer state})`."""

    controller: dfx.AbstractStepSizeController
    writers: dict[str, Any]
    interpolation_cls: Callable[..., dfx.AbstractLocalInterpolation] = eqx.field(static=True)

    def wrap(self, direction):
        return Writing(self.controller.wrap(direction), self.writers, self.interpolation_cls)

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        tnext, inner = self.controller.init(terms, t0, t1, y0, dt0, args, func, error_order)
        return tnext, (inner, {k: w.init(t0, y0) for k, w in self.writers.items()})

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order,
                        controller_state):
        y_error, dense_info = y_error
        inner, states = controller_state
        keep, tprev, tnext, made_jump, inner, result = self.controller.adapt_step_size(
            t0, t1, y0, y1_candidate, args, y_error, error_order, inner)
        interpolation = self.interpolation_cls(t0=t0, t1=t1, **dense_info)
        states = {k: w.write(states[k], t0, t1, dense_info, interpolation, keep)
                  for k, w in self.writers.items()}
        return keep, tprev, tnext, made_jump, (inner, states), result
