"""Solvers that wrap another and delegate everything but `init` and `step` to it:
`AbstractDelegatingSolver`, and `TracedOnce`, whose step is traced once per run."""

from collections.abc import Callable

import diffrax as dfx
import equinox as eqx


class AbstractDelegatingSolver(dfx.AbstractWrappedSolver):
    """The wrapped solver's properties and orders, for wrappers that add to what its steps
    return (`Reporting`). Subclasses declare the field `solver` and override `init` and
    `step`."""

    @property
    def scan_kind(self):  # read by diffrax from the Runge-Kutta solvers it wraps
        return self.solver.scan_kind

    @property
    def root_finder(self):  # read by diffrax from an implicit solver it wraps (`isinstance`
        return self.solver.root_finder  # sees through the wrapper); filled in beforehand by
                                        # `_fixed.with_root_finder_tolerances`

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def interpolation_cls(self):  # pyright: ignore
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)


def _step(solver, terms, t0, t1, y0, args, solver_state, made_jump):
    return solver.step(terms, t0, t1, y0, args, solver_state, made_jump)


class TracedOnce(AbstractDelegatingSolver):
    """`solver`, whose step is traced once where `diffrax.diffeqsolve` would trace it four
    times: for the shapes of its dense information, twice to learn which parts of the loop's
    state stay constant (`body_fun_aux`, under `filter_eval_shape`), and for the loop itself.
    The step is a nested `jit` of the same inputs each time (everything it reads is passed
    in, nothing closed over), so JAX traces it once and reuses its jaxpr; XLA inlines the
    call, so the compiled program is the one `diffeqsolve` builds unwrapped. Measured on
    7 Dec 2026: the falling rod's `simulate` traced its Runge-Kutta step in 0.11 s instead of
    0.21 s; `tests/test_rod.py`, `test_outcomes.py` and `test_hard_cases.py` traced in 20 s
    instead of 30 s.

    Each wrapper holds a `jit` of its own (`step_once`), made with it: a run reuses its step's
    trace, and no later run reuses it (a later trace of the same scene sees the values its
    Python functions read then, as without the wrapper, and nothing outlives the run's
    tracing in JAX's caches).

    diffrax's `isinstance` checks of a solver's kind see through one wrapper, not two
    (`TracedOnce(Reporting(...))`), so what `diffeqsolve` does for a kind is done before
    wrapping (`_hybrid`): an implicit solver's root finder gets its tolerances
    (`_fixed.with_root_finder_tolerances`), a Runge-Kutta solver its stage loop for the
    adjoint (`scan_kind`)."""

    solver: dfx.AbstractSolver
    step_once: Callable = eqx.field(static=True)

    def __init__(self, solver):
        self.solver = solver
        self.step_once = eqx.filter_jit(_step)

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        return self.step_once(self.solver, terms, t0, t1, y0, args, solver_state, made_jump)
