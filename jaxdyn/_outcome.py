"""How a run ended: one enumeration of outcomes for every kind of run.

A single run (`simulate`), a hybrid run and every trajectory of an ensemble (each mode) report
the same codes with the same messages. Codes are computed inside the compiled program and
turned into errors or labels on the host, from this one table.
"""

import enum

import diffrax as dfx
import jax.numpy as jnp


class Outcome(enum.IntEnum):
    """How a run ended. `completed` and `event` are successes; every other value is a failure
    whose message (`MESSAGES`) names the cause and what to change."""

    completed = 0
    """The run reached `t1`."""
    event = 1
    """A terminating event ended the run (a success: the rod lies flat)."""
    max_steps_reached = 2
    step_size_underflow = 3
    non_finite = 4
    invalid_input = 5
    nonlinear_solve_failed = 6
    linear_solve_failed = 7
    solver_failed = 8


SUCCESS = (Outcome.completed, Outcome.event)

MESSAGES = {
    Outcome.completed: "the run reached t1",
    Outcome.event: "a terminating event ended the run",
    Outcome.max_steps_reached: (
        "the step budget `max_steps` ran out before t1: increase max_steps or loosen rtol/atol; "
        "if the steps became tiny the problem may be stiff: use an implicit solver such as "
        "diffrax.Kvaerno5()"),
    Outcome.step_size_underflow: (
        "the step size fell to round-off: the solution may be singular or the problem stiff: "
        "use an implicit solver such as diffrax.Kvaerno5(), or loosen rtol/atol"),
    Outcome.non_finite: (
        "the state became non-finite (NaN or inf): check the parameters and initial state"),
    Outcome.invalid_input: "a parameter or initial value failed the scene's checks",
    Outcome.nonlinear_solve_failed: (
        "the implicit solver's nonlinear iteration did not converge: tighten rtol/atol (smaller "
        "steps) or give the solver a more robust root finder"),
    Outcome.linear_solve_failed: (
        "a linear solve in the implicit solver was singular or broke down: use an explicit "
        "solver or smaller steps"),
    Outcome.solver_failed: "the solver failed",
}

NAMES = tuple(o.name for o in Outcome)
"""Outcome names by code."""

# diffrax's results, by name, and the outcome each one is.
_FROM_DIFFRAX = {
    "successful": Outcome.completed,
    "event_occurred": Outcome.event,
    "max_steps_reached": Outcome.max_steps_reached,
    "max_steps_rejected": Outcome.max_steps_reached,
    "dt_min_reached": Outcome.step_size_underflow,
    "nonfinite": Outcome.non_finite,
    "nonfinite_input": Outcome.non_finite,
    "nonlinear_max_steps_reached": Outcome.nonlinear_solve_failed,
    "nonlinear_divergence": Outcome.nonlinear_solve_failed,
    "singular": Outcome.linear_solve_failed,
    "breakdown": Outcome.linear_solve_failed,
    "stagnation": Outcome.linear_solve_failed,
    "conlim": Outcome.linear_solve_failed,
}


def from_diffrax(result, finite, invalid=False):
    """The outcome code (int32, traceable) of a diffrax `result`, given whether the final
    state is `finite` and whether the inputs were `invalid`. A success that ended non-finite
    is `non_finite`; diffrax results without a counterpart are `solver_failed`."""
    R = dfx.RESULTS
    code = jnp.asarray(int(Outcome.solver_failed), jnp.int32)
    for name, outcome in _FROM_DIFFRAX.items():
        item = getattr(R, name, None)
        if item is not None:
            code = jnp.where(result == item, jnp.int32(outcome), code)
    success = (code == Outcome.completed) | (code == Outcome.event)
    code = jnp.where(success & ~finite, jnp.int32(Outcome.non_finite), code)
    return jnp.where(invalid, jnp.int32(Outcome.invalid_input), code)


def to_diffrax(code):
    """The diffrax result closest to an outcome code (for a `Trajectory.result` built from
    an ensemble's batch engine; `Trajectory.outcome` holds the code itself)."""
    R = dfx.RESULTS
    result = R.internal_error
    for name, outcome in reversed(list(_FROM_DIFFRAX.items())):
        item = getattr(R, name, None)
        if item is not None:
            result = R.where(code == outcome, item, result)
    return result


class SimulationError(RuntimeError):
    """A run that failed at run time. `outcome` is the [`jaxdyn.Outcome`][] code; the message
    names the cause and what to change (`MESSAGES`)."""

    def __init__(self, outcome, message: str | None = None):
        self.outcome = Outcome(int(outcome))
        super().__init__(message or MESSAGES[self.outcome])


def is_success(code):
    return (code == Outcome.completed) | (code == Outcome.event)
