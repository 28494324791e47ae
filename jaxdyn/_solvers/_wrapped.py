"""A solver that wraps another and delegates everything but `init` and `step` to it."""

import diffrax as dfx


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
