"""JAX's persistent compilation cache, for the command and for notebooks.

Compiled programs are written to a directory and reused by later processes, so the second
`jaxdyn run` (or the second kernel start of a notebook) skips compilation. jaxdyn's public
programs carry no host callbacks (failures come back as outcome codes, raised on the host),
so JAX can cache every one of them. Beside JAX's entries, `jaxdyn-programs/` keeps the
programs jaxdyn builds once per structure, compiled for this machine
(`jaxdyn._programs`), which a later process loads without tracing them again.
"""

import os
from pathlib import Path

ENV = "JAXDYN_CACHE_DIR"
"""Environment variable: a directory for the cache, or `off` to turn it off."""


def default_cache_dir() -> Path | None:
    """`$JAXDYN_CACHE_DIR` (`None` where it is `off`), else `jaxdyn/jax` under the user's
    cache directory (`$XDG_CACHE_HOME`, else `~/.cache`)."""
    value = os.environ.get(ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "off", "0", "false", "no") else Path(value)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "jaxdyn" / "jax"


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache.

    **Arguments:**

    - `path`: the cache directory (created if needed). Default: `$JAXDYN_CACHE_DIR`, or
      `~/.cache/jaxdyn/jax` (under `$XDG_CACHE_HOME` where set); `JAXDYN_CACHE_DIR=off`
      leaves the cache off.

    **Returns:**

    The directory in use, or `None` where the cache stays off. Every program is cached
    however quickly it compiled (JAX's default keeps only those above one second); jaxdyn's
    own programs are also kept there, in `jaxdyn-programs/`, compiled for this machine.
    """
    import sys

    where = Path(path) if path is not None else default_cache_dir()
    if where is None:
        return None
    where = where.expanduser()
    where.mkdir(parents=True, exist_ok=True)
    settings = {"jax_compilation_cache_dir": str(where),
                "jax_persistent_cache_min_compile_time_secs": 0.0,
                "jax_persistent_cache_min_entry_size_bytes": 0}
    if "jax" in sys.modules:
        import jax

        for name, value in settings.items():
            jax.config.update(name, value)
    else:  # JAX reads these when it is first imported (a command that needs no JAX skips it)
        os.environ.update({name.upper(): str(value) for name, value in settings.items()})
    return where
