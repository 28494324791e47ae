"""Attitude representations: quaternions, modified Rodrigues parameters, 3-2-1 Euler angles.

All functions are pure `jax.numpy`, and may be `jax.jit`-ed, `jax.vmap`-ed and differentiated.
They batch over leading axes: an array of quaternions has shape `(..., 4)`, of vectors or
MRPs `(..., 3)`, of rotation matrices `(..., 3, 3)`, of angles `(...)`. Binary functions
broadcast their batch axes against each other. Every function preserves the floating dtype
of its input (`float32` in, `float32` out); integer inputs are cast to JAX's default float.
Arguments of a binary function must share their dtype (Python scalars excepted).

**Frames.** `B` is the body frame, `N` the inertial frame. The direction cosine matrix
(rotation matrix) `[NB]` maps body-frame components to inertial components,
`v_N = [NB] v_B`; `[BN] = [NB]^T`. Every function here that returns a matrix returns `[NB]`
(the "active" rotation matrix, as `scipy.spatial.transform.Rotation.as_matrix` returns).

**Quaternions.** `q = (q0, q1, q2, q3)`, scalar first, unit norm, Hamilton product
`p ⊗ q = (p0 q0 - p·q, p0 q + q0 p + p × q)`. The attitude is represented so that
`(0, v_N) = q ⊗ (0, v_B) ⊗ q*`, i.e.

`[NB] = (q0² - |e|²) I + 2 e eᵀ + 2 q0 [e×]`,  with `e = (q1, q2, q3)`.

`q` and `-q` represent the same attitude. Composition: `quat_to_dcm(p ⊗ q) =
quat_to_dcm(p) @ quat_to_dcm(q)`. With the body angular velocity `ω` (components in `B`),
the kinematics are `q̇ = ½ q ⊗ (0, ω)`, equivalently `d[NB]/dt = [NB] [ω×]`.
(SciPy stores quaternions scalar *last*: `Rotation.from_quat([q1, q2, q3, q0])`.)

**Modified Rodrigues parameters** (Schaub & Junkins, "Analytical Mechanics of Space
Systems"). `σ = e / (1 + q0) = â tan(Φ/4)` for a rotation by `Φ` about the unit axis `â`;
it represents the same `[NB]` as the quaternion it comes from:

`[NB] = I + (8 [σ×]² + 4 (1 - |σ|²) [σ×]) / (1 + |σ|²)²`,

and `σ̇ = ¼ [(1 - |σ|²) I + 2 [σ×] + 2 σ σᵀ] ω`. (Schaub & Junkins parametrise `[BN]`, which
flips the sign of the `[σ×]` terms.) The shadow set `σˢ = -σ / |σ|²` (from `-q`) represents
the same attitude; functions that choose a set return the one with `|σ| <= 1`. The MRPs here
coincide with SciPy's `Rotation.from_mrp` / `as_mrp`.

**3-2-1 Euler angles** `(ψ, θ, φ)` (yaw, pitch, roll): starting from `N`, rotate by the yaw
`ψ` about axis 3, then by the pitch `θ` about the new axis 2, then by the roll `φ` about the
new axis 1, reaching `B`. Hence

`[NB] = R3(ψ) R2(θ) R1(φ)`,

where `Ri(α)` is the active (right-handed, counterclockwise) rotation by `α` about axis `i`,
e.g. `R3(ψ) = [[cos ψ, -sin ψ, 0], [sin ψ, cos ψ, 0], [0, 0, 1]]`. Equivalently
`[BN] = M1(φ) M2(θ) M3(ψ)` with the passive matrices `Mi = Riᵀ` of Schaub & Junkins.
In SciPy terms (intrinsic, upper-case axes):

`[NB] = Rotation.from_euler("ZYX", [ψ, θ, φ]).as_matrix()`, and
`(ψ, θ, φ) = Rotation.from_matrix([NB]).as_euler("ZYX")` away from the singularity.

The quaternion is `q = q3(ψ) ⊗ q2(θ) ⊗ q1(φ)`. Extracted angles lie in `ψ, φ ∈ [-π, π]`,
`θ ∈ [-π/2, π/2]`. At gimbal lock (`θ = ±π/2`) only `φ - ψ` (for `θ = +π/2`) or `φ + ψ`
(for `θ = -π/2`) is defined; there `dcm_to_euler321` returns `ψ = 0` and puts the whole
rotation about the vertical into `φ`, with finite values and finite gradients.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = [
    "dcm_to_euler321",
    "dcm_to_mrp",
    "dcm_to_quat",
    "euler321_to_dcm",
    "euler321_to_quat",
    "mrp_derivative",
    "mrp_from_quat",
    "mrp_shadow",
    "mrp_switch",
    "mrp_to_dcm",
    "quat_conjugate",
    "quat_derivative",
    "quat_from_axis_angle",
    "quat_from_mrp",
    "quat_multiply",
    "quat_normalize",
    "quat_rotate",
    "quat_to_axis_angle",
    "quat_to_dcm",
    "quat_to_euler321",
    "safe_norm",
    "skew",
]


# `dcm_to_euler321` treats a matrix as gimbal-locked when `cos(θ)`, estimated as
# `hypot(C[0, 0], C[1, 0])`, is below this many machine epsilons. Inside that band setting
# `ψ = 0` changes the reconstructed matrix by at most `cos(θ)`, i.e. by round-off only.
_GIMBAL_LOCK_EPS_FACTOR = 8.0


def _asarray(x: ArrayLike) -> Array:
    """Convert to a JAX array; non-floating input is cast to the default float dtype."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.inexact):
        x = x.astype(jnp.result_type(float))
    return x


def _split_quat(q: Array) -> tuple[Array, Array]:
    return q[..., 0], q[..., 1:]


def _join_quat(q0: Array, e: Array) -> Array:
    q0 = q0[..., None]
    shape = jnp.broadcast_shapes(q0.shape, e.shape[:-1] + (1,))
    q0 = jnp.broadcast_to(q0, shape)
    e = jnp.broadcast_to(e, shape[:-1] + (3,))
    return jnp.concatenate([q0, e], axis=-1)


def _dot(a: Array, b: Array) -> Array:
    return jnp.sum(a * b, axis=-1)


def _stack_matrix(rows: list[list[Array]]) -> Array:
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


def _sym_plus_skew(a: Array, sym_scale: Array, skew_scale: Array, diag: Array) -> Array:
    """`diag I + sym_scale a aᵀ + skew_scale [a×]`, built elementwise (no matmul)."""
    a1, a2, a3 = a[..., 0], a[..., 1], a[..., 2]
    s, k = sym_scale, skew_scale
    return _stack_matrix(
        [
            [diag + s * a1 * a1, s * a1 * a2 - k * a3, s * a1 * a3 + k * a2],
            [s * a2 * a1 + k * a3, diag + s * a2 * a2, s * a2 * a3 - k * a1],
            [s * a3 * a1 - k * a2, s * a3 * a2 + k * a1, diag + s * a3 * a3],
        ]
    )


#
# Generic helpers
#


def skew(v: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """The cross-product matrix `[v×]`, such that `skew(v) @ u == cross(v, u)`.

    **Arguments:**

    - `v`: a vector, shape `(..., 3)`.

    **Returns:**

    The skew-symmetric matrix `[[0, -v3, v2], [v3, 0, -v1], [-v2, v1, 0]]`, shape
    `(..., 3, 3)`.
    """
    v = _asarray(v)
    v1, v2, v3 = v[..., 0], v[..., 1], v[..., 2]
    zero = jnp.zeros_like(v1)
    return _stack_matrix([[zero, -v3, v2], [v3, zero, -v1], [-v2, v1, zero]])


def safe_norm(
    x: Float[ArrayLike, "*batch n"], axis: int = -1, *, keepdims: bool = False
) -> Float[Array, "*batch"]:
    """Euclidean norm whose gradient at `x = 0` is `0` rather than `NaN`.

    **Arguments:**

    - `x`: an array.
    - `axis`: the axis to reduce over.
    - `keepdims`: whether to keep the reduced axis (with size one).

    **Returns:**

    `sqrt(sum(x**2, axis))`. Elsewhere than at zero its gradient is the usual `x / |x|`.
    """
    x = _asarray(x)
    # Scaled by the largest component before squaring, so that neither 1e200 nor 1e-200
    # over- or underflows (the norm is homogeneous: the scale's gradient cancels).
    big = jax.lax.stop_gradient(jnp.max(jnp.abs(x), axis=axis, keepdims=True))
    big = jnp.where(jnp.isfinite(big) & (big > 0), big, 1.0)
    sq = jnp.sum((x / big) ** 2, axis=axis, keepdims=True)
    is_zero = sq == 0
    # Double-`where`: the unselected branch never sees `sqrt(0)`, so no `0 * inf` in the VJP.
    norm = big * jnp.where(is_zero, 0.0, jnp.sqrt(jnp.where(is_zero, 1.0, sq)))
    return norm if keepdims else jnp.squeeze(norm, axis=axis)


def unit(x: Float[ArrayLike, "*batch n"], axis: int = -1) -> Float[Array, "*batch n"]:
    """`x / |x|` along `axis`, overflow- and underflow-safe (see `safe_norm`); a zero vector
    gives NaN, so callers check for it first."""
    x = _asarray(x)
    return x / safe_norm(x, axis=axis, keepdims=True)


#
# Quaternions
#


def quat_multiply(
    p: Float[ArrayLike, "*#batch 4"], q: Float[ArrayLike, "*#batch 4"]
) -> Float[Array, "*batch 4"]:
    """Hamilton product `p ⊗ q = (p0 q0 - p·q, p0 q + q0 p + p × q)`.

    With the conventions of this module, `quat_to_dcm(p ⊗ q) = quat_to_dcm(p) @ quat_to_dcm(q)`.

    **Arguments:**

    - `p`: the left quaternion, scalar first, shape `(..., 4)`.
    - `q`: the right quaternion, scalar first, shape `(..., 4)`.

    **Returns:**

    The product quaternion, shape `(..., 4)` (batch axes broadcast).
    """
    p0, pv = _split_quat(_asarray(p))
    q0, qv = _split_quat(_asarray(q))
    r0 = p0 * q0 - _dot(pv, qv)
    rv = p0[..., None] * qv + q0[..., None] * pv + jnp.cross(pv, qv)
    return _join_quat(r0, rv)


def quat_conjugate(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """Quaternion conjugate `q* = (q0, -q1, -q2, -q3)`.

    For a unit quaternion this is the inverse, representing `[BN] = [NB]ᵀ`.

    **Arguments:**

    - `q`: a quaternion, scalar first, shape `(..., 4)`.

    **Returns:**

    The conjugate, shape `(..., 4)`.
    """
    q0, e = _split_quat(_asarray(q))
    return _join_quat(q0, -e)


def quat_normalize(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """Scale a quaternion to unit norm.

    Differentiable at any nonzero `q` (the zero quaternion has no direction: `NaN`).

    **Arguments:**

    - `q`: a nonzero quaternion, shape `(..., 4)`.

    **Returns:**

    `q / |q|`, shape `(..., 4)`.
    """
    return unit(q)


def quat_to_dcm(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix `[NB]` of a unit quaternion.

    `[NB] = (q0² - |e|²) I + 2 e eᵀ + 2 q0 [e×]` with `e = (q1, q2, q3)`, so that
    `v_N = [NB] v_B` corresponds to `(0, v_N) = q ⊗ (0, v_B) ⊗ q*`. Equal to SciPy's
    `Rotation.from_quat([q1, q2, q3, q0]).as_matrix()`.

    **Arguments:**

    - `q`: a unit quaternion, scalar first, shape `(..., 4)`.

    **Returns:**

    The rotation matrix `[NB]`, shape `(..., 3, 3)`.
    """
    q0, e = _split_quat(_asarray(q))
    return _sym_plus_skew(e, 2.0, 2.0 * q0, q0 * q0 - _dot(e, e))


def dcm_to_quat(C: Float[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 4"]:
    """Unit quaternion of a rotation matrix `[NB]`, by Shepperd's method.

    Shepperd (1978), "Quaternion from rotation matrix", J. Guidance and Control 1(3), 223-224.
    The four quantities `4 q_i²` (`1 + tr C` and `1 + 2 C_ii - tr C`) always sum to `4`;
    the largest (which is `>= 1`) gives one component by a square root, and the other three
    follow from sums/differences of off-diagonal entries divided by it. The branch is
    selected with `jnp.where` (no Python control flow), and the square root and division
    only ever see the selected value `>= 1`, so the function is jit-able and its gradient is
    finite everywhere (including the identity and 180-degree rotations).

    **Arguments:**

    - `C`: a rotation matrix `[NB]`, shape `(..., 3, 3)`.

    **Returns:**

    The quaternion `q` with `quat_to_dcm(q) = C`, scalar first, shape `(..., 4)`; of the two
    (`±q`) the one with `q0 >= 0` is returned.
    """
    C = _asarray(C)
    c00, c01, c02 = C[..., 0, 0], C[..., 0, 1], C[..., 0, 2]
    c10, c11, c12 = C[..., 1, 0], C[..., 1, 1], C[..., 1, 2]
    c20, c21, c22 = C[..., 2, 0], C[..., 2, 1], C[..., 2, 2]
    trace = c00 + c11 + c22
    # K = 4 q qᵀ, from the entries of C (symmetric; its diagonal holds the four 4 q_i²).
    t0 = 1.0 + trace
    t1 = 1.0 + 2.0 * c00 - trace
    t2 = 1.0 + 2.0 * c11 - trace
    t3 = 1.0 + 2.0 * c22 - trace
    d1, d2, d3 = c21 - c12, c02 - c20, c10 - c01  # 4 q0 q1, 4 q0 q2, 4 q0 q3
    a12, a13, a23 = c01 + c10, c02 + c20, c12 + c21  # 4 q1 q2, 4 q1 q3, 4 q2 q3
    K = _stack_matrix(
        [[t0, d1, d2, d3], [d1, t1, a12, a13], [d2, a12, t2, a23], [d3, a13, a23, t3]]
    )
    # Row k of K is 4 q_k q; dividing by 4 |q_k| = 2 sqrt(K_kk) gives ±q. Choosing the
    # largest diagonal entry (>= 1, since the trace of K is 4) keeps the division
    # well-conditioned and the square root away from zero, for values and gradients alike.
    diag = jnp.stack([t0, t1, t2, t3], axis=-1)
    onehot = jnp.argmax(diag, axis=-1)[..., None] == jnp.arange(4)
    row = jnp.sum(jnp.where(onehot[..., None], K, 0.0), axis=-2)
    t_max = jnp.sum(jnp.where(onehot, diag, 0.0), axis=-1)
    q = row / (2.0 * jnp.sqrt(t_max))[..., None]
    return jnp.where(q[..., :1] < 0, -q, q)


def quat_rotate(
    q: Float[ArrayLike, "*#batch 4"], v: Float[ArrayLike, "*#batch 3"]
) -> Float[Array, "*batch 3"]:
    """Rotate a vector: `[NB] v`, i.e. the vector part of `q ⊗ (0, v) ⊗ q*`.

    Maps body-frame components to inertial components. Equal to SciPy's
    `Rotation.from_quat([q1, q2, q3, q0]).apply(v)`.

    **Arguments:**

    - `q`: a unit quaternion, scalar first, shape `(..., 4)`.
    - `v`: a vector, shape `(..., 3)`.

    **Returns:**

    The rotated vector `quat_to_dcm(q) @ v`, shape `(..., 3)` (batch axes broadcast).
    """
    q0, e = _split_quat(_asarray(q))
    v = _asarray(v)
    t = 2.0 * jnp.cross(e, v)
    return v + q0[..., None] * t + jnp.cross(e, t)


def quat_derivative(
    q: Float[ArrayLike, "*#batch 4"], w: Float[ArrayLike, "*#batch 3"]
) -> Float[Array, "*batch 4"]:
    """Quaternion kinematics `q̇ = ½ q ⊗ (0, ω)`, with `ω` the body angular velocity.

    Equivalent to `d[NB]/dt = [NB] [ω×]`.

    **Arguments:**

    - `q`: the attitude quaternion, scalar first, shape `(..., 4)`.
    - `w`: the angular velocity of `B` relative to `N`, components in `B`, shape `(..., 3)`.

    **Returns:**

    The time derivative `q̇`, shape `(..., 4)` (batch axes broadcast).
    """
    w = _asarray(w)
    return 0.5 * quat_multiply(q, _join_quat(jnp.zeros_like(w[..., 0]), w))


def quat_from_axis_angle(
    axis: Float[ArrayLike, "*#batch 3"], angle: Float[ArrayLike, "*#batch"]
) -> Float[Array, "*batch 4"]:
    """Quaternion `(cos(Φ/2), sin(Φ/2) â)` of a rotation by `Φ` about the axis `â`.

    The rotation is right-handed (counterclockwise looking down `â`) and active:
    `quat_to_dcm` of the result is `expm(Φ [â×])`. Differentiable everywhere, including
    `Φ = 0`.

    **Arguments:**

    - `axis`: the rotation axis, shape `(..., 3)`; it need not be unit (it is normalised
      internally) but must be nonzero.
    - `angle`: the rotation angle `Φ` in radians, shape `(...)`.

    **Returns:**

    The unit quaternion, scalar first, shape `(..., 4)`.
    """
    axis = _asarray(axis)
    angle = _asarray(angle)
    unit_axis = axis / safe_norm(axis, keepdims=True)
    half = 0.5 * angle
    return _join_quat(jnp.cos(half), jnp.sin(half)[..., None] * unit_axis)


def quat_to_axis_angle(
    q: Float[ArrayLike, "*batch 4"],
) -> tuple[Float[Array, "*batch 3"], Float[Array, "*batch"]]:
    """Axis and angle of the rotation represented by a quaternion.

    Uses `Φ = 2 atan2(|e|, |q0|)` (accurate for small and large angles) with the sign of `q`
    chosen so that `q0 >= 0`. At the identity the axis is undefined; `(1, 0, 0)` is
    returned there, and gradients are finite (zero for the axis) thanks to a safe norm.

    **Arguments:**

    - `q`: a nonzero quaternion, scalar first, shape `(..., 4)` (need not be unit).

    **Returns:**

    A 2-tuple `(axis, angle)`: the unit axis, shape `(..., 3)`, and the angle
    `Φ ∈ [0, π]`, shape `(...)`, such that `quat_from_axis_angle(axis, angle) = ±q/|q|`.
    """
    q0, e = _split_quat(_asarray(q))
    negative = q0 < 0
    e = jnp.where(negative[..., None], -e, e)
    q0 = jnp.where(negative, -q0, q0)
    n = safe_norm(e)
    angle = 2.0 * jnp.arctan2(n, q0)
    nonzero = (n > 0)[..., None]
    default = jnp.zeros_like(e).at[..., 0].set(1.0)
    axis = jnp.where(nonzero, e / jnp.where(nonzero, n[..., None], 1.0), default)
    return axis, angle


#
# Modified Rodrigues parameters
#


def mrp_from_quat(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3"]:
    """Modified Rodrigues parameters `σ = e / (1 + q0)` of a unit quaternion.

    `-q` is used when `q0 < 0`, so the returned set has `|σ| <= 1` (rotation angle
    `<= 180` degrees). See Schaub & Junkins, "Analytical Mechanics of Space Systems".

    **Arguments:**

    - `q`: a unit quaternion, scalar first, shape `(..., 4)`.

    **Returns:**

    The MRPs `σ`, shape `(..., 3)`, representing the same `[NB]`.
    """
    q = _asarray(q)
    q = jnp.where(q[..., :1] < 0, -q, q)
    q0, e = _split_quat(q)
    return e / (1.0 + q0[..., None])


def quat_from_mrp(sigma: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 4"]:
    """Unit quaternion of a set of modified Rodrigues parameters.

    `q = ((1 - |σ|²), 2 σ) / (1 + |σ|²)`; this has `q0 >= 0` exactly when `|σ| <= 1`.

    **Arguments:**

    - `sigma`: the MRPs, shape `(..., 3)` (any magnitude).

    **Returns:**

    The quaternion, scalar first, shape `(..., 4)`, representing the same `[NB]`.
    """
    sigma = _asarray(sigma)
    s2 = _dot(sigma, sigma)
    denom = 1.0 + s2
    return _join_quat((1.0 - s2) / denom, 2.0 * sigma / denom[..., None])


def mrp_shadow(sigma: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """The shadow set `σˢ = -σ / |σ|²`, representing the same attitude as `σ`.

    It corresponds to the quaternion `-q`. Not defined (infinite) at `σ = 0`; use
    `mrp_switch` to switch only where needed.

    **Arguments:**

    - `sigma`: nonzero MRPs, shape `(..., 3)`.

    **Returns:**

    The shadow MRPs, shape `(..., 3)`.
    """
    sigma = _asarray(sigma)
    return -sigma / _dot(sigma, sigma)[..., None]


def mrp_switch(sigma: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """Switch to the shadow set when `|σ| > 1`, so that the result has `|σ| <= 1`.

    Typically applied after each step when integrating MRP kinematics. Gradient-safe:
    the unselected branch never divides by zero (so `σ = 0` has gradient identity).

    **Arguments:**

    - `sigma`: the MRPs, shape `(..., 3)`.

    **Returns:**

    `mrp_shadow(sigma)` where `|σ| > 1`, else `sigma`; shape `(..., 3)`.
    """
    sigma = _asarray(sigma)
    s2 = _dot(sigma, sigma)[..., None]
    outside = s2 > 1
    return jnp.where(outside, -sigma / jnp.where(outside, s2, 1.0), sigma)


def mrp_to_dcm(sigma: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix `[NB]` of a set of modified Rodrigues parameters.

    `[NB] = I + (8 [σ×]² + 4 (1 - |σ|²) [σ×]) / (1 + |σ|²)²` (the transpose of Schaub &
    Junkins' `[BN]`). Equal to SciPy's `Rotation.from_mrp(sigma).as_matrix()`.

    **Arguments:**

    - `sigma`: the MRPs, shape `(..., 3)` (any magnitude; a set and its shadow give the same
      matrix).

    **Returns:**

    The rotation matrix, shape `(..., 3, 3)`.
    """
    sigma = _asarray(sigma)
    s2 = _dot(sigma, sigma)
    denom = (1.0 + s2) ** 2
    # [σ×]² = σ σᵀ - |σ|² I
    return _sym_plus_skew(sigma, 8.0 / denom, 4.0 * (1.0 - s2) / denom, 1.0 - 8.0 * s2 / denom)


def dcm_to_mrp(C: Float[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """Modified Rodrigues parameters of a rotation matrix `[NB]`, with `|σ| <= 1`.

    Computed through `dcm_to_quat` (Shepperd's method), so it is well-conditioned and
    gradient-safe for every rotation.

    **Arguments:**

    - `C`: a rotation matrix `[NB]`, shape `(..., 3, 3)`.

    **Returns:**

    The MRPs, shape `(..., 3)`, with `mrp_to_dcm(σ) = C`.
    """
    return mrp_from_quat(dcm_to_quat(C))


def mrp_derivative(
    sigma: Float[ArrayLike, "*#batch 3"], w: Float[ArrayLike, "*#batch 3"]
) -> Float[Array, "*batch 3"]:
    """MRP kinematics `σ̇ = ¼ [(1 - |σ|²) I + 2 [σ×] + 2 σ σᵀ] ω`.

    Schaub & Junkins, "Analytical Mechanics of Space Systems". Valid for either set (`σ` or
    its shadow); combine with `mrp_switch` to keep `|σ| <= 1` during integration.

    **Arguments:**

    - `sigma`: the MRPs, shape `(..., 3)`.
    - `w`: the body angular velocity (components in `B`), shape `(..., 3)`.

    **Returns:**

    The time derivative `σ̇`, shape `(..., 3)` (batch axes broadcast).
    """
    sigma = _asarray(sigma)
    w = _asarray(w)
    s2 = _dot(sigma, sigma)[..., None]
    return 0.25 * (
        (1.0 - s2) * w + 2.0 * jnp.cross(sigma, w) + 2.0 * sigma * _dot(sigma, w)[..., None]
    )


#
# 3-2-1 Euler angles
#


def euler321_to_dcm(angles: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix `[NB] = R3(ψ) R2(θ) R1(φ)` of 3-2-1 Euler angles.

    Yaw `ψ` about axis 3, then pitch `θ` about the new axis 2, then roll `φ` about the new
    axis 1. Equal to SciPy's `Rotation.from_euler("ZYX", [ψ, θ, φ]).as_matrix()`.

    **Arguments:**

    - `angles`: `(ψ, θ, φ)` in radians, shape `(..., 3)`.

    **Returns:**

    The rotation matrix `[NB]`, shape `(..., 3, 3)`.
    """
    angles = _asarray(angles)
    c = jnp.cos(angles)
    s = jnp.sin(angles)
    cpsi, cth, cphi = c[..., 0], c[..., 1], c[..., 2]
    spsi, sth, sphi = s[..., 0], s[..., 1], s[..., 2]
    return _stack_matrix(
        [
            [cpsi * cth, cpsi * sth * sphi - spsi * cphi, cpsi * sth * cphi + spsi * sphi],
            [spsi * cth, spsi * sth * sphi + cpsi * cphi, spsi * sth * cphi - cpsi * sphi],
            [-sth, cth * sphi, cth * cphi],
        ]
    )


def dcm_to_euler321(C: Float[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """3-2-1 Euler angles `(ψ, θ, φ)` of a rotation matrix `[NB] = R3(ψ) R2(θ) R1(φ)`.

    `ψ = atan2(C10, C00)`; then, with `M = R3(ψ)ᵀ C = R2(θ) R1(φ)`, `θ = atan2(-C20, M00)`
    and `φ = atan2(-M12, M11)`. Computing `θ` and `φ` from `M` makes the decomposition
    reproduce `C` to round-off even close to gimbal lock. At gimbal lock (`θ = ±π/2`, detected
    as `hypot(C00, C10)` below a few machine epsilons) `ψ = 0` is returned and `φ` carries
    the whole rotation about the vertical; outputs and gradients are finite there.
    Matches SciPy's `Rotation.from_matrix(C).as_euler("ZYX")` away from gimbal lock.

    **Arguments:**

    - `C`: a rotation matrix `[NB]`, shape `(..., 3, 3)`.

    **Returns:**

    `(ψ, θ, φ)`, shape `(..., 3)`, with `ψ, φ ∈ [-π, π]` and `θ ∈ [-π/2, π/2]`.
    """
    C = _asarray(C)
    c00, c10, c20 = C[..., 0, 0], C[..., 1, 0], C[..., 2, 0]
    eps = float(jnp.finfo(C.dtype).eps)
    locked = c00 * c00 + c10 * c10 < (_GIMBAL_LOCK_EPS_FACTOR * eps) ** 2
    psi = jnp.where(
        locked, 0.0, jnp.arctan2(jnp.where(locked, 0.0, c10), jnp.where(locked, 1.0, c00))
    )
    cpsi, spsi = jnp.cos(psi), jnp.sin(psi)
    # M = R3(ψ)ᵀ C = [[cθ, sθ sφ, sθ cφ], [0, cφ, -sφ], [-sθ, cθ sφ, cθ cφ]]
    m00 = jnp.where(locked, 0.0, cpsi * c00 + spsi * c10)
    m11 = cpsi * C[..., 1, 1] - spsi * C[..., 0, 1]
    m12 = cpsi * C[..., 1, 2] - spsi * C[..., 0, 2]
    theta = jnp.arctan2(-c20, m00)
    phi = jnp.arctan2(-m12, m11)
    return jnp.stack([psi, theta, phi], axis=-1)


def euler321_to_quat(angles: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 4"]:
    """Unit quaternion `q3(ψ) ⊗ q2(θ) ⊗ q1(φ)` of 3-2-1 Euler angles.

    The sign is not canonicalised (it is the smooth closed form, so `q0` may be negative);
    `quat_to_dcm` of the result equals `euler321_to_dcm(angles)`.

    **Arguments:**

    - `angles`: `(ψ, θ, φ)` in radians, shape `(..., 3)`.

    **Returns:**

    The quaternion, scalar first, shape `(..., 4)`.
    """
    angles = _asarray(angles)
    c = jnp.cos(0.5 * angles)
    s = jnp.sin(0.5 * angles)
    cz, cy, cx = c[..., 0], c[..., 1], c[..., 2]
    sz, sy, sx = s[..., 0], s[..., 1], s[..., 2]
    return jnp.stack(
        [
            cx * cy * cz + sx * sy * sz,
            sx * cy * cz - cx * sy * sz,
            cx * sy * cz + sx * cy * sz,
            cx * cy * sz - sx * sy * cz,
        ],
        axis=-1,
    )


def quat_to_euler321(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3"]:
    """3-2-1 Euler angles `(ψ, θ, φ)` of a unit quaternion.

    Computed as `dcm_to_euler321(quat_to_dcm(q))`, so the same ranges and gimbal-lock
    convention apply, and `q` and `-q` give the same angles.

    **Arguments:**

    - `q`: a unit quaternion, scalar first, shape `(..., 4)`.

    **Returns:**

    `(ψ, θ, φ)`, shape `(..., 3)`.
    """
    return dcm_to_euler321(quat_to_dcm(q))
