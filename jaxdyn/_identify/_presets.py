"""What to fit for each kind of body: small declarative pieces on top of the generic fitter.

Each entry names the parameters to fit (with their parameterisations), the initial-state
variables to fit, the outputs that data files hold (with their CSV columns), and explanations
for components that the generic identifiability check may find undetermined. Nothing in the
fitter depends on these tables; the command line uses them to turn a data file into a call of
[`jaxdyn.fit`][].
"""

import dataclasses
from collections.abc import Mapping

from ._parameterisation import (
    AbstractParameterisation,
    Positive,
    Unconstrained,
    UnitQuaternion,
    ValidInertia,
)


@dataclasses.dataclass(frozen=True)
class FitSpec:
    """What the data of one kind of body determine, and how to read them.

    **Fields:**

    - `parameters`: body or effect parameters to fit, by scene parameter name.
    - `initial`: initial-state variables to fit, by state name.
    - `initial_names`: scene-file names of the initial values (`omega0`) -> state names.
    - `columns`: for each output that a data file must hold, its CSV columns.
    - `optional_columns`: outputs that a data file may hold as well.
    - `optional_initial`: initial-state variables fitted when their optional output is given.
    - `notes`: why a component may be undetermined, by component name.
    """

    parameters: Mapping[str, AbstractParameterisation]
    initial: Mapping[str, AbstractParameterisation]
    initial_names: Mapping[str, str]
    columns: Mapping[str, tuple[str, ...]]
    optional_columns: Mapping[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)
    optional_initial: Mapping[str, AbstractParameterisation] = dataclasses.field(
        default_factory=dict
    )
    notes: Mapping[str, str] = dataclasses.field(default_factory=dict)


FIT_SPECS: dict[str, FitSpec] = {
    "rigid-body": FitSpec(
        parameters={"inertia": ValidInertia()},
        initial={"omega": Unconstrained()},
        initial_names={"omega0": "omega", "quaternion0": "quaternion"},
        columns={"omega": ("wx", "wy", "wz")},
        optional_columns={"quaternion": ("q0", "q1", "q2", "q3")},
        optional_initial={"quaternion": UnitQuaternion()},
        notes={
            "inertia.scale": "the rates of a torque-free body do not change when its inertia "
            "is multiplied by a constant, so only the normalised tensor is fitted (principal "
            "moments scaled so that the largest is 1); a known torque or rotor momentum in "
            "the scene would fix the scale",
        },
    ),
    "falling-rod": FitSpec(
        parameters={"length": Positive(), "mass": Positive()},
        initial={"theta": Unconstrained(), "theta_dot": Unconstrained()},
        initial_names={"theta0": "theta", "theta_dot0": "theta_dot"},
        columns={"theta": ("theta",)},
        notes={
            "mass": "the mass cancels from the rod's equation of motion (theta(t) depends on "
            "g/L only); with g known the length is determined, the mass is not",
        },
    ),
}
