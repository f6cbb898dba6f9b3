"""What a file on disk is, and the rules of every read and write of the command line.

- :func:`read_input` reads a motion file through a size cap; a device, a FIFO or a directory is
  refused before it is opened (``/dev/zero`` would never end, a FIFO would block);
- :func:`file_kind` names what an existing file is (a motion texture, a contact model, a BVH
  clip, a picture, ...), from its first bytes and, for a model file, its metadata;
- :func:`check_output` is the door of every output of ``mtex``: an output that is one of the
  inputs is an error; replacing a file of another kind needs ``force``; only regular files are
  replaced; a missing folder is named.
"""

from __future__ import annotations

import json
import os
import stat
import zipfile
from collections.abc import Iterable
from pathlib import Path

from ._atomic import check_writable
from ._limits import limit

__all__ = ["check_output", "describe_kind", "file_kind", "read_input"]

_META_MEMBER = "__meta_json__.npy"
_MAX_META_BYTES = 1 << 20
_HEAD_BYTES = 1 << 16
_WORDS = {
    "mtex_jax.MotionTexture": "motion texture model",
    "mtex_jax.ContactModel": "contact model",
    "mtex_jax.FeatureMap": "feature map",
    "mtex_jax.LearnCheckpoint": "learn checkpoint",
    "bvh": "BVH motion file",
    "deepmimic": "DeepMimic motion file",
    "json": "JSON file",
    "png": "PNG picture",
    "gif": "GIF animation",
    "html": "HTML page",
    "npz": "NumPy archive (not an mtex_jax model)",
    "other": "file of unknown kind",
}
#: The file-name suffixes of each kind of output ``mtex`` writes: the name says what the file
#: is (a model file named ``tex.png`` would be a zip archive a picture viewer cannot open).
_SUFFIXES = {
    "mtex_jax.MotionTexture": (".npz",),
    "mtex_jax.ContactModel": (".npz",),
    "mtex_jax.FeatureMap": (".npz",),
    "mtex_jax.LearnCheckpoint": (".npz",),
    "npz": (".npz",),
    "bvh": (".bvh",),
    "deepmimic": (".json",),
    "json": (".json",),
    "png": (".png",),
    "gif": (".gif",),
    "html": (".html", ".htm"),
}


def describe_kind(kind: str) -> str:
    """A few words for a kind of :func:`file_kind` (``"BVH motion file"``)."""
    return _WORDS.get(kind, kind)


def read_input(path: str | os.PathLike[str], what: str) -> bytes:
    """The bytes of the regular file ``path``, read through the cap ``MAX_INPUT_BYTES``.

    Args:
        path: the file.
        what: what the file should be, for the errors (``"BVH file"``).

    Raises:
        ValueError: naming the file: missing, not a regular file (a directory, a device such
            as ``/dev/zero``, a FIFO: refused before it is opened), larger than the cap (its
            size and the limit), or unreadable.
    """
    p = Path(path)
    cap = int(limit("MAX_INPUT_BYTES"))
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise ValueError(f"{p}: cannot read {what}: no such file") from None
    except OSError as e:
        raise ValueError(f"{p}: cannot read {what}: {e.strerror or e}") from None
    if stat.S_ISDIR(st.st_mode):
        raise ValueError(f"{p}: is a directory, expected a {what}")
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{p}: not a regular file (a device, FIFO or socket); expected a {what}")
    if st.st_size > cap:
        raise ValueError(
            f"{p}: {st.st_size:,} bytes exceed the limit MAX_INPUT_BYTES = {cap:,} for a {what} "
            "(raise it with mtex_jax.core.set_limit('MAX_INPUT_BYTES', N))"
        )
    try:
        with open(p, "rb") as fh:
            data = fh.read(cap + 1)
    except OSError as e:
        raise ValueError(f"{p}: cannot read {what}: {e.strerror or e}") from None
    if len(data) > cap:  # grew while it was read
        raise ValueError(f"{p}: more than MAX_INPUT_BYTES = {cap:,} bytes; not read")
    return data


def _model_kind(p: Path) -> str:
    """The ``kind`` in the metadata of an ``.npz`` model file, or ``"npz"``."""
    import numpy as np

    try:
        with zipfile.ZipFile(p) as zf:
            info = zf.getinfo(_META_MEMBER)
            if info.file_size > _MAX_META_BYTES:
                return "npz"
            with zf.open(info) as fh:
                raw = np.lib.format.read_array(fh, allow_pickle=False)
        meta = json.loads(raw.tobytes().decode("utf-8"))
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, RuntimeError, EOFError):
        return "npz"
    kind = meta.get("kind") if isinstance(meta, dict) else None
    return kind if isinstance(kind, str) and kind else "npz"


def file_kind(path: str | os.PathLike[str]) -> str | None:
    """What the existing file ``path`` is; ``None`` if there is none.

    Returns:
        ``"directory"``, ``"device"``, ``"fifo"`` or ``"special"`` for what is not a regular
        file; ``"empty"``; a model file's metadata kind (``"mtex_jax.MotionTexture"``,
        ``"mtex_jax.ContactModel"``, ...) or ``"npz"`` for another zip archive; ``"bvh"``,
        ``"deepmimic"`` (JSON with ``"Frames"``), ``"json"``, ``"png"``, ``"gif"``, ``"html"``;
        else ``"other"``.
    """
    p = Path(path)
    try:
        st = os.stat(p)
    except OSError:
        return None
    if stat.S_ISDIR(st.st_mode):
        return "directory"
    if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode):
        return "device"
    if stat.S_ISFIFO(st.st_mode):
        return "fifo"
    if not stat.S_ISREG(st.st_mode):
        return "special"
    if st.st_size == 0:
        return "empty"
    try:
        with open(p, "rb") as fh:
            head = fh.read(_HEAD_BYTES)
    except OSError:
        return "other"
    if head.startswith(b"PK\x03\x04"):
        return _model_kind(p)
    if head.startswith(b"\x89PNG"):
        return "png"
    if head[:6] in (b"GIF87a", b"GIF89a"):
        return "gif"
    text = head.removeprefix(b"\xef\xbb\xbf").lstrip()
    if text[:9].upper() == b"HIERARCHY":
        return "bvh"
    if text.startswith(b"{"):
        return "deepmimic" if b'"Frames"' in head else "json"
    if text[:14].lower().startswith((b"<!doctype html", b"<html")):
        return "html"
    return "other"


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.abspath(a) == os.path.abspath(b)


def check_output(
    path: str | os.PathLike[str],
    kind: str,
    *,
    inputs: Iterable[str | os.PathLike[str]] = (),
    force: bool = False,
    option: str = "-o/--output",
) -> Path:
    """Check an output file before any work is done; returns it as a :class:`Path`.

    Args:
        path: the file to write.
        kind: what will be written, a kind of :func:`file_kind` (``"bvh"``,
            ``"mtex_jax.MotionTexture"``, ``"png"``, ...). A kind that has a file-name
            suffix (``.npz`` for a model file, ``.bvh``, ``.png``, ``.gif``, ``.json``,
            ``.html``) requires it, in any case.
        inputs: the files the command reads (``example:NAME`` sources are skipped): the output
            may not be one of them, with or without ``force``.
        force: allow replacing an existing file of another kind.
        option: the option that named ``path``, for the errors.

    Raises:
        ValueError: the name does not end in the suffix of ``kind``; the output is an input; it
            exists and is not a regular file; it is a file of another kind and ``force`` is
            not set (the message says ``--force``).
        FileNotFoundError: its folder does not exist (the message names ``path``).
    """
    p = Path(path)
    suffixes = _SUFFIXES.get(kind)
    if suffixes is not None and p.suffix.lower() not in suffixes:
        raise ValueError(
            f"{option} {p}: the file written is a {describe_kind(kind)}, so its name must end "
            f"in {' or '.join(suffixes)}" + (f" (not {p.suffix})" if p.suffix else "")
        )
    for src in inputs:
        s = str(src)
        if s.startswith("example:"):
            continue
        if _same_file(p, Path(s)):
            raise ValueError(
                f"{option} {p} is also an input ({s}); it would be overwritten. Choose another "
                "output file"
            )
    check_writable(p)
    have = file_kind(p)
    if have in (None, "empty", kind) or force:
        return p
    raise ValueError(
        f"{option} {p} is an existing {describe_kind(have)}; writing a {describe_kind(kind)} "
        "over it needs --force"
    )
