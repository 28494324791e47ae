"""What `jaxdyn fit` fits for each kind of body, derived from the body's declared inputs.

A body's inputs ([`jaxdyn.Input`][]) say which parameters and initial values are fitted by
default (`fit`: how they are parameterised), which CSV columns measure a state variable
(`columns`), and the body's `identifiability` notes explain components that the generic
identifiability check may find undetermined. Nothing in the fitter depends on these; the
command uses them to turn a data file into a call of [`jaxdyn.fit`][].
"""

import dataclasses
from collections.abc import Mapping

from .._inputs import all_registered
from ._parameterisation import (
    AbstractParameterisation,
    Positive,
    Unconstrained,
    UnitQuaternion,
    ValidInertia,
)

PARAMETERISATIONS = {"free": Unconstrained, "positive": Positive, "inertia": ValidInertia,
                     "unit": UnitQuaternion}
"""`Input.fit` -> the parameterisation that `fit` optimises over."""


@dataclasses.dataclass(frozen=True)
class FitSpec:
    """What the data of one kind of body determine, and how to read them.

    **Fields:**

    - `parameters`: body parameters to fit, by scene parameter name.
    - `initial`: initial-state variables to fit, by state name.
    - `initial_names`: scene-file names of the initial values (`omega0`) -> state names.
    - `columns`: for each output that a data file must hold, its CSV columns.
    - `optional_columns`: outputs that a data file may hold as well.
    - `optional_initial`: initial-state variables fitted when their optional output is given.
    - `notes`: why a component may be undetermined, by component name.
    - `scene`: the built-in scene of the body alone (the default for its data files).
    """

    parameters: Mapping[str, AbstractParameterisation]
    initial: Mapping[str, AbstractParameterisation]
    initial_names: Mapping[str, str]
    columns: Mapping[str, tuple[str, ...]]
    optional_columns: Mapping[str, tuple[str, ...]]
    optional_initial: Mapping[str, AbstractParameterisation]
    notes: Mapping[str, str]
    scene: str | None


def fit_spec(body_cls) -> FitSpec | None:
    """The fit preset of a body class, or `None` where it declares nothing to fit."""
    inputs = [i for i in body_cls.inputs if i.fit is not None]
    if not inputs:
        return None
    parameters, initial, optional_initial = {}, {}, {}
    columns, optional_columns = {}, {}
    for inp in inputs:
        how = PARAMETERISATIONS[inp.fit]()
        if inp.role == "parameter":
            parameters[inp.name] = how
        elif inp.measured_optionally:
            optional_initial[inp.state] = how
        else:
            initial[inp.state] = how
        if inp.columns:
            (optional_columns if inp.measured_optionally else columns)[inp.state] = inp.columns
    return FitSpec(
        parameters=parameters, initial=initial, optional_initial=optional_initial,
        initial_names={i.name: i.state for i in body_cls.inputs if i.role == "initial"},
        columns=columns, optional_columns=optional_columns,
        notes=dict(body_cls.identifiability), scene=body_cls.plain_scene,
    )


def fit_specs() -> dict[str, FitSpec]:
    """The fit presets of every registered body that declares something to fit, by kind."""
    bodies, _ = all_registered()
    specs = {kind: fit_spec(cls) for kind, cls in sorted(bodies.items())}
    return {kind: spec for kind, spec in specs.items() if spec is not None}
