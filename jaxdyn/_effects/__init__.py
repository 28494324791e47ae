from ._gravity_gradient import GravityGradient as GravityGradient
from ._rotor import Rotor as Rotor
from ._torque import ExternalTorque as ExternalTorque
from ._wheels import (
    AttitudeTracking as AttitudeTracking,
    RateDamping as RateDamping,
    Wheels as Wheels,
)
