"""Atomic file writes: a failed write leaves the previous file intact."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

__all__ = ["atomic_write"]


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "wb", **open_kw: Any) -> Iterator[IO]:
    """Open a temporary file beside ``path``; on success flush, fsync and rename it to ``path``.

    The temporary file lives in the same folder (so that :func:`os.replace` is an atomic
    rename on the same file system). If the body raises (disk full, an unserialisable value,
    Ctrl-C), the temporary file is removed and ``path`` keeps its previous content.

    Args:
        path: the final file.
        mode: ``"wb"`` or ``"w"`` (text; ``open_kw`` such as ``encoding`` are passed on).
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write: mode must be 'w' or 'wb', got {mode!r}")
    p = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent or ".")
    try:
        with os.fdopen(fd, mode, **open_kw) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        try:  # keep the permissions of a file that is replaced
            os.chmod(tmp, os.stat(p).st_mode & 0o7777)
        except OSError:
            os.chmod(tmp, 0o644)
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
