"""The `jaxdyn` command. Each subcommand is a module in `jaxdyn/_commands/` that defines
`HELP`, `add_arguments(parser)` and `run(args) -> int`, and `LAPACK = True` where its programs
call LAPACK (`jaxdyn._xla.lapack_without_scipy_linalg`); they are discovered automatically.

Errors: invalid input exits with status 2 and a one-line message; a failure at run time (a
runtime check inside `jit`, an exhausted step budget) exits with status 1 and a one-line message.

The console script is `console`: `main`, then the end of the process without the interpreter's
teardown (see `_end`).
"""

import argparse
import atexit
import gc
import importlib
import os
import pkgutil
import re
import sys
import threading
import time
import warnings
from typing import NoReturn


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # one line, exit status 2
        self.exit(2, f"jaxdyn: error: {message} (see 'jaxdyn --help')\n")


def _commands() -> dict[str, object]:
    from . import _commands as package

    out = {}
    for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda i: i.name):
        if not info.name.startswith("_"):
            out[info.name] = importlib.import_module(f"{package.__name__}.{info.name}")
    return out


def _build_parser(commands, argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser. Only the command named in `argv` gets its arguments (some derive their help
    from the bodies' declarations, which imports JAX); the others list their one-line help."""
    argv = sys.argv[1:] if argv is None else argv
    chosen = next((a for a in argv if a in commands), None)
    p = _Parser(prog="jaxdyn", description="Differentiable rigid-body dynamics in JAX.")
    _cache_arguments(p, None, False)
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for name, module in commands.items():
        command = sub.add_parser(name, help=module.HELP, description=module.HELP)
        if name == chosen:
            module.add_arguments(command)
        # Accepted after the command too; SUPPRESS keeps a value given before it.
        _cache_arguments(command, argparse.SUPPRESS, argparse.SUPPRESS)
    return p


def _cache_arguments(p, dir_default, off_default) -> None:
    p.add_argument("--cache-dir", metavar="DIR", default=dir_default,
                   help="JAX's persistent compilation cache (default: $JAXDYN_CACHE_DIR or "
                        "~/.cache/jaxdyn/jax): a second run of a command skips compiling")
    p.add_argument("--no-cache", action="store_true", default=off_default,
                   help="do not use the compilation cache (also JAXDYN_CACHE_DIR=off)")


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    (file or sys.stderr).write(f"jaxdyn: warning: {_squeezed(message)}\n")


def _fail(message: str, status: int = 2) -> NoReturn:
    sys.stderr.write(f"jaxdyn: error: {message}\n")
    raise SystemExit(status)


def _runtime_message(error: RuntimeError) -> str:
    """The message of an `eqx.error_if` failure, without equinox's debugging advice."""
    text = str(error)
    match = re.search(r"EquinoxRuntimeError: (.*)", text)
    line = match.group(1) if match else next(
        (ln.strip() for ln in text.splitlines() if ln.strip()), type(error).__name__)
    return line.replace("`max_steps`", "--max-steps").replace("max_steps", "--max-steps")


def main(argv: list[str] | None = None) -> int:
    t_start = time.perf_counter()
    from ._xla import add_settings

    add_settings()  # (before JAX starts: see `jaxdyn._xla`)
    commands = _commands()
    args = _build_parser(commands, argv).parse_args(argv)
    args.t_start = t_start
    if getattr(commands[args.command], "LAPACK", False):
        from ._xla import lapack_without_scipy_linalg

        lapack_without_scipy_linalg()  # (before JAX needs LAPACK: see `jaxdyn._xla`)
    from ._errors import ParameterError

    # The one error boundary: every failure ends in one line on stderr, never a traceback.
    try:
        with warnings.catch_warnings():
            # A warning is one line too, without a source location (a user's line in Python;
            # here the console script's, which tells the user nothing).
            warnings.showwarning = _show_warning
            if not args.no_cache:
                _enable_cache(args.cache_dir)
            return commands[args.command].run(args)
    except ParameterError as e:
        _fail(str(e), 2)
    except ModuleNotFoundError as e:
        if e.name == "matplotlib":
            _fail("plots need matplotlib: pip install 'jaxdyn[plot]'", 2)
        _fail(f"missing module {e.name!r}: reinstall jaxdyn", 1)
    except RecursionError:
        _fail("input nested too deeply (a scene file or value with deeply nested lists)", 2)
    except MemoryError:
        _fail("out of memory: use a smaller --n, --chunk or --samples", 1)
    except UnicodeError as e:
        _fail(f"input is not UTF-8 text ({e.reason} at byte {getattr(e, 'start', '?')})", 2)
    except BrokenPipeError:  # the reader of the output went away (`jaxdyn run | head`):
        # quietly, as Python's documentation advises (no message on the closed stream's
        # behalf; the rest of the output goes nowhere)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except OSError as e:  # the paths the user named: missing, unwritable, a folder...
        where = f" {e.filename!r}" if e.filename else ""
        _fail(f"cannot use{where}: {e.strerror or e}", 2)
    except RuntimeError as e:  # runtime checks inside jit (eqx.error_if), solver failures
        _fail(f"simulation failed: {_runtime_message(e)}", 1)
    except (TypeError, ValueError, OverflowError, KeyError, IndexError) as e:
        # Values of the wrong type or size that got past the checks: still the input's fault.
        _fail(f"invalid input: {_one_line(e)}", 2)
    except Exception as e:  # anything else: one line naming the cause
        _fail(f"failed: {type(e).__name__}: {_one_line(e)}", 1)


def _defer_full_collections() -> None:
    """No full garbage collections (CPython's generation 2) in the command's process; the
    younger generations are collected as usual. A command imports JAX, diffrax and their
    kin, then traces and compiles its programs: the heap grows throughout, and each full
    collection walks all of it again (0.05-0.3 s each; a cold `jaxdyn run` made two or three,
    0.15-0.2 s of its 3.1 s, measured on 7 Dec 2026). What a full collection would free is
    cyclic garbage that outlived two younger collections, which a command's bounded run
    hardly leaves: its processes' peak memory did not change (`jaxdyn montecarlo`, 2e5 runs).
    PyTorch's compiler defers them for the same reason while it compiles. For the command's
    own process only (`console`): `main` called in a caller's process leaves its collector
    alone."""
    young, middle, _ = gc.get_threshold()
    gc.set_threshold(young, middle, 1 << 30)


def _enable_cache(path: str | None) -> None:
    from ._cache import enable_compilation_cache

    try:
        enable_compilation_cache(path)
    except OSError as e:
        if path is not None:  # a directory the user named: their input
            raise
        sys.stderr.write(f"jaxdyn: warning: compilation cache off ({e.strerror or e}: "
                         f"{e.filename}); set JAXDYN_CACHE_DIR or --cache-dir\n")


def _squeezed(text) -> str:
    """`str(text)` on one line, its runs of white space one space."""
    return " ".join(str(text).split())


def _one_line(error: BaseException) -> str:
    text = _squeezed(error)
    return (text[:300] + "...") if len(text) > 300 else (text or type(error).__name__)


def console() -> NoReturn:
    """The `jaxdyn` command (and `python -m jaxdyn`): `main`, then `_end`."""
    _defer_full_collections()
    try:
        status = main()
    except SystemExit as e:
        status = e.code
    _end(status)


def _end(status) -> NoReturn:
    """End the process with `status` (as `SystemExit` takes it) once the command is done,
    without the interpreter's teardown: that frees every module and JAX's compiled programs
    one by one, 0.3-0.4 s of a 1-3 s command on 2 cores (`jaxdyn run`, cold and warm; the
    exit handlers themselves take about 10 ms). What a normal exit does that matters is done
    first, in its order: `threading._shutdown` (its hooks, such as waking an idle thread
    pool's workers to end, then joining the threads that are not daemons: a program still
    compiling for the persistent cache), the exit handlers (`atexit`: JAX's, logging's,
    `weakref.finalize`'s, a temporary directory's clean-up), and flushing the output."""
    if status is None:
        code = 0
    elif isinstance(status, int):
        code = status
    else:  # a message, as SystemExit prints it
        sys.stderr.write(f"{status}\n")
        code = 1
    shutdown = getattr(threading, "_shutdown", None)
    run_exit_handlers = getattr(atexit, "_run_exitfuncs", None)
    if shutdown is None or run_exit_handlers is None:  # (not CPython: its own exit)
        raise SystemExit(code)
    shutdown()  # its hooks (an idle thread pool's workers woken to end), then the threads
    run_exit_handlers()
    for stream in (sys.stdout, sys.stderr):
        if stream is None:  # (a closed descriptor: nothing to flush)
            continue
        try:
            stream.flush()
        except (OSError, ValueError):  # a reader that went away, a closed stream: quietly,
            code = code or 1  # as `main` ends on a broken pipe, but not with status 0
    os._exit(code)


if __name__ == "__main__":
    console()
