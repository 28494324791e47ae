"""Input checks shared by every public entry point.

A check is a triple `(field, violated, allowed)`: `violated` is a boolean array, true where the
value is not allowed. The same triple is raised eagerly as a `ParameterError` when the value is
concrete, and attached with `eqx.error_if` when the value is only known inside `jit`.
"""

from collections.abc import Iterable

import jax
import jax.numpy as jnp
import numpy as np

from ._errors import (
    ParameterError as ParameterError,
    format_value as format_value,
    message as message,
)

Check = tuple[str, object, jax.Array | bool, str]
"""`(field, value, violated, allowed)`: `field` names what is checked and `allowed` says what it
may be, both fixed text (not formatted from the values: under a trace the values are unknown,
and an ensemble reads the messages once per structure, `Scene.violation_messages`)."""


def is_concrete(*xs) -> bool:
    """True when none of `xs` is a tracer, so their values can be inspected eagerly."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(xs))


def raise_if_violated(checks: Iterable[Check]) -> None:
    """Raise `ParameterError` for the first violated check whose value is concrete."""
    for field, value, violated, allowed in checks:
        if is_concrete(value, violated) and bool(np.any(np.asarray(violated))):
            raise ParameterError(message(field, value, allowed))


def as_float_array(field: str, value, shape: tuple[int, ...] | None = None, dtype=None,
                   host: bool = False):
    """Convert `value` to a floating array, with a clear error for wrong types and shapes.
    `host=True`: a value not already a JAX array becomes a NumPy array on the host, always a
    copy (for a caller that passes it straight to a compiled program, whose call puts it on
    the device at a fraction of the cost of `jnp.asarray`; on a CPU that call may share the
    array's memory while the program runs asynchronously, so the caller's own array, which
    it may change after the call returns, is never the one passed)."""
    if isinstance(value, str | bytes) or value is None:
        raise ParameterError(message(field, value, "expected a number or an array of numbers"))
    if isinstance(value, jax.Array):
        arr = value
        if not jnp.issubdtype(arr.dtype, jnp.floating):
            arr = arr.astype(dtype or jnp.result_type(float))
    else:
        try:
            np_value = np.asarray(value)
        except (TypeError, ValueError) as e:
            raise ParameterError(message(field, value, "expected a number or an array")) from e
        if np_value.dtype.kind not in "biuf":
            raise ParameterError(message(field, value, "expected real numbers"))
        def convert(a, dtype=None):
            # A copy (`np.array`): the caller's own array is never the one used. Off the host,
            # it is put on the device, which compiles nothing (`jnp.asarray` compiled a
            # conversion program for each new shape and dtype).
            copy = np.array(a, dtype=dtype)
            return copy if host else jax.device_put(copy)

        if np_value.dtype.kind == "f" and dtype is None and np_value.dtype != np.float64:
            arr = convert(np_value)  # keep float32/float16 as given
        else:
            arr = convert(np_value, dtype=dtype or jnp.result_type(float))
    if dtype is not None and arr.dtype != dtype:
        arr = arr.astype(dtype)
    if shape is not None and arr.shape != shape:
        raise ParameterError(
            f"{field} has shape {arr.shape}: expected shape {shape}"
        )
    return arr


def as_rows(field: str, value, dtype=None):
    """An `(N, 3)` array of vectors, one per device (one vector alone is one row)."""
    arr = as_float_array(field, value, None, dtype)
    arr = arr[None] if arr.ndim == 1 else arr
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ParameterError(f"{field} has shape {arr.shape}: expected (N, 3)")
    if arr.shape[0] == 0:  # (a scene without such devices leaves the effect out)
        raise ParameterError(f"{field} has shape {arr.shape}: expected (N, 3) with N >= 1, "
                             "one row per device")
    return arr


def as_per_row(field: str, value, n: int, dtype):
    """An `(n,)` array, one value per device (one value alone is given to all)."""
    arr = as_float_array(field, value, None, dtype)
    arr = jnp.broadcast_to(arr, (n,)) if arr.ndim == 0 else arr
    if arr.shape != (n,):
        raise ParameterError(f"{field} has shape {arr.shape}: expected ({n},)")
    return arr


def on_host(*xs):
    """`(np, *xs as NumPy arrays)` where all of `xs` are concrete, else `(jnp, *xs)`: a check of
    concrete values is computed by NumPy on the host, where it costs no compiled program (each
    eager `jax.numpy` operation is one, looked up in the compilation cache on every new
    process: about 10-20 ms each on a warm command)."""
    if is_concrete(*xs):
        return (np, *(np.asarray(x) for x in xs))
    return (jnp, *xs)


def device_array(x, dtype):
    """`x` as a JAX array of `dtype`: a concrete value is converted by NumPy and put on the
    device, which compiles nothing (`jnp.asarray` would compile a conversion program)."""
    if is_concrete(x):
        return jax.device_put(np.asarray(x, dtype))
    return jnp.asarray(x, dtype)


def key_from_seed(seed: int):
    """`jax.random.key(seed)`, made on the host: the same key, without the two small programs
    (`stage`, `_threefry_seed`) that `jax.random.key` compiles on its first call (0.02-0.04 s
    of a cold command). For the default implementation (threefry2x32) with 64-bit integers
    enabled, as in the command, the key's data are the seed's high and low 32 bits; otherwise
    `jax.random.key` itself."""
    seed = int(seed)
    if (jax.config.jax_default_prng_impl != "threefry2x32" or not jax.config.jax_enable_x64
            or not -(2**63) <= seed < 2**63):
        return jax.random.key(seed)
    return jax.random.wrap_key_data(
        np.array([(seed >> 32) & 0xFFFFFFFF, seed & 0xFFFFFFFF], np.uint32))


def finite_check(field: str, x) -> Check:
    xp, v = on_host(x)
    return (field, x, ~xp.isfinite(v), "must be finite")


def nonnegative_check(field: str, x) -> Check:
    xp, v = on_host(x)
    return (field, x, ~(xp.isfinite(v) & (v >= 0)), "must be finite and non-negative")


def positive_check(field: str, x) -> Check:
    xp, v = on_host(x)
    return (field, x, ~((v > 0) & xp.isfinite(v)), "must be positive and finite")


def nonzero_unit(field: str, x, axis: int = -1):
    """`x / |x|` (overflow-safe), refusing a zero vector (or a zero row) by name when `x` is
    concrete; a traced zero vector gives NaN, caught by the scene's finiteness checks."""
    from ._rotations import unit

    if is_concrete(x):
        a = np.asarray(x)
        zero = ~np.any(a != 0, axis=axis)
        if np.any(zero):
            raise ParameterError(message(field, x, "must be nonzero (it is normalised to a "
                                         "unit vector)"))
        return unit_on_host(a, axis)
    return unit(x, axis=axis)


def unit_on_host(x, axis: int = -1):
    """`_rotations.unit(x)` of a concrete `x`, computed by NumPy as `unit` computes it (scaled by
    the largest component first) and put on the device: `unit`'s eager operations compiled a
    dozen programs. A zero or non-finite vector gives NaN, as there."""
    a = np.asarray(x)
    if not np.issubdtype(a.dtype, np.inexact):
        a = a.astype(jax.dtypes.canonicalize_dtype(np.float64))
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        big = np.max(np.abs(a), axis=axis, keepdims=True)
        big = np.where(np.isfinite(big) & (big > 0), big, np.ones((), a.dtype))
        norm = big * np.sqrt(np.sum((a / big) ** 2, axis=axis, keepdims=True))
        return jax.device_put(a / norm)
