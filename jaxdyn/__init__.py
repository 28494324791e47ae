"""jaxdyn: differentiable rigid-body dynamics in pure JAX."""
