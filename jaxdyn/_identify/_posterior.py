r"""A posterior sampled by NUTS (blackjax) through the fit's own residuals.

Where the Gauss--Newton approximation cannot be trusted (near a direction the data hardly
determine, as the axes of a nearly axisymmetric body), the posterior of the fitted
quantities is sampled instead, in each parameterisation's sampling coordinates `w`
(`AbstractParameterisation.sampling`; for [`jaxdyn.ValidInertia`][] the linear coordinates of
the body's shape, smooth where two moments are equal and at a flat plate):

$$\log p(w \mid d) = -\frac{|r(w)|^2}{2 s^2} + \log p(w) + \mathrm{const},$$

a Gaussian likelihood of the fit's residuals `r` (weighted as in the fit) with the noise
variance `s^2` estimated at the optimum, and each parameterisation's prior
(`AbstractParameterisation.log_prior`: for an inertia, uniform in its principal moments over
the physical bodies and over its axes; Gaussian of standard deviation 10 around the starting
point for the other components). Components that
the data do not determine stay at their values.

Diagnosed on a nearly axisymmetric thin body (moments 1, 1.001, 2: also nearly a flat plate),
where one chain in the moments-and-axes coordinates with a prior uniform in them covered 73 %
of 90 % intervals: that prior piles up where those coordinates are singular (a flat plate is
a shape logit at infinity, a plateau of the likelihood that the chain wandered into, up to
500 leapfrog steps per draw), and the matrix logarithm of the shape kept a one-sided tail in
the flat-plate direction (split R-hat 1.7 over four chains). In the linear coordinates the
posterior is nearly Gaussian up to the physical boundary: about 6 leapfrog steps per draw
and R-hat near 1. A trajectory that leaves the physical bodies counts as divergent (and is
rejected): divergences are expected where the posterior reaches that boundary (on that body,
up to a few tens per chain of 50 draws on the seeds whose posterior reaches the flat plate;
as many with a prior uniform over the tensor as with the prior uniform in the moments).
A prior uniform over the tensor (in the linear coordinates) made nearly equal moments rare:
its density in the moments carries the Vandermonde factor, and the posterior's central 90 %
intervals of the larger of the two close moments covered the truth in 63 % of 40 noise
draws (both moments 79 %).

Several chains (NUTS, Hoffman and Gelman 2014), side by side on a CPU's cores,
started dispersed around the optimum (twice the Gauss--Newton spread), each with the
Gauss--Newton covariance in the sampling coordinates as its (dense) inverse mass matrix and its
step size adapted by dual averaging during warm-up (whose trajectories are bounded more tightly
than the draws', `WARMUP_DOUBLINGS`); gradients come from forward mode through
the integrator, like the fit's Jacobians. The chains' agreement is checked by the split
potential scale reduction (R-hat, Gelman et al. 2013) and their effective sample size.
"""

import concurrent.futures
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._errors import warn
from .._programs import start_prepared

RHAT_MAX = 1.05  # above this split R-hat, the chains disagree: a warning
ACCEPTANCE_MIN = 0.3  # below this mean acceptance rate (NUTS aims at 0.8), a chain is stuck
# The most trajectory doublings of one NUTS draw: at most 2**10 - 1 = 1023 leapfrog steps (Stan's
# and blackjax's default). Draws that reach it are counted (`"max_depth_draws"`) and said in a
# warning where they are many. Measured on the coverage benchmark's 12 seeds (28 Nov 2026) and
# not kept: a bound of 7 doublings for the draws as well (with the warm-up started from Hoffman
# and Gelman's reasonable step size) held the truth in 19 of 24 central 90 % intervals against
# 24 of 24 (truncated trajectories explore less, and 50 draws per chain are few); the
# reasonable start alone took 16 % fewer gradients, holding it in 20 of 24.
MAX_DOUBLINGS = 10
# The most doublings of one warm-up step: 2**7 - 1 = 127 leapfrog steps. Most of the sampling time
# on a nearly axisymmetric body was the warm-up's: while dual averaging still searches, a chain
# whose step size is briefly small builds trees of up to 1023 steps (the near-plate body of
# tests/test_posterior.py, key 3: one chain's 100 warm-up steps took about 12800 leapfrog steps,
# 9700 of them in 13 steps, its 50 draws 750). The warm-up only adapts the step size and brings the
# chain to the posterior's bulk, so its trajectories are bounded; the draws keep NUTS's full bound,
# so they are exact NUTS as before. (blackjax's own staged warm-up bounds its trees to 5 doublings
# for the same reason.) Measured on the near-plate body of tests/test_posterior.py, keys 1, 2, 4
# after a first fit that compiled: a fit with its posterior in 11.7-18.4 s against 25.6-31.7 s,
# split R-hat 1.018-1.035 against 0.996-1.067 (see benchmarks/latency-log.md, 7 Dec 2026, s38).
WARMUP_DOUBLINGS = 7
DEPTH_WARN = 0.1  # a warning when more than this fraction of a chain's draws reach the bound
# Where the chains disagree and more than this fraction of all draws were divergent, the
# warning says that the posterior lies against the edge of the prior's support.
EDGE_SHARE = 0.5
DISPERSION = 2.0  # chains start at this many Gauss--Newton standard deviations


def _import_blackjax():
    try:
        import blackjax
    except ImportError:
        from .._validation import ParameterError

        raise ParameterError(
            "posterior=...: sampling needs blackjax (pip install 'jaxdyn[posterior]')"
        ) from None
    return blackjax


def _split(problem, x):
    offsets = np.cumsum((0,) + problem.sizes)
    return [x[a:b] for a, b in zip(offsets[:-1], offsets[1:])]


def _to_sampling(problem, sampled, u):
    """The sampling coordinates of the fit's unconstrained vector `u`."""
    return jnp.concatenate([s.to_unconstrained(m(part)).astype(u.dtype) for m, s, part
                            in zip(problem.maps, sampled.maps, problem.split(u))])


def _log_density(sampled, w, free_index, w_start, free, ts, data, weights, s2):
    """The log posterior density of the free components `v` of `w` (gradient by forward
    mode), and the map from `v` to the whole of `w`."""

    def full(v):
        return w.at[free_index].set(v)

    def f(v):
        x = full(v)
        prior = sum(m.log_prior(p, p0, fr) for m, p, p0, fr in zip(
            sampled.maps, _split(sampled, x), _split(sampled, w_start),
            _split(sampled, free)))
        # Outside the prior's support (a body that is not physical) the density is zero
        # whatever the residuals, so they are not integrated there: the optimum `w` (a
        # physical body) is integrated instead, so a proposal far outside costs what one
        # inside does (an inertia that breaks the triangle inequality can make the
        # integrator take many more steps).
        inside = jnp.isfinite(prior)
        r = sampled.residuals(jnp.where(inside, x, w), ts, data, weights)
        return jnp.where(inside, -0.5 * jnp.sum(r**2) / s2 + prior, -jnp.inf)

    def log_density_and_grad(v):
        # (The value as the primal of the forward-mode pass, one integration instead of two,
        # is the same to 1e-15 and compiled the chain in 7.3 s instead of 16.5 s, but over
        # seeds 0-5 of `benchmarks/identify.py --coverage 6`, twice each, 5 of 12 fits had a
        # split R-hat above 1.05 and one chain stuck, against 0 of 12 this way: kept until a
        # longer comparison says whether that was chance.)
        return f(v), jax.jacfwd(f)(v)

    @jax.custom_vjp
    def log_density(v):  # the value alone where no gradient is asked for (a chain's start)
        return f(v)

    def fwd(v):
        return log_density_and_grad(v)

    def bwd(grad, cotangent):
        return (cotangent * grad,)

    log_density.defvjp(fwd, bwd)
    return log_density, full


@eqx.filter_jit
def _mass_and_starts(cov, v0, key, chains):
    """The inverse mass matrix (the covariance `cov` of the sampling coordinates), and the
    chains' starting points (dispersed around `v0`)."""
    # The Gauss--Newton covariance in the sampling coordinates is the inverse mass matrix:
    # where the approximation holds it has the posterior's scales and correlations (a few
    # leapfrog steps per draw); where it does not the sampler stays exact, only slower.
    # (A dense mass matrix estimated from a few hundred warm-up draws, as Stan's windows do,
    # was measured to need about 290 leapfrog steps per draw on the well-determined body of
    # tests/test_posterior.py, against a handful here.) It comes from the residuals' Jacobian
    # in the sampling coordinates themselves (`sample`).
    inverse_mass = 0.5 * (cov + cov.T)
    inverse_mass = inverse_mass + 1e-12 * jnp.trace(inverse_mass) * jnp.eye(v0.size,
                                                                              dtype=v0.dtype)
    z = jax.random.normal(key, (chains, v0.size), v0.dtype)
    return inverse_mass, v0 + DISPERSION * z @ jnp.linalg.cholesky(inverse_mass).T


@eqx.filter_jit
def _chain(*args, draws, warmup):
    """`draws` NUTS draws of one chain (`_chain_in_standard_promotion`), traced under JAX's
    standard dtype promotion (blackjax's code promotes implicitly) whatever the caller's: under
    `jax_numpy_dtype_promotion="strict"` outside, the functions traced both inside and outside
    the chain's scan were lowered twice (12867 lines of StableHLO against 11132 for the same
    chain), so a process in either mode compiled its own program where the other's, in JAX's
    persistent cache, would have served (`tests/` run strict, the notebooks standard)."""
    with jax.numpy_dtype_promotion("standard"):
        return _chain_in_standard_promotion(*args, draws=draws, warmup=warmup)


def _chain_in_standard_promotion(sampled, w, free_index, w_start, free, ts, data, weights, s2,
                                 inverse_mass, start, key, *, draws, warmup):
    """`draws` NUTS draws of one chain of the free components of `w` (the others fixed) from
    `start`, with each draw's acceptance rate, divergence, leapfrog steps and energy, and
    the leapfrog steps of each warm-up step."""
    blackjax = _import_blackjax()
    log_density, full = _log_density(sampled, w, free_index, w_start, free, ts, data,
                                     weights, s2)
    da_init, da_update, da_final = blackjax.adaptation.step_size.dual_averaging_adaptation(0.8)

    def nuts(step_size, doublings):
        return blackjax.nuts(log_density, step_size=step_size, inverse_mass_matrix=inverse_mass,
                             max_num_doublings=doublings)

    # Warm-up and draws in one scan (the step size adapted by dual averaging while warming
    # up, then fixed at its final value; the warm-up's trees bounded by WARMUP_DOUBLINGS, the
    # draws' by MAX_DOUBLINGS, one or the other taken by `lax.cond`).
    def one_step(carry, xs):
        state, da, final = carry
        k, warming = xs
        step_size = jnp.where(warming, jnp.exp(da.log_step_size), final)
        state, info = jax.lax.cond(
            warming, lambda: nuts(step_size, WARMUP_DOUBLINGS).step(k, state),
            lambda: nuts(step_size, MAX_DOUBLINGS).step(k, state))
        da = jax.tree.map(lambda new, old: jnp.where(warming, new, old),
                          da_update(da, info.acceptance_rate), da)
        final = jnp.where(warming, da_final(da), final)
        return (state, da, final), (state.position, info.acceptance_rate, info.is_divergent,
                                    info.num_integration_steps, info.energy,
                                    info.num_trajectory_expansions >= MAX_DOUBLINGS)

    k_warm, k_draw = jax.random.split(key)
    # A dispersed start outside the support (a body that is not physical, where the optimum
    # lies near that boundary) would never move: such a chain starts at the optimum instead.
    start = jnp.where(jnp.isfinite(log_density(start)), start, w[free_index])
    da = da_init(jnp.asarray(1.0, start.dtype))
    keys = jnp.concatenate([jax.random.split(k_warm, warmup), jax.random.split(k_draw, draws)])
    warming = jnp.arange(warmup + draws) < warmup
    _, (vs, *out) = jax.lax.scan(one_step, (nuts(1.0, MAX_DOUBLINGS).init(start), da,
                                            da_final(da)),
                                 (keys, warming))
    warm_steps = out[2][:warmup]
    vs, out = vs[warmup:], [x[warmup:] for x in out]
    return (jax.vmap(full)(vs), *out, warm_steps)


def _split_halves(x):
    """Each chain cut into its two halves (chains, draws, ...) -> (2 chains, draws // 2, ...):
    the split R-hat also catches a chain that drifts."""
    half = x.shape[1] // 2
    return np.concatenate([x[:, :half], x[:, half:2 * half]], axis=0)


@functools.cache
def _rhat_and_ess():
    """blackjax's split R-hat and effective sample size as one compiled program: called
    eagerly, they traced and compiled their loops anew on every fit (0.25 s of a 2.4 s fit
    with `posterior=200`)."""
    blackjax = _import_blackjax()
    return jax.jit(lambda split: (blackjax.diagnostics.potential_scale_reduction(split),
                                  blackjax.diagnostics.effective_sample_size(split)))


def diagnostics(x, energy, acceptance, divergent, steps, deep, warm_steps, names):
    """Convergence diagnostics of draws `x` (chains, draws, components) named `names`."""
    split = _split_halves(np.asarray(x, np.float64))
    rhat, ess = (np.asarray(v) for v in _rhat_and_ess()(split))
    # Energy Bayesian fraction of missing information (Betancourt 2016) of each chain: below
    # about 0.3, the momentum resampling cannot move the chain across the energy levels (a
    # heavy tail or a funnel).
    energy = np.asarray(energy, np.float64)
    bfmi = (np.sum(np.diff(energy, axis=1) ** 2, axis=1)
            / np.sum((energy - energy.mean(axis=1, keepdims=True)) ** 2, axis=1))
    return {
        "chains": int(x.shape[0]), "draws_per_chain": int(x.shape[1]),
        "rhat": dict(zip(names, rhat.tolist())), "ess": dict(zip(names, ess.tolist())),
        "max_rhat": float(np.max(rhat)), "min_ess": float(np.min(ess)),
        "acceptance": np.asarray(acceptance).mean(axis=1).tolist(),
        "divergences": np.asarray(divergent).sum(axis=1).astype(int).tolist(),
        "leapfrogs": np.asarray(steps).mean(axis=1).tolist(), "bfmi": bfmi.tolist(),
        "max_depth_draws": np.asarray(deep).sum(axis=1).astype(int).tolist(),
        "warmup_leapfrogs": np.asarray(warm_steps).mean(axis=1).tolist(),
    }


def sample(problem, u, free, u_start, ts, data, weights, s2, covariance, key, summaries, *,
           draws, warmup, chains):
    """Posterior draws of the fitted quantities (`summaries(problem, u, free)` of each draw,
    `draws` in all) and the chains' diagnostics (see `FitResult.posterior_diagnostics`).

    `free` is the NumPy mask of the fitted components of `u`, `u_start` the fit's starting
    point (the prior's centre), `covariance(sampled, w)` the Gauss--Newton covariance of the
    coordinates `w` of the problem `sampled` at `w` (with the prior's spread along the
    directions the data do not determine); `covariance(sampled, w, prepare=True)` has the
    program it needs, if any, made ready on another core (`StoredProgram.prepare`)."""
    free = np.asarray(free)
    maps = tuple(m.sampling(f) for m, f in zip(problem.maps, _split(problem, free)))
    if any(s.size() != m.size() for s, m in zip(maps, problem.maps)):
        raise ValueError("a sampling parameterisation must have as many components as its own")
    sampled = eqx.tree_at(lambda p: p.maps, problem, maps)
    w = _to_sampling(problem, sampled, u)
    index = np.nonzero(free)[0]
    per_chain = -(-draws // chains)
    # The covariance in the sampling coordinates from the residuals' Jacobian there, not the
    # fit's carried over by the Jacobian `G` of the change of coordinates (`G cov G^T`,
    # exact in exact arithmetic): at an optimum on the flat plate, where the fit's shape
    # logits run off towards infinity, `G` is singular (a singular value of 3e-12 on the
    # 1 : 2 : 3 plate) and the fit's variance along that logit 8e14, and their product was
    # round-off: a standard deviation of 0.077 for a shape coordinate whose posterior spreads
    # 4e-4, so NUTS's draws ran to their bound of 1023 leapfrog steps (4 chains of 50 draws:
    # 711 steps per draw, 68 % of the draws at the bound, 207 s against 37 s). On the nearly
    # flat body of notebook 09 the two agree to four digits.
    # Its Jacobian's program, where one is needed, is compiled on the other core while the
    # chains' program compiles here. A first fit with its posterior on the nearly
    # axisymmetric body of tests/test_posterior.py (2 cores, compilation cache on): 33.3-35.8
    # s against 34.0-37.5 s before that Jacobian was needed; with the cache off, where
    # nothing is prepared (`StoredProgram.prepare`), 36.6-38.1 s against 30.8-32.6 s.
    covariance(sampled, w, prepare=True)
    # One compiled program, called for each chain on a thread of its own. Vmapped, the
    # chains' nested loops (NUTS's trajectories around the integrator's steps) were measured
    # to run tens of times slower on a CPU; XLA:CPU runs a call on one core without Python's
    # lock, so chains called from threads run side by side on a CPU's cores, where calls
    # from one thread run one after the other (the nearly axisymmetric body of notebook 09,
    # 2 cores: 47 s for its four chains against 80 s). A thread per chain: the longest chain
    # then starts at once. Traced and compiled here, with every input already a JAX array,
    # under the caller's settings (`jax.enable_x64`, `jax.default_device` and the like are
    # per thread as context managers); the threads only call the program, and each chain's
    # draws are those it gives alone. A call cannot be interrupted: a chain that fails, or
    # Ctrl-C, is reported once the chains already running have ended.
    common = jax.tree.map(
        lambda x: jnp.asarray(x) if isinstance(x, (np.ndarray, np.generic)) else x,
        (sampled, w, index, _to_sampling(problem, sampled, u_start), free, ts, data, weights,
         s2))
    k_start, k_chains = jax.random.split(key)
    keys = jax.random.split(k_chains, chains)
    static = dict(draws=per_chain, warmup=warmup)  # (the compiled program ignores their values)
    if not jax.config.jax_disable_jit:
        # Lowered for the shapes of the inverse mass matrix and a start (their values are
        # the program's inputs), before they are known.
        shaped = jnp.zeros((index.size, index.size), w.dtype), jnp.zeros(index.size, w.dtype)
        lowered = _chain.lower(*common, *shaped, keys[0], **static)
        start_prepared()
        chain = lowered.compile()
    cov = np.asarray(covariance(sampled, w))
    inverse_mass, starts = _mass_and_starts(
        jax.device_put(cov[index][:, index].astype(w.dtype)), w[index], k_start, chains)
    common = (*common, inverse_mass)
    if jax.config.jax_disable_jit:  # (no compiled program: each chain run as Python)
        def run(starts, keys):
            return [_chain(*common, start, k, **static) for start, k in zip(starts, keys)]
    else:
        def run(starts, keys):
            with concurrent.futures.ThreadPoolExecutor(len(keys)) as pool:
                return list(pool.map(
                    lambda start, k: jax.block_until_ready(chain(*common, start, k, **static)),
                    starts, keys))
    runs = run(starts, keys)
    # A chain that accepted almost none of its proposals (its step size adapted to a region
    # where NUTS cannot move, as a dispersed start next to the flat plate) is run again once,
    # from the optimum with a key of its own; its first run is discarded and the restart is
    # said in the diagnostics (`"restarted"`). On the nearly flat plate of
    # `tests/test_posterior.py` (4 chains of 50 draws), whether a chain sticks is chaotic in
    # the fit's round-off, and in the machine's: with this fit none of 48 chains stuck (keys
    # 1-12); with Nielsen's damping in the fit (measured and not kept), 2 of 48 stuck at
    # acceptances of about 0.02, the test's key among them (28 Nov 2026), and on another
    # machine none of the same 48 (29 Nov 2026; none of 160 with Marquardt's damping). A
    # chain that is stuck again is kept, and warned about.
    stuck = _stuck([float(np.mean(r[1])) for r in runs])
    if stuck:
        again = run([np.asarray(w)[index]] * len(stuck),
                    [jax.random.fold_in(keys[i], 1) for i in stuck])
        for i, r in zip(stuck, again):
            runs[i] = r
    ws, acceptance, divergent, steps, energy, deep, warm_steps = (
        jnp.stack(x) for x in zip(*runs))
    names = [c for name, m in zip(sampled.names, sampled.maps) for c in m.components(name)]
    report = diagnostics(np.asarray(ws)[:, :, index], energy, acceptance, divergent, steps,
                         deep, warm_steps, [names[i] for i in index])
    report["restarted"] = stuck
    flat = ws.reshape(-1, ws.shape[-1])[:draws]
    out = jax.tree.map(np.asarray, jax.vmap(lambda x: summaries(sampled, x, free))(flat))
    warn_on_diagnostics(report)
    return out, report


def _stuck(acceptance):
    """The chains whose mean acceptance rates `acceptance` are below `ACCEPTANCE_MIN` (or not
    a number): stuck."""
    return [i for i, a in enumerate(acceptance) if not a >= ACCEPTANCE_MIN]


def warn_on_diagnostics(report):
    """The warnings of `fit(posterior=...)` on its chains' diagnostics (`diagnostics`): the
    chains disagree (split R-hat), a chain is stuck (acceptance), or many draws reached
    NUTS's bound of leapfrog steps."""
    chains, per_chain = report["chains"], report["draws_per_chain"]
    bad = {k: round(v, 3) for k, v in report["rhat"].items() if not v <= RHAT_MAX}
    if bad:
        # A trajectory that leaves the prior's support (a body that is not physical) is
        # divergent. Where most are, the posterior lies against that edge (a body fitted
        # on the flat plate, I3 = I1 + I2): NUTS's trajectories stop there, so the chains
        # move in short steps and need more draws to agree (on the noisy 1 : 2 : 3 plate,
        # 4 chains of 50 draws: split R-hat 1.6-1.75, every draw divergent; of 400 draws:
        # 1.08). Said, since "sample longer" is then the remedy, not a sign of a bad fit.
        divergent = sum(report["divergences"])
        edge = (f" {divergent} of the {chains * per_chain} draws were divergent. A "
                "trajectory that leaves the prior's support (a body that is not physical, as "
                "past the flat plate I3 = I1 + I2) is: where the posterior lies against that "
                "edge, the chains move in short steps and need more draws to agree."
                if divergent > EDGE_SHARE * chains * per_chain else "")
        warn(
            f"posterior: the halves of the {chains} chain(s) disagree (split R-hat above "
            f"{RHAT_MAX}: {bad}); "
            "the draws are not yet a sample of the posterior." + edge + " Sample longer "
            "(larger warmup= and posterior=), or compare with the Gauss-Newton intervals "
            "(FitResult.std).",
            RuntimeWarning)
    stuck = {i: round(report["acceptance"][i], 3) for i in _stuck(report["acceptance"])}
    if stuck:
        # (The split R-hat can miss it: a chain that hardly moves has almost no spread of
        # its own.)
        warn(
            f"posterior: chain(s) {sorted(stuck)} accepted almost none of their proposals "
            f"(mean acceptance {stuck}, below {ACCEPTANCE_MIN}; NUTS aims at 0.8): their "
            "draws repeat a few points and are not a sample of the posterior. Sample again "
            "with another key=, or longer (larger warmup=).",
            RuntimeWarning)
    capped = {i: n for i, n in enumerate(report["max_depth_draws"])
              if n > DEPTH_WARN * per_chain}
    if capped:
        warn(
            f"posterior: draws of chain(s) {sorted(capped)} reached NUTS's bound of "
            f"{2**MAX_DOUBLINGS - 1} leapfrog steps ({capped} of {per_chain} draws each): the "
            "trajectories were cut short and the chains explore slowly (a posterior far from "
            "the Gauss-Newton approximation's scales). Compare the draws with "
            "FitResult.std, or sample longer (larger posterior=).",
            RuntimeWarning)
