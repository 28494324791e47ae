"""Identification: fit a scene's parameters and initial state to sampled outputs."""

from ._fit import FitResult as FitResult, fit as fit
from ._parameterisation import (
    AbstractParameterisation as AbstractParameterisation,
    Positive as Positive,
    Unconstrained as Unconstrained,
    UnitQuaternion as UnitQuaternion,
    ValidInertia as ValidInertia,
)
