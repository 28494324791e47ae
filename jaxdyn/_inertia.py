"""Inertia: principal moments, principal axes and physical validity."""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._validation import Check, on_host


def principal_axes(
    tensor: Float[Array, "3 3"],
) -> tuple[Float[Array, "3"], Float[Array, "3 3"]]:
    """Principal moments (ascending) and principal axes of a symmetric inertia tensor.

    **Arguments:**

    - `tensor`: the inertia tensor in some body frame.

    **Returns:**

    `(moments, axes)` with `tensor = axes @ diag(moments) @ axes.T`. The columns of `axes` are the
    principal axes in the body frame; each column's largest component is positive, then the last
    column is flipped if needed so that `axes` is a proper rotation (`det = +1`).
    """
    moments, axes = jnp.linalg.eigh(0.5 * (tensor + tensor.T))
    idx = jnp.argmax(jnp.abs(axes), axis=0)
    signs = jnp.sign(axes[idx, jnp.arange(3)])
    axes = axes * jnp.where(signs == 0, 1.0, signs).astype(axes.dtype)
    det = jnp.linalg.det(axes)
    axes = axes.at[:, 2].multiply(jnp.sign(det).astype(axes.dtype))
    return moments, axes


def inertia_tensor(
    moments: Float[Array, "3"], axes: Float[Array, "3 3"] | None = None
) -> Float[Array, "3 3"]:
    """The inertia tensor `axes @ diag(moments) @ axes.T` (`diag(moments)` if `axes` is None)."""
    if axes is None:
        return jnp.diag(moments)
    return (axes * moments) @ axes.T


def moments_checks(field: str, moments: Float[Array, "3"]) -> list[Check]:
    """Physical validity of principal moments: positive, finite, triangle inequality.

    The triangle inequality `I_i <= I_j + I_k` is allowed to hold with equality (a flat plate),
    up to a relative round-off of `8 eps`.
    """
    xp, m = on_host(moments)
    eps = jnp.finfo(m.dtype).eps  # (jnp: it knows bfloat16; it compiles nothing)
    total = xp.sum(m)
    triangle = m > (total - m) * (1 + 8 * eps)
    return [
        (field, moments, ~(xp.isfinite(m) & (m > 0)),
         "principal moments of inertia must be positive and finite"),
        (field, moments, triangle,
         "each principal moment must not exceed the sum of the other two (triangle inequality)"),
    ]


def tensor_checks(field: str, tensor: Float[Array, "3 3"]) -> list[Check]:
    """Checks for a full inertia tensor: finite, symmetric, then its principal moments."""
    xp, t = on_host(tensor)
    eps = jnp.finfo(t.dtype).eps
    scale = xp.max(xp.abs(t))
    asym = xp.abs(t - t.T) > 1e3 * eps * scale
    finite = xp.isfinite(t)
    checks: list[Check] = [
        (field, tensor, ~finite, "inertia tensor entries must be finite"),
        (field, tensor, asym, "inertia tensor must be symmetric"),
    ]
    safe = xp.where(finite & ~asym, t, xp.eye(3, dtype=t.dtype))
    if xp is np and t.dtype not in (np.float32, np.float64):  # (LAPACK: float32 at least)
        moments = np.linalg.eigvalsh(0.5 * (safe + safe.T).astype(np.float32)).astype(t.dtype)
    else:
        moments = xp.linalg.eigvalsh(0.5 * (safe + safe.T))
    return checks + moments_checks(field + " (principal moments)", moments)


def invert3(tensor: Float[Array, "3 3"]) -> Float[Array, "3 3"]:
    """Closed-form inverse of a 3x3 matrix (adjugate over determinant)."""
    a = tensor
    cof = jnp.stack(
        [
            jnp.cross(a[1], a[2]),
            jnp.cross(a[2], a[0]),
            jnp.cross(a[0], a[1]),
        ]
    )
    det = jnp.dot(a[0], cof[0])
    return cof.T / det
