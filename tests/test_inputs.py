"""Inputs declared once (issue 18): every front end derives from the bodies' and effects'
declarations, and every declared input refuses what it does not allow, by name."""

import inspect
import re
from pathlib import Path
from typing import ClassVar

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import jaxdyn as jd
from jaxdyn._identify._presets import fit_specs
from jaxdyn._inputs import REQUIRED, all_registered, defaults, markdown

BODIES, EFFECTS = all_registered()
CLASSES = [*BODIES.values(), *EFFECTS.values()]
FUZZ = settings(max_examples=60, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow])


def _example(inp):
    """A valid value of a declared input (1 in its first shape, N = 1)."""
    if inp.type == "bool":
        return False
    if inp.type == "text":
        return inp.choices[0] if inp.choices else "text"
    fill = 0.5 if inp.bound == "nonnegative" else 1.0  # friction: mu_k <= mu_s = 0.5
    return np.full([1 if d == "N" else d for d in inp.shapes[0]], fill).tolist() \
        if inp.shapes[0] else fill


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(float(value)) if np.isfinite(value) else ("nan" if np.isnan(value)
                                                          else ("inf" if value > 0 else "-inf"))


def _minimal_scene(tmp_path: Path, cls) -> tuple[Path, str]:
    """A scene file holding `cls` with only its required inputs; returns it and the prefix of
    `cls`'s names in `--set`."""
    if cls in BODIES.values():
        body, effect, prefix = cls, None, ""
    else:
        body, effect, prefix = BODIES["rigid-body"], cls, f"{cls.kind}."
    needed = {i.name: _example(i) for i in body.inputs if defaults(body)[i.name] is REQUIRED}
    lines = [f'body = "{body.kind}"', "t1 = 1.0", "[parameters]"]
    lines += [f"{k} = {_toml(v)}" for k, v in needed.items()]
    if effect is not None:
        lines += ["[[effects]]", f'type = "{effect.kind}"']
        lines += [f"{i.name} = {_toml(_example(i))}" for i in effect.inputs
                  if defaults(effect)[i.name] is REQUIRED]
    path = tmp_path / f"{cls.kind}.toml"
    path.write_text("\n".join(lines) + "\n")
    return path, prefix


def test_readme_parameter_tables_are_generated_from_the_declarations():
    text = Path(__file__).parents[1].joinpath("README.md").read_text()
    block = re.search(r"<!-- --8<-- \[start:parameters\] -->\n(.*?)<!-- --8<-- "
                      r"\[end:parameters\] -->", text, re.S)
    assert block is not None
    assert block.group(1) == markdown(), "regenerate with: jaxdyn scenes --parameters --markdown"


def test_every_builtin_body_and_effect_is_registered():
    assert set(BODIES) >= {"rigid-body", "falling-rod", "rough-floor-rod"}
    assert set(EFFECTS) >= {"rotor", "torque", "gravity-gradient", "wheels", "ring-damper"}
    for name in jd.builtin_scenes():
        spec = jd.load_scene(name)
        assert spec.scene.body.kind in BODIES
        assert all(e.kind in EFFECTS for e in spec.scene.effects)


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.kind)
def test_declarations_match_the_classes(cls):
    """Every declared parameter is an argument of the class (no stale declaration), every
    argument without a default is declared, every initial value is one its state takes."""
    build = inspect.signature(cls.from_inputs).parameters
    init = inspect.signature(cls.__init__).parameters
    start = inspect.signature(cls.initial_state).parameters
    takes_any = any(p.kind is p.VAR_KEYWORD for p in build.values())
    for inp in cls.inputs:
        if inp.role == "parameter":
            assert inp.name in build or (takes_any and inp.name in init), inp.name
        elif inp.role == "initial":
            assert inp.state in start, inp.name
    declared = {i.name for i in cls.inputs}
    for name, p in init.items():
        if name != "self" and p.default is p.empty and p.kind is p.POSITIONAL_OR_KEYWORD:
            assert name in declared, f"{cls.kind}: argument {name} is not declared"


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.kind)
def test_minimal_scenes_from_the_declarations_load(tmp_path, cls):
    path, prefix = _minimal_scene(tmp_path, cls)
    spec = jd.load_scene(str(path))
    assert spec.t1 == 1.0
    # Every optional input can be given too (valid example values).
    for inp in cls.inputs:
        if defaults(cls)[inp.name] is not REQUIRED and inp.name not in (
                "motor", "gain", "target", "kp", "kd", "control"):
            jd.load_scene(str(path), {prefix + inp.name: _example(inp)})


def _bad_values(inp):
    """Values the declaration does not allow."""
    if inp.type == "bool":
        return st.sampled_from([1.0, "yes", [True]])
    if inp.type == "text":
        return st.sampled_from([1.0, True, ["body"], "no such choice " + "x" * 200]
                               if inp.choices else [1.0, True])
    scalar_bad = ["one", True, float("nan"), float("inf"), -float("inf"), 10**400, None]
    if inp.bound == "positive":
        scalar_bad += [0.0, -1.0, -1e-300]
    elif inp.bound == "nonnegative":
        scalar_bad += [-1.0, -1e-300]
    shape = [1 if d == "N" else d for d in inp.shapes[0]]

    def embed(x):  # the bad element inside an otherwise valid value
        if not shape:
            return x
        arr = np.ones(shape).tolist()
        row = arr
        while isinstance(row[0], list):
            row = row[0]
        row[0] = x
        return arr

    wrong_shapes = [np.ones(s).tolist() for s in ((2,), (5,), (2, 2), (2, 2, 2))
                    if not any(len(s) == len(d) and all(a == b or b == "N"
                               for a, b in zip(s, d)) for d in inp.shapes)]
    return st.one_of(st.sampled_from(scalar_bad).map(embed),
                     *( [st.sampled_from(wrong_shapes)] if wrong_shapes else []))


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.kind)
@FUZZ
@given(data=st.data())
def test_every_declared_input_refuses_what_it_does_not_allow(tmp_path_factory, cls, data):
    path, prefix = _minimal_scene(tmp_path_factory.mktemp("scene"), cls)
    inp = data.draw(st.sampled_from(cls.inputs))
    value = data.draw(_bad_values(inp))
    if value is None:
        value = []
    field = prefix + inp.name
    with pytest.raises(jd.ParameterError) as err:
        jd.load_scene(str(path), {field: value})
    text = str(err.value)
    assert "\n" not in text and len(text) < 600, text
    assert field in text, text
    # Either the declared range or the class's own check (a unit vector cannot be zero) says
    # what is allowed.
    assert "expected" in text or "must be" in text or "allowed" in text, text


def test_unknown_names_list_what_is_allowed(tmp_path):
    path, _ = _minimal_scene(tmp_path, EFFECTS["rotor"])
    with pytest.raises(jd.ParameterError, match=r"unknown parameter 'rotor.moment'.*"
                                                r"'rotor.momentum'"):
        jd.load_scene(str(path), {"rotor.moment": [0.0, 1.0, 0.0]})
    with pytest.raises(jd.ParameterError, match=r"unknown parameter 'lenght'.*'inertia'"):
        jd.load_scene(str(path), {"lenght": 1.0})


def test_a_new_effect_needs_only_its_own_declaration(tmp_path):
    """An effect defined anywhere (here, in this test) that declares its inputs is known to
    scene files, `--set` and the parameter tables, with no edit of any front end."""

    class Spring(jd.AbstractEffect):
        """A torsional spring about the body's z axis (test only)."""

        stiffness: jnp.ndarray
        kind: ClassVar[str] = "test-spring"
        inputs: ClassVar[tuple] = (jd.Input("stiffness", "spring constant", "N m/rad",
                                            bound="nonnegative"),)
        needs_attitude: ClassVar[bool] = True

        def __init__(self, stiffness):
            self.stiffness = jnp.asarray(stiffness, float)

        def torque(self, t, y, own, body):
            return -self.stiffness * jnp.array([0.0, 0.0, 1.0]) * y["quaternion"][3]

    try:
        path = tmp_path / "spring.toml"
        path.write_text('body = "rigid-body"\n[parameters]\ninertia = [1.0, 1.0, 1.0]\n'
                        'omega0 = [0.0, 0.0, 0.1]\n[[effects]]\ntype = "test-spring"\n'
                        "stiffness = 2.0\n")
        spec = jd.load_scene(str(path), {"test-spring.stiffness": 3.0})
        assert float(spec.scene.effects[0].stiffness) == 3.0
        assert spec.scene.attitude
        with pytest.raises(jd.ParameterError, match=r"test-spring.stiffness=-1: expected a "
                                                    r"non-negative finite number \(N m/rad\)"):
            jd.load_scene(str(path), {"test-spring.stiffness": -1.0})
        assert "`test-spring`" in markdown()
    finally:
        del EFFECTS["test-spring"]


def test_fit_presets_derive_from_the_declarations():
    specs = fit_specs()
    rigid = specs["rigid-body"]
    assert set(rigid.parameters) == {"inertia"} and isinstance(rigid.parameters["inertia"],
                                                                 jd.ValidInertia)
    assert rigid.columns == {"omega": ("wx", "wy", "wz")}
    assert rigid.optional_columns == {"quaternion": ("q0", "q1", "q2", "q3")}
    assert rigid.initial_names["omega0"] == "omega" and rigid.scene == "torque-free"
    rod = specs["falling-rod"]
    assert set(rod.parameters) == {"length", "mass"}
    assert set(rod.initial) == {"theta", "theta_dot"} and "mass" in rod.notes
    assert "rough-floor-rod" not in specs  # it declares nothing to fit
