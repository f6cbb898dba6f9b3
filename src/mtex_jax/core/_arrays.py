"""Model files: one ``.npz`` archive of plain arrays plus JSON metadata, never pickled."""

from __future__ import annotations

import fnmatch
import json
import os
import stat
import struct
import zipfile
import zlib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ._atomic import atomic_write
from ._limits import MAX_MEMBER_BYTES, MAX_MODEL_BYTES
from ._numbers import load_json

__all__ = ["load_arrays_json", "save_arrays_json"]

_META_KEY = "__meta_json__"
_MAX_MEMBERS = 10_000
_MAX_META_BYTES = 16 << 20
# what a damaged archive may raise while it is read (CRC, inflate, header, short data)
_READ_ERRORS = (
    zipfile.BadZipFile,
    zlib.error,
    OSError,
    EOFError,
    ValueError,
    KeyError,
    RuntimeError,
    NotImplementedError,
    struct.error,
    SyntaxError,
    OverflowError,
    UnicodeDecodeError,
)


def save_arrays_json(
    path: str | os.PathLike[str], arrays: dict[str, Any], meta: dict[str, Any]
) -> None:
    """Write ``arrays`` and JSON-serialisable ``meta`` to one ``.npz`` file, atomically.

    The metadata is stored as UTF-8 bytes in the array ``__meta_json__``; every array must be
    numeric or boolean, so the file loads with ``allow_pickle=False``. The file is written to
    a temporary file beside ``path`` and renamed over it only when complete: a failed save
    leaves the previous file intact.
    """
    out: dict[str, np.ndarray] = {}
    for k, v in arrays.items():
        a = np.asarray(v)
        if a.dtype.kind not in "biuf":
            raise TypeError(f"array {k!r} has dtype {a.dtype}; only numeric arrays are stored")
        out[k] = a
    out[_META_KEY] = np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8)
    with atomic_write(path, "wb") as fh:
        np.savez_compressed(fh, **out)  # type: ignore[arg-type]


def _header(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype declared by a member's ``.npy`` header (no data read)."""
    with zf.open(info) as fh:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise ValueError(f"unsupported .npy version {version}")
    return tuple(int(s) for s in shape), np.dtype(dtype)


def _matches(name: str, patterns: Iterable[str]) -> bool:
    return any(fnmatch.fnmatchcase(name, pat) for pat in patterns)


def load_arrays_json(
    path: str | os.PathLike[str],
    *,
    kind: str,
    required: tuple[str, ...] = (),
    allowed: tuple[str, ...] | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read a file written by :func:`save_arrays_json`.

    Only a regular file is opened (a FIFO or a device is refused first). The sizes the zip
    directory declares are summed before anything is inflated (at most
    :data:`~mtex_jax.core.MAX_MODEL_BYTES` in all); then every member's ``.npy`` header is read
    and checked before any data is allocated: numeric or boolean dtype (never pickled
    objects), at most :data:`~mtex_jax.core.MAX_MEMBER_BYTES` per array; unknown members are
    refused before their data is read, and each array is read only when its turn comes.

    Args:
        path: the ``.npz`` file.
        kind: what the caller expects (``meta["kind"]`` must equal it).
        required: array names that must be present.
        allowed: the names (``fnmatch`` patterns such as ``"texton.*"``) the caller reads,
            besides ``required``; any other member is rejected before it is decompressed.
            ``None`` accepts every member.

    Raises:
        ValueError: naming the file and what is wrong (not a model file, truncated or corrupt,
            an array too large or of a refused dtype, unknown or missing arrays, wrong kind).
    """
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        if str(path).startswith("example:"):  # a shipped clip, named where a model belongs
            raise ValueError(
                f"{path}: example:NAME names a shipped motion clip, not a model file; learn a "
                f"model from clips first (mtex learn {path} -o model.npz)"
            ) from None
        raise ValueError(f"{p}: no such file") from None
    except OSError as e:
        raise ValueError(f"{p}: cannot read model file: {e.strerror or e}") from None
    if stat.S_ISDIR(st.st_mode):
        raise ValueError(f"{p}: is a directory, not a model file")
    if not stat.S_ISREG(st.st_mode):  # a FIFO would block, a device never end
        raise ValueError(f"{p}: not a regular file (a device, FIFO or socket); not a model file")
    try:
        zf = zipfile.ZipFile(p)
    except zipfile.BadZipFile:
        raise ValueError(f"{p}: not a model file (not an .npz archive)") from None
    except _READ_ERRORS as e:
        raise ValueError(f"{p}: cannot read model file: {e}") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > _MAX_MEMBERS:
            raise ValueError(f"{p}: {len(infos)} members (limit {_MAX_MEMBERS}); not a model file")
        members: dict[str, zipfile.ZipInfo] = {}
        for info in infos:
            name = info.filename
            if not name.endswith(".npy") or name[:-4] in members:
                raise ValueError(f"{p}: unexpected member {name!r}; not an mtex_jax model file")
            members[name[:-4]] = info
        if _META_KEY not in members:
            raise ValueError(f"{p}: missing metadata ({_META_KEY}); not an mtex_jax model file")
        declared = sum(info.file_size for info in infos)  # from the directory: nothing inflated
        if declared > MAX_MODEL_BYTES + _MAX_META_BYTES:
            raise ValueError(
                f"{p}: its members declare {declared:,} bytes, more than the limit "
                f"MAX_MODEL_BYTES = {MAX_MODEL_BYTES:,}; not read"
            )
        if members[_META_KEY].file_size > _MAX_META_BYTES:
            raise ValueError(f"{p}: metadata of {members[_META_KEY].file_size:,} bytes; not read")
        total = 0
        arrays: dict[str, np.ndarray] = {}
        try:
            for k, info in members.items():
                shape, dtype = _header(zf, info)
                if dtype.hasobject or dtype.kind not in "biuf":
                    raise ValueError(
                        f"array {k!r} has dtype {dtype} (pickled or non-numeric data is refused)"
                    )
                nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
                total += nbytes
                if nbytes > info.file_size:
                    raise ValueError(
                        f"array {k!r} declares shape {shape} of {dtype} ({nbytes:,} bytes) but "
                        f"its member holds {info.file_size:,} bytes"
                    )
                if nbytes > MAX_MEMBER_BYTES or total > MAX_MODEL_BYTES:
                    raise ValueError(
                        f"array {k!r} declares shape {shape} of {dtype} ({nbytes:,} bytes); "
                        f"limits: {MAX_MEMBER_BYTES:,} bytes per array, {MAX_MODEL_BYTES:,} in all"
                    )
            with zf.open(members[_META_KEY]) as fh:
                raw = np.lib.format.read_array(fh, allow_pickle=False)
        except _READ_ERRORS as e:
            raise ValueError(f"{p}: not a readable mtex_jax model file: {e}") from None
        meta = _meta(p, raw, kind)
        if allowed is not None:
            known = (*required, *allowed)
            unknown = [k for k in members if k != _META_KEY and not _matches(k, known)]
            if unknown:
                raise ValueError(f"{p}: unknown arrays {sorted(unknown)[:5]} (not read)")
        try:
            for k, info in members.items():
                if k != _META_KEY:
                    with zf.open(info) as fh:
                        arrays[k] = np.lib.format.read_array(fh, allow_pickle=False)
        except _READ_ERRORS as e:
            raise ValueError(f"{p}: not a readable mtex_jax model file: {e}") from None
    missing = [k for k in required if k not in arrays]
    if missing:
        raise ValueError(f"{p}: missing arrays {missing}")
    return arrays, meta


def _meta(p: Path, raw: np.ndarray, kind: str) -> dict[str, Any]:
    """The metadata of a model file; ``ValueError`` unless it is a JSON object of ``kind``."""
    try:
        text = raw.tobytes().decode("utf-8")
        # the numbers' rule of every reader (a 401-digit integer, NaN: refused, naming where)
        meta = load_json(text, "metadata", nonfinite=True)
    except (UnicodeDecodeError, ValueError) as e:
        raise ValueError(f"{p}: corrupt metadata: {e}") from None
    if not isinstance(meta, dict) or meta.get("kind") != kind:
        got = meta.get("kind") if isinstance(meta, dict) else None
        raise ValueError(f"{p}: expected a {kind!r} file, found kind {got!r}")
    return meta
