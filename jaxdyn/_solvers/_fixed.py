"""What `diffrax.diffeqsolve` would check or fill in at run time, done so that a run's program
holds no host callback (JAX's persistent compilation cache refuses programs that do).

- `FixedStep`: `diffrax.ConstantStepSize` with its step held by the controller instead of
  passed as `dt0`. `diffeqsolve` checks the sign of a `dt0` (`(t1 - t0) * dt0 >= 0`) with
  `equinox.error_if`, a host callback wherever the step is a traced value (an argument of the
  program: every fixed-step run). The step is checked on the host by the caller instead
  (positive and finite; the runs go forwards in time), or inside the program where the caller
  traces it.
- `with_root_finder_tolerances`: an implicit solver's root finder given the step-size
  controller's tolerances where it leaves them to the controller (`use_stepsize_tol`, diffrax's
  default), as `diffeqsolve` does for an implicit solver; needed where the solver is wrapped
  twice (`TracedOnce(Reporting(...))`): diffrax's check of a solver's kind sees through one
  wrapper only.
"""

import diffrax as dfx
import equinox as eqx
from diffrax._root_finder import use_stepsize_tol  # (diffrax's sentinel, not exported)
from jaxtyping import Array


class FixedStep(dfx.AbstractStepSizeController):
    """`diffrax.ConstantStepSize()` stepping by `step` (the same steps to the bit), for a run
    forwards in time; `diffeqsolve` is then given `dt0=None`."""

    step: Array

    def wrap(self, direction):
        return self  # (as ConstantStepSize; the runs go forwards: direction 1)

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        return dfx.ConstantStepSize().init(terms, t0, t1, y0, self.step, args, func, error_order)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order,
                        controller_state):
        return dfx.ConstantStepSize().adapt_step_size(t0, t1, y0, y1_candidate, args, y_error,
                                                      error_order, controller_state)


def _unset(root_finder) -> tuple[str, ...]:
    return tuple(a for a in ("rtol", "atol", "norm")
                 if getattr(root_finder, a, None) is use_stepsize_tol)


def with_root_finder_tolerances(solver, controller):
    """`solver` (implicit) with the tolerances and norm its root finder leaves to the step-size
    controller taken from `controller`, as `diffrax.diffeqsolve` fills them in."""
    unset = _unset(solver.root_finder)
    if not unset:
        return solver
    if not isinstance(controller, dfx.AbstractAdaptiveStepSizeController):
        raise ValueError(
            f"solver {type(solver).__name__} is implicit and its root finder takes its "
            "tolerances from an adaptive step-size controller: use one (the default), or give "
            "the root finder rtol, atol and norm")
    return eqx.tree_at(lambda s: tuple(getattr(s.root_finder, a) for a in unset), solver,
                       tuple(getattr(controller, a) for a in unset))
