"""Shared pieces of the ``mtex`` commands: help strings, reading a motion source, and the
checks of option values (one place for all commands)."""

from __future__ import annotations

import math

__all__ = [
    "SOURCE_HELP",
    "UserError",
    "frames_of_seconds",
    "non_negative",
    "positive",
    "positive_int",
    "read_source",
]

SOURCE_HELP = "a .bvh file, a DeepMimic JSON motion file, or example:NAME (see 'mtex examples')"


class UserError(Exception):
    """An error caused by the user's input: printed as one line."""


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
    if seconds is None:
        return None
    if not seconds > 0:
        raise ValueError(f"--{name} must be positive seconds, got {seconds}")
    return max(3, round(seconds * fps))
