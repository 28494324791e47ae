"""A scene: a body plus exactly the effects it calls for, behind one protocol."""

from collections.abc import Callable, Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from ._body import AbstractBody
from ._custom_types import Scalar, State
from ._effect import AbstractEffect
from ._programs import _signature
from ._validation import ParameterError

_SHAPES: dict = {}  # state layouts by scene structure: they never change for a structure


def _relative_difference(value, reference):
    """`max |value - reference| / max |reference|` (NaN where either does not exist)."""
    value, reference = jnp.asarray(value), jnp.asarray(reference)
    scale = jnp.max(jnp.abs(reference))
    diff = jnp.max(jnp.abs(value - reference))
    return jnp.where(scale > 0, diff / jnp.where(scale > 0, scale, 1.0), diff)


class Scene(eqx.Module):
    """A body plus the effects that the scene calls for.

    The state layout and the vector field are assembled from exactly these parts: an effect that
    is not declared is not traced, stored or integrated, and attitude is integrated only when an
    effect needs it or `attitude=True` asks for it. Parameters are array leaves (so `jax.grad` and
    `jax.vmap` work over them and changing a value does not recompile); which effects are present
    is static structure.

    Everything built on scenes (simulation, accuracy studies, identification, separatrices,
    ensembles) uses only this protocol: `state`, `vector_field`, `invariants`, `conserved`,
    `outputs`, `events`, `parameters`, `replace`, `check` and `summary`.

    **Arguments:**

    - `body`: a [`jaxdyn.RigidBody`][] or a [`jaxdyn.FallingRod`][].
    - `effects`: a tuple of effects ([`jaxdyn.Rotor`][], [`jaxdyn.ExternalTorque`][],
      [`jaxdyn.GravityGradient`][]).
    - `attitude`: integrate the attitude quaternion even if no effect needs it.
    """

    body: AbstractBody
    effects: tuple[AbstractEffect, ...]
    attitude: bool = eqx.field(static=True)
    labels: tuple[str, ...] = eqx.field(static=True)

    def __init__(
        self, body: AbstractBody, effects: tuple[AbstractEffect, ...] | list = (), *,
        attitude: bool = False,
    ):
        if not isinstance(body, AbstractBody):
            raise ParameterError(
                f"body={body!r}: expected a jaxdyn body (RigidBody or FallingRod)"
            )
        effects = tuple(effects)
        labels = []
        for e in effects:
            if not isinstance(e, AbstractEffect):
                raise ParameterError(f"effects contains {e!r}: expected jaxdyn effects")
            if not e.accepts(type(body)):
                raise ParameterError(
                    f"effect {e.kind!r} cannot act on a {body.kind}: "
                    "effects act on rigid bodies"
                )
            label = e.kind
            k = 2
            while label in labels:
                label = f"{e.kind}{k}"
                k += 1
            labels.append(label)
        needs = any(e.needs_attitude for e in effects)
        if attitude and body.kind != "rigid-body":
            raise ParameterError(f"attitude=True: a {body.kind} has no 3-D attitude")
        self.body = body
        self.effects = effects
        self.attitude = bool(attitude or needs)
        self.labels = tuple(labels)

    # -- state ----------------------------------------------------------------------------------

    def state(self, **values: Any) -> State:
        """Build a state from named initial values.

        Body values by name (`omega`, `quaternion` for a rigid body; `theta`, `theta_dot` for the
        rod); an effect's own state as `"<label>.<name>"` (pass with `**{...}`).
        """
        body_values = {k: v for k, v in values.items() if "." not in k}
        y = dict(self.body.initial_state(self.attitude, **body_values))
        body_state = dict(y)
        for label, e in zip(self.labels, self.effects):
            prefix = label + "."
            own = {k[len(prefix):]: v for k, v in values.items() if k.startswith(prefix)}
            y.update({prefix + k: v for k, v in e.initial_state(body_state, **own).items()})
        unknown = [k for k in values if "." in k and k.split(".")[0] not in self.labels]
        if unknown:
            raise ParameterError(
                f"unknown state variables {unknown}: effects present are {list(self.labels)}"
            )
        return y

    def state_shapes(self) -> dict[str, tuple[int, ...]]:
        """Names and shapes of the state variables, as integrated (cached per structure)."""
        leaves, treedef = jax.tree_util.tree_flatten(self)
        key = (treedef, tuple(getattr(x, "shape", None) for x in leaves))
        if key not in _SHAPES:
            layout = jax.eval_shape(lambda: self._example_state())
            _SHAPES[key] = {k: v.shape for k, v in layout.items()}
        return dict(_SHAPES[key])

    def _example_state(self) -> State:
        required = {i.state: jnp.zeros(i.shapes[0]) for i in self.body.inputs
                    if i.role == "initial" and i.required}
        return self.state(**required)

    def check_state(self, y: Mapping[str, Any]) -> State:
        """Check that `y` has exactly this scene's state variables, with the right shapes."""
        if not isinstance(y, Mapping):
            raise ParameterError(
                f"y0 is a {type(y).__name__}: expected a state dict from scene.state(...)"
            )
        expected = self.state_shapes()
        if set(y) != set(expected):
            raise ParameterError(
                f"y0 has variables {sorted(y)}: this scene integrates {sorted(expected)}"
            )
        out = {}
        for k, shape in expected.items():
            v = jnp.asarray(y[k])
            if v.shape != shape:
                raise ParameterError(f"y0[{k!r}] has shape {v.shape}: expected {shape}")
            out[k] = v
        return out

    def check_precision(self, y: State) -> None:
        """A run integrates each state variable in its own dtype: refuse a state whose
        derivative under this scene comes out in another (a float32 state with float64
        parameters), naming the variable, both dtypes and the scene's wider values. Checked by
        shapes and dtypes alone (`jax.eval_shape`), once per structure."""
        floats = {k: jnp.result_type(v) for k, v in y.items()
                  if jnp.issubdtype(jnp.result_type(v), jnp.floating)}
        if not floats:
            return
        leaves, treedef = jax.tree_util.tree_flatten(self)
        bits = min(jnp.finfo(d).bits for d in floats.values())
        if len(set(floats.values())) == 1 and not any(
                _floating(x) and jnp.finfo(x.dtype).bits > bits for x in leaves):
            return  # nothing in the scene is wider than the state: nothing to widen it
        # (Cached for scenes of arrays and numbers: a Python function, which may hold a
        # caller's tracers, is not kept.)
        key = _structure_key("precision", treedef, leaves, y)
        found = _PRECISION.get(key)
        if found is None:
            spec = {k: jax.ShapeDtypeStruct(jnp.shape(v), jnp.result_type(v)) for k, v in y.items()}
            with jax.numpy_dtype_promotion("standard"):  # (the dtypes it would promote to)
                t = jax.ShapeDtypeStruct((), jnp.result_type(*floats.values()))
                dy = jax.eval_shape(lambda t, y: self.vector_field(t, y), t, spec)
            found = tuple((k, d, dy[k].dtype) for k, d in floats.items() if dy[k].dtype != d)
            if key is not None:
                _PRECISION[key] = found
        if found:
            name, have, get = found[0]
            wider = [jax.tree_util.keystr(path).lstrip(".")
                     for path, x in jax.tree_util.tree_flatten_with_path(self)[0]
                     if _floating(x) and x.dtype == get and not getattr(x, "weak_type", False)]
            held = f" (the scene holds {get.name} values: {', '.join(wider[:3])})" if wider else ""
            raise ParameterError(
                f"y0[{name!r}] is {have.name} but its derivative under this scene is "
                f"{get.name}{held}: give y0[{name!r}] in {get.name}, or build the scene from "
                f"{have.name} values")

    def _own(self, y: State) -> tuple:
        return tuple((e, _own_state(y, label)) for label, e in zip(self.labels, self.effects))

    # -- dynamics -------------------------------------------------------------------------------

    def vector_field(self, t: Scalar, y: State, args: Any = None) -> State:
        """Time derivative of the state (diffrax signature `(t, y, args)`)."""
        pairs = self._own(y)
        dy = dict(self.body.derivative(t, y, pairs, self.attitude))
        for label, (e, own) in zip(self.labels, pairs):
            for k, v in e.state_derivative(t, y, own, self.body).items():
                dy[f"{label}.{k}"] = v
        return dy

    def split_flow(self, axis: int, dt, y: State) -> State:
        """Exact flow of one term of a splitting of the vector field (see
        `RigidBody.split_flow`), for scenes whose effects keep their internal momentum constant.
        Raises `ParameterError` for scenes that cannot be split that way."""
        split = getattr(self.body, "split_flow", None)
        pairs = self._own(y)
        blocked = [e.kind for e, own in pairs if e.split_momentum(y, own) is None]
        if split is None or blocked:
            why = f"effects {blocked} exchange momentum or apply torques" if blocked else (
                f"a {self.body.kind} has no rotation splitting")
            raise ParameterError(
                f"this scene cannot use a splitting integrator: {why}; use a Runge-Kutta "
                "solver such as diffrax.Tsit5()"
            )
        return split(axis, dt, y, pairs, self.attitude)

    def exact_final(self, y0: State, t1) -> tuple | None:
        """`(t_final, y_final)` by an independent exact route (closed form, quadrature), or
        `None` where none is known for this scene."""
        return self.body.exact_final(y0, t1, self._own(y0), self.attitude)

    def natural_scales(self, t0: Scalar, t1: Scalar, y0: State) -> tuple[dict[str, Array], Array]:
        """The natural scale of each state variable for a run from `y0` over `[t0, t1]` (one
        positive, finite scalar per variable) and the scene's time scale.

        Declared by the body (`AbstractBody.natural_scales`) and, for an effect's own state,
        by what the variable measures (`AbstractEffect.state_kinds`). Error control measures
        each variable against `rtol` times the larger of its magnitude and its scale, which
        makes accuracy at the default tolerances independent of the units."""
        pairs = self._own(y0)
        body_scales, ref = self.body.natural_scales(t0, t1, y0, pairs, self.attitude)
        scales = {}
        for name, value in y0.items():
            s = body_scales.get(name)
            scales[name] = jnp.max(jnp.abs(value)) if s is None else s
        for label, (e, own) in zip(self.labels, pairs):
            for k, v in own.items():
                kind = e.state_kinds.get(k)
                if kind is not None:
                    scales[f"{label}.{k}"] = jnp.maximum(scales[f"{label}.{k}"], ref[kind])
        dtype = jnp.result_type(*jax.tree_util.tree_leaves(y0))

        def positive(s):
            s = jnp.asarray(s, dtype)
            return jnp.where(jnp.isfinite(s) & (s > 0), s, jnp.ones((), dtype))

        return {k: positive(v) for k, v in scales.items()}, positive(ref["time"])

    def invariants(self, t: Scalar, y: State) -> dict[str, Array]:
        """Energy and momentum-like quantities (conserved only if listed in `conserved`)."""
        return self.body.invariants(t, y, self._own(y), self.attitude)

    @property
    def conserved(self) -> tuple[str, ...]:
        """Invariants conserved by this scene: the body's, less those an effect breaks."""
        names = []
        for name in self.body.invariant_names:
            if all(name in e.conserves for e in self.effects):
                names.append(name)
        if self.attitude and "momentum" in names:
            names.append("momentum_inertial")
        return tuple(names)

    def outputs(self, t: Scalar, y: State) -> dict[str, Array]:
        """Every derived output at one instant: the body's outputs, the invariants, and what
        each effect's sensors read (`"<label>.<name>"`, such as a wheel's speed)."""
        pairs = self._own(y)
        out = dict(self.body.outputs(t, y, pairs, self.attitude))
        out.update(self.invariants(t, y))
        for label, (e, own) in zip(self.labels, pairs):
            out.update({f"{label}.{k}": v for k, v in e.outputs(t, y, own, self.body).items()})
        return out

    def output_names(self, flat=None) -> tuple[str, ...]:
        """Names of the derived outputs (cached per scene structure: no tracing after the
        first call). `flat`: the scene's `jax.tree_util.tree_flatten`, where the caller has it."""
        leaves, treedef = flat if flat is not None else jax.tree_util.tree_flatten(self)
        key = ("outputs", treedef, tuple(getattr(x, "shape", None) for x in leaves))
        if key not in _SHAPES:
            y = self._example_state()
            _SHAPES[key] = tuple(jax.eval_shape(lambda: self.outputs(jnp.zeros(()), y)))
        return _SHAPES[key]

    def units(self) -> dict[str, str]:
        """Units of the state variables and derived outputs, where declared: the body's
        `output_units`, and the unit of each initial value's state variable."""
        units = {i.state: i.unit for i in self.body.inputs if i.role == "initial"}
        units.update(self.body.output_units)
        return {k: v for k, v in units.items() if v not in ("", "1")}

    def events(self) -> dict[str, Callable[[Scalar, State], Scalar]]:
        """Events: name -> `f(t, y)`, positive while the run goes on in its mode. The body's
        (they end the run, or switch a hybrid body's mode), then each switching effect's as
        `"<label>.<name>"` (they change the effect's own state)."""
        events = dict(self.body.events())
        for label, e in zip(self.labels, self.effects):
            for name, fn in e.events().items():
                events[f"{label}.{name}"] = _OwnEvent(fn, label)
        return events

    def jump_times(self) -> Array | None:
        """The times at which an effect's torque jumps (`AbstractEffect.jump_times`), sorted,
        or `None` where none does."""
        parts = [j for j in (e.jump_times() for e in self.effects) if j is not None]
        if len(parts) < 2:  # (one effect's times are sorted already)
            return parts[0] if parts else None
        return jnp.sort(jnp.concatenate([jnp.ravel(j) for j in parts]))

    @property
    def max_switches(self) -> int:
        """The most switches one run may take: the body's mode switches and the switching
        effects' (0: the scene has no switches; it runs as one segment)."""
        return self.body.max_switches + sum(e.max_switches for e in self.effects)

    def start_mode(self, t0: Scalar, y: State) -> tuple[State, Array]:
        """The initial state mapped into the body's first mode and each switching effect's
        first command, and whether the run ends at once (see `AbstractBody.start_mode`)."""
        y, stop = self.body.start_mode(t0, y)
        y = dict(y)
        for label, (e, own) in zip(self.labels, self._own(y)):
            if e.max_switches:
                y.update({f"{label}.{k}": v for k, v in e.start_mode(t0, y, own).items()})
        return y, stop

    def switch_mode(self, t: Scalar, y: State, fired: Mapping[str, Array]) -> tuple[State, Array]:
        """At the events `fired`: the body's switch (if one of its events fired; it may end
        the run) and each effect's (see `AbstractBody.switch_mode`,
        `AbstractEffect.switch_mode`)."""
        body_names = tuple(self.body.events())
        stop = jnp.asarray(False)
        if body_names:
            hit = jnp.any(jnp.stack([jnp.asarray(fired[n]) for n in body_names]))
            y_body, body_stop = self.body.switch_mode(t, y, {n: fired[n] for n in body_names})
            y = jax.tree.map(lambda a, b: jnp.where(hit, a, b), dict(y_body), dict(y))
            stop = hit & body_stop
        y = dict(y)
        for label, (e, own) in zip(self.labels, self._own(y)):
            mine = {n: fired[f"{label}.{n}"] for n in e.events()}
            if mine:
                y.update({f"{label}.{k}": v
                          for k, v in e.switch_mode(t, y, own, mine).items()})
        return y, stop

    # -- parameters -----------------------------------------------------------------------------

    def parameters(self) -> dict[str, Any]:
        """All physical parameters by name: body fields, then `"<label>.<name>"` for effects."""
        params = {name: getattr(self.body, name) for name in self.body.parameter_names}
        for label, e in zip(self.labels, self.effects):
            params.update({f"{label}.{k}": v for k, v in e.parameters().items()})
        return params

    def replace(self, values: Mapping[str, Any] | None = None, /, **kwargs: Any) -> "Scene":
        """A copy with some parameters changed (same structure, so no recompilation).

        `scene.replace(inertia=I)`, or `scene.replace({"rotor.momentum": h})` for effects.
        """
        values = {**(values or {}), **kwargs}
        allowed = self.parameters()
        unknown = sorted(set(values) - set(allowed))
        if unknown:
            raise ParameterError(
                f"unknown parameter(s) {unknown}: this scene has {sorted(allowed)}"
            )
        body_args = {n: getattr(self.body, n) for n in self.body.parameter_names}
        body_args.update({k: v for k, v in values.items() if "." not in k})
        body = type(self.body)(**body_args)
        effects = []
        for label, e in zip(self.labels, self.effects):
            prefix = label + "."
            new = {k[len(prefix):]: v for k, v in values.items() if k.startswith(prefix)}
            effects.append(type(e)(**{**e.constructor_args(), **new}) if new else e)
        return Scene(body, tuple(effects), attitude=self.attitude)

    def check(self, y: State) -> State:
        """Attach runtime checks of the parameters to the state `y` (returned unchanged).

        Concrete values are checked when a body or effect is built; values known only inside
        `jit`, `grad` or `vmap` are checked here with `eqx.error_if`, so that a simulation with an
        invalid parameter fails with a message naming it instead of returning wrong numbers.
        """
        flags, msgs = self.violations(y)
        return eqx.branched_error_if(y, jnp.any(flags), jnp.argmax(flags), msgs)

    def violations(self, y: State) -> tuple[Array, list[str]]:
        """The checks behind `check`, without raising: a boolean array (true where a check is
        violated) and the message of each check. Ensembles use it to report an invalid sample
        as a failed trajectory instead of stopping the batch."""
        checks = list(self.body.checks())
        for e in self.effects:
            checks += e.checks()
        for name, value in y.items():
            checks.append((f"y0[{name!r}]", value, ~jnp.isfinite(value), "must be finite"))
        checks += self.body.state_checks(y)
        flags = jnp.stack([jnp.any(violated) for _, _, violated, _ in checks])
        msgs = [f"invalid {field}: {allowed}" for field, _, _, allowed in checks]
        return flags, msgs

    def violation_messages(self, y: State) -> tuple[str, ...]:
        """The messages of `violations(y)`, in the order of its flags, from a trace alone (no
        check is evaluated: each eager operation would compile a program of its own). Cached
        per structure of the scene and of `y` (its variables' shapes and dtypes): an ensemble
        call traces nothing after the first of its structure. A check's field and allowed
        values are its fixed text (`Check`), so the messages do not depend on the values. A
        scene holding a Python function (which may hold a caller's tracers) is traced each
        time, as `check_precision` does."""
        leaves, treedef = jax.tree_util.tree_flatten(self)
        key = _structure_key("violations", treedef, leaves, y)
        found = _MESSAGES.get(key)
        if found is None:
            messages: list[str] = []

            def flags(y):
                flags, msgs = self.violations(y)
                messages.extend(msgs)
                return flags

            jax.eval_shape(flags, y)
            found = tuple(messages)
            if key is not None:
                _MESSAGES[key] = found
        return found

    # -- reporting ------------------------------------------------------------------------------

    def summary(self, ts, ys: State, valid, t_final, y_final: State,
                event: Mapping[str, Array]) -> dict[str, Any]:
        """Summary of a run as arrays: the body's own keys, and the largest relative drift of
        each conserved invariant over the valid samples (`<name>_rel_error`)."""
        y_start = jax.tree.map(lambda a: a[0], ys)
        out = dict(self.body.summary(ts, ys, valid, t_final, y_final, event,
                                     effects=self._own(y_start), attitude=self.attitude))
        if out.get("reference"):
            out["relative_difference"] = {
                k: _relative_difference(out[k], ref)
                for k, ref in out["reference"].items() if k in out}
        inv = jax.vmap(self.invariants)(ts, ys)
        for name in self.conserved:
            v = inv[name]
            if v.ndim == 1:
                drift = jnp.abs(v - v[0])
                scale = self.body.invariant_scale(name, v[0])
            else:
                drift = jnp.linalg.norm(v - v[0], axis=-1)
                scale = self.body.invariant_scale(name, jnp.linalg.norm(v[0]))
            out[f"{name}_rel_error"] = jnp.max(jnp.where(valid, drift, 0.0)) / scale
        return out


def _structure_key(kind: str, treedef, leaves, y) -> tuple | None:
    """The key of what a trace of the scene (`treedef`, `leaves`) and a state `y` found, the
    same for every call it holds for: arrays by shape and dtype, any other leaf by its type and
    value (as a compiled program takes them: fixed); `None` (nothing kept) where a leaf is a
    Python function, which may hold a caller's tracers, or cannot be hashed."""
    if any(callable(x) for x in leaves):
        return None
    key = (kind, treedef, *(_signature([x])[0] if hasattr(x, "dtype") else (type(x), x)
                           for x in leaves), tuple(y), _signature(y.values()))
    try:
        hash(key)
    except TypeError:
        return None
    return key


_PRECISION: dict = {}  # Scene.check_precision's findings, per structure
_MESSAGES: dict = {}  # Scene.violation_messages, per structure of the scene and the state


def _floating(x) -> bool:
    return hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating)


def _own_state(y: State, label: str) -> State:
    """The state variables of the effect labelled `label`, by their own names."""
    prefix = label + "."
    return {k[len(prefix):]: v for k, v in y.items() if k.startswith(prefix)}


class _OwnEvent(eqx.Module):
    """An effect's event as a function of `(t, y)`: the effect's own state picked out of `y`."""

    fn: Callable
    label: str = eqx.field(static=True)

    def __call__(self, t, y):
        return self.fn(t, y, _own_state(y, self.label))
