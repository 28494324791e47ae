from ._splitting import RotationSplitting as RotationSplitting
