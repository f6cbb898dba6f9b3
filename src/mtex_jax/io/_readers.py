"""One entry point for every supported motion source (files and embedded examples)."""

from __future__ import annotations

import os
from pathlib import Path

from ..core import file_kind
from ..motion import Motion
from ._bvh import read_bvh
from ._data import load_example
from ._deepmimic import read_deepmimic

__all__ = ["read_motion"]


def read_motion(source: str | os.PathLike[str]) -> Motion:
    """Read a motion from a ``.bvh`` file, a DeepMimic JSON file, or ``example:NAME``.

    Raises:
        ValueError: unknown example, missing file, not a regular file (a device, a FIFO, a
            directory: refused before it is opened), or malformed content (with file and
            line).
    """
    s = str(source)
    if s.startswith("example:"):
        return load_example(s[len("example:") :])
    p = Path(s)
    kind = file_kind(p)
    if kind is None:
        raise ValueError(f"{p}: no such file")
    if kind == "directory":
        raise ValueError(f"{p}: is a directory, expected a motion file")
    if kind in ("device", "fifo", "special"):
        raise ValueError(f"{p}: not a regular file (a {kind}); expected a motion file")
    if p.suffix.lower() == ".bvh":
        return read_bvh(p)
    with open(p, "rb") as fh:
        head = fh.read(64).removeprefix(b"\xef\xbb\xbf").lstrip()
    if head.startswith(b"{"):
        return read_deepmimic(p)
    if head.upper().startswith(b"HIERARCHY"):
        return read_bvh(p)
    raise ValueError(f"{p}: unknown motion format (expected BVH or DeepMimic JSON)")
