r"""Relative equilibria, their stability and the separatrices of conservative rotational scenes.

Everything here works through the scene protocol (`vector_field`, `invariants`, `conserved`), so
one code path serves the torque-free body, the gyrostat and any other scene whose body rates
conserve the kinetic energy $T$ and the momentum $|\mathbf{H}|$.

**Relative equilibria.** A relative equilibrium is a fixed point of the body-rate dynamics
$\dot\omega = f(\omega)$. Fixed points come in one-parameter families (for the torque-free body,
a spin about a principal axis at any rate), so each meets a momentum sphere $|\mathbf{H}| = H$ in
isolated points. They are the roots of the square system

$$R(\omega) = f(\omega) + \big(|\mathbf{H}|(\omega) - H\big)\,\hat n(\omega) = 0,$$

where $\hat n = \nabla|\mathbf{H}| / \|\nabla|\mathbf{H}|\|$ is the normal of the momentum sphere
(in rate space). Because $|\mathbf{H}|$ is conserved, $f$ is tangent to the sphere, so both terms
vanish separately at a root; at a non-degenerate relative equilibrium the Jacobian of $R$ is the
tangent-plane part of $\partial f/\partial\omega$ plus the normal row, which is non-singular.
Newton iteration (`optimistix.Newton`, Jacobians by automatic differentiation) starts from a
Fibonacci lattice on the momentum sphere; the roots are then deduplicated.

**Stability.** $J = \partial f/\partial\omega$ maps every vector into the tangent plane of the
sphere (differentiate $\nabla|\mathbf{H}|\cdot f = 0$ at $f = 0$), and its third eigenvalue is
zero, along the family. The linearisation on the sphere is the $2\times 2$ matrix
$A = Q^\top J Q$, with $Q$ an orthonormal basis of the tangent plane; a conservative flow has
$\operatorname{tr}A = 0$, so its eigenvalues are $\pm\lambda$ with $\lambda^2 = -\det A$: a real
pair is a saddle, an imaginary pair a centre.

**Separatrices.** The separatrix energies are the saddles' energies; the separatrix curves are the
saddles' unstable manifolds, traced with [`jaxdyn.simulate`][] from each saddle displaced by a
small step along $\pm$ its unstable eigenvector, until the trajectory comes back to a saddle.

Reference: P. C. Hughes, *Spacecraft Attitude Dynamics* (Wiley, 1986), on the torque-free body
and the gyrostat.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Complex, Float, Int

from ._effects import Rotor
from ._rigid_body import RigidBody
from ._scene import Scene
from ._stored_jit import stored_filter_jit
from ._validation import ParameterError, as_float_array, device_array, on_host

_NUM_STARTS = 64  # Fibonacci points on the momentum sphere; a gyrostat has at most 6 equilibria.


# -- tolerances, keyed by dtype ----------------------------------------------------------------


def _eps(dtype) -> float:
    return float(jnp.finfo(dtype).eps)


def _newton_tol(dtype) -> float:
    # Newton converges quadratically: ask for a few hundred times the round-off.
    return 256 * _eps(dtype)


def _same_point_tol(dtype) -> float:
    # Roots from different starts agree to round-off; distinct equilibria are far apart.
    return float(np.sqrt(_eps(dtype)) * 64)


def _complex(dtype):
    return jnp.complex128 if jnp.dtype(dtype) == jnp.float64 else jnp.complex64


def _degenerate_tol(dtype) -> float:
    # |lambda^2| below this fraction of |A|^2 is a zero eigenvalue pair up to round-off.
    return float(np.sqrt(_eps(dtype)) * 8)


# -- results -----------------------------------------------------------------------------------


class Equilibria(eqx.Module):
    r"""The relative equilibria on one momentum sphere, from [`jaxdyn.find_equilibria`][].

    Isolated equilibria, ordered by energy (then by rates), stacked along the first axis:

    - `omega`: body rates, shape `(n, 3)`.
    - `energy`: kinetic energy $\tfrac12\omega\cdot I\omega$ (the scene's `"energy"` invariant),
      shape `(n,)`.
    - `eigenvalues`: the eigenvalue pair of the linearisation restricted to the tangent plane of
      the momentum sphere, shape `(n, 2)`, complex; $\pm\lambda$ for a saddle, $\pm i\nu$ for a
      centre.
    - `unstable_direction`: for a saddle, the unit eigenvector of $+\lambda$ (tangent to the
      sphere, in rate space); zero for a centre. Shape `(n, 3)`.
    - `kind`: `"saddle"` or `"center"` for each equilibrium.
    - `momentum`: the sphere's $H = |I\omega + \mathbf{h}|$.
    - `degenerate`: rates of equilibria whose linearisation vanishes on the sphere (both
      eigenvalues zero), shape `(m, 3)`. These are not isolated or not structurally stable: a
      continuum of equilibria (two equal principal moments give a whole circle of them) or a
      bifurcation point (a saddle and a centre merging as a rotor's momentum grows). They are
      listed apart and are neither saddles nor centres. `m = 0` in the generic case.
    """

    omega: Float[Array, "n 3"]
    energy: Float[Array, " n"]
    eigenvalues: Complex[Array, "n 2"]
    unstable_direction: Float[Array, "n 3"]
    momentum: Float[Array, ""]
    degenerate: Float[Array, "m 3"]
    kind: tuple[str, ...] = eqx.field(static=True)

    def __len__(self) -> int:
        return len(self.kind)

    @property
    def is_saddle(self) -> np.ndarray:
        """Boolean mask of the saddles, shape `(n,)`."""
        return np.array([k == "saddle" for k in self.kind], dtype=bool)

    @property
    def growth_rate(self) -> Float[Array, " n"]:
        r"""$\lambda = \max \operatorname{Re}$ of the eigenvalues: the saddle's rate of departure
        along its unstable manifold (zero for a centre). (NumPy where the eigenvalues are
        concrete: eager, each `jnp` operation compiled a program.)"""
        xp, eigenvalues = on_host(self.eigenvalues)
        rate = xp.max(xp.real(eigenvalues), axis=-1).clip(min=0)
        return jax.device_put(rate) if xp is np else rate

    @property
    def separatrix_energies(self) -> Float[Array, " k"]:
        """The distinct energies of the saddles, ascending (saddles related by symmetry share one
        energy). Empty when there is no saddle."""
        energies = np.sort(np.asarray(self.energy)[self.is_saddle])
        tol = _same_point_tol(self.energy.dtype) * max(float(np.max(np.abs(energies), initial=0)),
                                                       np.finfo(energies.dtype).tiny)
        keep = np.concatenate([[True], np.diff(energies) > tol]) if energies.size else []
        return jnp.asarray(energies[keep], dtype=self.energy.dtype)

    @property
    def continuum(self) -> bool:
        """Whether degenerate (non-isolated or bifurcating) equilibria were found."""
        return bool(self.degenerate.shape[0])


class Separatrices(eqx.Module):
    """Separatrix curves from [`jaxdyn.trace_separatrices`][]: one branch per saddle and sign of
    its unstable direction, each resampled at `num` points evenly spaced in arc length.

    - `omega`: body rates along each branch, shape `(branches, num, 3)`.
    - `angular_momentum`: total body-frame momentum $I\\omega + \\mathbf{h}$ along each branch
      (the scene's `"angular_momentum"` output), shape `(branches, num, 3)`.
    - `energy`: the energy of each branch (its saddle's), shape `(branches,)`.
    - `saddle`: index of the branch's saddle in the equilibria, shape `(branches,)`.
    - `sign`: `+1` or `-1`, the side of the unstable direction the branch leaves along.
    - `duration`: time from the start of the branch to its end, shape `(branches,)`.
    - `returned`: whether the branch came back to a saddle within the horizon (then it ends at
      its closest approach to that saddle; otherwise at the horizon).
    - `end_saddle`: index of the saddle the branch came back to (`-1` if none).
    """

    omega: Float[Array, "branches num 3"]
    angular_momentum: Float[Array, "branches num 3"]
    energy: Float[Array, " branches"]
    saddle: Int[Array, " branches"]
    sign: Int[Array, " branches"]
    duration: Float[Array, " branches"]
    returned: Bool[Array, " branches"]
    end_saddle: Int[Array, " branches"]

    def __len__(self) -> int:
        return int(self.omega.shape[0])


# -- checks ------------------------------------------------------------------------------------


def _check_scene(scene) -> None:
    if not isinstance(scene, Scene):
        raise ParameterError(f"scene={scene!r}: expected a jaxdyn.Scene")
    shapes = scene.state_shapes()
    if scene.attitude:
        raise ParameterError(
            f"scene integrates attitude (state {sorted(shapes)}): relative equilibria are "
            "found for the body rates alone; use a scene without attitude"
        )
    if shapes != {"omega": (3,)}:
        raise ParameterError(
            f"scene has state {sorted(shapes)}: relative equilibria need a scene whose state is "
            "the body rates 'omega' alone (a rigid body with rotors or no effects)"
        )
    missing = [name for name in ("energy", "momentum") if name not in scene.conserved]
    if missing:
        raise ParameterError(
            f"scene conserves {list(scene.conserved)}: the separatrix finder needs a "
            f"conservative scene (energy and momentum conserved), missing {missing}"
        )


_DTYPES: dict = {}  # the rates' dtype by scene structure, leaf types and default float


def _scene_dtype(scene: Scene):
    # The body rates take the body's dtype; effects cast their contributions to it. Found once
    # per structure (by an abstract evaluation, which traces).
    leaves, treedef = jax.tree_util.tree_flatten(scene)
    key = (treedef, tuple((np.shape(x), getattr(x, "dtype", type(x))) for x in leaves),
           jnp.dtype(jnp.result_type(float)))
    if key not in _DTYPES:
        _DTYPES[key] = jax.eval_shape(lambda: scene.state(omega=jnp.zeros(3)))["omega"].dtype
    return _DTYPES[key]


def _positive_scalar(field: str, value, dtype):
    arr = as_float_array(field, value, (), dtype)
    v = float(arr)
    if not (np.isfinite(v) and v > 0):
        raise ParameterError(f"{field}={v:g}: must be positive and finite")
    return arr


# -- the finder --------------------------------------------------------------------------------


def _fibonacci_sphere(n: int) -> np.ndarray:
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    r = np.sqrt(1 - z**2)
    phi = np.pi * (1 + np.sqrt(5.0)) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _rates(scene: Scene, omega):
    t = jnp.zeros((), omega.dtype)
    return scene.vector_field(t, {"omega": omega})["omega"]


def _invariant(scene: Scene, name: str, omega):
    t = jnp.zeros((), omega.dtype)
    return scene.invariants(t, {"omega": omega})[name]


def _sphere_frame(scene: Scene, momentum):
    """Centre, shape and scales of the momentum sphere `|H|(omega) = H` in rate space.

    With `M2 = |H|^2 / 2` quadratic in the rates (exactly so for rigid bodies with rotors),
    one Newton step gives the centre `omega_c` (where `|H| = 0`) and the Hessian `G`; the sphere
    is then `omega_c + H G^(-1/2) d` over unit vectors `d`.
    """
    dtype = momentum.dtype

    def m2(w):
        return 0.5 * _invariant(scene, "momentum", w) ** 2

    # Away from |H| = 0, where the norm is not differentiable.
    p = jnp.asarray([0.3, 0.5, 0.7], dtype) * momentum
    g = jax.hessian(m2)(p)
    centre = p - jnp.linalg.solve(g, jax.grad(m2)(p))
    ev, vecs = jnp.linalg.eigh(g)
    ev = jnp.maximum(ev, jnp.finfo(dtype).tiny)
    shape = (vecs / jnp.sqrt(ev)) @ vecs.T  # G^(-1/2)
    rate_scale = momentum / jnp.sqrt(jnp.mean(ev))  # |omega - omega_c| ~ H / I
    scale = jnp.linalg.norm(centre) + rate_scale  # size of the rates on the sphere
    return centre, shape, rate_scale, scale


def _tangent_linearisation(scene: Scene, omega):
    """`J = df/domega`, the tangent basis `Q` and `A = Q^T J Q` at `omega`."""
    jac = jax.jacfwd(lambda w: _rates(scene, w))(omega)
    normal = jax.grad(lambda w: _invariant(scene, "momentum", w))(omega)
    normal = normal / jnp.linalg.norm(normal)
    # The eigenvectors of I - n n^T with eigenvalue 1 span the tangent plane.
    _, vecs = jnp.linalg.eigh(jnp.eye(3, dtype=omega.dtype) - jnp.outer(normal, normal))
    q = vecs[:, 1:]
    return jac, q, q.T @ jac @ q


def _classify(scene: Scene, omega):
    """Eigenvalue pair, lambda^2 relative to |A|^2, and the unstable direction at `omega`."""
    _, q, a = _tangent_linearisation(scene, omega)
    half_tr = 0.5 * jnp.trace(a)
    disc = half_tr**2 - jnp.linalg.det(a)  # lambda^2 for a traceless A
    size = jnp.sum(a**2)
    ctype = _complex(omega.dtype)
    root = jnp.sqrt(disc.astype(ctype))
    eig = jnp.stack([half_tr.astype(ctype) + root, half_tr.astype(ctype) - root])
    mu = half_tr + jnp.sqrt(jnp.maximum(disc, 0.0))
    # Eigenvector of A for mu: (b, mu - a) or (mu - d, c), whichever is better conditioned.
    v1 = jnp.stack([a[0, 1], mu - a[0, 0]])
    v2 = jnp.stack([mu - a[1, 1], a[1, 0]])
    v = jnp.where(jnp.sum(v1**2) >= jnp.sum(v2**2), v1, v2)
    u = q @ v
    norm = jnp.linalg.norm(u)
    u = jnp.where((disc > 0) & (norm > 0), u / jnp.where(norm > 0, norm, 1.0), 0.0)
    rel = disc / jnp.where(size > 0, size, 1.0)
    return eig, rel, u


@stored_filter_jit(light=True)  # one small problem per call (`_programs`)
def _solve_all(scene: Scene, momentum, directions):
    centre, shape, rate_scale, scale = _sphere_frame(scene, momentum)
    dtype = momentum.dtype
    f_scale = rate_scale * scale  # |f| ~ |H| |omega| / I

    def residual(u, args):
        w = u * scale
        f = _rates(scene, w)
        m, g = jax.value_and_grad(lambda x: _invariant(scene, "momentum", x))(w)
        return f / f_scale + (m / momentum - 1) * g / jnp.linalg.norm(g)

    tol = _newton_tol(dtype)
    # SVD: least-squares Newton steps stay finite where the Jacobian is singular (a continuum of
    # equilibria), so those roots are found and reported instead of silently lost.
    solver = optx.Newton(rtol=tol, atol=tol, linear_solver=lx.SVD())

    def one(d):
        u0 = (centre + momentum * (shape @ d)) / scale
        sol = optx.root_find(residual, solver, u0, throw=False, max_steps=100)
        u = sol.value
        ok = (sol.result == optx.RESULTS.successful) & jnp.all(jnp.isfinite(u))
        ok = ok & (jnp.max(jnp.abs(residual(u, None))) < 16 * tol)
        w = u * scale
        eig, rel, unstable = _classify(scene, w)
        energy = _invariant(scene, "energy", w)
        return w, ok, energy, eig, rel, unstable

    return jax.lax.map(one, directions) + (scale,)


def _normalised(scene: Scene, momentum) -> tuple[Scene, float, float]:
    """The scene in units where the largest moment of inertia and the sphere's radius are 1
    (momenta divided by `H`, inertia by `I_max`), and the rate unit `H / I_max` and inertia
    unit `I_max` that convert back. The equilibria of the gyrostat equations scale exactly so,
    and solving in these units keeps every intermediate (rates, their squares, the Hessian of
    `|H|^2`) near one: inertia of 1e20 or momenta of 1e-300 lose nothing to overflow."""
    # (On the host, in each value's own dtype: `find_equilibria` is never traced, and an eager
    # division would be a program of its own.)
    inertia = np.asarray(scene.body.inertia)
    big = float(np.max(np.abs(inertia.astype(np.float64))))
    h = float(momentum)
    values = {"inertia": device_array(inertia / np.asarray(big, inertia.dtype), inertia.dtype)}
    for label, e in zip(scene.labels, scene.effects):
        for name, kind in e.parameter_kinds.items():
            if kind == "momentum":
                v = np.asarray(e.parameters()[name])
                values[f"{label}.{name}"] = device_array(v / np.asarray(h, v.dtype), v.dtype)
    return scene.replace(values), h / big, big


def find_equilibria(scene: Scene, momentum: float | ArrayLike = 1.0) -> Equilibria:
    r"""All relative equilibria of a conservative scene on the momentum sphere $|\mathbf{H}| = H$.

    Newton iteration with automatic Jacobians from 64 starting points spread over the sphere
    (a Fibonacci lattice), on the square system $f(\omega) + (|\mathbf{H}| - H)\hat n = 0$; the
    roots are deduplicated and classified by the eigenvalues of the linearisation restricted to
    the tangent plane of the sphere (see the module notes in `jaxdyn/_separatrix.py`).

    **Arguments:**

    - `scene`: a [`jaxdyn.Scene`][] whose state is the body rates alone and which conserves
      `"energy"` and `"momentum"`: a torque-free [`jaxdyn.RigidBody`][] (principal moments or a
      full tensor), optionally with [`jaxdyn.Rotor`][] effects (a gyrostat).
    - `momentum`: the sphere's radius $H = |I\omega + \mathbf{h}|$ (positive).

    **Returns:**

    A [`jaxdyn.Equilibria`][] in the scene's floating dtype. The Newton solves run compiled (once
    per scene structure); the deduplication runs on the host, as the number of equilibria depends
    on the values, so `find_equilibria` itself is not traced by `jit`, `grad` or `vmap`.

    For the torque-free body with three distinct moments: centres $\pm H/I_k$ on the major and
    minor axes and saddles on the intermediate axis, at energy $H^2/(2I_2)$. With two equal
    moments the equilibria about those axes form a circle; they are returned in `degenerate`,
    and no saddle is reported.

    **Raises:**

    `jaxdyn.ParameterError` for a scene that integrates attitude, carries state other than the
    body rates, or does not conserve energy and momentum, and for a momentum that is not positive.
    """
    _check_scene(scene)
    dtype = _scene_dtype(scene)
    momentum = _positive_scalar("momentum", momentum, dtype)
    directions = jnp.asarray(_fibonacci_sphere(_NUM_STARTS), dtype)
    unit_scene, rate_unit, _ = _normalised(scene, momentum)
    w, ok, energy, eig, rel, unstable, scale = jax.device_get(
        _solve_all(unit_scene, device_array(1.0, dtype), directions)
    )
    tol = _same_point_tol(dtype) * float(scale)
    found: list[int] = []
    for i in np.flatnonzero(ok):
        if all(np.linalg.norm(w[i] - w[j]) > tol for j in found):
            found.append(int(i))
    deg_tol = _degenerate_tol(dtype)
    regular = [i for i in found if abs(rel[i]) > deg_tol]
    degenerate = [i for i in found if abs(rel[i]) <= deg_tol]
    e_scale = max([abs(float(energy[i])) for i in regular], default=1.0) or 1.0
    regular.sort(key=lambda i: (round(float(energy[i]) / e_scale, 9), *np.round(w[i] / scale, 9)))
    degenerate.sort(key=lambda i: tuple(np.round(w[i] / scale, 9)))
    idx = np.asarray(regular, dtype=int)
    ctype = _complex(dtype)
    kinds = tuple("saddle" if rel[i] > 0 else "center" for i in regular)
    # Poincare-Hopf: the indices of the isolated equilibria of a flow on the sphere add up to
    # its Euler characteristic, 2 (+1 for a centre, -1 for a saddle). A circle of degenerate
    # equilibria (an axisymmetric body) contributes as a band, so only then can the count
    # differ from centres - saddles = 2.
    if not degenerate and kinds.count("center") - kinds.count("saddle") != 2:
        raise RuntimeError(
            f"find_equilibria found {kinds.count('center')} centres and "
            f"{kinds.count('saddle')} saddles at momentum={float(momentum):g}; on a sphere "
            "centres - saddles must be 2, so some equilibria were missed (the body may be "
            "nearly degenerate at this dtype's precision)"
        )
    with np.errstate(over="ignore"):  # unrepresentable values become inf, as they would
        return Equilibria(
            omega=jnp.asarray(w[idx].reshape(-1, 3) * rate_unit, dtype),
            energy=jnp.asarray(energy[idx] * float(momentum) * rate_unit, dtype),
            eigenvalues=jnp.asarray(eig[idx].reshape(-1, 2) * rate_unit, ctype),
            unstable_direction=jnp.asarray(unstable[idx].reshape(-1, 3), dtype),
            momentum=momentum,
            degenerate=jnp.asarray(
                w[np.asarray(degenerate, dtype=int)].reshape(-1, 3) * rate_unit, dtype),
            kind=kinds,
        )


# -- separatrices ------------------------------------------------------------------------------


@eqx.filter_jit
def _rate_scale(scene: Scene, momentum):
    return _sphere_frame(scene, momentum)[3]


@eqx.filter_jit
def _start_on_sphere(scene: Scene, saddle, direction, step, momentum):
    """`saddle + step * direction`, pulled back onto the momentum sphere by Newton steps along
    the sphere's normal (the displacement is tangent, so it leaves it only at second order)."""
    w = saddle + step * direction
    for _ in range(3):
        m, g = jax.value_and_grad(lambda x: _invariant(scene, "momentum", x))(w)
        w = w - (m - momentum) * g / jnp.sum(g**2)
    return w


@eqx.filter_jit
def _evaluate(traj, ts):
    ys = traj.evaluate(ts)
    out = jax.vmap(traj.scene.outputs)(ts, ys)
    return ys["omega"], out["angular_momentum"]


def _cut(ts, dist, leave, arrive):
    """Index where a branch ends: its closest approach to a saddle on its first return."""
    away = np.flatnonzero(dist > leave)
    if away.size == 0:
        return len(ts) - 1, False
    near = np.flatnonzero((dist < arrive) & (np.arange(len(ts)) > away[0]))
    if near.size == 0:
        return len(ts) - 1, False
    i = int(near[0])
    while i + 1 < len(ts) and dist[i + 1] <= dist[i]:
        i += 1
    return i, True


def trace_separatrices(
    scene: Scene,
    equilibria: Equilibria | float | ArrayLike = 1.0,
    *,
    num: int = 201,
    step: float = 1e-7,
    horizon: float = 50.0,
    samples: int = 4001,
    rtol: float | None = None,
    atol: float | None = None,
) -> Separatrices:
    r"""Trace the separatrices: the unstable manifolds of the saddles on a momentum sphere.

    From each saddle, displaced by `step` (relative to the size of the rates) along $\pm$ its
    unstable eigenvector and put back on the sphere, the scene is integrated with
    [`jaxdyn.simulate`][] for `horizon / lambda` ($\lambda$ the saddle's growth rate). A branch
    ends at its closest approach to a saddle on its first return (another saddle, for the
    torque-free body's heteroclinic orbits; the same one, for a gyrostat's homoclinic loops).
    The curves lie on the momentum sphere and on the saddle's energy surface.

    **Arguments:**

    - `scene`: the [`jaxdyn.Scene`][] (as for [`jaxdyn.find_equilibria`][]).
    - `equilibria`: the [`jaxdyn.Equilibria`][] from `find_equilibria(scene, ...)`, or the
      momentum $H$, in which case they are found first.
    - `num`: points per branch, evenly spaced in arc length.
    - `step`: initial displacement from the saddle, relative to the size of the rates. The
      curve leaves the separatrix by $O(\text{step}^2)$.
    - `horizon`: integration time in units of $1/\lambda$. A departure from distance `step`
      and the return take about $2\ln(1/\text{step})/\lambda$ ($\approx 32/\lambda$ for the
      default).
    - `samples`: samples of the dense output used to locate the return.
    - `rtol`, `atol`: integration tolerances (default: $10^{-10}$ in float64, $10^{-5}$ in
      float32; error control in the natural scales, as [`jaxdyn.simulate`][]; `atol`, an
      optional floor, relative to the size of the rates).

    **Returns:**

    A [`jaxdyn.Separatrices`][], with no branches when there is no saddle.
    """
    from ._simulate import simulate  # (the integration stack: only where a branch is traced)

    _check_scene(scene)
    if not isinstance(equilibria, Equilibria):
        equilibria = find_equilibria(scene, equilibria)
    if not isinstance(num, int) or num < 2:
        raise ParameterError(f"num={num!r}: must be an integer of at least 2")
    if not isinstance(samples, int) or samples < 10:
        raise ParameterError(f"samples={samples!r}: must be an integer of at least 10")
    for name, value in (("step", step), ("horizon", horizon)):
        if not (np.isfinite(value) and value > 0):
            raise ParameterError(f"{name}={value!r}: must be positive and finite")
    dtype = equilibria.omega.dtype
    momentum = jnp.asarray(equilibria.momentum, dtype)
    # The equilibria on the host once (each branch reads them there).
    w_all = np.asarray(equilibria.omega)
    unstable = np.asarray(equilibria.unstable_direction)
    energies = np.asarray(equilibria.energy)
    saddles = np.flatnonzero(equilibria.is_saddle)
    scale = float(_rate_scale(scene, momentum))
    if rtol is None:
        rtol = 1e-10 if dtype == jnp.float64 else 1e-5
    rates = np.asarray(equilibria.growth_rate)

    branches = []
    for s in saddles:
        lam = float(rates[s])
        t1 = horizon / lam
        ts = np.asarray(jnp.linspace(0.0, t1, samples, dtype=dtype))
        for sign in (1, -1):
            w0 = _start_on_sphere(scene, w_all[s], sign * unstable[s],
                                  np.asarray(step * scale, dtype), momentum)
            traj = simulate(scene, scene.state(omega=w0), t1, ts=ts, rtol=rtol,
                            atol=None if atol is None else atol * scale, dense=True)
            w = np.asarray(traj.ys["omega"])
            dist = np.min(np.linalg.norm(w[:, None, :] - w_all[saddles][None], axis=-1), axis=1)
            end, returned = _cut(ts, dist / scale, leave=1e-2, arrive=1e-2)
            end_saddle = int(saddles[np.argmin(np.linalg.norm(w_all[saddles] - w[end], axis=-1))])
            # Resample evenly in arc length, evaluating the dense output (so every point is an
            # integrated state, not an interpolation between samples).
            seg = np.linalg.norm(np.diff(w[: end + 1], axis=0), axis=1)
            arc = np.concatenate([[0.0], np.cumsum(seg)])
            t_even = np.interp(np.linspace(0.0, arc[-1], num), arc, ts[: end + 1])
            omega, h = _evaluate(traj, device_array(t_even, dtype))
            branches.append((omega, h, energies[s], s, sign, t_even[-1], returned,
                             end_saddle if returned else -1))

    # (Assembled by NumPy and put on the device: eager `jnp` calls compile a program each.)
    def column(i, dt, shape=()):
        values = [np.asarray(b[i]) for b in branches]
        return device_array(np.stack(values) if values else np.zeros((0, *shape)), dt)

    return Separatrices(
        omega=column(0, dtype, (num, 3)), angular_momentum=column(1, dtype, (num, 3)),
        energy=column(2, dtype), saddle=column(3, int), sign=column(4, int),
        duration=column(5, dtype), returned=column(6, bool), end_saddle=column(7, int))


# -- critical rotor momenta --------------------------------------------------------------------


def _spin_scene(inertia, axis, h):
    e = jnp.zeros(3, inertia.dtype).at[axis].set(1.0)
    return Scene(RigidBody(inertia), (Rotor(h * e),))


def _lambda_squared(inertia, axis, rate, h):
    r"""$\lambda^2$ of the spin `rate` about `axis` with a rotor `h` along it: minus the sum of the
    principal 2x2 minors of $J = \partial f/\partial\omega$.

    $J$ annihilates the spin axis (spins about it at any rate are equilibria), so its
    characteristic polynomial is $\mu(\mu^2 - \operatorname{tr}J\,\mu + c_2)$ with $c_2$ that sum;
    with $\operatorname{tr}J = 0$ the transverse pair is $\pm\sqrt{-c_2}$. Unlike the tangent
    restriction this stays smooth where the total momentum $I_K W + h$ passes through zero.
    """
    scene = _spin_scene(inertia, axis, h)
    w = jnp.zeros(3, inertia.dtype).at[axis].set(rate)
    jac = jax.jacfwd(lambda x: _rates(scene, x))(w)
    c2 = 0.5 * (jnp.trace(jac) ** 2 - jnp.trace(jac @ jac))
    return 0.25 * jnp.trace(jac) ** 2 - c2


@stored_filter_jit(light=True)  # one small problem per call (`_programs`)
def _critical_roots(inertia, axis, rate, guesses):
    size = jnp.sum(inertia) * jnp.abs(rate)  # momentum scale S |W|

    def g(x):  # dimensionless: lambda^2 / W^2 as a function of h / (S |W|)
        return _lambda_squared(inertia, axis, rate, x * size) / rate**2

    # Simple roots: Newton on lambda^2 itself. Double roots (lambda^2 touching zero, where Newton
    # on lambda^2 converges only linearly and stalls in round-off): Newton on its derivative,
    # kept where lambda^2 vanishes there. One loop for both (`turning` selects).
    def fn(x, turning):
        return jnp.where(turning, jax.grad(g)(x), g(x))

    tol = _newton_tol(inertia.dtype)
    solver = optx.Newton(rtol=tol, atol=tol)

    def newton(x0, turning):
        sol = optx.root_find(fn, solver, x0, turning, throw=False, max_steps=100)
        x = sol.value
        ok = (sol.result == optx.RESULTS.successful) & jnp.isfinite(x)
        return x * size, ok & (~turning | (jnp.abs(g(x)) < 16 * tol))

    n = guesses.shape[0]
    turning = jnp.arange(2 * n) >= n
    return jax.vmap(newton)(jnp.concatenate([guesses, guesses]), turning) + (size,)


def critical_rotor_momenta(
    inertia: Float[ArrayLike, "3"], spin_axis: int, rate: float | ArrayLike
) -> Float[Array, " k"]:
    r"""Rotor momenta at which a spin about a principal axis changes stability.

    A body with principal moments `inertia` spins at `rate` $W$ about axis $K$ = `spin_axis`,
    carrying a rotor with momentum $h$ along the same axis. Linearising the gyrostat's equations
    $I\dot\omega = (I\omega + \mathbf{h})\times\omega$ about $\omega = W\hat e_K$ gives a transverse
    pair $\pm\lambda$ whose square $\lambda^2(h)$ is computed from the scene's vector field by
    automatic differentiation; its roots, found by Newton iteration (optimistix) from a scan of
    starting guesses, are the critical momenta. Analytically,

    $$\lambda^2 = -\frac{(I_K W + h - I_i W)(I_K W + h - I_j W)}{I_i I_j},$$

    so the spin is stable where $(I_K W + h - I_i W)(I_K W + h - I_j W) > 0$, and the roots are
    $h = (I_i - I_K)W$ and $h = (I_j - I_K)W$ for the two other axes $i, j$.

    **Arguments:**

    - `inertia`: three principal moments.
    - `spin_axis`: index of the spin axis in `inertia`: 0, 1 or 2.
    - `rate`: the spin rate $W$ (nonzero, rad/s).

    **Returns:**

    The critical rotor momenta in ascending order, in the dtype of `inertia`: two values, or one
    when the two transverse moments are equal (a double root, where the spin is only marginally
    stable and stability does not change).
    """
    inertia = as_float_array("inertia", inertia, (3,))
    RigidBody(inertia)  # validates the moments (positive, triangle inequality)
    if isinstance(spin_axis, bool) or not isinstance(spin_axis, int | np.integer) or not (
        0 <= spin_axis <= 2
    ):
        raise ParameterError(f"spin_axis={spin_axis!r}: must be 0, 1 or 2 (an index into inertia)")
    dtype = inertia.dtype
    rate = as_float_array("rate", rate, (), dtype)
    if not (np.isfinite(float(rate)) and float(rate) != 0):
        raise ParameterError(f"rate={float(rate):g}: must be nonzero and finite")
    # |roots| <= max |I_i - I_K| |W| < S |W|: starting guesses on both sides of every root.
    # (Inputs prepared on the host: each eager operation would be a program of its own.)
    guesses = device_array(np.linspace(-2.0, 2.0, 21), dtype)
    axis = device_array(int(spin_axis), int)  # traced: one compilation for every axis
    # The roots are h = (I_i - I_K) W: solved for unit rate and largest moment, then scaled
    # back, so that no rate is squared at its own size (1e160 rad/s would overflow).
    big = float(np.max(np.abs(np.asarray(inertia))))
    unit = big * abs(float(rate))
    if not np.isfinite(unit):
        raise ParameterError(
            f"rate={float(rate):g}: the critical momenta (about max(inertia) x rate = "
            f"{big:g} x {abs(float(rate)):g}) overflow {jnp.dtype(dtype).name}")
    roots, ok, size = jax.device_get(_critical_roots(
        device_array(np.asarray(inertia) / np.asarray(big, dtype), dtype), axis,
        device_array(np.sign(np.asarray(rate)), dtype), guesses))
    roots, size = roots * unit, float(size) * unit
    found = np.sort(roots[ok])
    # Roots closer than this (relative to S |W|) are one root: a double root is located only to
    # about the square root of the solver tolerance.
    tol = 4 * np.sqrt(_newton_tol(dtype)) * float(size)
    clusters = np.split(found, np.flatnonzero(np.diff(found) > tol) + 1) if found.size else []
    return device_array([c.mean() for c in clusters], dtype)
