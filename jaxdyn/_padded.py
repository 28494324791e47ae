"""Padded lengths: a new number of times reuses a compiled program.

A `jax.jit` program is specialised to the shapes of its inputs, so a function of an array of
times compiles anew for each number of times: 0.4 s for `traj.evaluate(t)`, 1.4-1.8 s for
`torque_free_omega`, 2.8-3.3 s for `torque_free_attitude` on 2 cores, at each move of a
notebook's slider over the time span or the resolution. Where each time is treated alone
(nothing couples one time to another), the times are padded to one of a few lengths
(`padded_length`: four per octave) and the padding is cut off afterwards by a small program of
its own (one per count and shape), so a new count costs a call.
"""

import functools
from collections.abc import Callable

import jax
import numpy as np

from ._validation import is_concrete


def padded_length(n: int) -> int:
    """The length `n` times are padded to: at least 16, then four lengths per octave (16, 20,
    24, 28, 32, 40, ...), so that at most a fifth of the work is padding."""
    if n <= 16:
        return 16
    octave = 1 << (n.bit_length() - 1)  # the power of two at or below n
    return next(octave * k // 4 for k in (4, 5, 6, 7, 8) if n <= octave * k // 4)


def over_padded_times(fn: Callable, t, *inputs):
    """`fn(t)` for a function that treats each time alone and returns arrays (or a tree of
    them) with a leading axis over the flattened times (`t`: any shape): evaluated over the
    times padded with the last one to `padded_length`, the padding cut off and the leading
    axis reshaped to `t.shape`. Where `t` or any of the other `inputs` `fn` depends on is
    traced (the caller's `jit`, `grad` or `vmap`), `fn(t)` as it is: the caller's program has
    one length."""
    if not is_concrete(t, *inputs):
        return fn(t)
    t = np.asarray(t)
    n = t.size
    padded = np.empty(padded_length(n), t.dtype)
    padded[:n] = t.reshape(-1)
    padded[n:] = padded[n - 1] if n else 0
    return _cut(fn(padded), n, t.shape)


@functools.partial(jax.jit, static_argnums=(1, 2))
def _cut(out, n, shape):
    """The first `n` rows of each array of `out`, the first axis reshaped to `shape`."""
    return jax.tree.map(lambda x: x[:n].reshape(shape + x.shape[1:]), out)
