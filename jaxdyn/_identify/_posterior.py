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
stay at their values. NUTS (Hoffman and Gelman 2014) with Stan's window adaptation of the step
size and a dense mass matrix (started from the Gauss--Newton covariance); its gradients come
from forward mode through the integrator, like the fit's Jacobians.
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
    """`draws` NUTS draws of `u` (the free components sampled, the others fixed at `u`), and
    the mean acceptance rate."""
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
    warm = blackjax.window_adaptation(
        blackjax.nuts, log_density, is_mass_matrix_diagonal=False,
        initial_inverse_mass_matrix=cov + 1e-12 * jnp.eye(v0.size, dtype=v0.dtype),
        adaptation_info_fn=lambda *a: None)
    # blackjax's adaptation schedule mixes Python integers and booleans: traced under the
    # standard promotion rules, whatever the caller's (strict promotion, as in the tests).
    with jax.numpy_dtype_promotion("standard"):
        (state, params), _ = warm.run(k_warm, v0, num_steps=warmup)
    kernel = blackjax.nuts(log_density, **params)

    def step(state, k):
        state, info = kernel.step(k, state)
        return state, (state.position, info.acceptance_rate)

    _, (vs, acceptance) = jax.lax.scan(step, state, jax.random.split(k_draw, draws))
    return jax.vmap(full)(vs), jnp.mean(acceptance)
