"""Distributions for ensembles, and their text form (`normal(0, 0.01)`) for the command line.

Each trajectory `i` of an ensemble draws its values from `jax.random.fold_in(key, i)`, and each
varied name from its own sub-key, so a trajectory's sample depends only on the key, its index
and the name: never on the chunk size, the number of devices, or what else is varied.
"""

import abc
import ast
import re
import zlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from ._validation import ParameterError, format_value


class AbstractDistribution(eqx.Module):
    """A distribution of a value (a scalar, or an array whose shape broadcasts against the
    varied quantity)."""

    @abc.abstractmethod
    def sample(self, key: Array, shape: tuple[int, ...], dtype) -> Array:
        """One draw of shape `shape`."""

    @abc.abstractmethod
    def shifted(self, c: ArrayLike) -> "AbstractDistribution":
        """The distribution of `c + X`."""

    @abc.abstractmethod
    def scaled(self, c: ArrayLike) -> "AbstractDistribution":
        """The distribution of `c * X`."""

    @property
    @abc.abstractmethod
    def shape(self) -> tuple[int, ...]:
        """Shape of the distribution's own parameters."""

    def __check_init__(self):
        for name, value, ok, allowed in self._checks():
            if not bool(np.all(ok)):
                raise ParameterError(
                    f"{type(self).__name__} {name}={format_value(value)}: {allowed}")

    def _checks(self):
        return []


def _arr(x):
    a = np.asarray(x, dtype=float)
    if not np.all(np.isfinite(a)):
        raise ParameterError(f"distribution parameter {format_value(x)}: must be finite")
    return a


class Normal(AbstractDistribution):
    """Normal distribution with mean `mean` and standard deviation `std` (`std >= 0`)."""

    mean: np.ndarray = eqx.field(converter=_arr)
    std: np.ndarray = eqx.field(converter=_arr)

    def _checks(self):
        return [("std", self.std, self.std >= 0, "must be >= 0")]

    def sample(self, key, shape, dtype):
        return (jnp.asarray(self.mean, dtype)
                + jnp.asarray(self.std, dtype) * jax.random.normal(key, shape, dtype))

    def shifted(self, c):
        return Normal(self.mean + np.asarray(c, float), self.std)

    def scaled(self, c):
        c = np.asarray(c, float)
        return Normal(self.mean * c, self.std * np.abs(c))

    @property
    def shape(self):
        return np.broadcast_shapes(self.mean.shape, self.std.shape)


class Uniform(AbstractDistribution):
    """Uniform distribution on `[low, high]` (`low <= high`)."""

    low: np.ndarray = eqx.field(converter=_arr)
    high: np.ndarray = eqx.field(converter=_arr)

    def _checks(self):
        return [("high", self.high, self.high >= self.low, f"must be >= low={self.low}")]

    def sample(self, key, shape, dtype):
        return jax.random.uniform(key, shape, dtype, jnp.asarray(self.low, dtype),
                                  jnp.asarray(self.high, dtype))

    def shifted(self, c):
        c = np.asarray(c, float)
        return Uniform(self.low + c, self.high + c)

    def scaled(self, c):
        c = np.asarray(c, float)
        a, b = self.low * c, self.high * c
        return Uniform(np.minimum(a, b), np.maximum(a, b))

    @property
    def shape(self):
        return np.broadcast_shapes(self.low.shape, self.high.shape)


class LogNormal(AbstractDistribution):
    """`scale * exp(sigma * Z)`, `Z` standard normal: positive, with median `scale` (`scale > 0`,
    `sigma >= 0`). `lognormal(1, 0.01)` is a relative spread of about 1%."""

    scale: np.ndarray = eqx.field(converter=_arr)
    sigma: np.ndarray = eqx.field(converter=_arr)

    def _checks(self):
        return [("scale", self.scale, self.scale > 0, "must be > 0"),
                ("sigma", self.sigma, self.sigma >= 0, "must be >= 0")]

    def sample(self, key, shape, dtype):
        return jnp.asarray(self.scale, dtype) * jnp.exp(
            jnp.asarray(self.sigma, dtype) * jax.random.normal(key, shape, dtype))

    def shifted(self, c):
        raise ParameterError("a lognormal distribution cannot be shifted: use NAME*=lognormal(...)"
                             " (a relative spread about the scene's value) or NAME=lognormal(...)")

    def scaled(self, c):
        c = np.asarray(c, float)
        if np.any(c <= 0):
            raise ParameterError(f"lognormal scaled by {format_value(c)}: the scene's value must "
                                 "be positive")
        return LogNormal(self.scale * c, self.sigma)

    @property
    def shape(self):
        return np.broadcast_shapes(self.scale.shape, self.sigma.shape)


class Fixed(AbstractDistribution):
    """A fixed value (every trajectory gets `value`)."""

    value: np.ndarray = eqx.field(converter=_arr)

    def sample(self, key, shape, dtype):
        return jnp.broadcast_to(jnp.asarray(self.value, dtype), shape)

    def shifted(self, c):
        return Fixed(self.value + np.asarray(c, float))

    def scaled(self, c):
        return Fixed(self.value * np.asarray(c, float))

    @property
    def shape(self):
        return self.value.shape


_DISTRIBUTIONS = {"normal": (Normal, 2), "uniform": (Uniform, 2), "lognormal": (LogNormal, 2)}

DISTRIBUTION_SYNTAX = (
    "NAME=DIST, NAME+=DIST (added to the scene's value) or NAME*=DIST (multiplying it); NAME is a "
    "parameter (inertia, length, rotor.momentum, ...) or an initial value (omega, theta, ...), "
    "optionally one component (omega[1]); DIST is normal(MEAN, STD), uniform(LOW, HIGH), "
    "lognormal(MEDIAN, SIGMA) or a number; arguments are numbers or lists ([0.1, 1, 0.1])"
)

_VARY = re.compile(r"^\s*([A-Za-z_][\w.]*)\s*(\[[^\]]*\])?\s*([+*]?=)\s*(.+?)\s*$")
_CALL = re.compile(r"^([a-z]+)\s*\((.*)\)$", re.S)


def parse_distribution(text: str) -> AbstractDistribution:
    """A distribution from its text form: `normal(MEAN, STD)`, `uniform(LOW, HIGH)`,
    `lognormal(MEDIAN, SIGMA)`, or a number (a fixed value). Arguments may be lists."""
    text = text.strip()
    m = _CALL.match(text)
    if m is None:
        if re.search(r"\b(True|False|None)\b", text):
            raise ParameterError(f"distribution {text!r}: expected a number, not True, False "
                                 "or None")
        try:
            return Fixed(ast.literal_eval(text))
        except (ValueError, SyntaxError, TypeError, ParameterError):
            raise ParameterError(
                f"distribution {text!r}: expected normal(MEAN, STD), uniform(LOW, HIGH), "
                "lognormal(MEDIAN, SIGMA) or a number") from None
    name, inner = m.groups()
    if re.search(r"\b(True|False|None)\b", inner):
        raise ParameterError(f"distribution {text!r}: arguments must be numbers or lists of "
                             "numbers (not True, False or None)")
    if name not in _DISTRIBUTIONS:
        raise ParameterError(
            f"distribution {name!r} in {text!r}: allowed are {sorted(_DISTRIBUTIONS)}")
    cls, nargs = _DISTRIBUTIONS[name]
    try:
        args = ast.literal_eval(f"({inner},)")
    except (ValueError, SyntaxError):
        raise ParameterError(f"distribution {text!r}: arguments must be numbers or lists "
                             "of numbers") from None
    if len(args) != nargs:
        raise ParameterError(f"distribution {text!r}: {name} takes {nargs} arguments, "
                             f"got {len(args)}")
    try:
        return cls(*args)
    except (TypeError, ValueError) as e:
        if isinstance(e, ParameterError):
            raise ParameterError(f"distribution {text!r}: {e}") from None
        raise ParameterError(f"distribution {text!r}: arguments must be numbers or lists "
                             "of numbers") from None


def parse_vary(text: str) -> tuple[str, str, AbstractDistribution]:
    """`"omega[1]+=normal(0, 0.01)"` -> `("omega[1]", "+=", Normal(0, 0.01))`."""
    m = _VARY.match(text)
    if m is None:
        raise ParameterError(f"--vary {text!r}: expected {DISTRIBUTION_SYNTAX}")
    name, index, op, dist = m.groups()
    return name + (index or ""), op, parse_distribution(dist)


def split_name(name: str) -> tuple[str, tuple[int, ...] | None]:
    """`"omega[1]"` -> `("omega", (1,))`; `"inertia"` -> `("inertia", None)`."""
    m = re.match(r"^([A-Za-z_][\w.]*)(?:\[([^\]]*)\])?$", name.strip())
    if m is None:
        raise ParameterError(f"varied name {name!r}: expected NAME or NAME[i] (NAME[i, j])")
    base, index = m.groups()
    if index is None:
        return base, None
    try:
        idx = tuple(int(v) for v in index.split(","))
    except ValueError:
        raise ParameterError(f"varied name {name!r}: indices must be integers") from None
    return base, idx


def name_seed(name: str) -> int:
    """A stable per-name sub-key seed (independent of what else is varied)."""
    return zlib.crc32(name.encode()) & 0x7FFFFFFF
