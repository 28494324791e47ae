r"""Parameterisations: maps from unconstrained vectors to physically valid parameter values.

The fitter works in an unconstrained space $u \in \mathbb{R}^n$; each fitted quantity owns a
slice of $u$ and a parameterisation that turns it into a valid value, so that every iterate of
every optimiser is physical by construction (no constraints, no projections, no clipping).
"""

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from .._inertia import principal_axes
from .._rotations import (
    dcm_to_mrp,
    mrp_from_quat,
    mrp_to_dcm,
    quat_from_mrp,
    quat_multiply,
    quat_normalize,
)
from .._validation import ParameterError, is_concrete, unit_on_host


class AbstractParameterisation(eqx.Module):
    """Maps an unconstrained vector `u` to a parameter value.

    The fitter first calls `bind(value)` with the starting value (this fixes the shape, or a
    reference point); the bound parameterisation then gives `size()`, `components(name)`,
    `to_unconstrained(value)` (the starting point), `__call__(u)` (the value) and, optionally,
    `restart(key, u)` (a random starting point for a restart) and `summary(name, u, free)`
    (derived quantities reported with 1-sigma intervals, such as principal moments).
    """

    def bind(self, value: Array) -> "AbstractParameterisation":
        """A copy anchored at the starting value `value` (its shape, or a reference)."""
        return self

    @abc.abstractmethod
    def size(self) -> int:
        """Number of unconstrained components."""

    @abc.abstractmethod
    def components(self, name: str) -> tuple[str, ...]:
        """Names of the unconstrained components (used to report what is not identifiable)."""

    @abc.abstractmethod
    def to_unconstrained(self, value: Array) -> Float[Array, " n"]:
        """The unconstrained vector of a valid value (the inverse of `__call__`)."""

    @abc.abstractmethod
    def __call__(self, u: Float[Array, " n"]) -> Array:
        """The parameter value of an unconstrained vector."""

    def restart(self, key: PRNGKeyArray, u: Float[Array, " n"]) -> Float[Array, " n"]:
        """A random starting point for a restart, given the first starting point `u`.

        The default keeps `u` (for quantities that the data pin down well, such as an initial
        state read off the first sample). The fitter draws all restarts in one compiled
        program; a `restart` that cannot be traced (NumPy or Python logic on the values of
        `u`) is called eagerly instead.
        """
        return u

    def summary(
        self, name: str, u: Float[Array, " n"], free: Bool[Array, " n"]
    ) -> dict[str, Array]:
        """Quantities to report, as differentiable functions of `u` (their 1-sigma intervals
        are propagated from the covariance of `u`).

        `free` marks the components that were fitted; the others were found not identifiable
        and kept at their starting values. The default reports the value itself.
        """
        return {name: self(u)}

    def sampling(self, free: np.ndarray) -> "AbstractParameterisation":
        """The parameterisation in which a posterior of this quantity is sampled, given which
        components were fitted (`free`, a NumPy mask): the same values and the same number of
        components, in coordinates where the posterior is smooth. The default is this one."""
        return self

    def log_prior(self, u: Float[Array, " n"], start: Float[Array, " n"],
                  free: Bool[Array, " n"]) -> Float[Array, ""]:
        """The log prior density of a posterior, up to a constant, in these coordinates.

        The default is weakly informative: an independent Gaussian of standard deviation
        `PRIOR_SD` (10) on each fitted component around its starting value `start`.
        """
        return -0.5 * jnp.sum(jnp.where(free, (u - start) / PRIOR_SD, 0.0) ** 2)


PRIOR_SD = 10.0


def _element_names(name: str, shape: tuple[int, ...]) -> tuple[str, ...]:
    if shape == ():
        return (name,)
    return tuple(f"{name}[{i}]" for i in range(int(np.prod(shape))))


class _Elementwise(AbstractParameterisation):
    """A parameterisation acting element by element on a value of any shape, with fields
    `spread` and `shape`."""

    def bind(self, value):
        return type(self)(self.spread, tuple(jnp.shape(value)))

    def size(self):
        return int(np.prod(self.shape))

    def components(self, name):
        return _element_names(name, self.shape)


class Unconstrained(_Elementwise):
    """Any real value (the identity map), for example an initial state.

    **Arguments:**

    - `spread`: standard deviation of the random perturbation of restarts (default 0: every
      restart starts from the same value).
    """

    spread: float = 0.0
    shape: tuple[int, ...] | None = eqx.field(static=True, default=None)

    def to_unconstrained(self, value):
        return jnp.ravel(jnp.asarray(value))

    def __call__(self, u):
        return jnp.reshape(u, self.shape)

    def restart(self, key, u):
        if self.spread == 0:
            return u
        return u + self.spread * jax.random.normal(key, u.shape, u.dtype)


class Positive(_Elementwise):
    """A positive value, `value = exp(u)` (elementwise).

    Fitting the logarithm also makes the steps of an optimiser relative, so that lengths of
    0.1 m and 10 m are equally easy to fit.

    **Arguments:**

    - `spread`: standard deviation of `log(value)` for the random starting points of restarts
      (0 starts every restart from the same value).
    """

    spread: float = 0.5
    shape: tuple[int, ...] | None = eqx.field(static=True, default=None)

    def to_unconstrained(self, value):
        return jnp.log(jnp.ravel(jnp.asarray(value)))

    def __call__(self, u):
        return jnp.reshape(jnp.exp(u), self.shape)

    def restart(self, key, u):
        return u + self.spread * jax.random.normal(key, u.shape, u.dtype)


class ValidInertia(AbstractParameterisation):
    r"""A physically valid inertia tensor, by construction.

    Six unconstrained numbers `u = (s, a, b, σ)` give

    $$(x, y, z) = e^{s}\,\mathrm{softmax}(a, b, 0), \qquad
    (I_1, I_2, I_3) = (y + z,\; x + z,\; x + y), \qquad
    \mathbf{I} = A \,\mathrm{diag}(I_1, I_2, I_3)\, A^T,$$

    with $A$ the rotation matrix of the modified Rodrigues parameters $σ$
    ([`jaxdyn.mrp_to_dcm`][]). With $x, y, z > 0$ every moment is positive and smaller than the
    sum of the other two (the triangle inequality): every iterate is a physical body. $e^s =
    (I_1 + I_2 + I_3)/2$ carries the scale, `(a, b)` the shape, and the columns of $A$ are the
    principal axes in the body frame. (A side benefit: $|I_j - I_k| / I_i < 1$ keeps Euler's
    equations non-stiff for every iterate.)

    Torque-free rates do not change when the tensor is multiplied by a constant, so there the
    scale component is not identifiable: the fitter finds its Jacobian column to be zero,
    keeps it fixed, and the reported principal moments are normalised so that the largest is 1.
    When the scene fixes the scale (a rotor of known momentum, a known torque) the scale is
    fitted and the moments are absolute.

    Symmetries: permuting the moments together with the axes, or flipping an axis, gives the
    same tensor. Reported moments are therefore ascending, with the axes as columns under the
    sign convention of [`jaxdyn.principal_axes`][].

    **Arguments:**

    - `spread`: standard deviation of the shape logits `(a, b)` for the random starting points
      of restarts (the axes of a restart are drawn uniformly over rotations).
    """

    spread: float = 1.0

    names: ClassVar[tuple[str, ...]] = ("scale", "shape1", "shape2", "axes1", "axes2", "axes3")

    def size(self):
        return 6

    def components(self, name):
        return tuple(f"{name}.{c}" for c in self.names)

    def to_unconstrained(self, value):
        value = jnp.asarray(value)
        if value.shape == (3,):
            moments, axes = value, jnp.eye(3, dtype=value.dtype)
        elif value.shape == (3, 3):
            moments, axes = principal_axes(value)
        else:
            raise ParameterError(
                f"inertia has shape {value.shape}: expected 3 principal moments or a 3x3 tensor"
            )
        total = jnp.sum(moments)
        # x = (I2 + I3 - I1) / 2 and so on. A flat plate (x = 0) is the limit at infinity,
        # where the gradient vanishes: a start there is moved slightly inside.
        xyz = jnp.maximum(0.5 * total - moments, 0.02 * total)
        logs = jnp.log(xyz)
        scale = jnp.log(jnp.sum(xyz))
        return jnp.concatenate([scale[None], logs[:2] - logs[2], dcm_to_mrp(axes)])

    def moments(self, u: Float[Array, "6"]) -> Float[Array, "3"]:
        """The principal moments `(I1, I2, I3)`, in the order of the columns of `axes(u)`."""
        logits = jnp.stack([u[1], u[2], jnp.zeros_like(u[1])])
        x, y, z = jnp.exp(u[0]) * jax.nn.softmax(logits)
        return jnp.stack([y + z, x + z, x + y])

    def axes(self, u: Float[Array, "6"]) -> Float[Array, "3 3"]:
        """The principal axes (columns) in the body frame, in the order of `moments(u)`."""
        return mrp_to_dcm(u[3:6])

    def __call__(self, u):
        axes = self.axes(u)
        return (axes * self.moments(u)) @ axes.T

    def restart(self, key, u):
        k1, k2 = jax.random.split(key)
        shape = self.spread * jax.random.normal(k1, (2,), u.dtype)
        q = quat_normalize(jax.random.normal(k2, (4,), u.dtype))  # uniform over rotations
        return jnp.concatenate([u[:1], shape, mrp_from_quat(q)])

    def summary(self, name, u, free):
        moments = jnp.sort(self.moments(u))
        moments = jnp.where(free[0], moments, moments / moments[2])
        _, axes = principal_axes(self(u))
        return {
            name: self(u),
            f"{name}.principal_moments": moments,
            f"{name}.principal_axes": axes,
        }

    def sampling(self, free):
        # The moments and axes are singular coordinates where two moments are equal (the
        # axes of those two turn freely) and near a flat plate (a shape logit runs off to
        # infinity): a posterior is sampled in the linear coordinates of the shape instead,
        # when all five shape components are fitted.
        return _ShapeInertia() if bool(np.all(free[1:])) else self


# Below this gap between two eigenvalues of the unit-trace shape, the shape prior of
# _ShapeInertia is flat: finite where two moments are equal.
_GAP_FLOOR = 1e-8

# An orthonormal basis (Frobenius) of the traceless symmetric 3x3 matrices.
_R2, _R6 = 1 / np.sqrt(2), 1 / np.sqrt(6)
_TRACELESS = np.array([
    [[_R2, 0, 0], [0, -_R2, 0], [0, 0, 0]],
    [[_R6, 0, 0], [0, _R6, 0], [0, 0, -2 * _R6]],
    [[0, _R2, 0], [_R2, 0, 0], [0, 0, 0]],
    [[0, 0, _R2], [0, 0, 0], [_R2, 0, 0]],
    [[0, 0, 0], [0, 0, _R2], [0, _R2, 0]],
])


class _ShapeInertia(AbstractParameterisation):
    r"""A valid inertia tensor from the linear coordinates of its shape: the coordinates in
    which the posterior of a [`jaxdyn.ValidInertia`][] is sampled.

    Six numbers `u = (s, c_1..c_5)` give the second-moment tensor
    $\mathbf{M} = \int \mathbf{r}\mathbf{r}^T dm$ and the inertia tensor

    $$\mathbf{M} = e^{s}\,\mathbf{N}, \qquad
    \mathbf{N} = \tfrac{1}{3}\mathbf{1} + \sum_k c_k \mathbf{E}_k, \qquad
    \mathbf{I} = \mathrm{tr}(\mathbf{M})\,\mathbf{1} - \mathbf{M},$$

    with $\mathbf{E}_k$ an orthonormal basis of the traceless symmetric matrices: the shape
    $\mathbf{N}$ (unit trace) is linear in `c`, so the map is smooth everywhere, in particular
    where two moments are equal (there the moments-and-axes coordinates of
    [`jaxdyn.ValidInertia`][] are singular: the axes of the two equal moments turn freely)
    and at a flat plate (where its shape logits run off to infinity). The scale $e^s$ is
    that of [`jaxdyn.ValidInertia`][] (the same first component).

    Not every `c` is a physical body. The prior is zero outside the physical shapes (those
    with $\mathbf{N}$ positive semi-definite, the triangle inequality of the moments) and,
    inside, uniform in the body's principal moments (normalised, over the triangle of
    physical bodies) and uniform over its orientations (Haar measure on the principal
    axes), independently; Gaussian of standard deviation `PRIOR_SD` on the scale `s` where
    the scale is fitted. In the linear coordinates that is the density
    $\prod_{i<j} |\lambda_i - \lambda_j|^{-1}$ of the eigenvalues $\lambda$ of
    $\mathbf{N}$: the volume element of the symmetric matrices in eigenvalues and axes is
    $\prod_{i<j} |\lambda_i - \lambda_j| \, d\lambda \, dR$ (the Vandermonde factor),
    so a prior uniform over the tensors would make nearly equal moments rare (the sorted
    moments of its draws repel each other; on a body with two moments 0.1 % apart, 90 %
    intervals of the larger one covered the truth in 63 % of 40 noise draws). The density
    is integrable (the equal-moment bodies have codimension 2) and is capped at gaps below
    `_GAP_FLOOR` (of the unit trace), so that it stays finite where two moments are
    exactly equal. (A prior uniform in the moments-and-axes coordinates of
    [`jaxdyn.ValidInertia`][] would pile up at flat plates, where its shape logits run off
    while the tensor hardly changes.)
    """

    names: ClassVar[tuple[str, ...]] = ("scale", "shape1", "shape2", "shape3", "shape4",
                                        "shape5")

    def size(self):
        return 6

    def components(self, name):
        return tuple(f"{name}.{c}" for c in self.names)

    def shape_of(self, c: Float[Array, "5"]) -> Float[Array, "3 3"]:
        """The shape `M / tr(M)` of the coordinates `c`."""
        basis = jnp.asarray(_TRACELESS, c.dtype)
        return jnp.eye(3, dtype=c.dtype) / 3 + jnp.einsum("k,kij->ij", c, basis)

    def __call__(self, u):
        M = jnp.exp(u[0]) * self.shape_of(u[1:])
        return jnp.trace(M) * jnp.eye(3, dtype=u.dtype) - M

    def to_unconstrained(self, value):
        value = jnp.asarray(value)
        tensor = jnp.diag(value) if value.shape == (3,) else value
        M = 0.5 * jnp.trace(tensor) * jnp.eye(3, dtype=tensor.dtype) - tensor
        c = jnp.einsum("ij,kij->k", M / jnp.trace(M), jnp.asarray(_TRACELESS, M.dtype))
        return jnp.concatenate([jnp.log(jnp.trace(M))[None], c])

    def summary(self, name, u, free):
        # As ValidInertia's (the moments here from the eigenvalues: for draws, not for
        # intervals, whose derivatives would be ill-conditioned at equal moments).
        moments, axes = principal_axes(self(u))
        return {
            name: self(u),
            f"{name}.principal_moments": jnp.where(free[0], moments, moments / moments[2]),
            f"{name}.principal_axes": axes,
        }

    def log_prior(self, u, start, free):
        lam = jnp.linalg.eigvalsh(self.shape_of(u[1:]))  # ascending, summing to 1
        gaps = jnp.stack([lam[1] - lam[0], lam[2] - lam[1], lam[2] - lam[0]])
        # Uniform in the moments and axes: the inverse of the Vandermonde factor.
        shape = -jnp.sum(jnp.log(jnp.maximum(gaps, _GAP_FLOOR)))
        scale = jnp.where(free[0], (u[0] - start[0]) / PRIOR_SD, 0.0)
        return jnp.where(lam[0] >= 0, shape - 0.5 * scale**2, -jnp.inf)


class UnitQuaternion(AbstractParameterisation):
    r"""A unit quaternion (scalar first) as a rotation from a reference, `q = q_ref ⊗ q(σ)`.

    Three modified Rodrigues parameters `σ` (zero at the reference, the starting value) avoid
    both the norm constraint and the `q`/`-q` ambiguity of fitting four numbers.
    """

    reference: Float[Array, "4"] | None = None

    def bind(self, value):
        if is_concrete(value):  # (a fit's start: on the host, compiling nothing)
            return UnitQuaternion(unit_on_host(value))
        return UnitQuaternion(quat_normalize(jnp.asarray(value)))

    def size(self):
        return 3

    def components(self, name):
        return tuple(f"{name}.{c}" for c in ("sigma1", "sigma2", "sigma3"))

    def to_unconstrained(self, value):
        return jnp.zeros(3, jnp.asarray(value).dtype)

    def __call__(self, u):
        return quat_multiply(self.reference.astype(u.dtype), quat_from_mrp(u))
