"""Model files: one ``.npz`` archive of plain arrays plus JSON metadata, never pickled."""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["load_arrays_json", "save_arrays_json"]

_META_KEY = "__meta_json__"


def save_arrays_json(
    path: str | os.PathLike[str], arrays: dict[str, Any], meta: dict[str, Any]
) -> None:
    """Write ``arrays`` and JSON-serialisable ``meta`` to one ``.npz`` file.

    The metadata is stored as UTF-8 bytes in the array ``__meta_json__``; every array must be
    numeric or boolean, so the file loads with ``allow_pickle=False``.
    """
    out: dict[str, np.ndarray] = {}
    for k, v in arrays.items():
        a = np.asarray(v)
        if a.dtype.kind not in "biuf":
            raise TypeError(f"array {k!r} has dtype {a.dtype}; only numeric arrays are stored")
        out[k] = a
    out[_META_KEY] = np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8)
    p = Path(path)
    with open(p, "wb") as fh:
        np.savez_compressed(fh, **out)  # type: ignore[arg-type]


def load_arrays_json(
    path: str | os.PathLike[str], *, kind: str, required: tuple[str, ...] = ()
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read a file written by :func:`save_arrays_json`.

    Args:
        path: the ``.npz`` file.
        kind: what the caller expects (``meta["kind"]`` must equal it).
        required: array names that must be present.

    Raises:
        ValueError: naming the file and what is wrong (not a zip/npz archive, truncated or
            corrupt, missing metadata or arrays, wrong kind).
    """
    p = Path(path)
    try:
        with np.load(p, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise ValueError(f"{p}: no such file") from None
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, KeyError) as e:
        raise ValueError(
            f"{p}: not a readable mtex_jax model file (corrupt or truncated: {e})"
        ) from None
    if _META_KEY not in arrays:
        raise ValueError(f"{p}: missing metadata ({_META_KEY}); not an mtex_jax model file")
    try:
        meta = json.loads(arrays.pop(_META_KEY).tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{p}: corrupt metadata: {e}") from None
    if not isinstance(meta, dict) or meta.get("kind") != kind:
        got = meta.get("kind") if isinstance(meta, dict) else None
        raise ValueError(f"{p}: expected a {kind!r} file, found kind {got!r}")
    missing = [k for k in required if k not in arrays]
    if missing:
        raise ValueError(f"{p}: missing arrays {missing}")
    return arrays, meta
