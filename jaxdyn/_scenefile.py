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

import dataclasses
import importlib.resources
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax.numpy as jnp

from ._custom_types import State
from ._effects import AttitudeTracking, ExternalTorque, GravityGradient, RateDamping, Rotor, Wheels
from ._rigid_body import RigidBody
from ._rod import FallingRod
from ._rough_rod import RoughFloorRod
from ._scene import Scene
from ._validation import ParameterError, format_value

# Per body: parameters passed to the body, then initial values and their state names.
_BODIES: dict[str, dict[str, Any]] = {
    "falling-rod": {
        "cls": FallingRod,
        "parameters": {"length": "m", "mass": "kg", "g": "m/s^2"},
        "initial": {"theta0": "theta", "theta_dot0": "theta_dot"},
        "options": {},
        "required": ("length", "theta0"),
    },
    "rough-floor-rod": {
        "cls": RoughFloorRod,
        "parameters": {"length": "m", "mass": "kg", "g": "m/s^2", "mu_s": "1", "mu_k": "1"},
        "initial": {"theta0": "theta", "theta_dot0": "theta_dot"},
        "options": {},
        "required": ("length", "theta0"),
    },
    "rigid-body": {
        "cls": RigidBody,
        "parameters": {"inertia": "kg m^2"},
        "initial": {"omega0": "omega", "quaternion0": "quaternion"},
        "options": {"attitude": bool},
        "required": ("inertia", "omega0"),
    },
}

def _build_wheels(control: str = "none", gain=None, kp=None, kd=None, target=None, **kwargs):
    laws = {
        "none": lambda: None,
        "rate-damping": lambda: RateDamping(_need("wheels.gain", gain)),
        "attitude-tracking": lambda: AttitudeTracking(
            _need("wheels.target", target), _need("wheels.kp", kp), _need("wheels.kd", kd)
        ),
    }
    if not isinstance(control, str) or control not in laws:
        raise ParameterError(f"wheels.control={control!r}: allowed are {sorted(laws)}")
    uses = {"none": (), "rate-damping": ("gain",), "attitude-tracking": ("kp", "kd", "target")}
    given = {"gain": gain, "kp": kp, "kd": kd, "target": target}
    stray = sorted(k for k, v in given.items() if v is not None and k not in uses[control])
    if stray:
        raise ParameterError(
            f"wheels.{stray[0]} given, but wheels.control={control!r} does not use it: set "
            f"wheels.control to {'rate-damping' if stray[0] == 'gain' else 'attitude-tracking'}"
            " or remove it")
    law = laws[control]()
    if law is not None:
        if "motor" in kwargs:
            raise ParameterError("wheels.motor: give constant motor torques or a control law, "
                                 "not both")
        kwargs["motor"] = law
    return Wheels(**kwargs)


def _build_ring_damper(axis=None, inertia=None, damping=None):
    return Wheels(axes=[_need("ring-damper.axis", axis)], inertia=[_need("ring-damper.inertia",
                  inertia)], damping=[_need("ring-damper.damping", damping)])


def _need(field: str, value):
    if value is None:
        raise ParameterError(f"{field} is required")
    return value


_EFFECTS: dict[str, dict[str, Any]] = {
    "rotor": {"cls": Rotor, "parameters": ("momentum",), "options": {}},
    "torque": {"cls": ExternalTorque, "parameters": ("torque",), "options": {"frame": str}},
    "gravity-gradient": {
        "cls": GravityGradient, "parameters": ("orbit_rate", "phase"), "options": {},
    },
    # Momentum wheels (reaction wheels, a dual spinner's rotor): initial relative spins `speed`.
    "wheels": {
        "cls": _build_wheels,
        "parameters": ("axes", "inertia", "motor", "max_torque", "max_speed", "damping", "gain",
                       "kp", "kd", "target"),
        "options": {"control": str},
        "initial": ("speed",),
    },
    # A viscous ring damper: one wheel without a motor, coupled to the body by viscous friction.
    "ring-damper": {
        "cls": _build_ring_damper,
        "parameters": ("axis", "inertia", "damping"),
        "options": {},
        "initial": ("speed",),
    },
}

def _effect_keys(etype: str) -> set[str]:
    spec = _EFFECTS[etype]
    return set(spec["parameters"]) | set(spec["options"]) | set(spec.get("initial", ()))


_TOP_KEYS = {"description", "body", "t1", "rtol", "atol", "parameters", "effects"}
_RUN_KEYS = ("t1", "rtol", "atol")


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    """A scene with its initial state and run settings, as read from a scene file.

    **Fields:** `name`, `description`, `scene` ([`jaxdyn.Scene`][]), `y0` (initial state),
    `t1`, `rtol`, `atol`, and `values` (every named value after overrides, for reporting).
    """

    name: str
    description: str
    scene: Scene
    y0: State
    t1: float
    rtol: float
    atol: float
    values: dict[str, Any]


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


def _number_or_list(field: str, value: Any) -> float | list[float]:
    def num(x):
        if isinstance(x, bool) or not isinstance(x, int | float):
            raise ParameterError(f"{field}={format_value(value)}: expected numbers")
        return float(x)

    if isinstance(value, list):
        return [_number_or_list(field, x) if isinstance(x, list) else num(x) for x in value]
    return num(value)


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

    A [`jaxdyn.SceneSpec`][]. Invalid names or values raise [`jaxdyn.ParameterError`][] naming
    the field, the value and what is allowed.
    """
    name, data = _read(name_or_path)
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise ParameterError(f"unknown key(s) {unknown} in scene {name!r}: allowed are "
                             f"{sorted(_TOP_KEYS)}")
    kind = data.get("body")
    if not isinstance(kind, str) or kind not in _BODIES:
        raise ParameterError(f"body={kind!r}: allowed are {sorted(_BODIES)}")
    spec = _BODIES[kind]
    params = data.get("parameters", {})
    if not isinstance(params, dict):
        raise ParameterError("parameters: expected a table of named values")
    effects = data.get("effects", [])
    if not isinstance(effects, list) or not all(isinstance(e, dict) for e in effects):
        raise ParameterError("effects: expected an array of tables ([[effects]])")

    allowed = {**spec["parameters"], **spec["initial"], **spec["options"]}
    values: dict[str, Any] = {}
    for key, value in params.items():
        if key not in allowed:
            raise ParameterError(
                f"unknown parameter {key!r} for a {kind}: allowed are {sorted(allowed)}"
            )
        values[key] = value
    for key in _RUN_KEYS:
        if key in data:
            values[key] = data[key]
    effect_specs = []
    for i, e in enumerate(effects):
        etype = e.get("type")
        if not isinstance(etype, str) or etype not in _EFFECTS:
            raise ParameterError(f"effects[{i}].type={etype!r}: allowed are {sorted(_EFFECTS)}")
        eallowed = _effect_keys(etype)
        for key, value in e.items():
            if key == "type":
                continue
            if key not in eallowed:
                raise ParameterError(
                    f"unknown parameter {key!r} for effect {etype!r}: allowed are "
                    f"{sorted(eallowed)}"
                )
            values[f"{etype}.{key}"] = value
        effect_specs.append(etype)

    for key, value in (overrides or {}).items():
        etype = key.split(".")[0] if "." in key else None
        if etype is not None:
            if etype not in effect_specs:
                raise ParameterError(
                    f"{key}: scene {name!r} has no {etype!r} effect; its effects are "
                    f"{effect_specs}"
                )
            sub = key.split(".", 1)[1]
            eallowed = _effect_keys(etype)
            if sub not in eallowed:
                raise ParameterError(
                    f"unknown parameter {key!r}: allowed for {etype!r} are "
                    f"{sorted(etype + '.' + k for k in eallowed)}"
                )
        elif key not in allowed and key not in _RUN_KEYS:
            raise ParameterError(
                f"unknown parameter {key!r} for scene {name!r}: allowed are "
                f"{sorted(set(allowed) | set(_RUN_KEYS))}"
            )
        values[key] = value

    for key in spec["required"]:
        if key not in values:
            raise ParameterError(f"{key} is required for a {kind}")

    # Types.
    for key, value in values.items():
        option = spec["options"].get(key)
        if option is None and "." in key:
            etype, sub = key.split(".", 1)
            option = _EFFECTS[etype]["options"].get(sub)
        if option is bool:
            if not isinstance(value, bool):
                raise ParameterError(f"{key}={format_value(value)}: expected true or false")
        elif option is str:
            if not isinstance(value, str):
                raise ParameterError(f"{key}={format_value(value)}: expected text")
        else:
            values[key] = _number_or_list(key, value)

    run = {"t1": 10.0, "rtol": 1e-10, "atol": 0.0}
    for key in _RUN_KEYS:
        if key in values:
            v = values[key]
            if isinstance(v, list):
                raise ParameterError(f"{key}={format_value(v)}: expected one number")
            if key == "t1" and not (v > 0 and v < float("inf")):
                raise ParameterError(f"{key}={format_value(v)}: must be a positive number")
            run[key] = v
    from ._simulate import check_tolerances

    check_tolerances(run["rtol"], run["atol"], jnp.float64)

    if kind == "rigid-body" and isinstance(values["inertia"], list) \
            and len(values["inertia"]) == 9 and not isinstance(values["inertia"][0], list):
        flat = values["inertia"]  # nine tensor entries, row by row
        values["inertia"] = [flat[0:3], flat[3:6], flat[6:9]]
    body = spec["cls"](**{k: values[k] for k in spec["parameters"] if k in values})
    effect_objs = []
    for etype in effect_specs:
        espec = _EFFECTS[etype]
        kwargs = {k: values[f"{etype}.{k}"] for k in (*espec["parameters"], *espec["options"])
                  if f"{etype}.{k}" in values}
        if len(set(effect_specs)) != len(effect_specs):
            raise ParameterError(f"effects: {effect_specs}: each effect type may appear once "
                                 "in a scene file")
        try:
            effect_objs.append(espec["cls"](**kwargs))
        except TypeError as err:
            raise ParameterError(f"effect {etype!r}: {err}") from None
    scene = Scene(body, tuple(effect_objs), attitude=bool(values.get("attitude", False))
                  or "quaternion0" in values)
    initial = {key: state for key, state in spec["initial"].items() if key in values}
    for label, etype in zip(scene.labels, effect_specs):
        for key in _EFFECTS[etype].get("initial", ()):
            if f"{etype}.{key}" in values:
                initial[f"{etype}.{key}"] = f"{label}.{key}"
    try:
        y0 = scene.state(**{state: values[key] for key, state in initial.items()})
    except ParameterError as e:
        raise ParameterError(f"{', '.join(initial)}: {e}") from None
    return SceneSpec(
        name=name, description=str(data.get("description", "")), scene=scene, y0=y0,
        t1=float(run["t1"]), rtol=float(run["rtol"]), atol=float(run["atol"]), values=values,
    )
