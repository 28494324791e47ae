"""The body protocol: kinematics and mass properties, state layout, invariants, events."""

import abc
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from ._custom_types import Scalar, State
from ._inputs import BODIES, Input, register
from ._validation import Check


class AbstractBody(eqx.Module):
    """A body: owns its state variables, mass properties and equations of motion.

    Concrete bodies declare their inputs once (`inputs`: parameters, initial values, options,
    with units and ranges; see [`jaxdyn.Input`][]), build their part of the state in
    `initial_state`, and assemble their equations of motion from the loads contributed by the
    scene's effects in `derivative`. Declaring `inputs` registers the body under its `kind` for
    scene files and the command.
    """

    kind: ClassVar[str]
    """Name of the body type, as used in scene files (`"rigid-body"`, `"falling-rod"`)."""
    inputs: ClassVar[tuple[Input, ...]] = ()
    """What scene files, `--set`, `--vary`, `fit` and the docs know of this body."""
    parameter_names: ClassVar[tuple[str, ...]]
    """Fields that are physical parameters (array leaves; by default the numeric inputs with
    role `"parameter"`)."""
    accepts_effects: ClassVar[bool] = False
    """Whether effects (torques, rotors, wheels) can act on this body."""
    identifiability: ClassVar[Mapping[str, str]] = {}
    """For `fit`: why a fitted component may be undetermined, by component name."""
    output_units: ClassVar[Mapping[str, str]] = {}
    """Units of the derived outputs, by name (for exports)."""
    plain_scene: ClassVar[str | None] = None
    """The built-in scene of this body alone, if any (`jaxdyn fit` picks it from a data
    file's columns)."""
    invariant_names: ClassVar[tuple[str, ...]]
    """Quantities conserved by the body's own dynamics (before effects are added)."""
    max_switches: ClassVar[int] = 0
    """Hybrid bodies: the most mode switches one run may take (0: a body with a single mode).

    A hybrid body is simulated as a sequence of segments (see `jaxdyn._hybrid`): each segment is
    integrated until one of the body's `events` reaches zero, located by root finding, and then
    `switch_mode` maps the state into the next mode or ends the run."""
    residual_kinds: ClassVar[Mapping[str, str]] = {}
    """How `fit` compares an output with its measurements, where not by difference:
    `"rotation"` for an attitude (the rotation between the two, whatever the sign of a
    measured quaternion)."""
    report_labels: ClassVar[Mapping[str, Mapping[float, str]]] = {}
    """Summary keys whose values are codes, reported by name (`{1.0: "forward"}`)."""

    @abc.abstractmethod
    def initial_state(self, attitude: bool, **values: Any) -> State:
        """The body's part of the state from user-facing values (defaults where sensible)."""

    @abc.abstractmethod
    def derivative(self, t: Scalar, y: State, effects: tuple, attitude: bool) -> State:
        """Time derivative of the body's state, including the loads of `effects`."""

    @abc.abstractmethod
    def outputs(self, t: Scalar, y: State, effects: tuple, attitude: bool) -> dict[str, Array]:
        """Derived outputs at one instant (energies, forces, positions...)."""

    @abc.abstractmethod
    def invariants(self, t: Scalar, y: State, effects: tuple, attitude: bool) -> dict[str, Array]:
        """Quantities that are conserved when every effect conserves them."""

    @abc.abstractmethod
    def checks(self) -> list[Check]:
        """Validity conditions on the parameters."""

    def state_checks(self, y: State) -> list[Check]:
        """Validity conditions on an initial state beyond finiteness (checked on the host for
        concrete states, inside the program under a trace)."""
        return []

    def events(self) -> Mapping[str, Callable[[Scalar, State], Scalar]]:
        """Terminating events: name -> function of `(t, y)`, positive while the run goes on.

        The run ends where one reaches zero (located by root finding); one that is already
        zero or negative at the start ends the run at once.
        """
        return {}

    def start_mode(self, t0: Scalar, y0: State) -> tuple[State, Array]:
        """Hybrid bodies: the initial state mapped into the mode the run starts in, and whether
        the run ends at once (traceable). Default: unchanged, and the run goes on."""
        return y0, jnp.asarray(False)

    def switch_mode(self, t: Scalar, y: State, fired: Mapping[str, Array]) -> tuple[State, Array]:
        """Hybrid bodies: at an event, the state mapped into the next mode, and whether the run
        ends there (traceable). `fired` maps each event name to whether it reached zero here
        (more than one where events coincide). Default: every event ends the run."""
        return y, jnp.asarray(True)

    def exact_final(self, y0: State, t1, effects: tuple, attitude: bool):
        """`(t_final, y_final)` of a run from `y0` to `t1` (or to its terminating event) by an
        independent exact route, or `None` where none is known. Used by accuracy studies."""
        return None

    def natural_scales(self, t0: Scalar, t1: Scalar, y0: State, effects: tuple,
                       attitude: bool) -> tuple[dict[str, Array], dict[str, Array]]:
        """Natural scales of a run from `y0`: the size of each of the body's state variables
        (one positive scalar each), and reference quantities for the effects' state
        (`"time"`, `"momentum"`, `"energy"`; see [`jaxdyn.AbstractEffect`][]).

        Error control measures every state variable against `rtol` times the larger of its
        magnitude and its scale, so the scales make the default tolerances independent of the
        units (see [`jaxdyn.simulate`][]). Default: no declared scale (the scene then uses
        each variable's largest initial magnitude), and the time span."""
        one = jnp.ones((), jnp.result_type(t0))
        return {}, {"time": jnp.abs(t1 - t0), "momentum": one, "energy": one}

    def invariant_scale(self, name: str, value: Array) -> Array:
        """Scale against which the drift of invariant `name` is measured (default: its
        initial magnitude). Bodies override it where that can vanish."""
        return jnp.abs(value)

    def summary(self, ts, ys: State, valid, t_final, y_final: State,
                event: Mapping[str, Array], effects: tuple = (),
                attitude: bool = False) -> dict[str, Any]:
        """Body-specific summary of a run, as arrays (traceable: it runs under `jit`).

        Values that an independent route (a closed form, a quadrature) also gives are repeated
        under `"reference"` with the same key; the scene adds their `"relative_difference"`.

        `valid` masks the saved samples reached by the run. A value that does not exist for
        this run (the impact time of a rod that never lies flat) is returned as `nan`; reports
        turn non-finite values into `null`.
        """
        return {}

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        register(BODIES, cls)

    @classmethod
    def from_inputs(cls, **values: Any) -> "AbstractBody":
        """The body from validated scene-file values of its `"parameter"` inputs."""
        return cls(**values)

    def __check_init__(self):
        from ._validation import raise_if_violated

        raise_if_violated(self.checks())
