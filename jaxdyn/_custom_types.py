"""Type aliases used across jaxdyn."""

from typing import Any, TypeAlias

from jaxtyping import Array, ArrayLike, Bool, Float

State: TypeAlias = dict[str, Float[Array, "..."]]
"""A scene's state: a dict of named arrays, assembled from the body and the declared effects."""

Scalar: TypeAlias = Float[Array, ""]
ScalarLike: TypeAlias = float | Float[ArrayLike, ""]
Vector3: TypeAlias = Float[Array, "3"]
Matrix3: TypeAlias = Float[Array, "3 3"]
Args: TypeAlias = Any

__all__ = ["Array", "ArrayLike", "Bool", "Float", "State", "Scalar", "ScalarLike", "Vector3",
           "Matrix3", "Args"]
