"""Inputs declared once: what a body or an effect takes from a scene file, `--set` or `--vary`.

Each body and effect lists its inputs in its own file (`inputs = (Input(...), ...)`), with
name, meaning, unit, shape, allowed range, whether it sets the initial state, and what `fit`
may do with it. Declaring `inputs` registers the class under its `kind`: scene files, `--set`,
the `fit` presets, `jaxdyn scenes --parameters` and the README's parameter tables are derived
from these declarations, so adding an effect (a file in `jaxdyn/_effects/`) adds no entry in
any front end.

Values are validated with msgspec (a typed struct per body or effect, built from the
declarations: numbers are finite and within their bounds, texts among their choices, unknown
and missing names refused), then shapes against the declared ones; errors name the field, the
value and what is allowed.
"""

import dataclasses
import inspect
import re
import sys
from typing import Annotated, Any, Literal

import msgspec
import numpy as np

from ._errors import ParameterError, format_value

Role = Literal["parameter", "initial", "scene"]
BODIES: dict[str, type] = {}
"""Body classes by `kind`, registered when a body class declares `inputs`."""
EFFECTS: dict[str, type] = {}
"""Effect classes by `kind`, registered when an effect class declares `inputs`."""

_MAX = sys.float_info.max
_BOUNDS = {  # element types: finite numbers, with their bounds (NaN fails every comparison)
    "finite": (Annotated[float, msgspec.Meta(ge=-_MAX, le=_MAX)], "finite"),
    "positive": (Annotated[float, msgspec.Meta(gt=0.0, le=_MAX)], "positive finite"),
    "nonnegative": (Annotated[float, msgspec.Meta(ge=0.0, le=_MAX)], "non-negative finite"),
}


class _Required:
    def __repr__(self):
        return "required"


REQUIRED: Any = _Required()


@dataclasses.dataclass(frozen=True)
class Input:
    """One input of a body or an effect.

    **Fields:**

    - `name`: the name in scene files and `--set` (an effect's inputs are prefixed with its
      kind there: `rotor.momentum`).
    - `doc`: what it is, in a few words.
    - `unit`: its SI unit (`"1"` for a pure number, `""` for text and switches).
    - `shapes`: allowed shapes, the first the usual one; `"N"` is any positive length (one per
      wheel). `()` is one number.
    - `type`: `"number"`, `"bool"` or `"text"`.
    - `bound`: `"finite"`, `"positive"` or `"nonnegative"` (numbers are always finite).
    - `choices`: the allowed texts.
    - `role`: `"parameter"` (passed to the class), `"initial"` (an initial value of the state
      variable `state`) or `"scene"` (an option of the scene, such as `attitude`).
    - `required`: whether a scene must give it (inputs without a default are required too).
    - `needs_attitude`: giving it makes the scene integrate the attitude.
    - `fit`: how `jaxdyn fit` fits it by default: `None` (it stays known), `"free"`,
      `"positive"`, `"inertia"` (a physically valid inertia) or `"unit"` (a unit quaternion).
    - `columns`: for an initial value, the CSV columns of `jaxdyn fit` that measure the output
      of the same name as its state variable (an effect's output `<kind>.<state>`); for a
      parameter, the columns that give it as a known input over time (held from each sample
      to the next: a zero-order hold, [`jaxdyn.CommandedTorques`][]). `{i}` in a name stands
      for the element's number, from 1 (one column per wheel: `wheel{i}_speed`). An effect's
      columns are optional as a group: all of them, or none.
    - `measured_optionally`: those columns may be absent (the variable is then not fitted).
    - `fits`: for an initial value measured by `columns` that is not itself a state variable
      (a wheel's speed), the state variable that `fit` fits in its place (its momentum).
    - `measures`: for an effect's parameter, the body's reference quantity it measures
      (`"momentum"`), for uses that solve in natural units.
    """

    name: str
    doc: str
    unit: str = "1"
    shapes: tuple[tuple, ...] = ((),)
    type: Literal["number", "bool", "text"] = "number"
    bound: Literal["finite", "positive", "nonnegative"] = "finite"
    choices: tuple[str, ...] = ()
    role: Role = "parameter"
    state: str | None = None
    required: bool = False
    needs_attitude: bool = False
    fit: str | None = None
    columns: tuple[str, ...] = ()
    measured_optionally: bool = False
    fits: str | None = None
    measures: str | None = None

    def __post_init__(self):
        if (self.role == "initial") != (self.state is not None):
            raise TypeError(f"Input {self.name!r}: an initial value names its state variable")

    def allowed(self) -> str:
        """What is allowed, in words (`"3 finite numbers (rad/s)"`)."""
        if self.type == "bool":
            return "true or false"
        if self.type == "text":
            return ("one of " + ", ".join(repr(c) for c in self.choices)) if self.choices \
                else "text"
        bound = _BOUNDS[self.bound][1]
        unit = f" ({self.unit})" if self.unit not in ("", "1") else ""
        return " or ".join(_shape_words(s, bound) for s in self.shapes) + unit

    def value_type(self):
        """The msgspec type that validates this input's values (shapes are checked after)."""
        if self.type == "bool":
            return bool
        if self.type == "text":
            return Literal[self.choices] if self.choices else str  # type: ignore[valid-type]
        element = _BOUNDS[self.bound][0]
        ndim = max(len(s) for s in self.shapes)
        if ndim == 0:
            return element
        inner = list[element] if ndim == 1 else list[element | list[element]]
        return element | inner if any(len(s) == 0 for s in self.shapes) else inner

    def check_shape(self, field: str, value) -> None:
        if self.type != "number":
            return
        try:
            shape = np.shape(np.asarray(value, dtype=float))
        except ValueError:
            raise ParameterError(f"{field}={short_value(value)}: ragged lists; expected "
                                 f"{self.allowed()}") from None
        if not any(_matches(shape, s) for s in self.shapes):
            raise ParameterError(f"{field}={short_value(value)}: expected {self.allowed()}")


def _matches(shape, declared) -> bool:
    return len(shape) == len(declared) and all(
        (d == "N" and n >= 1) or n == d for n, d in zip(shape, declared))


def _shape_words(shape: tuple, bound: str) -> str:
    if shape == ():
        return f"a {bound} number"
    if len(shape) == 1:
        count = "one or more" if shape[0] == "N" else str(shape[0])
        return f"{count} {bound} numbers"
    dims = " x ".join(str(d) for d in shape)
    return f"{dims} {bound} numbers"


def short_value(value, limit: int = 80) -> str:
    text = format_value(value)
    return text if len(text) <= limit else text[: limit - 4] + " ..."


def defaults(cls) -> dict[str, Any]:
    """Default of each declared input, read from the class's own signatures (`__init__` for
    parameters, `initial_state` for initial values): `REQUIRED` where there is none."""
    def signature(name):
        method = getattr(cls, name, None)
        return inspect.signature(method).parameters if method is not None else {}

    build, init, start = signature("from_inputs"), signature("__init__"), \
        signature("initial_state")
    out = {}
    for inp in cls.inputs:
        if inp.role == "initial":
            param = start.get(inp.state)
        elif inp.role == "parameter":
            param = build.get(inp.name) or init.get(inp.name)
        else:  # options of the scene are off by default
            param = None
        default = param.default if param is not None else None
        if inp.required or default is inspect.Parameter.empty:
            default = REQUIRED
        elif default is None and inp.type == "bool":
            default = False
        out[inp.name] = default
    return out


def register(registry: dict[str, type], cls) -> None:
    """Register a class that declares `inputs` under its `kind` (called on subclassing)."""
    if "inputs" not in cls.__dict__:
        return
    names = [i.name for i in cls.inputs]
    if len(set(names)) != len(names):
        raise TypeError(f"{cls.__name__}.inputs: a name is declared twice: {names}")
    if "parameter_names" not in cls.__dict__:
        cls.parameter_names = tuple(i.name for i in cls.inputs
                                    if i.role == "parameter" and i.type == "number")
    if "parameter_kinds" not in cls.__dict__:
        cls.parameter_kinds = {i.name: i.measures for i in cls.inputs if i.measures}
    registry[cls.kind] = cls


_STRUCTS: dict[type, type] = {}


def _struct(cls) -> type:
    if cls not in _STRUCTS:
        fields, given = [], defaults(cls)
        for inp in cls.inputs:
            default = given[inp.name]
            typ = inp.value_type()
            fields.append((inp.name, typ) if default is REQUIRED
                          else (inp.name, typ, msgspec.UNSET))
        _STRUCTS[cls] = msgspec.defstruct(cls.kind, fields, kw_only=True,
                                          forbid_unknown_fields=True)
    return _STRUCTS[cls]


_PATH = re.compile(r" - at `\$\.([A-Za-z_0-9]+)(.*)`$")


def validate(cls, values: dict[str, Any], where: str, prefix: str = "") -> dict[str, Any]:
    """Check `values` against `cls.inputs`; returns the values given, converted to Python
    floats, lists, booleans and texts. Errors name the field (with `prefix`), the value and
    what is allowed; `where` says whose inputs these are (`"a rigid-body"`)."""
    by_name = {i.name: i for i in cls.inputs}
    unknown = sorted(set(values) - set(by_name))
    if unknown:
        raise ParameterError(f"unknown parameter {prefix + unknown[0]!r} for {where}: allowed "
                             f"are {sorted(prefix + n for n in by_name)}")
    try:
        obj = msgspec.convert(values, _struct(cls), strict=True)
    except msgspec.ValidationError as e:
        text = str(e)
        missing = re.search(r"missing required field `(\w+)`", text)
        if missing:
            inp = by_name[missing.group(1)]
            raise ParameterError(f"{prefix}{inp.name} is required for {where}: "
                                 f"{inp.allowed()}") from None
        found = _PATH.search(text)
        if found is None:  # pragma: no cover - msgspec always gives the path of a field
            raise ParameterError(f"{where}: {text}") from None
        inp = by_name[found.group(1)]
        detail = "" if not found.group(2) else f" (at {found.group(2)})"
        raise ParameterError(f"{prefix}{inp.name}={short_value(values[inp.name])}: expected "
                             f"{inp.allowed()}{detail}") from None
    out = {}
    for name in values:
        value = getattr(obj, name)
        by_name[name].check_shape(prefix + name, value)
        out[name] = value
    return out


def table(cls) -> list[dict[str, str]]:
    """One row per input: name, shape and allowed values, unit, default, meaning."""
    rows, given = [], defaults(cls)
    for inp in cls.inputs:
        default = given[inp.name]
        rows.append({
            "name": inp.name,
            "allowed": inp.allowed(),
            "default": "required" if default is REQUIRED else "optional" if default is None
            else str(default).lower() if isinstance(default, bool) else format_value(default),
            "meaning": inp.doc + (f" (sets `{inp.state}`)" if inp.role == "initial" else ""),
        })
    return rows


def markdown() -> str:
    """The README's parameter tables: every body, then every effect (an effect's inputs are
    set as `<type>.<name>` with `--set`)."""
    lines = []
    for title, registry in (("Bodies (`body = ...`, values in `[parameters]`)", BODIES),
                            ("Effects (`[[effects]]`, `type = ...`)", EFFECTS)):
        lines.append(f"**{title}**")
        lines.append("")
        for kind, cls in sorted(registry.items()):
            doc = (inspect.getdoc(cls) or "").split("\n\n")[0].replace("\n", " ")
            lines.append(f"`{kind}`: {doc}")
            lines.append("")
            lines.append("| name | allowed | default | meaning |")
            lines.append("|---|---|---|---|")
            for row in table(cls):
                lines.append(f"| `{row['name']}` | {row['allowed']} | {row['default']} | "
                             f"{row['meaning']} |")
            lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def all_registered() -> tuple[dict[str, type], dict[str, type]]:
    """Every body and effect kind (importing the built-in ones first)."""
    from . import _effects, _rigid_body, _rod, _rough_rod  # noqa: F401  (they register)

    return BODIES, EFFECTS


