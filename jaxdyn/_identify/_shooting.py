r"""Multiple shooting: a fit of a long record, cut into segments.

A record over many periods, fitted by single shooting (one integration from the initial
state), has a loss with many local minima: a prediction that drifts out of phase matches the
data no better than noise. Multiple shooting (Bock 1981; Bock and Plitt 1984; for parameter
estimation in ODEs, Peifer and Timmer 2007) cuts the record into segments of a few natural
time units. The state at the start of each segment is an unknown of its own, started from the
data where the data measure it (gyro rates, star-tracker attitudes) and from a simulation of
the starting guess elsewhere (a wheel's momentum); continuity residuals tie each segment's end
to the next segment's start. Every segment's prediction starts in phase with its data, so the
fit converges from far away.

The unknowns are the global parameters `p` (the scene's fitted parameters and sensor biases)
and the segment states `s_0, ..., s_{S-1}`. Residuals of segment `k` depend on `p` and `s_k`
only; the continuity residual `d_k = W (x_k(t_{k+1}; p, s_k) - s_{k+1})` on `p`, `s_k` and
`s_{k+1}`. So the Jacobian is block sparse: each segment's blocks come from one forward-mode
pass through its own integration (all segments batched with `jax.vmap`, in chunks so that
memory stays bounded), and the normal equations are block tridiagonal in the segment states
with a border for `p`. Levenberg--Marquardt steps solve them by a block Thomas recursion and
the Schur complement on `p`: the cost is linear in the number of segments.

Continuity weights `W` are scale-free: a defect in a state variable counts as much as the
data of one segment would change if the next segment started off by that defect, times
`_CONTINUITY` (chosen so that defects end far below the noise); the weights start 100 times
smaller (nearly independent segments, each in phase with its data) and are then raised
(`_STAGES`). The caller fits the start of the record by single shooting first, which gives
the global parameters a start within the basin of every segment. Once the lifted problem has
converged, a few constrained Gauss--Newton steps (condensing: each segment's state change
expressed, through the linearised continuity conditions, by the changes of `p` and `s_0`)
close the defects exactly, so the estimate is the single-shooting least-squares estimate; the
condensed normal matrix is that of single shooting, and gives the Gauss--Newton covariance.

Where the dynamics amplify a perturbation over the record (issue 20's 1e5-sample wheel
record: an integration error grows 1e5-fold over its second half), the condensed steps have
no precision left and single shooting's estimate is out of reach in floating point. The fit
then keeps the lifted optimum, whose segments shadow the data with defects far below the
noise, and reports that estimator's own covariance (`lifted_covariance`).
"""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._stored_jit import stored_filter_jit
from ._parameterisation import Unconstrained, UnitQuaternion

_CONTINUITY = 10.0  # weight of a continuity defect, relative to its segment's data
_STAGES = (1e-2, 1.0)  # continuation: factors of the continuity weights
_LIFTED_TOL = 1e-4  # relative tolerance of the lifted stages (the condensed steps finish)
_INSIGNIFICANT = 1e-2  # a condensed step this many standard deviations long ends the fit
_HOPELESS = 1e4  # a first condensed step this many standard deviations long is not tried
_MEMORY = 2**28  # bytes of Jacobian blocks and saved tangents per chunk of segments
_SEGMENT_STEPS = 20_000
_CPU_BATCH = 8  # segments per batch of a linearisation on a CPU (see `chunk`)


@dataclasses.dataclass(frozen=True)
class Segments:
    """A record cut into segments: `ts` `(S, M + 1)` (each segment's sample times, padded with
    its end time, which is the next segment's first sample time, and then that end time),
    `data` by output `(S, M, ...)`, `weights` `(S, M)` (zero on padding), `has_next` `(S,)`."""

    ts: np.ndarray
    data: dict[str, np.ndarray]
    weights: np.ndarray
    has_next: np.ndarray
    first: np.ndarray  # index of each segment's first sample in the record


def cut(ts: np.ndarray, obs: dict[str, np.ndarray], count: int, bucket: int = 8) -> Segments:
    """Cut a record into `count` segments of equal duration (fewer where a segment would hold
    no samples; each holds at least two)."""
    edges = ts[0] + (ts[-1] - ts[0]) * np.arange(count) / count
    starts = np.unique(np.searchsorted(ts, edges, side="left"))
    ends = np.append(starts[1:], ts.size)
    while starts.size > 1 and ends[-1] - starts[-1] < 2:  # too short: merged into the previous
        starts, ends = starts[:-1], np.append(ends[:-2], ts.size)
    counts = ends - starts
    size = int(math.ceil(counts.max() / bucket) * bucket)
    idx = np.minimum(starts[:, None] + np.arange(size)[None, :], (ends - 1)[:, None])
    valid = np.arange(size)[None, :] < counts[:, None]
    end_t = np.append(ts[ends[:-1]], ts[-1])
    seg_ts = np.concatenate([np.where(valid, ts[idx], end_t[:, None]), end_t[:, None]], axis=1)
    has_next = np.ones(starts.size, ts.dtype)
    has_next[-1] = 0
    return Segments(seg_ts, {k: v[idx] for k, v in obs.items()}, valid.astype(ts.dtype),
                    has_next, starts)


class Layout(eqx.Module):
    """Where each unknown lives: the global parameters `p` (the problem's fitted names that are
    not initial-state variables) and one segment state `s` (every state variable)."""

    p_names: tuple[str, ...] = eqx.field(static=True)
    p_sizes: tuple[int, ...] = eqx.field(static=True)
    s_names: tuple[str, ...] = eqx.field(static=True)
    s_sizes: tuple[int, ...] = eqx.field(static=True)
    rotation: tuple[bool, ...] = eqx.field(static=True)

    def p_values(self, problem, p):
        maps = dict(zip(problem.names, problem.maps))
        offsets = np.cumsum((0,) + self.p_sizes)
        return {n: maps[n](p[a:b].astype(problem.dtype))
                for n, a, b in zip(self.p_names, offsets[:-1], offsets[1:])}

    def state(self, smaps, s, dtype):
        offsets = np.cumsum((0,) + self.s_sizes)
        return {n: m(s[a:b].astype(dtype))
                for n, m, a, b in zip(self.s_names, smaps, offsets[:-1], offsets[1:])}

    def defect(self, end, nxt):
        """Continuity defect of each state variable (a rotation's as a rotation vector)."""
        from ._fit import _rotation_error

        parts = []
        for n, rot in zip(self.s_names, self.rotation):
            if rot:
                parts.append(_rotation_error(end[n][None], nxt[n][None])[0])
            else:
                parts.append(jnp.ravel(end[n] - nxt[n]))
        return jnp.concatenate(parts)


def layout(problem, scene) -> tuple[Layout, tuple] | None:
    """The layout and unbound segment-state parameterisations, or `None` where multiple
    shooting does not apply (no global parameter, or a state whose parameterisation does not
    have as many components as its continuity defect)."""
    p_names = tuple(n for n, s in zip(problem.names, problem.is_state) if not s)
    if not p_names:
        return None
    maps = dict(zip(problem.names, problem.maps))
    shapes = scene.state_shapes()
    kinds = scene.body.residual_kinds
    templates, sizes, rotation = [], [], []
    for n, shape in shapes.items():
        rot = kinds.get(n, "value") == "rotation"
        m = maps.get(n) if n in problem.names else None
        m = m if m is not None else (UnitQuaternion() if rot else Unconstrained())
        width = 3 if rot else int(np.prod(shape))
        bound = m.bind(np.ones(shape) / np.sqrt(max(np.prod(shape), 1)))
        if bound.size() != width:
            return None
        templates.append(m)
        sizes.append(width)
        rotation.append(rot)
    p_sizes = tuple(maps[n].size() for n in p_names)
    return Layout(p_names, p_sizes, tuple(shapes), tuple(sizes), tuple(rotation)), \
        tuple(templates)


@eqx.filter_jit
def bind_segments(templates, names, ys):
    """Segment-state parameterisations bound to the starting states `ys` (batched), and the
    starting unknowns `(S, n_s)`."""

    def one(y):
        maps = tuple(m.bind(y[n]) for m, n in zip(templates, names))
        s = jnp.concatenate([jnp.ravel(m.to_unconstrained(y[n])) for m, n in zip(maps, names)])
        return maps, s

    return eqx.filter_vmap(one)(ys)


@stored_filter_jit
def linearise(problem, lay, p, s, smaps, seg_ts, seg_data, seg_w, has_next, wc, *,
              batch):
    """Per-segment blocks at `(p, s)`: data normal matrix `N` and gradient `g` over `(p,
    s_k)`, the weighted data residuals `r` and the sums of squares of each output `ss`, the
    weighted continuity defect `d` with its Jacobians `P` (on `p`), `G` (on `s_k`) and `E`
    (on `s_{k+1}`)."""
    n_p = p.shape[0]
    dyn, static = eqx.partition(smaps, eqx.is_array)
    shift = lambda x: jnp.concatenate([x[1:], x[-1:]])  # noqa: E731
    xs = (s, shift(s), dyn, jax.tree.map(shift, dyn), seg_ts, seg_data, seg_w, has_next)

    def one(args):
        s_k, s_n, dyn_k, dyn_n, ts_k, data_k, w_k, hn = args
        maps_k, maps_n = eqx.combine(dyn_k, static), eqx.combine(dyn_n, static)
        nxt = lay.state(maps_n, s_n, problem.dtype)

        def residuals(ps):
            values = lay.p_values(problem, ps[:n_p])
            params = {n: v for n, v in values.items() if not n.startswith("bias.")}
            scene = problem.scene.replace(params) if params else problem.scene
            y = lay.state(maps_k, ps[n_p:], problem.dtype)
            out, ys, ok = problem.simulate(scene, y, ts_k)
            pred = {k: jnp.where(ok, out[k][:-1], jnp.nan) for k in problem.outputs}
            parts = problem.output_residuals(values, pred, data_k, w_k)
            end = jax.tree.map(lambda v: jnp.where(ok, v[-1], jnp.nan), ys)
            d = lay.defect(end, nxt) * wc * hn
            r = jnp.concatenate(parts + [d]).astype(p.dtype)
            return r, (r, jax.lax.stop_gradient(end))

        J, (r, end) = jax.jacfwd(residuals, has_aux=True)(jnp.concatenate([p, s_k]))
        m = r.shape[0] - wc.shape[0]
        rd, d = r[:m], r[m:]
        from ._fit import _blocks, _width

        sizes = {k: (data_k[k].shape[0], _width(kind, data_k[k].shape[1:]))
                 for k, kind in zip(problem.outputs, problem.kinds)}
        ss = jnp.stack([jnp.sum(b**2) for b in _blocks(rd, sizes).values()])
        Jd, Jc = J[:m], J[m:]
        E = jax.jacfwd(lambda sn: lay.defect(end, lay.state(maps_n, sn, problem.dtype))
                       .astype(p.dtype) * wc * hn)(s_n)
        return {"N": Jd.T @ Jd, "g": Jd.T @ rd, "r": rd, "ss": ss, "d": d, "P": Jc[:, :n_p],
                "G": Jc[:, n_p:], "E": E}

    return jax.lax.map(one, xs, batch_size=batch)


@jax.jit
def _weighted(B, w):
    """Blocks `B` with the continuity residuals weighted `w` times more (a scalar, or one
    factor per component of a defect): the defects and their Jacobians scale alike."""
    w = jnp.asarray(w)
    rows = w[:, None] if w.ndim else w
    return {**B, "d": B["d"] * w, "P": B["P"] * rows, "G": B["G"] * rows, "E": B["E"] * rows}


def _shift_down(x):
    return jnp.concatenate([jnp.zeros_like(x[:1]), x[:-1]])


def _normal_blocks(B, p_free, s0_free):
    """The lifted normal equations: `Hpp`, `Hps` `(S, n_p, n_s)`, diagonal blocks `D`, upper
    blocks `C` (`C_k` couples `s_k` and `s_{k+1}`), gradients `gp`, `gs`; components held
    fixed have zero rows and columns and a unit diagonal."""
    N, g, P, G, E, d = B["N"], B["g"], B["P"], B["G"], B["E"], B["d"]
    n_p = P.shape[-1]
    Hpp = jnp.sum(N[:, :n_p, :n_p], 0) + jnp.einsum("kip,kiq->pq", P, P)
    Hps = (N[:, :n_p, n_p:] + jnp.einsum("kip,kis->kps", P, G)
           + _shift_down(jnp.einsum("kip,kis->kps", P, E)))
    D = (N[:, n_p:, n_p:] + jnp.einsum("kis,kit->kst", G, G)
         + _shift_down(jnp.einsum("kis,kit->kst", E, E)))
    C = jnp.einsum("kis,kit->kst", G, E)
    gp = jnp.sum(g[:, :n_p], 0) + jnp.einsum("kip,ki->p", P, d)
    gs = g[:, n_p:] + jnp.einsum("kis,ki->ks", G, d) + _shift_down(jnp.einsum("kis,ki->ks", E, d))
    # Fixed components: p (not identifiable) and s_0 (known initial values).
    fp = p_free.astype(Hpp.dtype)
    S = D.shape[0]
    fs = jnp.ones((S, D.shape[1]), Hpp.dtype).at[0].set(s0_free.astype(Hpp.dtype))
    Hpp = fp[:, None] * Hpp * fp[None, :] + jnp.diag(1 - fp)
    Hps = fp[None, :, None] * Hps * fs[:, None, :]
    D = fs[:, :, None] * D * fs[:, None, :] + jax.vmap(jnp.diag)(1 - fs)
    C = fs[:, :, None] * C * _shift_up(fs)[:, None, :]
    return Hpp, Hps, D, C, gp * fp, gs * fs


def _shift_up(x):
    return jnp.concatenate([x[1:], jnp.ones_like(x[-1:])])


def _block_tridiagonal_solve(D, C, R):
    """Solve `T X = R` for symmetric positive definite block-tridiagonal `T` with diagonal
    blocks `D_k` and upper blocks `C_k` (block Thomas recursion; `R` `(S, n, m)`)."""
    n = D.shape[1]
    C_prev = _shift_down(C)

    def forward(carry, inp):
        Dp_prev, Rp_prev = carry
        D_k, Cp_k, R_k = inp
        Z = jnp.linalg.solve(Dp_prev, jnp.concatenate([Cp_k, Rp_prev], axis=1))
        Dp = D_k - Cp_k.T @ Z[:, :n]
        Rp = R_k - Cp_k.T @ Z[:, n:]
        return (Dp, Rp), (Dp, Rp)

    eye = jnp.eye(n, dtype=D.dtype)
    _, (Dp, Rp) = jax.lax.scan(forward, (eye, jnp.zeros_like(R[0])), (D, C_prev, R))

    def backward(X_next, inp):
        Dp_k, Rp_k, C_k = inp
        X = jnp.linalg.solve(Dp_k, Rp_k - C_k @ X_next)
        return X, X

    C_last_zero = C.at[-1].set(0.0)
    _, X = jax.lax.scan(backward, jnp.zeros_like(R[0]), (Dp, Rp, C_last_zero), reverse=True)
    return X


def _bordered_solve(Hpp, Hps, D, C, bp, bs):
    """Solve the lifted normal equations `[[Hpp, Hps], [Hps^T, T]] [xp; xs] = [bp; bs]` (`T`
    block tridiagonal: diagonal blocks `D`, upper blocks `C`) for `m` right-hand sides, `bp`
    `(n_p, m)` and `bs` `(S, n_s, m)`: the block Thomas recursion for `T`, and the Schur
    complement on `p`."""
    n_p = Hpp.shape[0]
    Y = _block_tridiagonal_solve(D, C, jnp.concatenate([jnp.swapaxes(Hps, 1, 2), bs], axis=2))
    Yp, Yb = Y[:, :, :n_p], Y[:, :, n_p:]
    schur = Hpp - jnp.einsum("kps,ksq->pq", Hps, Yp)
    xp = jnp.linalg.solve(schur, bp - jnp.einsum("kps,ksm->pm", Hps, Yb))
    return xp, Yb - jnp.einsum("ksp,pm->ksm", Yp, xp)


@jax.jit
def lm_step(B, lam, p_free, s0_free):
    """A Levenberg--Marquardt step of the lifted problem (damping `lam` times the diagonal),
    and the reduction of the loss `0.5 |r|^2` that its linear model predicts."""
    Hpp, Hps, D, C, gp, gs = _normal_blocks(B, p_free, s0_free)
    diag_p, diag_s = jnp.diag(Hpp), jax.vmap(jnp.diag)(D)
    floor = 1e-12 * jnp.maximum(jnp.max(diag_p), jnp.max(diag_s))
    damp_p, damp_s = lam * jnp.maximum(diag_p, floor), lam * jnp.maximum(diag_s, floor)
    xp, xs = _bordered_solve(Hpp + jnp.diag(damp_p), Hps, D + jax.vmap(jnp.diag)(damp_s), C,
                             gp[:, None], gs[:, :, None])
    dp, ds = -xp[:, 0], -xs[:, :, 0]
    g_dot = gp @ dp + jnp.sum(gs * ds)
    damped = jnp.sum(damp_p * dp**2) + jnp.sum(damp_s * ds**2)
    return dp, ds, 0.5 * (damped - g_dot)


@jax.jit
def condense(B, p_free, s0_free):
    """The condensed problem in `z = (p, s_0)`: the linearised continuity conditions give
    `ds_k = a_k + Psi_k dz`; returns the normal matrix and gradient of the data residuals in
    `z` (the single-shooting ones where the defects vanish), `a` and `Psi`."""
    N, g, P, G, E, d = B["N"], B["g"], B["P"], B["G"], B["E"], B["d"]
    S, n_s = G.shape[0], G.shape[2]
    n_p = P.shape[2]
    n_z = n_p + n_s
    E = E.at[-1].set(-jnp.eye(n_s, dtype=E.dtype))  # the last segment has no successor
    sel_p = jnp.eye(n_p, n_z, dtype=N.dtype)

    def step(carry, inp):
        a, Psi = carry
        P_k, G_k, E_k, d_k = inp
        a_n = -jnp.linalg.solve(E_k, d_k + G_k @ a)
        Psi_n = -jnp.linalg.solve(E_k, P_k @ sel_p + G_k @ Psi)
        return (a_n, Psi_n), (a, Psi)

    start = (jnp.zeros(n_s, N.dtype), jnp.eye(n_s, n_z, n_p, dtype=N.dtype))
    _, (a, Psi) = jax.lax.scan(step, start, (P, G, E, d))
    T = jnp.concatenate([jnp.broadcast_to(sel_p, (S, n_p, n_z)), Psi], axis=1)
    H = jnp.einsum("kiz,kij,kjy->zy", T, N, T)
    Na = jnp.einsum("kij,kj->ki", N[:, :, n_p:], a)
    grad = jnp.einsum("kiz,ki->z", T, g + Na)
    free = jnp.concatenate([p_free, s0_free])
    H = jnp.where(free[:, None] & free[None, :], H, 0.0)
    return H, jnp.where(free, grad, 0.0), a, Psi


def identifiable(B, s0_free, tol) -> np.ndarray:
    """Components of `z = (p, s_0)` that the data depend on: a column of the condensed
    (single-shooting) Jacobian, or of the segments' own data Jacobians, above `tol` times the
    largest column of the same kind. (Where the dynamics amplify a perturbation over the
    record, the condensed columns of the components that feed the instability grow by as much:
    on issue 20's 3e5-sample wheel record, beside them the gyro bias and the initial attitude,
    seen directly by every segment's data, looked like zero columns and were held at their
    starting values. The segments' own columns are not propagated across segments.)"""
    n_p = B["P"].shape[2]
    H, *_ = condense(B, np.ones(n_p, bool), s0_free)
    N = np.asarray(B["N"])
    data = np.concatenate([np.diag(N[:, :n_p, :n_p].sum(axis=0)),
                           np.diag(N[0, n_p:, n_p:]) * np.asarray(s0_free)])

    def above(squares):
        norms = np.sqrt(np.maximum(np.nan_to_num(squares, nan=0.0, posinf=np.inf), 0.0))
        top = norms.max()
        return norms > tol * top if np.isfinite(top) else np.isposinf(norms)

    return above(np.diag(np.asarray(H))) | above(data)


@jax.jit
def lifted_covariance(B, p_free, s0_free):
    """The covariance of `z = (p, s_0)` at the lifted optimum, over the residual variance:
    the estimator is the minimiser of the lifted loss at these continuity weights, so the
    covariance is the sandwich `H^-1 A H^-1` (restricted to `z`), where `H` is the lifted
    normal matrix (data and continuity residuals) and `A` its data part: only the data are
    noisy. The columns `H^-1 e_z` come from the block Thomas recursion and the Schur
    complement on `p`, as the steps do, so the cost stays linear in the segments.

    Where the defects close, the condensed matrix (`condense`) gives single shooting's
    covariance; on a record where the dynamics amplify a perturbation over the record (issue
    20's 1e5-sample wheel record: a state error grows 1e5-fold in its second half), closing
    the defects is out of reach in floating point. The lifted estimator lets the segments
    shadow the data, and its covariance is larger than what the tied-up (condensed or tightly
    weighted) problem would claim: 1.5-3 times in some standard deviations there."""
    Hpp, Hps, D, C, _, _ = _normal_blocks(B, p_free, s0_free)
    N = B["N"]
    S, n_s, n_p = D.shape[0], D.shape[1], Hpp.shape[0]
    n_z = n_p + n_s
    # Right-hand sides e_z: unit vectors of p, and of s_0 (in the first segment's rows).
    bp = jnp.eye(n_p, n_z, dtype=D.dtype)
    bs = jnp.zeros((S, n_s, n_z), D.dtype).at[0].set(jnp.eye(n_s, n_z, n_p, dtype=D.dtype))
    xp, xs = _bordered_solve(Hpp, Hps, D, C, bp, bs)
    X = jnp.concatenate([jnp.broadcast_to(xp, (S, n_p, n_z)), xs], axis=1)  # H^-1 e_z by segment
    fp = p_free.astype(N.dtype)
    fs = jnp.ones((S, n_s), N.dtype).at[0].set(s0_free.astype(N.dtype))
    X = X * jnp.concatenate([jnp.broadcast_to(fp, (S, n_p)), fs], axis=1)[:, :, None]
    cov = jnp.einsum("kiz,kij,kjy->zy", X, N, X)
    free = jnp.concatenate([p_free, s0_free])
    return jnp.where(free[:, None] & free[None, :], cov, 0.0)


@jax.jit
def condensed_step(B, p_free, s0_free):
    """A constrained Gauss--Newton step: `dz` from the condensed normal equations, each
    segment's state change from the linearised continuity conditions; and `dz^T H dz`, the
    step's squared length in the metric of the estimate's covariance (times the residual
    variance)."""
    H, grad, a, Psi = condense(B, p_free, s0_free)
    free = jnp.concatenate([p_free, s0_free])
    dz = -jnp.linalg.solve(H + jnp.diag(jnp.where(free, 0.0, 1.0)), grad)
    n_p = p_free.shape[0]
    return dz[:n_p], a + jnp.einsum("ksz,z->ks", Psi, dz), dz @ H @ dz


def continuity_weights(B, lay: Layout, rho: float = _CONTINUITY) -> np.ndarray:
    """Scale-free continuity weights from blocks linearised with unit weights: for each state
    variable, the root-mean-square sensitivity of the next segment's data to a defect."""
    N, E = np.asarray(B["N"]), np.asarray(B["E"])
    n_p = np.asarray(B["P"]).shape[2]
    if E.shape[0] < 2:
        return np.ones(E.shape[1])
    Einv = np.linalg.pinv(E[:-1])
    sens = np.einsum("kji,kjl,kli->ki", Einv, N[1:, n_p:, n_p:], Einv)
    sens = np.sqrt(np.maximum(np.mean(sens, axis=0), 0.0))
    w, start = np.ones_like(sens), 0
    for size in lay.s_sizes:
        v = float(np.sqrt(np.mean(sens[start:start + size] ** 2)))
        # A variable that no data see: any positive weight (it does not change the fit).
        w[start:start + size] = v if v > 0 and np.isfinite(v) else 1.0
        start += size
    return rho * w


def memory_per_segment(points: int, unknowns: int, state_size: int, residual_width: int,
                       itemsize: int) -> int:
    """Rough bytes per segment of one linearisation (saved states with their tangents, the
    outputs and the residual Jacobian)."""
    return points * (unknowns + 1) * (state_size + 3 * residual_width) * itemsize


def chunk(n_segments: int, per_segment: int) -> int:
    """Segments per batch of a linearisation, so that a batch holds about `_MEMORY` bytes,
    and at most `_CPU_BATCH` on a CPU: a batch integrates its segments in lockstep, each
    waiting for the slowest, which costs more there than the batching saves (issue 20's
    1e4-sample wheel record, 31 segments, loaded 2-core CPU: 1.5 s per linearisation in one
    batch, 0.6 s in batches of 8, 0.8 s one by one)."""
    cap = _CPU_BATCH if jax.default_backend() == "cpu" else 1024
    return int(max(1, min(n_segments, cap, _MEMORY // max(per_segment, 1))))


@stored_filter_jit
def _simulate_to(problem, scene, y0, ts, *, max_steps):
    from .._simulate import simulate_unchecked
    from .._tolerance import ScaledPIDController

    traj = simulate_unchecked(
        scene, y0, ts[-1], t0=ts[0], ts=ts,
        stepsize_controller=ScaledPIDController(rtol=problem.rtol, atol=problem.atol),
        max_steps=max_steps, events=False)
    from .._outcome import is_success

    return traj.ys, is_success(traj.outcome)


class Shooting:
    """Multiple shooting of one fit problem over one record (see the module's docstring)."""

    def __init__(self, problem, lay: Layout, templates, seg: Segments, n_obs: int):
        # A segment spans a few natural time units: a trial point that needs many more steps
        # is rejected early (every segment of a batch waits for the slowest).
        self.max_steps = min(problem.max_steps, _SEGMENT_STEPS)
        self.lay, self.templates, self.seg, self.n_obs = lay, templates, seg, n_obs
        # (The host's work between the compiled programs is NumPy's: each eager `jax.numpy`
        # operation is a program of its own, compiled on its first call in a process; a first
        # fit by multiple shooting compiled about 140 of them, 2 s of its 11 s.)
        # (`device_put` gives the dtype `jnp.asarray` would: float32 without 64-bit mode.)
        self.seg_ts = jax.device_put(seg.ts)
        self.seg_data = {k: jax.device_put(v) for k, v in seg.data.items()}
        self.seg_w = jax.device_put(seg.weights)
        self.has_next = jax.device_put(seg.has_next)
        n_p, n_s = sum(lay.p_sizes), sum(lay.s_sizes)
        # u (the problem's unknowns) as components of z = (p, s_0).
        p_off = dict(zip(lay.p_names, np.cumsum((0,) + lay.p_sizes)[:-1]))
        s_off = dict(zip(lay.s_names, n_p + np.cumsum((0,) + lay.s_sizes)[:-1]))
        index = []
        s0_free = np.zeros(n_s, bool)
        for n, size, is_state in zip(problem.names, problem.sizes, problem.is_state):
            start = s_off[n] if is_state else p_off[n]
            index.extend(range(start, start + size))
            if is_state:
                s0_free[start - n_p:start - n_p + size] = True
        self.z_of_u = np.asarray(index)
        self.p_of_u = self.z_of_u[self.z_of_u < n_p]
        self.u_is_p = self.z_of_u < n_p
        self.s0_free = s0_free
        self.n_p, self.n_s = n_p, n_s
        S, M = seg.weights.shape
        width = sum(int(np.prod(v.shape[2:])) for v in seg.data.values())
        state_size = sum(lay.s_sizes) + 1
        per = memory_per_segment(M + 1, n_p + n_s, state_size, width,
                                 jnp.dtype(problem.dtype).itemsize)
        self.batch = chunk(S, per)

    @property
    def segments(self) -> int:
        return int(self.seg.weights.shape[0])

    def anchor(self, problem, u):
        """Starting segment states: the data at each segment's first sample where they
        measure a state variable (less the bias being fitted), else a simulation of the
        starting guess; segment 0 is the initial state at `u`."""
        from ._fit import _BIAS, _scene_and_state

        scene, y0 = _scene_and_state(problem, u)
        starts = self.seg.ts[:, 0]  # (the program's call converts it as `seg_ts`)
        steps = max(problem.max_steps, 2000 * self.segments)
        ys, ok = _simulate_to(problem, scene, y0, starts, max_steps=steps)
        y0 = {n: np.asarray(v) for n, v in y0.items()}
        if not bool(ok):
            ys = {n: np.broadcast_to(v, (self.segments,) + v.shape) for n, v in y0.items()}
        ys = {n: np.array(v) for n, v in ys.items()}  # (writable copies)
        biases = [n for n in ys if n in self.seg_data and _BIAS + n in problem.names]
        values = _problem_values(problem, u) if biases else {}
        for n, v in ys.items():
            v[0] = y0[n]
            if n in self.seg_data:
                d = np.asarray(self.seg_data[n])[:, 0]
                if n in biases:
                    d = d - np.asarray(values[_BIAS + n])
                v[1:] = d[1:]
        return ys

    def series(self, problem, r) -> dict[str, np.ndarray]:
        """The data residuals `r` `(S, m)` of the segments as each output's residuals over
        the record's samples `(N, width)`, in time order."""
        from ._fit import _blocks, _width

        sizes = {name: (self.seg.data[name].shape[1], _width(kind, self.seg.data[name].shape[2:]))
                 for name, kind in zip(problem.outputs, problem.kinds)}
        valid = self.seg.weights > 0
        return {name: b[valid] for name, b in _blocks(np.asarray(r), sizes).items()}

    def _lin(self, problem, p, s, smaps, wc):
        problem = dataclasses.replace(problem, max_steps=self.max_steps)
        return linearise(problem, self.lay, p, s, smaps, self.seg_ts, self.seg_data,
                         self.seg_w, self.has_next, wc, batch=self.batch)

    def start(self, problem, u, resume=None):
        """Anchored segment states, their parameterisations, continuity weights and the
        first linearisation at `u`; or, with `resume` (`(p, s, smaps)` of an earlier run on
        this record), from that run's segment states."""
        if resume is None:
            ys = self.anchor(problem, u)
            smaps, s = bind_segments(self.templates, self.lay.s_names, ys)
            s = np.asarray(s)
            p = np.asarray(u)[self.p_of_u]
        else:
            p, s, smaps = resume
        ones = np.ones(self.n_s, p.dtype)
        B = self._lin(problem, p, s, smaps, ones)
        # A segment whose integration fails from its starting state has no residuals: no
        # step of the lifted problem can start (and its weights are undefined).
        bad = ~(np.all(np.isfinite(np.asarray(B["r"])), axis=1)
                & np.all(np.isfinite(np.asarray(B["d"])), axis=1))
        if bad.any():
            k, n = int(np.argmax(bad)), int(bad.sum())
            others = f" and {n - 1} other segment{'s' if n > 2 else ''}" if n > 1 else ""
            raise RuntimeError(
                f"multiple shooting: the integration of segment {k + 1} of {self.segments} "
                f"(t = {self.seg.ts[k, 0]:g} to {self.seg.ts[k, -1]:g}){others} failed from "
                f"its starting state: its step budget ({self.max_steps} steps per segment) "
                f"ran out or its state left the finite numbers; loosen rtol, or fit fewer "
                f"samples")
        wc = np.asarray(continuity_weights(B, self.lay), p.dtype)
        return p, s, smaps, wc, _weighted(B, wc)

    def free(self, problem, u, tol):
        """Components of `u` that the data determine (see `identifiable`), at the start."""
        _, _, _, _, B = self.start(problem, u)
        return identifiable(B, self.s0_free, tol)[self.z_of_u]

    def u_of(self, p, s, u_like):
        z = np.concatenate([p, s[0]])
        return jax.device_put(z[self.z_of_u].astype(u_like.dtype))

    def integration_variance(self, problem) -> float:
        """The variance of a weighted residual that the integration's error alone gives:
        `rtol` times each output's size, over its `sigma`, averaged over the samples'
        components."""
        from ._fit import _data_scale

        valid = self.seg.weights > 0
        total, count = 0.0, 0
        for name, kind, sigma in zip(problem.outputs, problem.kinds, problem.sigma):
            d = self.seg.data[name][valid]
            floor = float(problem.rtol) * _data_scale(d, kind) / np.asarray(sigma, float)
            width = int(np.prod(d.shape[1:])) if kind != "rotation" else 3
            total += d.shape[0] * float(np.sum(np.broadcast_to(floor**2, (width,))))
            count += d.shape[0] * width
        return total / max(count, 1)

    def _levenberg_marquardt(self, problem, p, s, smaps, wc, B, p_free, tol, max_iter, tick,
                             history, floor=0.0):
        """Levenberg--Marquardt on the lifted problem; converged at a step or decrease below
        `tol` (relative), or where the undamped (Gauss--Newton) step's predicted decrease is
        below `floor`: then without another linearisation, whose decrease would be round-off
        and its step as often rejected as accepted."""
        loss = _lifted(B)
        history.append(loss)
        tick(loss)
        lam, nu, converged, k = 1e-3, 2.0, False, 0
        for k in range(1, max_iter + 1):  # noqa: B007
            if floor > 0 and float(lm_step(B, 0.0, p_free, self.s0_free)[2]) <= floor:
                converged = True
                k -= 1
                break
            dp, ds, predicted = lm_step(B, lam, p_free, self.s0_free)
            dp, ds = np.asarray(dp), np.asarray(ds)
            p1, s1 = p + dp, s + ds
            B1 = self._lin(problem, p1, s1, smaps, wc)
            loss1 = _lifted(B1)
            tick(loss1)
            predicted = float(predicted)
            ratio = (loss - loss1) / predicted if predicted > 0 else -1.0
            if np.isfinite(loss1) and ratio > 1e-4:
                small_step = _max_abs(dp, ds) <= tol * (1 + _max_abs(p1, s1))
                small_decrease = loss - loss1 <= tol * loss1 or predicted <= floor
                p, s, B, loss = p1, s1, B1, loss1
                # (Nielsen's update, and a tenth where the linear model predicted the decrease
                # to 1 %: the lifted problem is nearly linear near its optimum, and a third per
                # step took 9 steps to undo the starting damping on the 1e5-sample wheel
                # record. At ratios of 0.9-0.95 a tenth overshot on a 1e5-sample torque-free
                # record: each next step was rejected, 46 steps where Nielsen's took 23.)
                lam *= 0.1 if ratio > 0.99 else max(1 / 3, 1 - (2 * ratio - 1) ** 3)
                nu = 2.0
                history.append(loss)
                if small_step or small_decrease:
                    converged = True
                    break
            else:
                lam *= nu
                nu *= 2
                history.append(loss)
                if lam > 1e16:
                    break
        return p, s, B, k, converged

    def run(self, problem, u, free, tol, max_iter, tick, stages=None, resume=None):
        """Levenberg--Marquardt on the lifted problem from `u` (or from the segment states of
        an earlier run, `resume`: see `start`), then constrained Gauss--Newton steps that close
        the continuity defects; returns the run's summary (as single shooting's) with the
        normal matrix `H` of `u`, the sums of squares by output and the segment states
        (`lifted`, to resume from)."""
        free = np.asarray(free)
        p_free = free[self.u_is_p]
        p, s, smaps, wc, B = self.start(problem, u, resume)
        # Continuation in the continuity weight: nearly independent segments first (each
        # prediction starts in phase with its data: the basin of a short record), then tied.
        # A run resumed from an optimum (the same record, other output weights) needs no
        # lifted stage: the condensed steps below start at closed defects.
        stages = (_STAGES if stages is None else stages) if resume is None else ()
        history, iterations, converged = [], 0, not stages
        for i, factor in enumerate(stages):
            if i == 0:
                B = _weighted(B, np.asarray(factor, wc.dtype))
            else:
                B = self._lin(problem, p, s, smaps, wc * factor)
            p, s, B, k, converged = self._levenberg_marquardt(
                problem, p, s, smaps, wc * factor, B, p_free,
                max(tol, _LIFTED_TOL), max_iter, tick, history)
            iterations += k
        wc = wc * (stages[-1] if stages else 1.0)
        # Close the defects: constrained Gauss-Newton (condensed) steps, which converge
        # quadratically from the lifted optimum. They stop at a step below `tol` (relative)
        # or, on noisy data, below `_INSIGNIFICANT` standard deviations of the estimate: the
        # integration's own error (at `rtol`) moves the segments' ends, so steps driven by it
        # never vanish, and a loss or defect criterion would wait for them in vain.
        # On a record so long that the condensed steps lose their precision (sensitivities
        # propagated over hundreds of segments, through dynamics that amplify them), the
        # steps are hopelessly long or stop shrinking: the fit then keeps the lifted optimum,
        # whose defects are far below the data's noise, with its own covariance.
        closed = False
        dof = max(self.n_obs - int(np.sum(free)), 1)
        variance = lambda B: float(np.sum(np.asarray(B["ss"]))) / dof  # noqa: E731 (residuals')
        # (On noise-free data the residuals are the integration's error: a standard
        # deviation is never taken below what that error alone gives.)
        lifted_optimum = (p, s, B)
        s2 = max(variance(B), self.integration_variance(problem))
        previous = _HOPELESS**2 * s2
        for _ in range(8):
            dp, ds, metric = condensed_step(B, p_free, self.s0_free)
            dp, ds, metric = np.asarray(dp), np.asarray(ds), float(metric)
            # Longer than the last step, or a first step `_HOPELESS` standard deviations
            # long: the condensed linearisation has no precision left.
            if not metric < previous:
                break
            previous = metric
            p1, s1 = p + dp, s + ds
            B1 = self._lin(problem, p1, s1, smaps, wc)
            tick(_lifted(B1))
            if not np.isfinite(_lifted(B1)):
                break
            step = _max_abs(dp, ds)
            p, s, B = p1, s1, B1
            iterations += 1
            history.append(_lifted(B))
            if step <= tol * (1 + _max_abs(p, s)) or metric <= _INSIGNIFICANT**2 * s2:
                closed = True
                break
        if closed:
            # Closing (S - 1) n_s defects, each far below the noise, adds about that many
            # residual variances to the data's sum of squares at most; a closed point that
            # explains the data worse came from a linearisation without precision.
            constraints = (self.segments - 1) * self.n_s
            closed = (float(np.sum(np.asarray(B["ss"])))
                      - float(np.sum(np.asarray(lifted_optimum[2]["ss"])))
                      <= 2 * max(constraints, 1) * s2)
        if closed:
            H, *_ = condense(B, p_free, self.s0_free)
        else:
            # The lifted optimum, converged at `tol` (the stages stop at `_LIFTED_TOL`) or
            # where a step would move the estimate by less than `_INSIGNIFICANT` standard
            # deviations (its predicted decrease of the loss is half the square of that
            # length, in units of the residual variance), and the estimator's own covariance
            # (`lifted_covariance`), as a normal matrix.
            p, s, B = lifted_optimum
            floor = 0.5 * _INSIGNIFICANT**2 * s2
            p, s, B, k, closed = self._levenberg_marquardt(
                problem, p, s, smaps, wc, B, p_free, tol, max_iter, tick, history, floor)
            iterations += k
            cov = np.asarray(lifted_covariance(B, p_free, self.s0_free))
            fixed = ~np.concatenate([p_free, self.s0_free])
            H = np.where(fixed[:, None] | fixed[None, :], 0.0,
                         np.linalg.inv(cov + np.diag(fixed.astype(cov.dtype))))
        ss = np.asarray(B["ss"]).sum(axis=0)
        series = self.series(problem, B["r"])  # (the data residuals at the last point)
        data_loss = 0.5 * float(ss.sum())
        u_fit = self.u_of(p, s, u)
        Hu = np.asarray(H)[np.ix_(self.z_of_u, self.z_of_u)]
        return {"loss": data_loss if np.isfinite(data_loss) else np.inf, "u": u_fit,
                "converged": bool(converged and closed), "iterations": iterations,
                "history": np.asarray(history), "stages": (0,), "H": Hu, "ss": ss,
                "series": series, "lifted": (p, s, smaps),
                "defect": float(np.max(np.abs(np.asarray(B["d"]))))}


def _max_abs(a, b) -> float:
    return float(max(np.max(np.abs(a)), np.max(np.abs(b))))


def _lifted(B) -> float:
    return 0.5 * float(np.sum(np.asarray(B["ss"])) + np.sum(np.asarray(B["d"]) ** 2))


@stored_filter_jit
def _problem_values(problem, u):
    """`problem.values(u)` as one compiled program (eager, each of its operations is one)."""
    return problem.values(u)
