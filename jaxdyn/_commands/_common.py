"""Helpers shared by subcommands."""

import json
from typing import Any


def enable_x64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


def parse_sets(items: list[str]) -> dict[str, Any]:
    """`--set NAME=VALUE` items as a dict of parsed values."""
    from .._scenefile import parse_value
    from .._validation import ParameterError

    out = {}
    for item in items:
        if "=" not in item:
            raise ParameterError(f"--set {item!r}: expected NAME=VALUE")
        name, text = item.split("=", 1)
        out[name.strip()] = parse_value(name.strip(), text)
    return out


def fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.10g}"
    if isinstance(value, dict):
        return ", ".join(f"{k}={fmt(v)}" for k, v in value.items())
    if isinstance(value, list):
        return "[" + ", ".join(fmt(v) for v in value) + "]"
    return str(value)


def emit(out: dict[str, Any], as_json: bool, title: str = "") -> None:
    """Print one JSON object, or a readable `key: value` summary."""
    if as_json:
        print(json.dumps(out, indent=2))
        return
    if title:
        print(title)
    for key, value in out.items():
        print(f"  {key}: {fmt(value)}")
