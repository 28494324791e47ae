"""The effects: one file each. Every module here is imported, so an effect that declares its
`inputs` in a new file is known to scene files and the command with no other edit."""

import importlib
import pkgutil

from ._gravity_gradient import GravityGradient as GravityGradient
from ._linear_damping import LinearDamping as LinearDamping
from ._magnetorquers import MagneticTorquers as MagneticTorquers
from ._ring_damper import RingDamper as RingDamper
from ._rotor import Rotor as Rotor
from ._thrusters import Thrusters as Thrusters
from ._torque import ExternalTorque as ExternalTorque
from ._wheels import (
    AttitudeTracking as AttitudeTracking,
    CommandedTorques as CommandedTorques,
    RateDamping as RateDamping,
    Wheels as Wheels,
)

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")
