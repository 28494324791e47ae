r"""A posterior sampled by NUTS (blackjax) through the fit's own residuals.

Where the Gauss--Newton approximation cannot be trusted (near a direction the data hardly
determine, as the axes of a nearly axisymmetric body), the posterior of the unconstrained
vector `u` is sampled instead:

$$\log p(u \mid d) = -\frac{|r(u)|^2}{2 s^2}
  - \sum_i \frac{(u_i - u_{0,i})^2}{2 \cdot 10^2} + \mathrm{const},$$

a Gaussian likelihood of the fit's residuals `r` (weighted as in the fit) with the noise
variance `s^2` estimated at the optimum, and a weakly informative independent Gaussian prior
of standard deviation 10 on each fitted unconstrained component around the fit's starting
point (dimensionless for the inertia's log-scale, shape logits and axis Rodrigues parameters,
in the data's units for initial states and biases). Components that the data do not determine
stay at their values. NUTS (Hoffman and Gelman 2014) with the Gauss--Newton covariance as its
(dense) inverse mass matrix and the step size adapted by dual averaging during warm-up; its
gradients come from forward mode through the integrator, like the fit's Jacobians.
"""

import equinox as eqx
import jax
import jax.numpy as jnp

_PRIOR_SD = 10.0


def _import_blackjax():
    try:
        import blackjax
    except ImportError:
        from .._validation import ParameterError

        raise ParameterError(
            "posterior=...: sampling needs blackjax (pip install 'jaxdyn[posterior]')"
        ) from None
    return blackjax


@eqx.filter_jit
def sample(problem, u, free_index, u_prior, ts, data, weights, s2, cov, key, *, draws, warmup):
    """`draws` NUTS draws of `u` (the free components sampled, the others fixed at `u`), the
    mean acceptance rate and the mean number of leapfrog steps per draw."""
    blackjax = _import_blackjax()

    def full(v):
        return u.at[free_index].set(v)

    def log_density_and_grad(v):
        def f(v):
            r = problem.residuals(full(v), ts, data, weights)
            prior = jnp.sum((v - u_prior[free_index]) ** 2) / _PRIOR_SD**2
            return -0.5 * (jnp.sum(r**2) / s2 + prior)

        return f(v), jax.jacfwd(f)(v)

    @jax.custom_vjp
    def log_density(v):
        return log_density_and_grad(v)[0]

    def fwd(v):
        return log_density_and_grad(v)

    def bwd(grad, cotangent):
        return (cotangent * grad,)

    log_density.defvjp(fwd, bwd)
    k_warm, k_draw = jax.random.split(key)
    v0 = u[free_index]
    # The Gauss--Newton covariance is the inverse mass matrix: it already holds the
    # posterior's scales and correlations where the approximation holds, and where it does
    # not, the sampler stays exact (only slower). Warm-up adapts the step size alone (dual
    # averaging to an acceptance of 0.8): a dense mass matrix estimated from a few hundred
    # warm-up draws, as Stan's windows do, was measured to need about 290 leapfrog steps per
    # draw on the well-determined body of tests/test_posterior.py, against a handful here.
    inverse_mass = cov + 1e-12 * jnp.trace(cov) * jnp.eye(v0.size, dtype=v0.dtype)
    da_init, da_update, da_final = blackjax.adaptation.step_size.dual_averaging_adaptation(0.8)

    def warm_step(carry, k):
        state, da = carry
        kernel = blackjax.nuts(log_density, step_size=jnp.exp(da.log_step_size),
                               inverse_mass_matrix=inverse_mass)
        state, info = kernel.step(k, state)
        return (state, da_update(da, info.acceptance_rate)), None

    kernel = blackjax.nuts(log_density, step_size=1.0, inverse_mass_matrix=inverse_mass)
    da = da_init(jnp.asarray(1.0, v0.dtype))
    with jax.numpy_dtype_promotion("standard"):
        (state, da), _ = jax.lax.scan(warm_step, (kernel.init(v0), da),
                                      jax.random.split(k_warm, warmup))
    kernel = blackjax.nuts(log_density, step_size=da_final(da), inverse_mass_matrix=inverse_mass)

    def step(state, k):
        state, info = kernel.step(k, state)
        return state, (state.position, info.acceptance_rate, info.num_integration_steps)

    _, (vs, acceptance, steps) = jax.lax.scan(step, state, jax.random.split(k_draw, draws))
    return jax.vmap(full)(vs), jnp.mean(acceptance), jnp.mean(steps.astype(acceptance.dtype))
