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
