"""What `jaxdyn fit` fits for each kind of body and reads for each effect, derived from
their declared inputs.

A body's inputs ([`jaxdyn.Input`][]) say which parameters and initial values are fitted by
default (`fit`: how they are parameterised), which CSV columns measure a state variable
(`columns`), and the body's `identifiability` notes explain components that the generic
identifiability check may find undetermined. An effect's inputs may declare columns too: a
measured output (a wheel's tachometer, `wheel{i}_speed`) whose state is then fitted, or a
known input over time (commanded motor torques, `wheel{i}_torque`). Nothing in the fitter
depends on these; the command uses them to turn a data file into a call of [`jaxdyn.fit`][].
"""

import dataclasses
import re
from collections.abc import Mapping

import numpy as np

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


@dataclasses.dataclass(frozen=True)
class EffectColumns:
    """The data-file columns of one effect of a scene (see [`jaxdyn.Input`][] `columns`).

    **Fields:**

    - `label`: the effect's label in the scene (`"wheels"`).
    - `measured`: for each output the data may hold (`"wheels.speed"`), its columns.
    - `fitted`: for each such output, the state variable fitted (`"wheels.momentum"`) and
      how; `initial_names`: its scene-file name (`"wheels.speed"`), started from the first
      sample.
    - `held`: for each parameter that the data may give over time (`"wheels.motor"`), its
      columns (held from each sample to the next).
    - `units`: the unit of each column.
    """

    label: str
    measured: Mapping[str, tuple[str, ...]]
    fitted: Mapping[str, tuple[str, AbstractParameterisation]]
    initial_names: Mapping[str, str]
    held: Mapping[str, tuple[str, ...]]
    units: Mapping[str, str]


def expand(columns: tuple[str, ...], count: int) -> tuple[str, ...]:
    """Column names with `{i}` expanded to `1..count` (names without it are kept)."""
    return tuple(c.format(i=i) for c in columns
                 for i in (range(1, count + 1) if "{i}" in c else (0,)))


def _count(effect) -> int:
    """The number of elements (wheels) of an effect: the leading size of its first parameter
    declared with one row per element (`("N", ...)`)."""
    values = effect.parameters()
    for inp in type(effect).inputs:
        value = values.get(inp.name)
        if inp.role == "parameter" and inp.shapes[0][:1] == ("N",) and value is not None:
            return int(np.shape(value)[0])
    return 1


def effect_columns(scene) -> list[EffectColumns]:
    """The columns of each effect of `scene` that declares some, by its declarations."""
    out = []
    for label, effect in zip(scene.labels, scene.effects):
        n = _count(effect)
        measured, fitted, names, held, units = {}, {}, {}, {}, {}
        for inp in type(effect).inputs:
            if not inp.columns:
                continue
            cols = expand(inp.columns, n)
            units.update(dict.fromkeys(cols, inp.unit))
            if inp.role == "parameter":
                held[f"{label}.{inp.name}"] = cols
            else:
                output = f"{label}.{inp.state}"
                measured[output] = cols
                names[f"{label}.{inp.name}"] = output
                if inp.fit is not None:
                    fitted[output] = (f"{label}.{inp.fits or inp.state}",
                                      PARAMETERISATIONS[inp.fit]())
        if measured or held:
            out.append(EffectColumns(label, measured, fitted, names, held, units))
    return out


def effect_column_inputs() -> dict[str, list]:
    """The inputs that declare columns, of each registered effect that has some, by kind."""
    _, effects = all_registered()
    found = {kind: [i for i in cls.inputs if i.columns] for kind, cls in sorted(effects.items())}
    return {kind: inputs for kind, inputs in found.items() if inputs}


def effect_columns_help() -> list[str]:
    """One phrase per registered effect with columns: its column templates and units
    (measured outputs first, then known inputs)."""
    def phrase(i, c):
        how = "measured" if i.role == "initial" else "known input, held to the next sample"
        return f"{c} ({i.unit}, {how})"

    return [f"with a scene with {kind} (i = 1..N): "
            + ", ".join(phrase(i, c) for i in sorted(inputs, key=lambda i: i.role != "initial")
                       for c in i.columns)
            for kind, inputs in effect_column_inputs().items()]


def effect_of_column(column: str) -> str | None:
    """The kind of the registered effect that declares `column` (a template's instance)."""
    for kind, inputs in effect_column_inputs().items():
        for template in (c for i in inputs for c in i.columns):
            pattern = re.escape(template).replace(re.escape("{i}"), "[1-9][0-9]*")
            if re.fullmatch(pattern, column):
                return kind
    return None


def hold(scene, held: Mapping[str, tuple]):
    """`scene` with each effect parameter of `held` (`{"wheels.motor": (times, values)}`)
    replaced by its known values over time, held from each time to the next
    ([`jaxdyn.CommandedTorques`][], a law `(t, y, effect)`): commanded motor torques in place
    of the scene's control law."""
    from .._effects._wheels import CommandedTorques
    from .._scene import Scene

    effects = list(scene.effects)
    for name, (times, values) in held.items():
        label, param = name.split(".", 1)
        k = scene.labels.index(label)
        args = {**effects[k].constructor_args(), param: CommandedTorques(times, values)}
        effects[k] = type(effects[k])(**args)
    return Scene(scene.body, tuple(effects), attitude=scene.attitude)

