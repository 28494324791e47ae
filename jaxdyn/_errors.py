"""The error for invalid input, and how values are shown in its messages (numpy only: the
command reports input errors without importing JAX)."""

import numpy as np


class ParameterError(ValueError):
    """Raised for invalid input: the message names the field, the value and what is allowed."""


def format_value(value) -> str:
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError):
        return repr(value)
    if arr.dtype.kind not in "biuf":  # text, mixed lists: as written
        return repr(value)
    if arr.ndim == 0:
        return f"{arr.item():g}" if arr.dtype.kind == "f" else repr(arr.item())
    return np.array2string(arr, separator=", ", precision=6, max_line_width=10_000).replace(
        "\n", ""
    )


def message(field: str, value, allowed: str) -> str:
    return f"{field}={format_value(value)}: {allowed}"


# The code a warning is never attributed to: jaxdyn and the libraries it calls back through
# (a transformation of the caller's runs jaxdyn's code from inside JAX's).
_LIBRARIES = ("jaxdyn", "jax", "jaxlib", "equinox", "diffrax", "optimistix", "lineax",
              "functools", "contextlib")


def warn(text: str, category: type[Warning] = UserWarning) -> None:
    """`warnings.warn(text, category)` attributed to the caller's own line: the first frame
    outside jaxdyn and its libraries, however deep inside them the warning is raised and
    whatever wraps the public function (a fixed `stacklevel` pointed at a decorator's line
    once `jd.fit` was wrapped). The immediate caller where every frame is jaxdyn's. (The
    command line shows a warning as one line without its location: `_cli._show_warning`.)"""
    import sys
    import warnings

    frame, level = sys._getframe(1), 1
    while frame is not None and str(frame.f_globals.get("__name__", "")).split(".")[0] \
            in _LIBRARIES:
        frame, level = frame.f_back, level + 1
    warnings.warn(text, category, stacklevel=level + 1 if frame is not None else 2)
