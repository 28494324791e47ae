"""The effect protocol: forces, torques and extra state that a scene may call for."""

from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import equinox as eqx
from jaxtyping import Array

from ._custom_types import Scalar, State
from ._inputs import EFFECTS, Input, register
from ._validation import Check


class AbstractEffect(eqx.Module):
    r"""An effect acting on a rigid body.

    An effect may contribute any of: an external torque (`torque`), internal angular momentum
    stored in a device (`momentum`) and its rate (`momentum_rate`), its own state variables
    (`initial_state`/`state_derivative`), and an energy term (`energy`). Methods that do not apply
    return `None`, so nothing is traced for them: a scene pays only for the effects it declares.

    The rigid body assembles Euler's equations as
    $I \dot\omega = (I\omega + \sum h) \times \omega - \sum \dot h + \sum \tau$.
    """

    kind: ClassVar[str]
    """Name used in scene files and in parameter names (`"rotor"`, `"torque"`...)."""
    inputs: ClassVar[tuple[Input, ...]] = ()
    """What scene files, `--set`, `--vary`, `fit` and the docs know of this effect (see
    [`jaxdyn.Input`][]). Declaring them registers the effect under its `kind`: a new effect
    in its own file in `jaxdyn/_effects/` is then known to scene files and the command."""
    parameter_names: ClassVar[tuple[str, ...]] = ()
    needs_attitude: ClassVar[bool] = False
    """Whether the effect needs the attitude (and so makes the scene integrate it)."""
    conserves: ClassVar[frozenset[str]] = frozenset()
    """Body invariants that stay conserved when this effect acts (`"energy"`, `"momentum"`)."""
    parameter_kinds: ClassVar[dict[str, str]] = {}
    """What each parameter measures (`"momentum"`, `"inertia"`, `"torque"`, `"rate"`), for uses
    that solve in the scene's natural units (the separatrix finder divides momenta by the
    sphere's radius and inertia by the largest moment)."""
    state_kinds: ClassVar[dict[str, str]] = {}
    """What each of the effect's state variables measures, as one of the body's reference
    quantities (`"momentum"`, `"energy"`, `"time"`): its error is controlled relative to the
    larger of its magnitude and that reference (see `AbstractBody.natural_scales`). Variables
    not listed are measured against their initial magnitude."""

    uses_stored_momentum: ClassVar[bool] = False
    """Whether `torque` reads the momentum stored in the scene's devices (wheels, rotors): it
    is then called with `stored=`, their total angular momentum in the body frame (momentum
    dumping by magnetic torque rods)."""
    max_switches: ClassVar[int] = 0
    """Effects that switch (thrusters turning on and off): the most switches one run may take.
    A scene with such an effect is run as segments between its `events` (see
    `jaxdyn._hybrid`), so that each switch falls on a segment's end instead of inside a step."""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        register(EFFECTS, cls)

    @classmethod
    def from_inputs(cls, **values: Any) -> "AbstractEffect":
        """The effect from validated scene-file values of its `"parameter"` inputs."""
        return cls(**values)

    @classmethod
    def accepts(cls, body_cls) -> bool:
        """Whether this effect can act on bodies of class `body_cls` (default: on bodies that
        accept effects, the rigid body)."""
        return body_cls.accepts_effects

    def checks(self) -> list[Check]:
        return []

    def constructor_args(self) -> dict[str, Any]:
        """Arguments that rebuild this effect: parameters (by `parameter_names`) and options."""
        return {name: getattr(self, name) for name in self.parameter_names}

    def parameters(self) -> dict[str, Any]:
        args = self.constructor_args()
        return {name: args[name] for name in self.parameter_names}

    def __check_init__(self):
        from ._validation import raise_if_violated

        raise_if_violated(self.checks())

    def initial_state(self, body_state: State, **values: Any) -> State:
        """The effect's own state from named initial values (the body's state is given, for
        devices whose state depends on it)."""
        if values:
            from ._validation import ParameterError

            raise ParameterError(
                f"{self.kind} has no state: unexpected initial values {sorted(values)}"
            )
        return {}

    def state_derivative(self, t: Scalar, y: State, own: State, body) -> State:
        return {}

    def torque(self, t: Scalar, y: State, own: State, body) -> Array | None:
        return None

    def momentum(self, t: Scalar, y: State, own: State, body) -> Array | None:
        return None

    def momentum_rate(self, t: Scalar, y: State, own: State, body) -> Array | None:
        return None

    def energy(self, t: Scalar, y: State, own: State, body) -> Array | None:
        return None

    def outputs(self, t: Scalar, y: State, own: State, body) -> dict[str, Array]:
        """What the effect's own sensors read (a wheel's speed), as outputs of the scene
        named `"<label>.<name>"`: observable in trajectories and fittable by `fit`."""
        return {}

    def jump_times(self) -> Array | None:
        """Times, known before the run, at which this effect's torque or state derivative
        jumps (a zero-order hold's command times), or `None`. The integrator ends a step
        just before each and starts the next just after (`ScaledPIDController`): a step across
        a jump would be controlled by an error estimate that assumes a smooth vector field."""
        return None

    def split_momentum(self, y: State, own: State) -> Array | None:
        """For splitting integrators: the internal momentum, if it stays constant while the body
        turns (a constant-speed rotor, free wheels). Effects that exchange momentum or apply
        external torques return `None` and are not splittable."""
        return None

    # -- switching effects (`max_switches > 0`) ------------------------------------------------

    def events(self) -> Mapping[str, Callable[[Scalar, State, State], Scalar]]:
        """Switch events: name -> function of `(t, y, own)`, positive until the switch (scaled
        to order one). Where one reaches zero, `switch_mode` changes the effect's own state;
        an effect's switch never ends the run."""
        return {}

    def start_mode(self, t0: Scalar, y: State, own: State) -> State:
        """The effect's own state at the start of a run (a controller's first command)."""
        return own

    def switch_mode(self, t: Scalar, y: State, own: State, fired: Mapping[str, Array]) -> State:
        """The effect's own state after the events `fired` (name -> whether it fired here)."""
        return own
