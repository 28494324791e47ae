"""`equinox.filter_jit` whose programs are kept between processes (`_programs`).

For programs that are called with modules (a fit's problem, its parameterisations) rather
than with a scene's flat leaves: the arguments are split as `filter_jit` splits them (arrays
traced, everything else static), and the program of each static part is a `StoredProgram`,
so that a warm `jaxdyn fit` reads its Levenberg--Marquardt program (and its other small
ones) instead of tracing them. Where the compilation cache is off, or the static part names
code outside jaxdyn and its libraries, it is `jax.jit` of the same function, traced as
usual.
"""

import functools

import equinox as eqx
import jax

from ._programs import StoredProgram


def stored_filter_jit(fn=None, *, unless=None, light=False):
    """`eqx.filter_jit(fn)`, stored per static part (see the module's docstring). Outputs
    must be arrays (or modules of arrays). `unless(kwargs)`: calls that are traced as usual
    (for example those holding a host callback, which cannot be stored). `light`: its stored
    programs compiled with XLA's cheap settings where called with concrete arrays
    (`_programs`; not the calls that go to `filter_jit`)."""
    if fn is None:
        return functools.partial(stored_filter_jit, unless=unless, light=light)
    plain = eqx.filter_jit(fn)
    name = f"{fn.__module__}.{fn.__qualname__}"
    programs: dict = {}

    def program_for(args, kwargs):
        """The stored program for the static part of these arguments and its array leaves,
        or `None` (an unhashable static value: `filter_jit`'s own call, which refuses it)."""
        dynamic, static = eqx.partition((args, kwargs), eqx.is_array)
        leaves, treedef = jax.tree_util.tree_flatten(dynamic)
        static_leaves, static_def = jax.tree_util.tree_flatten(static)
        key = (treedef, static_def, tuple(static_leaves))
        try:
            program = programs.get(key)
        except TypeError:
            return None, leaves
        if program is None:
            def flat(*leaves):
                a, k = eqx.combine(jax.tree_util.tree_unflatten(treedef, leaves), static)
                return fn(*a, **k)

            flat.__name__ = flat.__qualname__ = fn.__name__  # JAX's logs name it after `fn`
            program = programs[key] = StoredProgram(
                name, f"{treedef}|{static_def}|{static_leaves!r}", (), flat, light=light)
        return program, leaves

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if unless is not None and unless(kwargs):
            return plain(*args, **kwargs)
        program, leaves = program_for(args, kwargs)
        if program is None:
            return plain(*args, **kwargs)
        return program(*leaves)

    def prepare(*args, **kwargs):
        """Have the program for arguments like these made ready on another core while the
        caller compiles (`StoredProgram.prepare`)."""
        if unless is not None and unless(kwargs):
            return
        program, leaves = program_for(args, kwargs)
        if program is not None:
            program.prepare(*leaves)

    call.prepare = prepare
    return call
