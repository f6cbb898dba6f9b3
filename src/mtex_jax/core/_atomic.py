"""Atomic file writes: a failed write leaves the previous file intact."""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

__all__ = ["atomic_write", "check_writable", "remove_stale_temporaries"]

# a temporary file without a process id (written before ids were in the name) is stale after
_STALE_SECONDS = 3600.0


def _kind_of_mode(mode: int) -> str:
    """A word for a file type that is not a regular file."""
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def check_writable(path: str | os.PathLike[str]) -> Path:
    """``path`` as a :class:`Path` if a write may create or replace it, else an error.

    Raises:
        FileNotFoundError: the folder of ``path`` does not exist (the message names the target,
            not a temporary file).
        ValueError: ``path`` exists and is not a regular file (a directory, a device, a FIFO, a
            socket): only regular files are replaced.
    """
    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"{p}: the output folder {folder} does not exist")
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        return p
    except OSError as e:
        raise ValueError(f"{p}: cannot write: {e.strerror or e}") from None
    if not stat.S_ISREG(mode):
        raise ValueError(f"{p} is {_kind_of_mode(mode)}; only regular files are replaced")
    return p


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True
    return True


def remove_stale_temporaries(path: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporary files that saves to ``path`` left behind when they were killed.

    A save's temporary file is ``.NAME.PID.RANDOM.tmp`` beside the target; it is stale when
    process ``PID`` no longer runs (a concurrent save's file is left alone). Files of the older
    form ``.NAME.RANDOM.tmp`` are stale after an hour. Returns the files removed.
    """
    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    prefix = f".{p.name}."
    removed = []
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    now = time.time()
    for name in names:
        if not (name.startswith(prefix) and name.endswith(".tmp")):
            continue
        parts = name[len(prefix) : -len(".tmp")].split(".")  # mkstemp's names have no dot
        if not (len(parts) == 1 or (len(parts) == 2 and parts[0].isdigit())):
            continue  # the temporary file of another target whose name extends this one
        tmp = folder / name
        try:
            if len(parts) == 2:
                stale = not _alive(int(parts[0]))
            else:
                stale = now - os.lstat(tmp).st_mtime > _STALE_SECONDS
            if stale and stat.S_ISREG(os.lstat(tmp).st_mode):
                os.unlink(tmp)
                removed.append(tmp)
        except OSError:
            continue
    return removed


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "wb", **open_kw: Any) -> Iterator[IO]:
    """Open a temporary file beside ``path``; on success flush, fsync and rename it to ``path``.

    The temporary file lives in the same folder (so that :func:`os.replace` is an atomic
    rename on the same file system). If the body raises (disk full, an unserialisable value,
    Ctrl-C), the temporary file is removed and ``path`` keeps its previous content. Temporary
    files of earlier saves to ``path`` that were killed are removed first
    (:func:`remove_stale_temporaries`). Only a regular file is replaced: a ``path`` that is a
    directory, a device or a FIFO is a ``ValueError`` (:func:`check_writable`), also when it
    turns into one while the body runs.

    Args:
        path: the final file.
        mode: ``"wb"`` or ``"w"`` (text; ``open_kw`` such as ``encoding`` are passed on).
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write: mode must be 'w' or 'wb', got {mode!r}")
    p = check_writable(path)
    remove_stale_temporaries(p)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{p.name}.{os.getpid()}.", suffix=".tmp", dir=p.parent or "."
    )
    try:
        with os.fdopen(fd, mode, **open_kw) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        check_writable(p)
        try:  # keep the permissions of a file that is replaced
            os.chmod(tmp, os.stat(p).st_mode & 0o7777)
        except OSError:
            os.chmod(tmp, 0o644)
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
