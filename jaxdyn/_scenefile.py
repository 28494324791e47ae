"""Scene files: TOML descriptions of a body, its effects, parameters and initial state.

```toml
description = "..."
body = "rigid-body"            # or "falling-rod"
t1 = 50.0                      # optional: final time, tolerances
rtol = 1e-10                   # atol: an optional absolute floor (default none: the
                               # tolerance follows each variable's natural scale)
[parameters]                   # body parameters and initial state, by flat name
inertia = [1.0, 2.0, 3.0]
omega0 = [0.3, 0.2, 1.0]

[[effects]]                    # zero or more
type = "rotor"
momentum = [0.0, 3.0, 0.0]
```

Every name can be overridden (`--set NAME=VALUE` on the command line): a parameter by its name,
an effect's parameter as `<type>.<name>` (`rotor.momentum`), and `t1`, `rtol`, `atol`.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ._errors import ParameterError
from ._inputs import Input, all_registered, defaults, short_value, validate

if TYPE_CHECKING:  # imported when a scene is built: `jaxdyn scenes` needs no JAX
    from ._custom_types import State
    from ._scene import Scene

_RUN_INPUTS = (  # the run settings a scene file (or --set) may give beside the scene
    Input("t1", "final time", "s", bound="positive"),
    Input("rtol", "relative tolerance (see jaxdyn.simulate)", bound="positive"),
    Input("atol", "absolute floor in the state's units (default: none; the tolerance follows "
          "each variable's natural scale)", bound="nonnegative"),
)
_TOP_KEYS = {"description", "body", "parameters", "effects", *(i.name for i in _RUN_INPUTS)}


class _Run:
    """The run settings, validated like a body's inputs (defaults in the signature)."""

    kind = "run settings"
    inputs = _RUN_INPUTS

    def __init__(self, t1: float = 10.0, rtol: float = 1e-10, atol: float = 0.0):
        pass


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    """A scene with its initial state and run settings, as read from a scene file.

    **Fields:** `name`, `description`, `scene` ([`jaxdyn.Scene`][]), `y0` (initial state),
    `t1`, `rtol`, `atol`, `values` (every named value after overrides, for reporting) and
    `initial` (the initial values by the names `scene.state` takes, from which `y0` was built).
    """

    name: str
    description: str
    scene: Scene
    y0: State
    t1: float
    rtol: float
    atol: float
    values: dict[str, Any]
    initial: dict[str, Any]


def builtin_scenes() -> dict[str, str]:
    """Names and descriptions of the scenes shipped with jaxdyn."""
    out = {}
    for entry in sorted(importlib.resources.files("jaxdyn").joinpath("scenes").iterdir(),
                        key=lambda p: p.name):
        if entry.name.endswith(".toml"):
            data = tomllib.loads(entry.read_text())
            out[entry.name[: -len(".toml")]] = str(data.get("description", ""))
    return out


def _read(name_or_path: str) -> tuple[str, dict[str, Any]]:
    builtin = importlib.resources.files("jaxdyn").joinpath("scenes", f"{name_or_path}.toml")
    if builtin.is_file():
        text, name = builtin.read_text(), name_or_path
    else:
        path = Path(name_or_path)
        if not path.is_file():
            raise ParameterError(
                f"scene={name_or_path!r}: not a built-in scene or a file; "
                f"built-in scenes are {sorted(builtin_scenes())}"
            )
        try:  # utf-8-sig: a byte-order mark from a Windows editor is not part of the TOML
            text, name = path.read_text(encoding="utf-8-sig"), path.stem
        except UnicodeDecodeError as e:
            raise ParameterError(
                f"scene file {name_or_path!r}: not UTF-8 text (byte {e.start}); save it as "
                "UTF-8") from None
        except OSError as e:
            raise ParameterError(f"scene file {name_or_path!r}: cannot be read "
                                 f"({e.strerror or e})") from None
    try:
        return name, tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ParameterError(f"scene file {name_or_path!r}: malformed TOML: {e}") from None


def parse_value(field: str, text: str) -> Any:
    """Parse a `--set` value: a number, comma-separated numbers, `true`/`false`, or text."""
    text = text.strip()
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        if len(parts) == 1:
            return text
        raise ParameterError(
            f"{field}={text}: expected a number or comma-separated numbers"
        ) from None
    return values if len(values) > 1 or "," in text else values[0]


def load_scene(name_or_path: str, overrides: Mapping[str, Any] | None = None) -> SceneSpec:
    """Read a built-in scene (by name) or a TOML scene file, apply overrides, build the scene.

    **Arguments:**

    - `name_or_path`: a name from [`jaxdyn.builtin_scenes`][] or the path of a TOML file.
    - `overrides`: values by flat name (`{"theta0": 0.1, "rotor.momentum": [0, 3, 0]}`).

    **Returns:**

    A [`jaxdyn.SceneSpec`][]. Every name and value is checked against the inputs that the
    body and each effect declare ([`jaxdyn.Input`][]); invalid ones raise
    [`jaxdyn.ParameterError`][] naming the field, the value and what is allowed.
    """
    import jax.numpy as jnp

    from ._scene import Scene

    bodies, effect_types = all_registered()
    name, data = _read(name_or_path)
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise ParameterError(f"unknown key(s) {unknown} in scene {name!r}: allowed are "
                             f"{sorted(_TOP_KEYS)}")
    kind = data.get("body")
    if not isinstance(kind, str) or kind not in bodies:
        # (A table here is the body's parameters in the wrong place: said so.)
        where = ("; the body's values go in the [parameters] table"
                 if isinstance(kind, dict) else "")
        raise ParameterError(f"body={short_value(kind)}: expected the name of a body, one of "
                             f"{sorted(bodies)}{where}")
    body_cls = bodies[kind]
    params = data.get("parameters", {})
    if not isinstance(params, dict):
        raise ParameterError("parameters: expected a table of named values")
    effects = data.get("effects", [])
    if not isinstance(effects, list) or not all(isinstance(e, dict) for e in effects):
        raise ParameterError("effects: expected an array of tables ([[effects]])")

    # Every value by its flat name: body inputs, run settings, `<type>.<name>` for effects.
    values: dict[str, Any] = dict(params)
    values.update({i.name: data[i.name] for i in _RUN_INPUTS if i.name in data})
    types = []
    for i, e in enumerate(effects):
        etype = e.get("type")
        if not isinstance(etype, str) or etype not in effect_types:
            raise ParameterError(f"effects[{i}].type={short_value(etype)}: allowed are "
                                 f"{sorted(effect_types)}")
        if etype in types:
            raise ParameterError(f"effects: {etype!r} appears twice: each effect type may "
                                 "appear once in a scene file")
        if not effect_types[etype].accepts(body_cls):
            raise ParameterError(f"effect {etype!r} cannot act on a {kind}")
        types.append(etype)
        values.update({f"{etype}.{k}": v for k, v in e.items() if k != "type"})
    for key, value in (overrides or {}).items():
        etype = key.split(".")[0] if "." in key else None
        if etype is not None and etype not in types:
            raise ParameterError(f"{key}: scene {name!r} has no {etype!r} effect; its effects "
                                 f"are {types}")
        values[key] = value

    # Validate each part against its declarations.
    run_names = {i.name for i in _RUN_INPUTS}
    own = {k: v for k, v in values.items() if "." not in k and k not in run_names}
    body_values = validate(body_cls, own, f"a {kind} (scene {name!r}; run settings: "
                           f"{sorted(run_names)})")
    run = {**defaults(_Run), **validate(_Run, {k: values[k] for k in run_names
                                              if k in values}, "the run")}
    from ._simulate import check_tolerances

    check_tolerances(run["rtol"], run["atol"], jnp.float64)
    effect_values = {
        etype: validate(effect_types[etype],
                        {k.split(".", 1)[1]: v for k, v in values.items()
                         if k.split(".", 1)[0] == etype and "." in k},
                        f"effect {etype!r}", prefix=f"{etype}.")
        for etype in types
    }

    # Build the scene and its initial state from the roles the inputs declare.
    def split(cls, given):
        by_role: dict[str, dict[str, Any]] = {"parameter": {}, "initial": {}, "scene": {}}
        for inp in cls.inputs:
            if inp.name in given:
                key = inp.state if inp.role == "initial" else inp.name
                by_role[inp.role][key] = given[inp.name]
        return by_role

    body_parts = split(body_cls, body_values)
    body = _build(body_cls, body_parts["parameter"], kind)
    effect_objs, initial, options = [], dict(body_parts["initial"]), body_parts["scene"]
    if any(inp.needs_attitude and inp.name in body_values for inp in body_cls.inputs):
        options["attitude"] = True  # a value that sets the attitude needs it integrated
    for etype in types:
        parts = split(effect_types[etype], effect_values[etype])
        effect_objs.append(_build(effect_types[etype], parts["parameter"], etype))
        initial.update({f"{etype}.{k}": v for k, v in parts["initial"].items()})
    scene = Scene(body, tuple(effect_objs), **options)
    try:
        y0 = scene.state(**initial)
    except ParameterError as e:
        raise ParameterError(f"initial values: {e}") from None
    report = {**body_values, **run}
    report.update({f"{etype}.{k}": v for etype in types for k, v in effect_values[etype].items()})
    return SceneSpec(
        name=name, description=str(data.get("description", "")), scene=scene, y0=y0,
        t1=float(run["t1"]), rtol=float(run["rtol"]), atol=float(run["atol"]), values=report,
        initial=initial,
    )


def _build(cls, values: dict[str, Any], what: str):
    try:
        return cls.from_inputs(**values)
    except TypeError as err:  # a combination the declarations cannot express
        raise ParameterError(f"{what}: {err}") from None

