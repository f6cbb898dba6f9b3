"""Shared pieces of the ``mtex`` commands: help strings, reading a motion source, and the
checks of option values (one place for all commands)."""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Iterable

__all__ = [
    "SOURCE_HELP",
    "UserError",
    "add_force",
    "float_arg",
    "frames_of_seconds",
    "int_arg",
    "non_negative",
    "output",
    "positive",
    "positive_int",
    "read_source",
    "seed_arg",
    "source_path",
]

#: Largest magnitude of an integer option (counts, frames, indices); a larger one is refused
#: by the parser, before any arithmetic can overflow.
MAX_INT_OPTION = 2**53
#: Largest magnitude of a real option (seconds, thresholds, noise levels).
MAX_REAL_OPTION = 1e12

SOURCE_HELP = "a .bvh file, a DeepMimic JSON motion file, or example:NAME (see 'mtex examples')"


class UserError(Exception):
    """An error caused by the user's input: printed as one line."""


def int_arg(text: str) -> int:
    """An integer option: decimal digits with an optional sign, at most ``2**53`` in
    magnitude (``argparse`` type)."""
    try:
        v = int(text.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if abs(v) > MAX_INT_OPTION:
        raise argparse.ArgumentTypeError(f"{text[:30]!r} is too large (limit 2**53)")
    return v


def seed_arg(text: str) -> int:
    """A random seed: an integer in ``[0, 2**63)`` (``argparse`` type)."""
    try:
        v = int(text.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer seed, got {text!r}") from None
    if not 0 <= v < 2**63:
        raise argparse.ArgumentTypeError(f"a seed must be in [0, 2**63), got {text[:30]}")
    return v


def float_arg(text: str) -> float:
    """A real option: a finite number of magnitude at most ``1e12`` (``argparse`` type;
    ``inf`` and ``nan`` are refused here, with the option's name)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    if abs(v) > MAX_REAL_OPTION:
        raise argparse.ArgumentTypeError(f"{text!r} is too large (limit {MAX_REAL_OPTION:g})")
    return v


def add_force(parser: argparse.ArgumentParser) -> None:
    """Add ``--force``: replace an existing output file of another kind."""
    parser.add_argument(
        "--force",
        action="store_true",
        help="replace an existing output file of another kind (never an input)",
    )


def source_path(spec: str) -> str:
    """The file of a ``CLIP:FRAME`` pose specification (``CLIP`` itself if there is no
    frame)."""
    clip, sep, frame = spec.rpartition(":")
    return clip if sep and frame.strip().lstrip("-").isdigit() else spec


def output(
    path: str | os.PathLike[str] | None,
    kind: str,
    inputs: Iterable[str | os.PathLike[str]],
    force: bool,
    option: str = "-o/--output",
) -> None:
    """Check an output file before any work (:func:`mtex_jax.core.check_output`): not an
    input, not a file of another kind unless ``force``, a regular file in an existing
    folder. ``None`` (no such output) passes."""
    from ..core import check_output

    if path is not None:
        check_output(path, kind, inputs=inputs, force=force, option=option)


def read_source(source: str):
    """Read a motion from a file path or ``example:NAME``."""
    from ..io import read_motion

    return read_motion(source)


def positive_int(name: str, value: int) -> int:
    """``value`` if it is at least 1, else ``ValueError`` naming the option ``--name``."""
    if value < 1:
        raise ValueError(f"--{name} must be at least 1, got {value}")
    return value


def positive(name: str, value: float) -> float:
    """``value`` if it is finite and positive, else ``ValueError`` naming ``--name``."""
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"--{name} must be a positive number, got {value}")
    return value


def non_negative(name: str, value: float) -> float:
    """``value`` if it is finite and at least 0, else ``ValueError`` naming ``--name``."""
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"--{name} must be a non-negative number, got {value}")
    return value


def frames_of_seconds(seconds: float | None, fps: float, name: str) -> int | None:
    """``seconds`` as a number of frames at ``fps`` (at least 3), or ``None``; a
    ``ValueError`` naming ``--name`` if it is not a positive finite number of seconds or is
    more frames than the limit ``MAX_SEGMENT_FRAMES`` of :mod:`mtex_jax.core`."""
    from ..core import limit

    if seconds is None:
        return None
    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"--{name} must be positive seconds, got {seconds}")
    cap = int(limit("MAX_SEGMENT_FRAMES"))
    if seconds * fps > cap:
        raise ValueError(
            f"--{name} {seconds:g} s is {seconds * fps:,.0f} frames at {fps:g} Hz, more than the "
            f"limit MAX_SEGMENT_FRAMES = {cap:,} frames"
        )
    return max(3, round(seconds * fps))
