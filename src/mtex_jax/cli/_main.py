"""The ``mtex`` command line.

Every sub-command reports a user error as one line on stderr (``mtex: error: ...``) and exits
with status 2; it never shows a traceback for bad input.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from typing import NoReturn

from ._validators import UserError

__all__ = ["main"]

# The command families, in the order of ``mtex --help``; each module's ``register(sub)`` adds
# its sub-commands. A new command family is a module with a ``register`` function, listed here.
_COMMANDS = (
    "_motion_cmds",  # info, render, examples, mirror
    "_demo",  # demo
    "_texture_cmds",  # learn, segment, synth, choreograph
    "_implicit",  # implicit-synth, track
    "_evaluate",  # evaluate
    "_edit",  # edit, contacts
    "_view",  # view
)


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (``mtex: error: ...``) and exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"mtex: error: {self.prog}: {message}\n")


def _parser() -> argparse.ArgumentParser:
    import importlib

    from .. import __version__

    p = _Parser(
        prog="mtex",
        description="Motion Texture and implicit motion models in JAX: inspect, render, learn "
        "and synthesise motion capture.",
    )
    p.add_argument("--version", action="version", version=f"mtex_jax {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMANDS:
        importlib.import_module(f"{__package__}.{name}").register(sub)
    return p


def _one_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mtex`` console script; returns the exit status.

    The error contract: every error is one line on stderr (``mtex: error: ...``) and exit
    status 2: bad arguments, unreadable or malformed files (naming the file and line), input
    beyond the limits of :mod:`mtex_jax.core`, and anything else that goes wrong (as
    ``internal error``; set ``MTEX_DEBUG=1`` to see the traceback instead). An interrupt
    (Ctrl-C), also while the program starts, is one line and status 130. When the reader of
    the output goes away (``mtex examples | head -1``) the command stops quietly, status 0.
    No traceback reaches the user.
    """
    try:
        return _run(argv)
    except BrokenPipeError:
        _quiet_stdout()
        return 0
    except KeyboardInterrupt:
        _say("mtex: interrupted")
        return 130
    except (ValueError, TypeError, OSError, ImportError, UserError) as e:
        _say(f"mtex: error: {_one_line(e)}")
        return 2
    except (RecursionError, MemoryError) as e:
        _say(f"mtex: error: input too large or too deeply nested ({type(e).__name__})")
        return 2
    except Exception as e:
        if os.environ.get("MTEX_DEBUG"):
            raise
        _say(
            f"mtex: error: internal error: {type(e).__name__}: {_one_line(e)} "
            "(set MTEX_DEBUG=1 for the traceback)"
        )
        return 2


def _run(argv: Sequence[str] | None) -> int:
    try:
        args = _parser().parse_args(argv)
    except SystemExit as e:  # --help, --version, or a usage error (printed as one line)
        return e.code if isinstance(e.code, int) else 2
    # The command-line program (not the library) chooses its precision: float64, like the
    # tests and benchmarks. Library functions follow the dtype of their inputs.
    import jax

    jax.config.update("jax_enable_x64", True)
    # ... and keeps compiled programs between runs, unless MTEX_NO_CACHE=1
    if os.environ.get("MTEX_NO_CACHE", "") not in ("1", "true", "yes"):
        from ..core import enable_compilation_cache

        try:
            enable_compilation_cache()
        except (OSError, ValueError):
            pass  # an unwritable cache folder: compile as usual
    if not getattr(args, "func", None):
        _parser().print_help()
        return 2
    code = int(args.func(args))
    sys.stdout.flush()
    return code


def _quiet_stdout() -> None:
    """The reader closed the pipe: point stdout at devnull so that the interpreter's final
    flush does not report the same error again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):
        pass  # not a real file (tests, embedding): nothing will be flushed at exit


def _say(line: str) -> None:
    """One line on stderr; a closed stderr is ignored (there is nobody to tell)."""
    try:
        print(line, file=sys.stderr, flush=True)
    except (OSError, ValueError):
        pass


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
