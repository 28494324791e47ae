r"""`fit`: identify a scene's parameters and initial state from sampled outputs.

The fitter only uses the scene protocol: parameters by the names of `scene.parameters()`
(changed with `scene.replace`, which does not recompile), state variables by the names of
`scene.state_shapes()`, observed outputs by the names of `scene.output_names()`, and
[`jaxdyn.simulate`][] to integrate. What is specific to a scene (a valid inertia tensor, which
parameters a rod's angle determines) is declared through parameterisation objects; nothing here
branches on the kind of scene.

Residuals are $r_k(u) = (y(t_k; u) - d_k)/\sigma$ over the samples, with $u$ the unconstrained
vector of every fitted quantity. Uncertainties are the Gauss--Newton covariance
$s^2 (J^T J)^{-1}$ at the optimum, with $s^2 = |r|^2 / (n_\mathrm{obs} - n_\mathrm{free})$,
propagated to the reported quantities with the Jacobian of their map from $u$; computed from
the singular values of $J$ (its columns scaled), never by inverting $J^T J$, whose condition
number is the square of $J$'s (see `_uncertainty`).

Choices, measured on the torque-free fit of `benchmarks/identify.py` (200 samples of three
rates, 6-9 unknowns, CPU):

- Derivatives: forward mode through the integrator (`diffrax.ForwardMode` and `jax.jacfwd`):
  one integration carrying all $n$ tangents gives the whole Jacobian in about 2-4 ms. Reverse
  mode (`RecursiveCheckpointAdjoint`) needs one backward pass per residual for the Jacobian
  (about 76 ms) and is no faster even for the gradient of the scalar loss (2.0 against 1.4 ms).
- Minimiser: Levenberg--Marquardt from optimistix parts (its damped Newton descent and
  classical trust region), stepped here so that every iteration's loss is recorded. It needs
  about 40 iterations and 0.04-0.08 s for that fit (39 iterations in `benchmarks/identify.py
  --quick`); optax's Adam (200 steps) then L-BFGS reaches the same optimum in about 420-440
  iterations and 0.7-1.3 s. Both are available (`method`).
- Continuation in the time span (`horizons`): each start is fitted to the first quarter of the
  samples, then half, then all; with it every random start reached the global optimum in our
  trials, without it about half did (oscillatory records have many local minima).
"""

import dataclasses
import functools
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from .._custom_types import State
from .._outcome import is_success
from .._programs import cancels_unused_preparations
from .._rotations import quat_conjugate, quat_multiply
from .._scene import Scene
from .._simulate import check_tolerances, simulate_unchecked
from .._stored_jit import stored_filter_jit
from .._tolerance import ScaledPIDController
from .._validation import ParameterError, device_array, format_value
from ._parameterisation import PRIOR_SD, AbstractParameterisation, Unconstrained

# Samples are padded (with zero weight) to a multiple of this, so that data sets of similar
# length share one compilation.
_BUCKET = 32


class _Problem(eqx.Module):
    """The residual function of a fit: everything static about it, plus the scene's arrays."""

    scene: Scene
    y0: State
    names: tuple[str, ...] = eqx.field(static=True)
    is_state: tuple[bool, ...] = eqx.field(static=True)
    maps: tuple[AbstractParameterisation, ...]
    sizes: tuple[int, ...] = eqx.field(static=True)
    outputs: tuple[str, ...] = eqx.field(static=True)
    kinds: tuple[str, ...] = eqx.field(static=True)  # per output: "value" or "rotation"
    sigma: tuple[Array, ...]
    rtol: Array
    atol: Array
    max_steps: int = eqx.field(static=True)
    dtype: Any = eqx.field(static=True)

    def split(self, u: Float[Array, " n"]) -> list[Array]:
        """The parts of `u` of each fitted quantity, in the dtype of the data."""
        u = u.astype(self.dtype) if jnp.issubdtype(u.dtype, jnp.floating) else u
        offsets = np.cumsum((0,) + self.sizes)
        return [u[a:b] for a, b in zip(offsets[:-1], offsets[1:])]

    def values(self, u: Float[Array, " n"]) -> dict[str, Array]:
        return {name: m(part) for name, m, part in zip(self.names, self.maps, self.split(u))}

    def scene_and_state(self, u: Float[Array, " n"], values=None) -> tuple[Scene, State]:
        """The scene and initial state at `u` (`values`: `self.values(u)`, if already made)."""
        values = self.values(u) if values is None else values
        params = {n: v for n, v, s in zip(self.names, values.values(), self.is_state)
                  if not s and not n.startswith(_BIAS)}
        y0 = dict(self.y0)
        y0.update({n: v for n, v, s in zip(self.names, values.values(), self.is_state) if s})
        scene = self.scene.replace(params) if params else self.scene
        return scene, y0

    def simulate(self, scene: Scene, y0: State, ts: Float[Array, " N"]):
        """Outputs and states of `scene` from `y0` at the times `ts` (from `ts[0]`), and
        whether the integration succeeded."""
        traj = simulate_unchecked(
            scene, y0, ts[-1], t0=ts[0], ts=ts,
            # A controller built here, so that the tolerances are arrays (no recompilation).
            stepsize_controller=ScaledPIDController(rtol=self.rtol, atol=self.atol),
            max_steps=self.max_steps, adjoint=dfx.ForwardMode(), events=False,
        )
        return jax.vmap(scene.outputs)(traj.ts, traj.ys), traj.ys, is_success(traj.outcome)

    def predict(self, u: Float[Array, " n"], ts: Float[Array, " N"],
                values=None) -> dict[str, Array]:
        scene, y0 = self.scene_and_state(u, values)
        out, _, ok = self.simulate(scene, y0, ts)
        # A failed integration (a trial point too wild to integrate) gives NaN residuals: the
        # optimiser rejects the point, and a fit that ends there reports not converging. No
        # runtime check rides in the program, so JAX's persistent cache can keep it.
        return {name: jnp.where(ok, out[name], jnp.nan) for name in self.outputs}

    def output_residuals(self, values, pred, data, weights) -> list[Array]:
        """Weighted residuals of each output (flat), from the predicted outputs `pred`."""
        parts = []
        for name, kind, sigma in zip(self.outputs, self.kinds, self.sigma):
            p = pred[name]
            if _BIAS + name in values:  # a sensor's constant bias: it reads output + bias
                p = p + values[_BIAS + name]
            if kind == "rotation":
                r = _rotation_error(p, data[name]) / sigma
            else:
                r = (p - data[name]) / sigma
            r = r.reshape(r.shape[0], -1) * jnp.sqrt(weights)[:, None]
            parts.append(r.ravel())
        return parts

    def residuals(self, u, ts, data, weights) -> Float[Array, " m"]:
        """Weighted residuals, in the dtype of `u` (the optimiser's), whatever the dtype of the
        simulation (the data's)."""
        values = self.values(u)  # once: the scene, the initial state and the sensor biases
        pred = self.predict(u, ts, values)
        return jnp.concatenate(self.output_residuals(values, pred, data, weights)).astype(u.dtype)


_BIAS = "bias."  # fitted sensor biases are named "bias.<output>"
_MIN_DRAWS_PER_CHAIN = 4  # the split R-hat and effective sample size need two per half


def _rotation_error(q, q_measured):
    """The rotation from each measured attitude to the predicted one, as the rotation vector
    `2 sign(dq_0) dq_vec` of `dq = q_measured^* (x) q` (rad; small-angle; `q` and `-q` are the
    same attitude, so a measured quaternion's sign does not matter)."""
    dq = jax.vmap(quat_multiply)(jax.vmap(quat_conjugate)(q_measured), q)
    sign = jnp.where(dq[:, :1] < 0, -1.0, 1.0).astype(dq.dtype)
    return 2 * sign * dq[:, 1:]


def _width(kind: str, shape) -> int:
    """Residuals per sample of an output of this kind and sample shape."""
    return 3 if kind == "rotation" else int(np.prod(shape))


# -- progress ---------------------------------------------------------------------------------

_BAR: dict[str, Any] = {}


def _tick(loss) -> None:
    bar = _BAR.get("bar")
    if bar is not None:
        bar.update(1)
        bar.set_postfix_str(f"loss {float(loss):.4g}", refresh=False)


def _reports_progress(kwargs) -> bool:
    """Whether a program reports its progress (a host callback: such programs are not
    stored, see `_stored_jit`)."""
    return bool(kwargs.get("progress"))


def _report_progress(progress: bool, loss) -> None:
    if progress:
        jax.debug.callback(_tick, loss)


# -- compiled pieces ----------------------------------------------------------------------------


def _loss(problem, u, ts, data, weights):
    r = problem.residuals(u, ts, data, weights)
    return 0.5 * jnp.sum(r**2)


def _jacobian_and_value(f, u):
    """`(df/du, f(u))` from one forward-mode pass (the value is the primal of that pass)."""

    def twice(u):
        r = f(u)
        return r, r

    return jax.jacfwd(twice, has_aux=True)(u)


@stored_filter_jit
def _jacobian(problem, u, ts, data, weights):
    """Residuals and their Jacobian (forward mode through the integrator)."""
    J, r = _jacobian_and_value(lambda u: problem.residuals(u, ts, data, weights), u)
    return r, J


@stored_filter_jit(unless=_reports_progress)
def _adam(problem, u0, free, ts, data, weights, learning_rate, *, steps, progress):
    """`steps` Adam steps; returns the last iterate and the loss before each step."""
    import optax  # (imported where used: 50 ms of every `jaxdyn fit` that uses neither)

    opt = optax.adam(learning_rate)
    _, value_and_grad = _forward_value_and_grad(problem, u0, free, ts, data, weights)

    def step(carry, _):
        u, state = carry
        loss, grad = value_and_grad(u)
        updates, state = opt.update(grad, state, u)
        _report_progress(progress, loss)
        return (optax.apply_updates(u, updates), state), loss

    (u, _), losses = jax.lax.scan(step, (u0, opt.init(u0)), None, length=steps)
    return u, losses


def _forward_value_and_grad(problem, u_fixed, free, ts, data, weights):
    """Loss and gradient, the gradient by forward mode (`jacfwd`), frozen components masked."""

    def loss(u):
        return _loss(problem, jnp.where(free, u, u_fixed), ts, data, weights)

    def value_and_grad(u):
        grad, value = _jacobian_and_value(loss, u)  # (one integration, not two)
        return value, grad

    return loss, value_and_grad


def _small_decrease(previous, loss, tol):
    """An accepted step lowered the loss by less than `tol` (relative); rejected steps, which
    leave the loss unchanged, do not count."""
    return (loss < previous) & (previous - loss <= tol * loss)


def _silent(**kwargs) -> None:
    pass


def _silent_tick(loss) -> None:
    pass


def _multiple_shooting(problem, setup, count, clock):
    """The multiple-shooting driver of this problem over `count` segments (`clock`: the
    natural time at each sample, see `_natural_clock`), or `None` where it does not apply
    (then the fit is by single shooting)."""
    from ._shooting import Shooting, cut, layout

    found = layout(problem, problem.scene)
    if found is None:
        return None
    seg = cut(setup.ts, setup.obs, count)
    if seg.weights.shape[0] < 3:
        return None
    shooting = Shooting(problem, *found, seg, setup.n_obs)
    ts = setup.ts
    shooting.prefix = (_time_at(clock, ts, 4 * _TURNS) - float(ts[0]) if clock[-1] > 0
                       else float(ts[-1] - ts[0]) / 4)
    return shooting


class _LevenbergMarquardt(optx.AbstractGaussNewton):
    """Levenberg--Marquardt assembled from optimistix parts, as optimistix documents for
    custom solvers: the damped Newton descent of `optimistix.LevenbergMarquardt` with a
    trust region that grows faster (x4 when the model predicts at least half of the
    reduction, instead of x3.5 at 99 %). On the fits of `benchmarks/identify.py` this takes
    about 40 % fewer iterations than the default."""

    rtol: float
    atol: float
    norm: Callable = optx.max_norm
    descent: optx.DampedNewtonDescent = optx.DampedNewtonDescent()
    search: optx.ClassicalTrustRegion = optx.ClassicalTrustRegion(
        high_cutoff=0.5, low_cutoff=0.01, high_constant=4.0, low_constant=0.25
    )
    verbose: Callable = _silent


def _with_forward_jacobian(residuals):
    """`residuals` with a JVP rule that builds the whole Jacobian in one forward-mode pass
    (`jacfwd`: one integration carrying all tangents) and then applies it. optimistix
    linearises the residuals and materialises the Jacobian from one JVP per column; through
    this rule the integration runs once per iteration, not once per column."""

    @jax.custom_jvp
    def f(v):
        return residuals(v)

    @f.defjvp
    def f_jvp(primals, tangents):
        (v,), (t,) = primals, tangents
        J, r = _jacobian_and_value(residuals, v)
        return r, J @ t

    return f


# Forward-mode linearisation (the residuals carry a forward-mode Jacobian rule).
_OPTIONS = {"jac": "fwd"}


@stored_filter_jit(unless=_reports_progress)
def _levenberg_marquardt(problem, u0, free, ts, data, weights, tol, exact, *, max_iter,
                         progress):
    """Levenberg--Marquardt (optimistix), stepped here so that the loss of every iteration is
    recorded. Converged when optimistix's Cauchy criterion holds (successive accepted iterates
    differ by less than `tol (1 + |u|)` and so do the residuals), when an accepted step
    lowered the loss by less than `tol` (relative), or when the fit is exact to `exact`: the
    RMS of the residuals, which are in units of the data's own size, below `exact` (0: not
    used). Single shooting passes its early stages' tolerance: an early stage has only to
    reach the basin of the next, and without this a noise-free record whose body is a flat
    plate ran every stage of its continuation into `max_iter` (the shape logits crawl towards
    the plate, which lies at infinity, while the loss keeps falling by a constant factor).
    The final stage does not use it: with a tolerance near the data's precision (float32's
    1e-5) it would stop before the estimate is as good as its reported interval; instead a
    final stage that runs out of iterations with residuals below `tol` (and the integration's
    `rtol`) counts as converged (`fit`)."""

    residuals = _with_forward_jacobian(
        lambda v: problem.residuals(jnp.where(free, v, u0), ts, data, weights)
    )

    def fn(v, args):
        r = residuals(v)
        return r, 0.5 * jnp.sum(r**2)

    solver = _LevenbergMarquardt(rtol=tol, atol=tol)
    tags = frozenset()
    f_struct, aux_struct = jax.eval_shape(lambda: fn(u0, None))
    state = solver.init(fn, u0, None, _OPTIONS, f_struct, aux_struct, tags)
    dynamic, static = eqx.partition(state, eqx.is_array)
    history = jnp.full(max_iter, jnp.nan, u0.dtype)
    inf = jnp.asarray(jnp.inf, u0.dtype)
    # The residuals that count (those of samples of positive weight) and the loss of a fit
    # exact to `exact`.
    n_counted = (jnp.sum(weights > 0) * (f_struct.size // weights.size)).astype(u0.dtype)
    exact_loss = 0.5 * n_counted * jnp.asarray(exact, u0.dtype) ** 2

    def cond(carry):
        _, _, k, done, failed, _ = carry
        return ~done & ~failed & (k < max_iter)

    def body(carry):
        u, dynamic, k, _, _, history = carry
        state = eqx.combine(static, dynamic)
        u, state, loss = solver.step(fn, u, None, _OPTIONS, state, tags)
        done, result = solver.terminate(fn, u, None, _OPTIONS, state, tags)
        previous = jnp.where(k > 0, history[jnp.maximum(k - 1, 0)], inf)
        done = done | _small_decrease(previous, loss, tol) | (loss < exact_loss)
        failed = (result != optx.RESULTS.successful) | ~jnp.isfinite(loss)
        _report_progress(progress, loss)
        dynamic = eqx.filter(state, eqx.is_array)
        return u, dynamic, k + 1, done, failed, history.at[k].set(loss)

    carry = (u0, dynamic, jnp.asarray(0), jnp.asarray(False), jnp.asarray(False), history)
    u, dynamic, k, done, failed, history = jax.lax.while_loop(cond, body, carry)
    # The residuals and Jacobian at `u`, the last accepted iterate: optimistix keeps them in
    # its state (the first step is always accepted, so they are those of `u0` after one
    # step). Returned, and the loss taken from them, so that the integration is compiled
    # once here, and in no second program (`_jacobian`: a third of a fit's compilation).
    # The columns of the fixed components are zero.
    info = eqx.combine(static, dynamic).f_info
    loss = 0.5 * jnp.sum(info.residual**2)
    return u, loss, k, done & ~failed, history, info.residual, info.jac.as_matrix()


@stored_filter_jit(unless=_reports_progress)
def _lbfgs(problem, u0, free, ts, data, weights, tol, exact, *, max_iter, progress):
    """L-BFGS (optax, zoom line search). Converged when the largest gradient component is
    below `tol`, or a step lowered the loss by less than `tol` (relative). (`exact`: unused,
    see `_levenberg_marquardt`.)"""
    import optax

    plain, value_and_grad = _forward_value_and_grad(problem, u0, free, ts, data, weights)

    # optax's line search differentiates the loss in reverse mode; answer with the
    # forward-mode gradient (no reverse pass through the integrator).
    @jax.custom_vjp
    def loss(u):
        return plain(u)

    def loss_fwd(u):
        value, grad = value_and_grad(u)
        return value, grad

    def loss_bwd(grad, cotangent):
        return (cotangent * grad,)

    loss.defvjp(loss_fwd, loss_bwd)
    opt = optax.lbfgs()
    from_state = optax.value_and_grad_from_state(loss)
    history = jnp.full(max_iter, jnp.nan, u0.dtype)

    def cond(carry):
        _, _, k, done, _ = carry
        return ~done & (k < max_iter)

    def body(carry):
        u, state, k, _, history = carry
        value, grad = from_state(u, state=state)
        updates, state = opt.update(grad, state, u, value=value, grad=grad, value_fn=loss)
        u = optax.apply_updates(u, updates)
        small_grad = jnp.max(jnp.abs(grad)) <= tol
        previous = jnp.where(k > 0, history[jnp.maximum(k - 1, 0)], jnp.inf)
        done = small_grad | _small_decrease(previous, value, tol) | ~jnp.isfinite(value)
        _report_progress(progress, value)
        return u, state, k + 1, done, history.at[k].set(value)

    carry = (u0, opt.init(u0), jnp.asarray(0), jnp.asarray(False), history)
    u, _, k, done, history = jax.lax.while_loop(cond, body, carry)
    loss_value = _loss(problem, u, ts, data, weights)
    # (No Jacobian at hand: `_jacobian` computes it where it is needed.)
    return u, loss_value, k, done & jnp.isfinite(loss_value), history, None, None


def _summaries(problem, u, free):
    out = {}
    for name, m, part, f in zip(problem.names, problem.maps, problem.split(u),
                                problem.split(free)):
        out.update(m.summary(name, part, f))
    return out


@stored_filter_jit
def _summaries_and_derivatives(problem, u, free):
    """The reported summaries at `u` and their derivatives with respect to `u`."""
    G, values = _jacobian_and_value(lambda u: _summaries(problem, u, free), u)
    return values, G


def _covariances(R, free, s2):
    """The Gauss--Newton covariance `s2 (R^T R)^+` of the free components from a square root
    `R` of the normal matrix (zero rows and columns for the others), by the singular value
    decomposition of `R` with its free columns scaled to unit norm (see `_uncertainty`);
    the sampler's covariance, which gives the directions the data do not determine at all
    the prior's spread; the components those directions involve; and the decomposition
    `(W, d, norms, sv, vt, resolved)` (`W`'s rows: the directions over their singular
    values; `d`: the columns' scales, `norms` their norms)."""
    dtype = np.result_type(np.asarray(R), np.asarray(s2))
    eps = np.finfo(dtype).eps
    s2 = np.asarray(s2, dtype)
    R = np.where(free[None, :], np.asarray(R, dtype), 0.0).astype(dtype)
    norms = np.sqrt(np.sum(R**2, axis=0))
    d = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 0.0).astype(dtype)
    _, sv, vt = np.linalg.svd(R * d[None, :], full_matrices=False)
    resolved = sv > R.shape[1] * eps * sv[0]
    inv_sv = np.where(resolved, 1.0 / np.where(resolved, sv, 1.0), 0.0).astype(dtype)
    W = (vt * inv_sv[:, None]) * d[None, :]  # rows: directions of u over their singular values
    cov = s2 * (W.T @ W)
    # The directions of `u` the data do not determine at all (unit rows; zero for the others
    # and for fixed components): their components' covariance is undetermined (`_uncertainty`
    # reports it as nan), and the sampler's covariance (its mass matrix and the spread of its
    # starting points) gives them the prior's spread: with the pseudo-inverse's zero variance
    # there, the chains started together along such a direction and hardly moved (a rod's
    # length and g both fitted: the draws of log length spread 0.001 where the posterior
    # spreads about 7, the prior's).
    null = np.where(resolved[:, None], 0.0, vt * d[None, :]).astype(dtype)
    size = np.sqrt(np.sum(null**2, axis=1, keepdims=True))
    null = np.where(size > 0, null / np.where(size > 0, size, 1.0), 0.0).astype(dtype)
    involved = np.any(np.abs(null) > np.sqrt(eps), axis=0)
    sampling_cov = cov + dtype.type(PRIOR_SD**2) * (null.T @ null)
    return cov, sampling_cov, involved, (W, d, norms, sv, vt, resolved)


def _sampling_covariance(sampled, w, *, fitted, R, free, ts, data, weights, s2,
                         prepare=False):
    """The posterior sampler's covariance (`_covariances`) of its coordinates `w` (of the
    problem `sampled`, the fit's `fitted` with each parameterisation's `sampling` one): from
    the fit's square root `R` of the normal matrix where those are the fit's own
    coordinates, else from the residuals' Jacobian at `w` (compiled once per problem
    structure, like the fit's). `prepare`: only have that Jacobian's program made ready on
    another core (`StoredProgram.prepare`)."""
    if all(s is m for s, m in zip(sampled.maps, fitted.maps)):
        return None if prepare else _covariances(R, free, s2)[1]
    if prepare:
        return _jacobian.prepare(sampled, w, ts, data, weights)
    _, J = _jacobian(sampled, w, ts, data, weights)
    J = np.asarray(J)
    if not np.all(np.isfinite(J)):
        raise RuntimeError(
            "posterior: the residuals' derivatives over the whole record are not finite "
            "numbers at the optimum (the sampler integrates the record in one piece, and "
            "their sensitivities overflowed, as on a long record of an unstable motion): "
            "the posterior cannot be sampled here; fit a shorter record, or use the "
            "Gauss-Newton intervals (fit without posterior=)")
    return _covariances(np.linalg.qr(J, mode="r"), free, s2)[1]


def _uncertainty(problem, u, free, R, rss, n_obs):
    """Gauss--Newton covariance of `u` and the 1-sigma intervals of the reported summaries,
    from a square root `R` of the normal matrix (`R^T R = J^T J`: the triangle of `J`'s QR
    decomposition, or `_root(H)`) and the residual sum of squares `rss` at the optimum `u`
    (both from the whole record, however they were accumulated).

    Everything comes from the singular value decomposition of `R` with its free columns
    scaled to unit norm, never from inverting `J^T J`: that squares the condition number,
    and where the shape logits of a near-flat plate run off towards infinity (the scaled
    condition number of the noise-free 1 : 2 : 3 plate's `J` is about 3e10, of `J^T J` 1e21)
    the inverse of `J^T J` is round-off: its variances came out negative and the intervals
    zero. A variance is a sum of squares here, so it cannot be negative; a
    direction whose singular value is zero to working precision is left out of the
    covariance (a pseudo-inverse), and a quantity that depends on it has no interval.

    Only the summaries and their derivatives are compiled (`_summaries_and_derivatives`);
    the linear algebra, on matrices of the size of `u`, is NumPy's on the host (LAPACK, as
    XLA:CPU's): a compiled program of it took about 1 s to compile in every new process."""
    values, G = _summaries_and_derivatives(problem, u, free)
    dtype = np.dtype(u.dtype)
    eps = np.finfo(dtype).eps
    free = np.asarray(free)
    dof = dtype.type(max(int(n_obs) - int(np.sum(free)), 1))
    s2 = np.asarray(rss, dtype) / dof
    cov, _, involved, (W, d, norms, sv, vt, resolved) = _covariances(R, free, s2)
    cov = np.where(involved[:, None] | involved[None, :], np.nan, cov).astype(dtype)
    std = {}
    for key, g in G.items():
        g = np.asarray(g, dtype).reshape(-1, u.shape[0])
        var = s2 * np.sum((g @ W.T) ** 2, axis=1)
        scale = np.max(np.abs(g * d[None, :]), axis=1, keepdims=True)
        # A quantity that depends on a component kept fixed (or free but with a zero column:
        # multiple shooting's normal matrix of a near-flat plate has such rows), or on a
        # direction the data do not determine at all (a zero singular value), has no interval.
        on_fixed = np.max(np.abs(np.where(free & (norms > 0), 0.0, g)), axis=1)
        on_null = np.max(np.where(resolved, 0.0, np.abs((g * d[None, :]) @ vt.T)), axis=1)
        undetermined = ((on_fixed > np.sqrt(eps) * np.max(np.abs(g)))
                        | (on_null > np.sqrt(eps) * scale[:, 0]))
        sd = np.where(undetermined, np.nan, np.sqrt(var))
        std[key] = jax.device_put(sd.reshape(values[key].shape).astype(values[key].dtype))
    # `sv` and `vt`: the conditioning of the free columns scaled to unit norm (a tiny singular
    # value is a combination of components that the data do not determine).
    # (Put on the device from NumPy: `jnp.asarray` compiles a program per shape.)
    return jax.device_put(cov), values, std, jax.device_put(s2), sv, vt


@stored_filter_jit
def _root(H):
    """A square root `R` of a normal matrix (`R^T R = H`), for `_uncertainty` where only `H`
    is at hand (multiple shooting condenses its normal matrix): from the eigenvalues of `H`
    with its columns scaled to unit diagonal. An eigenvalue is known only to about `eps`
    times the largest (`H` squares the condition number): those below `n eps` of it are
    round-off, and set to zero (so a quantity that depends on them has no interval)."""
    norms = jnp.sqrt(jnp.maximum(jnp.diag(H), 0.0))
    d = jnp.where(norms > 0, 1.0 / jnp.where(norms > 0, norms, 1.0), 0.0)
    lam, vecs = jnp.linalg.eigh(d[:, None] * H * d[None, :])
    lam = jnp.where(lam > H.shape[0] * jnp.finfo(H.dtype).eps * jnp.max(lam), lam, 0.0)
    return (jnp.sqrt(lam)[:, None] * vecs.T) * norms[None, :]


# -- public API -----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class FitResult:
    """The result of [`jaxdyn.fit`][].

    **Fields:**

    - `values`: fitted values by name: every fitted parameter and initial-state variable, and
      the quantities their parameterisations report (for [`jaxdyn.ValidInertia`][]:
      `"<name>.principal_moments"` (ascending; normalised so that the largest is 1 when the
      scale is not identifiable) and `"<name>.principal_axes"` (columns)).
    - `std`: 1-sigma intervals of `values` (Gauss--Newton), same keys; `nan` for a quantity
      that depends on a component the data do not determine.
    - `identifiable`: for each unconstrained component, whether the data determine it (a
      component whose Jacobian column is zero is kept at its starting value).
    - `notes`: one line per component or combination that the data do not determine.
    - `scene`, `y0`: the fitted scene and initial state.
    - `u`, `components`, `covariance`: the unconstrained optimum, the names of its components
      and their covariance (`nan` in the rows and columns of components along a direction
      the data do not determine at all).
    - `loss`: `0.5 |r|^2` at the optimum; `residual_rms`: RMS residual (in units of the data,
      divided by `sigma` if given); `residual_rms_by_output`: RMS residual of each output, in
      its own units; `noise_variance`: the residual variance `s^2` (of the residuals divided
      by `sigma`).
    - `converged`: the best start's optimiser converged and its residuals are consistent
      with a fit at the optimum (white noise: see `systematic`); `optimiser_converged`: the
      optimiser's own criterion alone; `iterations`: of the best start; `history`: its loss
      at every iteration (Adam steps, then the polishing method's over each horizon),
      `stages`: the iterations at which each stage (Adam, then each horizon) begins;
      `restart_losses`: the final loss of every start that was run.
    - `segments`: the number of segments of the fit (multiple shooting), 1 for single
      shooting.
    - `residual_autocorrelation`: lag-1 autocorrelation of the residuals of each channel
      of each output (about `N(0, 1/N)` for white noise over `N` samples); `systematic`:
      the channels (`"omega[0]"`) whose residuals are far from white (above `4.5 /
      sqrt(N)`) and above the integration's error floor: a local minimum or a model that
      lacks an effect (a sensor bias, a torque), said in `notes`; such a fit does not
      report `converged`.
    - `posterior`: with `fit(posterior=n)`, `n` posterior draws of each quantity of `values`
      (NUTS; shape `(n, *shape)`, the chains one after the other), else `None`;
      `posterior_acceptance`: NUTS's mean acceptance rate; `posterior_leapfrogs`: its mean
      number of leapfrog steps per draw (each costs one forward-mode gradient through the
      integrator); `posterior_diagnostics`: by chain `"acceptance"`, `"divergences"`,
      `"leapfrogs"`, `"max_depth_draws"` (draws whose trajectory reached NUTS's bound of
      1023 leapfrog steps: `fit` warns where they are more than a tenth of a chain's) and
      `"bfmi"` (energy fraction of missing information; below about 0.3 a chain explores
      poorly), and by sampled component (the sampling coordinates, for
      [`jaxdyn.ValidInertia`][] the linear coordinates of the shape) the split `"rhat"`
      (the chains agree when it is below about 1.05: `fit` warns otherwise) and `"ess"`
      (effective sample size), with `"max_rhat"`, `"min_ess"`, `"chains"`,
      `"draws_per_chain"`, and `"restarted"`: the chains that accepted almost none of their
      proposals (mean acceptance below 0.3) and were run again once from the optimum with
      another key (their first run discarded; a chain stuck again is kept and warned
      about).
    """

    values: dict[str, Array]
    std: dict[str, Array]
    identifiable: dict[str, bool]
    notes: tuple[str, ...]
    scene: Scene
    y0: State
    u: Array
    components: tuple[str, ...]
    covariance: Array
    loss: float
    residual_rms: float
    residual_rms_by_output: dict[str, float]
    noise_variance: float
    converged: bool
    iterations: int
    history: np.ndarray
    stages: tuple[int, ...]
    restart_losses: np.ndarray
    segments: int = 1
    optimiser_converged: bool = True
    residual_autocorrelation: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    systematic: tuple[str, ...] = ()
    posterior: dict[str, np.ndarray] | None = None
    posterior_acceptance: float | None = None
    posterior_leapfrogs: float | None = None
    posterior_diagnostics: dict[str, Any] | None = None


def _blocks(r, sizes):
    """The last axis of a residual vector `r` cut into each output's `(count, width)` block
    (`sizes`: name -> (count, width), in the residual vector's order)."""
    out, start = {}, 0
    for name, (count, width) in sizes.items():
        out[name] = r[..., start:start + count * width].reshape(*r.shape[:-1], count, width)
        start += count * width
    return out


def _series_by_output(r, obs, padded, kinds):
    """The residuals of each output `(N, width)` (sample by sample, padding dropped), from
    the whole residual vector `r` of single shooting."""
    sizes = {name: (padded, _width(kind, d.shape[1:])) for (name, d), kind in
             zip(obs.items(), kinds)}
    return {name: b[:obs[name].shape[0]] for name, b in _blocks(r, sizes).items()}


# Residuals of a fit at the optimum are white noise where the model holds (their lag-1
# autocorrelation is about N(0, 1/N) over N samples); a local minimum or a model that lacks an
# effect leaves a smooth misfit, autocorrelated (near 1 where it dominates the noise). A
# channel is flagged when its lag-1 autocorrelation exceeds `_WHITE_Z / sqrt(N)` (a 4.5-sigma
# excursion of the null distribution: false alarms about 3e-6 per channel) and its RMS
# residual exceeds `_MATERIAL` times the integration's `rtol` times the output's size (the
# floor of a noise-free record, whose residuals are the smooth integration error).
_WHITE_Z = 4.5
_MATERIAL = 1e3


def _whiteness(series) -> dict[str, np.ndarray]:
    """Lag-1 autocorrelation of each channel of each output's residuals (`sum r_k r_{k+1} /
    sum r_k^2`; 1 minus half the Durbin--Watson statistic)."""
    out = {}
    for name, r in series.items():
        r = np.asarray(r, float)
        num = np.sum(r[1:] * r[:-1], axis=0)
        den = np.sum(r * r, axis=0)
        out[name] = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return out


def _data_scale(d, kind) -> float:
    """The size of an output's data: 1 rad for an attitude (its residuals are rotation
    angles), else the RMS of its values."""
    if kind == "rotation":
        return 1.0
    size = float(np.sqrt(np.mean(np.square(d))))
    return size if np.isfinite(size) else 0.0


def _systematic(whiteness, series, obs, sigmas, kinds, floors) -> list[str]:
    """Channels (`"omega[0]"`) whose residuals are not white noise (see `_WHITE_Z`)."""
    flagged = []
    for (name, d), sigma, kind in zip(obs.items(), sigmas, kinds):
        r = np.asarray(series[name], float)
        n = r.shape[0]
        limit = _WHITE_Z / np.sqrt(max(n, 1))
        rms = np.sqrt(np.mean(r * r, axis=0)) * np.max(np.asarray(sigma))  # in data units
        for i, (rho, size) in enumerate(zip(whiteness[name], rms)):
            if rho > limit and size > floors[name]:
                flagged.append(f"{name}[{i}]" if r.shape[1] > 1 else name)
    return flagged


def _systematic_note(flagged, whiteness, n_samples) -> str:
    worst = max(float(np.max(v)) for v in whiteness.values())
    return (f"the residuals of {', '.join(flagged)} are not white noise (lag-1 "
            f"autocorrelation up to {worst:.2f}, against at most "
            f"{_WHITE_Z / np.sqrt(n_samples):.2g} for white noise over {n_samples} samples): "
            "a local minimum or a model that lacks an effect (a sensor bias, a torque); "
            "not reported as converged. Try more restarts, other segments, or --bias")


def _rms_by_output(sums, obs, sigmas, kinds):
    """RMS residual of each output in its own units, from its sum of squares."""
    return {name: float(np.sqrt(sums[name] / (d.shape[0] * _width(kind, d.shape[1:])))
                        * np.max(np.asarray(sigma)))
            for (name, d), sigma, kind in zip(obs.items(), sigmas, kinds)}


def _as_key(key):
    """`key` checked: a JAX PRNG key, or an integer seed (`None`: 0), kept as a Python `int`
    until a key is needed (`_key`: `jax.random.PRNGKey` is two compiled programs, which a fit
    that needs no random numbers does not load)."""
    if key is None:
        key = 0
    if isinstance(key, int | np.integer) and not isinstance(key, bool):
        if not -(2**63) <= int(key) < 2**63:
            raise ParameterError(f"key={int(key)}: a seed must be a 64-bit integer")
        return int(key)
    if isinstance(key, jax.Array | np.ndarray):
        if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
            if key.shape == ():
                return key
        elif key.dtype == np.uint32 and key.shape == jax.eval_shape(
                jax.random.PRNGKey, 0).shape:  # (a raw key of the default implementation)
            return key
    shown = (f"an array of shape {key.shape} and dtype {key.dtype}"
             if isinstance(key, jax.Array | np.ndarray) else format_value(key))
    raise ParameterError(f"key={shown}: expected an integer seed or one JAX PRNG key "
                         "(jax.random.key(0) or jax.random.PRNGKey(0))")


def _key(key):
    """A JAX key of `_as_key`'s value."""
    return jax.random.PRNGKey(key) if isinstance(key, int) else key


def _dtype(ts, data):
    """float32 if the times and every data array are float32; else the default float type."""
    arrays = [ts, *data.values()]
    if all(getattr(a, "dtype", None) == np.float32 for a in arrays):
        return jnp.dtype(jnp.float32)
    return jnp.dtype(jnp.result_type(float))


def _check_names(kind: str, names, allowed) -> None:
    unknown = [n for n in names if n not in allowed]
    if unknown:
        raise ParameterError(
            f"{kind}={unknown}: not in this scene; allowed are {sorted(allowed)}"
        )


_SHAPES: dict[Any, dict[str, tuple[int, ...]]] = {}


def _output_shapes(scene, dtype) -> dict[str, tuple[int, ...]]:
    """Names and shapes of the scene's outputs (traced once per scene structure)."""
    leaves, treedef = jax.tree_util.tree_flatten(scene)
    key = (treedef, tuple(jnp.shape(x) for x in leaves), jnp.dtype(dtype))
    if key not in _SHAPES:
        state = {k: jax.ShapeDtypeStruct(shape, dtype)
                 for k, shape in scene.state_shapes().items()}
        shapes = jax.eval_shape(scene.outputs, jax.ShapeDtypeStruct((), dtype), state)
        _SHAPES[key] = {k: tuple(v.shape) for k, v in shapes.items()}
    return _SHAPES[key]


def _prepare_data(shapes, ts, data, outputs, dtype):
    ts = np.asarray(ts)
    if ts.dtype.kind not in "iuf" or ts.ndim != 1:
        raise ParameterError(f"ts has shape {ts.shape}: expected a 1-D array of times")
    if not np.all(np.isfinite(ts)):
        raise ParameterError(f"ts={format_value(ts)}: times must be finite")
    if ts.size < 3:
        raise ParameterError(f"ts has {ts.size} samples: at least 3 are needed")
    if np.any(np.diff(ts) <= 0):
        i = int(np.argmax(np.diff(ts) <= 0))
        raise ParameterError(
            f"ts[{i + 1}]={ts[i + 1]:g}: times must be strictly increasing "
            f"(the previous time is {ts[i]:g})"
        )
    out = {}
    for name in outputs:
        arr = np.asarray(data[name])
        if arr.dtype.kind not in "iuf":
            raise ParameterError(f"data[{name!r}]: expected real numbers, got {arr.dtype}")
        expected = (ts.size,) + shapes[name]
        if arr.shape != expected:
            raise ParameterError(
                f"data[{name!r}] has shape {arr.shape}: expected {expected} "
                f"({ts.size} samples of the output {name!r})"
            )
        if not np.all(np.isfinite(arr)):
            raise ParameterError(f"data[{name!r}]: values must be finite")
        out[name] = arr.astype(dtype)
    return ts.astype(dtype), out


def _pad(ts, data, bucket=_BUCKET):
    """Pad to a multiple of `bucket` samples by repeating the last one with zero weight."""
    n = ts.size
    size = max(bucket, int(math.ceil(n / bucket)) * bucket)
    weights = np.zeros(size, ts.dtype)
    weights[:n] = 1
    ts_p = np.concatenate([ts, np.full(size - n, ts[-1], ts.dtype)])
    data_p = {k: np.concatenate([v, np.repeat(v[-1:], size - n, axis=0)]) for k, v in data.items()}
    return ts_p, data_p, weights


@stored_filter_jit
def _starting_point(maps, starting, names):
    return jnp.concatenate([jnp.ravel(m.to_unconstrained(starting[n]))
                            for n, m in zip(names, maps)]).astype(jnp.result_type(float))


def _restart_point(problem, u0, free, key):
    """One random starting point (each parameterisation's `restart`)."""
    keys = jax.random.split(key, len(problem.maps))
    u = jnp.concatenate([m.restart(k, part) for m, k, part in
                         zip(problem.maps, keys, problem.split(u0))]).astype(u0.dtype)
    return jnp.where(free, u, u0)


def _draw_restarts(problem, u0, free, key, *, count):
    """`count` random starting points, drawn eagerly one by one (for a `restart` that cannot
    be traced)."""
    return jnp.stack([_restart_point(problem, u0, free, k)
                      for k in jax.random.split(key, count)])


@stored_filter_jit
def _restart_points(problem, u0, free, key, *, count):
    """`count` random starting points, `_draw_restarts`'s (to round-off), in one program (drawn
    eagerly, they are about 30 operations, each lowered and looked up in the compilation cache
    on every run: 0.1-0.2 s of a warm `jaxdyn fit`), mapped over the keys (unrolled over
    them, the program's random-number code grows with `count`: 290 kB, 0.3 s to load from the
    cache)."""
    return jax.vmap(lambda k: _restart_point(problem, u0, free, k))(
        jax.random.split(key, count))


_UNTRACEABLE = (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError,
                jax.errors.TracerIntegerConversionError)


@stored_filter_jit
def _scene_and_state(problem, u):
    return problem.scene_and_state(u)


@dataclasses.dataclass(frozen=True)
class _Setup:
    problem: _Problem
    u0: Array
    components: tuple[str, ...]
    ts: np.ndarray
    obs: dict[str, np.ndarray]
    ts_p: Array
    obs_p: dict[str, Array]
    weights: Array
    n_obs: int
    dtype: Any
    scale: float  # residuals are divided by it (see `_setup`)


def _setup(scene, ts, data, parameters, initial, y0, sigma, rtol, atol, max_steps,
           bias=()) -> _Setup:
    """Check the inputs and build the residual function, the starting point and padded data."""
    if not isinstance(scene, Scene):
        raise ParameterError(f"scene={scene!r}: expected a jaxdyn.Scene")
    if not isinstance(parameters, Mapping):
        raise ParameterError("parameters: expected a mapping of names to parameterisations")
    if not isinstance(initial, Mapping):
        initial = {name: Unconstrained() for name in initial}
    if not isinstance(bias, Mapping):
        bias = {name: Unconstrained() for name in bias}
    if not isinstance(data, Mapping) or not data:
        raise ParameterError("data: expected a mapping of output names to arrays")
    for name, m in {**parameters, **initial, **bias}.items():
        if not isinstance(m, AbstractParameterisation):
            raise ParameterError(f"{name}: {m!r} is not a parameterisation")
    _check_names("parameters", parameters, scene.parameters())
    state_shapes = scene.state_shapes()
    _check_names("initial", initial, state_shapes)
    outputs = tuple(data)
    dtype = _dtype(ts, data)
    shapes = _output_shapes(scene, dtype)
    _check_names("data", outputs, shapes)
    _check_names("bias", bias, outputs)
    kinds = tuple(scene.body.residual_kinds.get(k, "value") for k in outputs)
    rotations = [k for k, kind in zip(outputs, kinds) if kind == "rotation" and k in bias]
    if rotations:
        raise ParameterError(f"bias={rotations}: an attitude has no additive bias; allowed "
                             f"are {[k for k in outputs if k not in rotations]}")
    recast = {k: v.astype(dtype) for k, v in scene.parameters().items()
              if isinstance(v, jax.Array) and jnp.issubdtype(v.dtype, jnp.floating)
              and v.dtype != dtype}
    if recast:
        scene = scene.replace(recast)
    ts, obs = _prepare_data(shapes, ts, data, outputs, dtype)
    n_samples = ts.size
    rtol, atol = check_tolerances(rtol, atol, dtype)

    if y0 is None:
        observed = {k: obs[k][0] for k in outputs if k in state_shapes}
        try:
            y0 = scene.state(**observed)
        except ParameterError as e:
            raise ParameterError(f"y0: no starting initial state could be built ({e}); "
                                 "pass y0=scene.state(...)") from None
    # (Put on the device from NumPy: `jnp.asarray` and `jnp.zeros` compile a program each.)
    y0 = {k: device_array(v, dtype) for k, v in scene.check_state(y0).items()}
    current = scene.parameters()
    starting = {**{k: device_array(current[k], dtype) for k in parameters},
                **{k: y0[k] for k in initial},
                **{_BIAS + k: jax.device_put(np.zeros(shapes[k], dtype)) for k in bias}}
    fitted = {**parameters, **initial, **{_BIAS + k: m for k, m in bias.items()}}
    maps = tuple(m.bind(starting[k]) for k, m in fitted.items())
    names = tuple(fitted)
    components = sum((m.components(n) for n, m in zip(names, maps)), ())
    # The optimiser works in the default float type (optimistix's trust region does), the
    # simulation in the dtype of the data; results are reported in the latter.
    u0 = _starting_point(maps, starting, names)
    n_obs = n_samples * sum(_width(kind, obs[k].shape[1:]) for k, kind in zip(outputs, kinds))
    if n_obs <= u0.size:
        raise ParameterError(
            f"data has {n_samples} samples ({n_obs} values): more than {u0.size} values are "
            f"needed to fit {u0.size} unknowns ({', '.join(components)})"
        )
    sigma = dict(sigma or {})
    _check_names("sigma", sigma, outputs)
    # The optimiser sees residuals in units of the data's own size (the RMS of data/sigma),
    # so that its damping and tolerances act alike in any units; reported losses and
    # variances are scaled back.
    sigmas = {k: np.asarray(sigma.get(k, 1.0), dtype) for k in outputs}
    scale = float(np.sqrt(np.mean(np.concatenate(
        [np.ravel(obs[k] / sigmas[k]) ** 2 for k in outputs]))))
    scale = scale if np.isfinite(scale) and scale > 0 else 1.0
    ts_p, obs_p, weights = _pad(ts, obs)
    problem = _Problem(
        scene=scene, y0=y0, names=names, is_state=tuple(n in initial for n in names),
        maps=maps, sizes=tuple(m.size() for m in maps), outputs=outputs, kinds=kinds,
        sigma=tuple(device_array(sigmas[k] * scale, dtype) for k in outputs),
        rtol=rtol, atol=atol, max_steps=max_steps,
        dtype=dtype,
    )
    return _Setup(problem, u0, components, ts, obs, jax.device_put(ts_p),
                  {k: jax.device_put(v) for k, v in obs_p.items()}, jax.device_put(weights),
                  n_obs, dtype, scale)


_TURNS = 10.0  # the first horizon of a long record, in natural time units (1/W)


_CLOCK_POINTS = 1024  # samples at which the natural clock reads the time scale


@stored_filter_jit
def _time_scales(scene, y0, t0, t1, measured):
    """The scene's natural time scale over each `[t0_k, t1_k]`, from `y0` with the state
    variables of `measured` replaced by their rows (batched)."""

    def one(a, b, row):
        return scene.natural_scales(a, b, {**y0, **row})[1]

    return jax.vmap(one)(t0, t1, measured)


def _natural_clock(problem, u0, ts, obs) -> np.ndarray:
    """Natural time elapsed at each sample since the first (`1/W` units, `W` the scene's
    rate scale). Where the data measure state variables (gyro rates), the time scale is read
    from them along the record (at up to `_CLOCK_POINTS` samples), so a record whose rates
    grow (commanded slews) counts the turns it makes; else it is the starting point's."""
    scene, y0 = _scene_and_state(problem, u0)
    names = [k for k in obs if k in y0 and np.shape(obs[k])[1:] == np.shape(y0[k])]
    if names:
        idx = np.unique(np.linspace(0, ts.size - 1, min(ts.size, _CLOCK_POINTS + 1))
                        .round().astype(int))
        measured = {k: device_array(obs[k][idx[:-1]], problem.dtype) for k in names}
        dt = np.diff(ts[idx])
        scales = np.asarray(_time_scales(scene, y0, jax.device_put(ts[idx[:-1]]),
                                         jax.device_put(ts[idx[1:]]), measured), float)
        ok = np.isfinite(scales) & (scales > 0)
        if np.all(ok):
            clock = np.concatenate([[0.0], np.cumsum(dt / scales)])
            return np.interp(ts, ts[idx], clock)
    time_scale = float(scene.natural_scales(ts[0], ts[-1], y0)[1])
    if not np.isfinite(time_scale) or time_scale <= 0:
        return np.zeros(ts.size)
    return (ts - ts[0]) / time_scale


def _time_at(clock, ts, natural: float) -> float:
    """The time at which the natural clock reads `natural`."""
    return float(np.interp(natural, clock, ts))


def _auto_horizons(clock, ts) -> tuple[float, ...]:
    """Continuation spans for a record of this length: `(0.25, 0.5, 1)` for a short record,
    else spans doubling from `_TURNS` natural time units (see `_natural_clock`) to the whole
    record."""
    natural = float(clock[-1])
    if natural <= 4 * _TURNS:
        return (0.25, 0.5, 1.0)
    k = int(np.ceil(np.log2(natural / _TURNS)))
    span = float(ts[-1] - ts[0])
    return tuple((_time_at(clock, ts, _TURNS * 2.0**i) - float(ts[0])) / span
                 for i in range(k)) + (1.0,)


def _auto_segments(clock, ts) -> int:
    """Segments for multiple shooting, for a record longer than `4 _TURNS` natural time units
    (else 1: single shooting): segments of equal duration (inputs that switch at fixed
    times, as commanded torques, then cost every segment alike, which keeps their batched
    integrations in step), as many as make the fastest segment span at most `_TURNS`."""
    if float(clock[-1]) <= 4 * _TURNS:
        return 1
    fastest = float(np.max(np.diff(clock) / np.diff(ts)))  # natural time per unit time
    return int(np.ceil(float(ts[-1] - ts[0]) * fastest / _TURNS))


@cancels_unused_preparations
def fit(
    scene: Scene,
    ts: Float[ArrayLike, " N"],
    data: Mapping[str, ArrayLike],
    *,
    parameters: Mapping[str, AbstractParameterisation],
    initial: Mapping[str, AbstractParameterisation] | Sequence[str] = (),
    bias: Mapping[str, AbstractParameterisation] | Sequence[str] = (),
    y0: State | None = None,
    sigma: Mapping[str, ArrayLike] | None = None,
    restarts: int = 8,
    agree: int = 2,
    key: Any = None,
    method: str = "lm",
    adam_steps: int = 0,
    learning_rate: float = 0.05,
    max_iter: int = 200,
    horizons: Sequence[float] | None = None,
    tol: float | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 100_000,
    identifiability_tol: float | None = None,
    notes: Mapping[str, str] | None = None,
    reweight: bool = False,
    progress: bool = False,
    segments: int | None = None,
    posterior: int = 0,
    warmup: int = 300,
    chains: int = 4,
) -> FitResult:
    r"""Fit parameters and initial state of a scene to sampled outputs (least squares).

    **Arguments:**

    - `scene`: the [`jaxdyn.Scene`][]; parameters not fitted keep their values (known).
    - `ts`: sample times, strictly increasing; the first is the time of the initial state.
    - `data`: observed outputs by name (any of `scene.output_names()`, e.g. `"omega"` or
      `"theta"`), each of shape `(len(ts), *output_shape)`.
    - `parameters`: the parameters to fit, by the names of `scene.parameters()`, each with its
      parameterisation ([`jaxdyn.ValidInertia`][], [`jaxdyn.Positive`][],
      [`jaxdyn.Unconstrained`][]); the starting value is the scene's current value.
    - `initial`: the initial-state variables to fit (names of `scene.state_shapes()`), as a
      sequence ([`jaxdyn.Unconstrained`][]) or a mapping to parameterisations.
    - `bias`: outputs read by a sensor with a constant unknown bias (a gyro's `"omega"`): the
      data are taken as output plus bias, and each bias is fitted (from zero) and reported as
      `"bias.<output>"`. Attitudes (`"quaternion"`, from a star tracker) are compared as
      rotations instead: the residual is the rotation vector from the measured attitude to
      the predicted one, whatever the measured quaternion's sign.
    - `y0`: the starting (and, for variables not fitted, known) initial state; by default the
      first sample of each observed state variable and the scene's defaults for the rest.
    - `sigma`: noise scale of each output (weights `1/sigma`); needed only to combine outputs
      with different units. The noise variance itself is estimated from the residuals.
    - `restarts`: number of starting points: the given one, then random ones drawn by each
      parameterisation's `restart`. The best final loss wins.
    - `agree`: stop early once this many converged starts agree on the best loss (to a
      relative `1e-5`): the minimum has then been found from independent starts. A start
      that fits the record exactly (the RMS of the residuals below `tol` and `rtol` of the
      data's size: noise-free data, to the integration's precision) ends the search alone:
      no start can fit better.
    - `key`: a JAX PRNG key or an integer seed for the restarts.
    - `method`: `"lm"` (Levenberg--Marquardt from optimistix's damped Newton descent and
      trust region; default) or `"lbfgs"` (optax's L-BFGS with a zoom line search).
    - `adam_steps`, `learning_rate`: Adam steps (optax) taken from each start before the
      polishing method (default 0 for `"lm"`, which converges from random starts on its own;
      use e.g. 200 with `"lbfgs"`).
    - `max_iter`: iteration budget of the polishing method per start and horizon.
    - `horizons`: continuation in the time span: each start is fitted to the samples up to
      these fractions of the span in turn (integrating only that far), the last of which must
      be 1. A short record has few local minima, so its optimum is found from far away, and
      it is a good start for a longer one (a record over many periods otherwise has many).
      Default: chosen by the record's length in the scene's natural time `1/W` (`W` the
      largest starting rate): `(0.25, 0.5, 1)` for a record of up to `4 H` with
      `H = 10 / W` (about one and a half turns), otherwise spans doubling from `H` to the
      whole record, so that each stage starts from an optimum whose prediction is still in
      phase over the next span.
    - `tol`: convergence tolerance of the polishing method on the whole record (default
      `1e-8` in float64, `1e-5` in float32); shorter horizons use `max(tol, 1e-4)`.
    - `rtol`, `atol`, `max_steps`: of the integration ([`jaxdyn.simulate`][]).
    - `identifiability_tol`: a component whose Jacobian column, at the starting point, is
      smaller than this times the largest column is reported as not identifiable and kept at
      its starting value (default `1e-6` in float64, `1e-3` in float32; under multiple
      shooting, a component above it in the single-shooting columns or in the segments' own
      columns is identifiable: over a long record whose dynamics amplify a perturbation, the
      single-shooting columns of the amplified components dwarf the others). At the optimum, a
      singular value of the column-scaled Jacobian below this times the largest is reported
      as a combination of components that the data do not determine (say `g` and `L` of the
      rod, of which only `g/L` enters).
    - `notes`: explanations to attach, by component name, when a component is found not
      identifiable (for example why a rod's mass does not enter its angle).
    - `reweight`: with several outputs in different units and no `sigma`: after the fit,
      weight each output by the RMS of its own residuals and refit from the optimum, so that
      each output counts by its noise level (and the intervals use each output's noise).
    - `progress`: show a tqdm progress bar over the iterations of all starts.
    - `segments`: multiple shooting (see below): the number of segments of equal duration
      the record is cut into; `1` fits by single shooting. Default: by the record's length
      in natural time, one segment per `10 / W` for a record longer than `40 / W`, else
      single shooting. Given `horizons`, single shooting.

    - `posterior`: a number of draws to sample from the posterior of the fitted quantities by
      NUTS (blackjax, `pip install 'jaxdyn[posterior]'`) after `warmup` adaptation steps
      (trajectories of at most 127 leapfrog steps; the draws' at most 1023),
      through the same residuals: a Gaussian likelihood with the fitted noise variance, a
      prior uniform in the principal moments (over the physical bodies) and over the axes of
      a [`jaxdyn.ValidInertia`][] and a weakly informative Gaussian prior (standard
      deviation 10) on each other unconstrained component around the starting point (see
      `FitResult.posterior`). For where the Gauss--Newton intervals cannot be trusted, as
      for the axes of a nearly axisymmetric body. Default 0: none; otherwise at least four
      draws per chain (`posterior >= 3 * chains + 1`), for the chains' split R-hat.
    - `chains`: the number of NUTS chains (run side by side, each on a thread of its own: on a
      CPU, on cores of their own; started dispersed around the optimum; `posterior` draws in all,
      each chain after its own `warmup`). Their agreement is checked (split R-hat in
      `FitResult.posterior_diagnostics`; a warning when they disagree, and when a chain is
      stuck: mean acceptance below 0.3). Default 4.

    Long records are fitted by multiple shooting: the state at the start of each segment is
    an unknown of its own, started from the data where they measure it (gyro rates less the
    fitted bias, star-tracker attitudes) and from a simulation of the starting guess
    elsewhere, tied to the previous segment's end by continuity residuals; the block-sparse
    normal equations are solved segment by segment, so time and memory grow linearly with
    the record. Once converged, the continuity defects are closed exactly (constrained
    Gauss--Newton steps), so the estimate and its intervals are those of single shooting.
    On a record over which the dynamics amplify a perturbation so much that the closing
    steps have no precision left (an unstable tumble over hours), the estimate is that of
    the segmented problem, with its own (sandwich) covariance: honest, and wider than single
    shooting's would be, since the segments give up part of the long baseline.

    **Returns:**

    A [`jaxdyn.FitResult`][].

    For example, the normalised inertia tensor and initial rates of a torque-free body from
    body rates `w` (shape `(N, 3)`) sampled at `ts`:

    ```python
    scene = jd.Scene(jd.RigidBody([0.6, 0.8, 1.0]))  # the starting guess
    res = jd.fit(scene, ts, {"omega": w}, parameters={"inertia": jd.ValidInertia()},
                 initial=["omega"])
    res.values["inertia.principal_moments"], res.std["inertia.principal_moments"]
    ```

    Terminating events of the scene are off during the fit: the samples define the time span,
    and a trial parameter set must not end the run before the last sample. The fit is
    compiled once per scene structure, set of fitted names and data length (padded to a
    multiple of 32 samples): further fits, restarts and new data of similar length reuse it.
    """
    if method not in ("lm", "lbfgs"):
        raise ParameterError(f"method={method!r}: allowed are 'lm', 'lbfgs'")
    for field, value, low in (("restarts", restarts, 1), ("agree", agree, 1),
                              ("posterior", posterior, 0), ("warmup", warmup, 1),
                              ("chains", chains, 1), ("max_iter", max_iter, 1),
                              ("adam_steps", adam_steps, 0)):
        if not isinstance(value, int) or value < low:
            kind = "a positive" if low else "a non-negative"
            raise ParameterError(f"{field}={value!r}: must be {kind} integer")
    if posterior and -(-posterior // chains) < _MIN_DRAWS_PER_CHAIN:
        raise ParameterError(
            f"posterior={posterior} with chains={chains}: each chain needs at least "
            f"{_MIN_DRAWS_PER_CHAIN} draws (two per half, for the split R-hat), so posterior= "
            f"must be 0 or at least {(_MIN_DRAWS_PER_CHAIN - 1) * chains + 1}")
    key = _as_key(key)
    if horizons is not None:
        horizons = tuple(float(h) for h in horizons)
        if not horizons or horizons[-1] != 1.0 or any(not 0 < h <= 1 for h in horizons):
            raise ParameterError(f"horizons={horizons}: fractions in (0, 1], the last one 1")
    if segments is not None and (not isinstance(segments, int) or segments < 1):
        raise ParameterError(f"segments={segments!r}: must be a positive integer (1: single "
                             "shooting)")
    setup = _setup(scene, ts, data, parameters, initial, y0, sigma, rtol, atol, max_steps,
                   bias)
    problem, u0, ts, obs = setup.problem, setup.u0, setup.ts, setup.obs
    clock = _natural_clock(problem, u0, ts, obs)
    automatic = segments is None and horizons is None
    if segments is None:
        segments = 1 if horizons is not None else _auto_segments(clock, ts)
    shooting = _multiple_shooting(problem, setup, segments, clock) if segments > 1 else None
    if horizons is None:
        horizons = (1.0,) if shooting is not None else _auto_horizons(clock, ts)
    ts_p, obs_p, weights = setup.ts_p, setup.obs_p, setup.weights
    components, n_obs, dtype = setup.components, setup.n_obs, setup.dtype
    outputs = problem.outputs
    eps = float(jnp.finfo(dtype).eps)
    if tol is None:
        tol = 1e-8 if eps < 1e-10 else 1e-5
    if identifiability_tol is None:
        identifiability_tol = 1e-6 if eps < 1e-10 else 1e-3
    # Structural identifiability: a zero Jacobian column at the start (the column of a
    # parameter that the outputs do not depend on) stays zero everywhere.
    if shooting is not None:
        free_np = shooting.free(problem, u0, identifiability_tol)
    else:
        if method == "lm":
            # From one step of the fit's own Levenberg-Marquardt program (every component
            # free, `exact` infinite: the first step is accepted and ends the loop), which
            # returns the Jacobian at `u0`: no program of its own to compile.
            everything = jax.device_put(np.ones(u0.shape, bool))
            # The summaries' program (known from here: the same problem, `u` and `free`
            # shaped as `u0`) is compiled on the other core while this one compiles.
            _summaries_and_derivatives.prepare(problem, u0, everything)
            inf = device_array(np.inf, u0.dtype)
            *_, J0 = _levenberg_marquardt(problem, u0, everything, ts_p, obs_p, weights, inf,
                                          inf, max_iter=max_iter, progress=progress)
        else:
            _, J0 = _jacobian(problem, u0, ts_p, obs_p, weights)
        norms = np.linalg.norm(np.asarray(J0), axis=0)
        free_np = norms > identifiability_tol * norms.max()
    free = jax.device_put(free_np)
    u0_np = np.asarray(u0)

    def _fixed(u):
        """`u` with the components not fitted back at their starting values (on the host: an
        eager `jnp.where` is a compiled program)."""
        return jax.device_put(np.where(free_np, np.asarray(u), u0_np))

    def _clipped(ts_, weights_, t_h):
        """Sample times clipped to `t_h` and weights zero beyond it (NumPy, on the host)."""
        return (jax.device_put(np.minimum(ts_, t_h)),
                jax.device_put(np.where(ts_ <= t_h, weights_, 0.0)))

    ts_host, weights_host = np.asarray(ts_p), np.asarray(weights)

    drawn = []

    def _start(i):
        """The `i`-th starting point: the given one, then the random ones, drawn when first
        needed (a fit that ends after its first start loads no program for them)."""
        if i and not drawn:
            try:
                points = _restart_points(problem, u0, free, _key(key), count=restarts - 1)
            except (*_UNTRACEABLE, NotImplementedError):  # a user's `restart` with NumPy
                # or Python logic, or a callback that cannot be mapped: drawn eagerly
                points = _draw_restarts(problem, u0, free, _key(key),
                                        count=restarts - 1)
            drawn.extend(np.asarray(points))
        return drawn[i - 1] if i else u0

    polish = _levenberg_marquardt if method == "lm" else _lbfgs
    tol_a = device_array(tol, u0.dtype)
    tol_early = device_array(max(tol, 1e-4), u0.dtype)
    zero = device_array(0.0, u0.dtype)
    lr = device_array(learning_rate, u0.dtype)
    # The loss of a fit whose residuals are all below `tol` of the data's size, and below the
    # integration's `rtol` (a loose `tol` is a convergence criterion, not a precision): noise-
    # free data, at the integration's precision (see `_levenberg_marquardt`).
    exact_level = 0.5 * n_obs * min(tol, float(problem.rtol)) ** 2

    def _prefix(shooting):
        """The start of the record (4 x 10/W), fitted first by single shooting with its
        short-record continuation (a quarter, half, all of it): the basin of a short
        record."""
        if shooting is None:
            return None, None, None, None
        n_pre = max(int(np.searchsorted(ts, ts[0] + shooting.prefix, side="right")), 3)
        pre_ts, pre_obs, pre_w = _pad(np.asarray(ts[:n_pre]),
                                      {k: v[:n_pre] for k, v in obs.items()})
        return n_pre, pre_ts, {k: jax.device_put(v) for k, v in pre_obs.items()}, pre_w

    n_pre, pre_ts, pre_obs, pre_w = _prefix(shooting)

    def _single(u, horizons, warm_up):
        """Single shooting from `u` over the continuation `horizons`."""
        history, stages, iterations = [], [], 0
        if adam_steps and warm_up:
            u, losses = _adam(problem, u, free, ts_p, obs_p, weights, lr, steps=adam_steps,
                              progress=progress)
            u = _fixed(u)
            history.append(np.asarray(losses))
            stages.append(0)
            iterations += adam_steps
        for h in horizons:
            # Samples up to `t_h` count; the integration stops there too (later sample times
            # are clipped to it: same shapes, so no recompilation).
            # (The whole record exactly at `h = 1`: `ts[0] + (ts[-1] - ts[0])` can fall an
            # ulp short of `ts[-1]`.)
            t_h = ts[-1] if h == 1.0 else ts[ts <= ts[0] + h * (ts[-1] - ts[0])][-1]
            ts_h, w = _clipped(ts_host, weights_host, t_h)
            stage_tol = tol_a if h == 1.0 else tol_early
            exact = zero if h == 1.0 else tol_early  # (see `_levenberg_marquardt`)
            u, loss, k, ok, hist, r, J = polish(problem, u, free, ts_h, obs_p, w, stage_tol,
                                                exact, max_iter=max_iter, progress=progress)
            u = _fixed(u)
            k = int(k)
            history.append(np.asarray(hist)[:k])
            stages.append(iterations)
            iterations += k
        loss = float(loss)
        # A final stage that ran out of iterations where its residuals were all below `tol`
        # (and `rtol`) of the data's size (a noise-free record, at the integration's
        # precision) has nothing left to fit: converged.
        ok = bool(ok) or loss <= exact_level
        # The last stage covers the whole record (its sample times are the record's, its
        # weights too): its residuals and Jacobian at `u` are those of `_jacobian`.
        return {"loss": loss if np.isfinite(loss) else np.inf, "u": u, "converged": ok,
                "iterations": iterations, "history": np.concatenate(history),
                "stages": tuple(stages), "rJ": None if J is None else (r, J)}

    def _multiple(u, warm_up, resume=None):
        """Multiple shooting from `u`, after single shooting on the record's start (or, with
        `resume`, from the segment states of an earlier run)."""
        history, stages, iterations = [], [], 0
        if warm_up:
            for h in (0.25, 0.5, 1.0):
                t_h = ts[:n_pre][ts[:n_pre] <= ts[0] + h * (ts[n_pre - 1] - ts[0])][-1]
                ts_h, w = _clipped(pre_ts, pre_w, t_h)
                u, _, k, _, hist, _, _ = polish(problem, u, free, ts_h, pre_obs, w, tol_early,
                                                zero, max_iter=max_iter, progress=progress)
                u = _fixed(u)
                history.append(np.asarray(hist)[:int(k)])
                stages.append(iterations)
                iterations += int(k)
        # (A refit from an optimum, `warm_up=False`, needs no continuation.)
        run = shooting.run(problem, u, free_np, tol, max_iter,
                           _tick if progress else _silent_tick,
                           stages=None if warm_up else (1.0,), resume=resume)
        if not run["converged"]:
            # The segments' defects did not close (an effect whose torque is not smooth in the
            # state, as a saturating B-dot law): single shooting finishes from multiple
            # shooting's estimate, which lies in its basin, and says whether it converged.
            history.append(run["history"])
            stages.append(iterations)
            iterations += run["iterations"]
            run = _single(run["u"], (1.0,), warm_up=False)
        return {**run, "history": np.concatenate(history + [run["history"]]),
                "stages": (*stages, *(iterations + s_ for s_ in run["stages"])),
                "iterations": iterations + run["iterations"]}

    def _run_start(u, horizons=horizons, warm_up=True, resume=None):
        if shooting is not None:
            return _multiple(u, warm_up, resume)
        return _single(u, horizons, warm_up)

    def _solve():
        """Every start, the best one (refitted with each output weighted by its own residual
        scale, with `reweight`), and the check of its residuals."""
        nonlocal problem
        runs = []
        bar = None
        if progress:
            from tqdm.auto import tqdm

            total = restarts * (adam_steps + len(horizons) * max_iter
                                + (max_iter + 10 if shooting is not None else 0))
            bar = tqdm(total=total, desc="fit", unit="it")
            _BAR["bar"] = bar
        try:
            for i in range(restarts):
                runs.append(_run_start(_start(i)))
                if bar is not None:
                    bar.update(max(0, bar.total // restarts * len(runs) - bar.n))
                losses = np.array([run["loss"] for run in runs])
                if runs[-1]["converged"] and runs[-1]["loss"] <= exact_level:
                    break  # exact to `tol`: the global minimum (see `agree`)
                agreeing = [run["converged"] and run["loss"] <= losses.min() * (1 + 1e-5)
                            for run in runs]
                if sum(agreeing) >= agree:
                    break
        finally:
            if bar is not None:
                bar.total = bar.n  # the starts left out after agreement
                bar.close()
                _BAR.pop("bar", None)

        best = runs[int(np.argmin([run["loss"] for run in runs]))]
        loss, u = best["loss"], best["u"]

        def normal_and_sums(best, u):
            """A square root of the normal matrix (see `_uncertainty`), the residual sum of
            squares and the sums by output at the optimum, and the residuals of each output
            over the samples `(N, width)`."""
            if "H" in best:  # multiple shooting's own normal matrix
                sums = dict(zip(outputs, (float(x) for x in best["ss"])))
                return _root(best["H"]), np.sum(list(sums.values())), sums, best["series"]
            r, J = best["rJ"] or _jacobian(problem, u, ts_p, obs_p, weights)
            series = _series_by_output(np.asarray(r), obs, ts_p.size, problem.kinds)
            sums = {k: float(np.sum(v**2)) for k, v in series.items()}  # (padding weighs 0)
            # (NumPy on the host: eager `jnp` calls would each compile a program.)
            r = np.asarray(r)
            return np.linalg.qr(np.asarray(J), mode="r"), np.sum(r**2), sums, series

        R, rss, sums, series = normal_and_sums(best, u)
        if reweight and len(outputs) > 1:
            # Weight each output by its own residual scale, and refit from the optimum (the
            # same compiled functions: `sigma` is an array of the problem).
            rms = _rms_by_output(sums, obs, problem.sigma, problem.kinds)
            problem = eqx.tree_at(lambda p: p.sigma, problem,
                                  tuple(device_array(rms[k] * setup.scale, dtype)
                                        for k in outputs))
            # (Multiple shooting resumes from its segment states: re-anchored at the data, they
            # would start far from the optimum in the new weights.)
            again = _run_start(u, horizons=(1.0,), warm_up=False, resume=best.get("lifted"))
            best = {**again, "history": np.concatenate([best["history"], again["history"]]),
                    "stages": best["stages"] + tuple(best["iterations"] + s_
                                                     for s_ in again["stages"]),
                    "iterations": best["iterations"] + again["iterations"]}
            loss, u = best["loss"], best["u"]
            R, rss, sums, series = normal_and_sums(best, u)
        rms_by_output = _rms_by_output(sums, obs, problem.sigma, problem.kinds)
        whiteness = _whiteness(series)
        floors = {k: _MATERIAL * float(problem.rtol) * _data_scale(obs[k], kind)
                  for k, kind in zip(outputs, problem.kinds)}
        systematic = _systematic(whiteness, series, obs, problem.sigma, problem.kinds, floors)
        loss0 = 0.5 * sum(sums[k] * float(np.max(np.asarray(sg)) / np.max(
            np.asarray(sg0))) ** 2 for k, sg, sg0 in zip(outputs, problem.sigma,
                                                          setup.problem.sigma))
        return dict(best=best, runs=runs, problem=problem, loss=loss, u=u, R=R, rss=rss,
                    sums=sums, rms_by_output=rms_by_output, whiteness=whiteness,
                    systematic=systematic, loss0=loss0,
                    segments=1 if shooting is None else shooting.segments)

    fitted = _solve()
    if fitted["systematic"] and automatic:
        # Residuals far from white: perhaps a local minimum of this segmentation. Fit again
        # with twice as many segments (or multiple shooting where single shooting was
        # used), and keep the better fit: white residuals first, then the lower loss.
        count = 2 * shooting.segments if shooting is not None else max(
            3, 2 * int(np.ceil(clock[-1] / _TURNS)))
        other = _multiple_shooting(setup.problem, setup, count, clock)
        if other is not None:
            first, shooting, problem = fitted, other, setup.problem
            n_pre, pre_ts, pre_obs, pre_w = _prefix(shooting)
            second = _solve()
            better = ((first["systematic"] and not second["systematic"])
                      or (bool(first["systematic"]) == bool(second["systematic"])
                          and second["loss0"] < first["loss0"]))
            fitted = second if better else first
    best, runs, problem = fitted["best"], fitted["runs"], fitted["problem"]
    loss, u, R, rss, sums = (fitted[k] for k in ("loss", "u", "R", "rss", "sums"))
    rms_by_output, whiteness, systematic = (fitted[k] for k in ("rms_by_output", "whiteness",
                                                                "systematic"))
    cov, values, std, s2, sv, vt = _uncertainty(problem, u, free, R, rss, n_obs)

    draws, acceptance, leapfrogs, report = None, None, None, None
    if posterior:
        from ._posterior import sample

        covariance = functools.partial(_sampling_covariance, fitted=problem, R=R, free=free_np,
                                       ts=ts_p, data=obs_p, weights=weights, s2=s2)
        draws, report = sample(problem, u.astype(u0.dtype), free_np, u0, ts_p, obs_p, weights,
                               s2, covariance, jax.random.fold_in(_key(key), 1), _summaries,
                               draws=posterior, warmup=warmup, chains=chains)
        acceptance = float(np.mean(report["acceptance"]))
        leapfrogs = float(np.mean(report["leapfrogs"]))
    identifiable = {c: bool(f) for c, f in zip(components, free_np)}
    notes = dict(notes or {})
    lines = []
    for c, f in identifiable.items():
        if not f:
            why = notes.get(c, "the outputs do not depend on it (its Jacobian column is zero)")
            lines.append(f"{c} is not identifiable from {', '.join(outputs)}: {why}; "
                         "kept at its starting value")
    sv, vt = np.asarray(sv), np.asarray(vt)
    n_free = int(free_np.sum())
    if n_free and sv[n_free - 1] < identifiability_tol * sv[0]:
        v = vt[n_free - 1]
        involved = [c for c, x in zip(components, v) if abs(x) > 0.1]
        # (A singular value of exactly zero: an infinite condition number, said so.)
        cond = (f"{sv[0] / sv[n_free - 1]:.1e}" if sv[n_free - 1] > 0 else "infinite")
        lines.append(f"only a combination of {', '.join(involved)} is determined by the data "
                     f"(condition number {cond})")
    if systematic:
        lines.append(_systematic_note(systematic, whiteness, n_samples=ts.size))
    scene_fit, y0_fit = _scene_and_state(problem, u)
    c2 = setup.scale**2  # the optimiser's losses back in units of data/sigma
    return FitResult(
        values=values, std=std, identifiable=identifiable, notes=tuple(lines),
        scene=scene_fit, y0=y0_fit, u=u, components=components, covariance=cov,
        loss=float(loss) * c2, residual_rms=float(np.sqrt(2 * loss * c2 / n_obs)),
        residual_rms_by_output=rms_by_output,
        noise_variance=float(s2) * c2, converged=best["converged"] and not systematic,
        optimiser_converged=best["converged"], residual_autocorrelation=whiteness,
        systematic=tuple(systematic),
        iterations=best["iterations"], history=best["history"] * c2, stages=best["stages"],
        restart_losses=np.array([run["loss"] for run in runs]) * c2,
        segments=fitted["segments"],
        posterior=draws, posterior_acceptance=acceptance, posterior_leapfrogs=leapfrogs,
        posterior_diagnostics=report,
    )

