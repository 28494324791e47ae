from ._rk4 import RK4 as RK4
from ._splitting import RotationSplitting as RotationSplitting
