"""Work-precision studies: `jaxdyn.accuracy.study(problem)` sweeps every method over tolerances
or step sizes and reports error, invariant drift, wall time, compile time and evaluations, with
scipy's `solve_ivp` as the outside baseline. See `jaxdyn accuracy --help` for the command."""

from ._accuracy import (
    TOLERANCES as TOLERANCES,
    Method as Method,
    Problem as Problem,
    builtin_problems as builtin_problems,
    default_methods as default_methods,
    drift_series as drift_series,
    reference as reference,
    speed_comparison as speed_comparison,
    study as study,
)
