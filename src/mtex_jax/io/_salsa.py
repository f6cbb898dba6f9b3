"""The package's default data: 14 CMU salsa clips (subject 60) at 60 Hz (see ``CREDIT.txt``).

The clips live in ``mtex_jax/data/salsa/``: ``salsa.npz`` holds every clip's root positions and
joint rotations (unit quaternions), each channel quantised to 16 bits between its per-clip
minimum and maximum; ``salsa.json`` holds the skeleton, the clip names and frame counts, the
fixed quality split and the SHA-256 of the ``.npz``. They are made from the BVH files by the
repository's package-data builder (``make_salsa_data.py``); every clip equals the BVH
resampled to 60 Hz within 0.003° of joint rotation and 0.05 mm of world joint position.
"""

from __future__ import annotations

import functools
import hashlib
import io
import zipfile
from importlib import resources
from importlib.resources.abc import Traversable
from typing import Any, overload

import numpy as np

from ..core import load_json
from ..motion import Motion, Skeleton

__all__ = ["load_salsa", "salsa_credit", "salsa_names", "salsa_split"]

_PACKAGE = "mtex_jax.data.salsa"
_FORMAT = "mtex_jax salsa 1"
_DAMAGED = "the installed salsa data is damaged; reinstall mtex_jax"


class _Pack:
    """The decoded data: skeleton, frame rate, clip names, per-clip channel arrays, split."""

    def __init__(self, meta: dict[str, Any], values: np.ndarray, starts: np.ndarray) -> None:
        self.skeleton = Skeleton.from_json_dict(meta["skeleton"])
        self.fps = float(meta["fps"])
        self.names: list[str] = [str(n) for n in meta["clips"]]
        self.split = (
            [str(n) for n in meta["split"]["training"]],
            [str(n) for n in meta["split"]["held_out"]],
        )
        self.values = values
        self.starts = starts

    def motion(self, i: int) -> Motion:
        x = self.values[self.starts[i] : self.starts[i + 1]]
        j = self.skeleton.n_joints
        rot = x[:, 3:].reshape(len(x), j, 4)
        rot = rot / np.linalg.norm(rot, axis=-1, keepdims=True)
        return Motion(self.skeleton, self.fps, x[:, :3].copy(), rot)


def _fail(folder: Traversable, what: str) -> ValueError:
    return ValueError(f"{_DAMAGED} ({folder}: {what})")


def _load_pack(folder: Traversable) -> _Pack:
    """Read and check ``salsa.json`` and ``salsa.npz`` in ``folder``.

    Raises:
        ValueError: a missing or damaged file (checksum, format, shapes, values; in
            ``salsa.json`` invalid JSON, NaN, Infinity or a number no float holds, with the
            line).
    """
    try:
        text = folder.joinpath("salsa.json").read_text(encoding="utf-8")
        data = folder.joinpath("salsa.npz").read_bytes()
    except (OSError, UnicodeDecodeError) as e:
        raise _fail(folder, f"cannot read salsa.json / salsa.npz: {e}") from None
    try:
        meta = load_json(text, "salsa.json")
    except ValueError as e:
        raise _fail(folder, str(e)) from None
    if not isinstance(meta, dict) or meta.get("format") != _FORMAT:
        raise _fail(folder, f"salsa.json is not in the format {_FORMAT!r}")
    if hashlib.sha256(data).hexdigest() != meta.get("sha256"):
        raise _fail(folder, "salsa.npz does not match the checksum in salsa.json")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            q, offset, scale = z["values"], z["offset"], z["scale"]
        names, frames = meta["clips"], [int(n) for n in meta["frames"]]
        pack = _Pack(meta, np.zeros((0, 0)), np.zeros(0, np.int64))
        fps = float(meta["fps"])
    except (OSError, KeyError, TypeError, ValueError, zipfile.BadZipFile) as e:
        raise _fail(folder, f"{type(e).__name__}: {e}") from None
    n_ch = 3 + 4 * pack.skeleton.n_joints
    n = len(names)
    if not (np.isfinite(fps) and fps > 0) or len(frames) != n or n == 0:
        raise _fail(folder, "bad frame rate or clip list")
    if len(set(names)) != n or not set(pack.split[0] + pack.split[1]) <= set(names):
        raise _fail(folder, "clip names repeated or split names unknown")
    if q.dtype != np.int16 or q.shape != (sum(frames), n_ch) or min(frames) < 2:
        raise _fail(folder, f"values have shape {q.shape} {q.dtype}, expected int16 rows")
    for a in (offset, scale):
        if a.shape != (n, n_ch) or not np.isfinite(a).all():
            raise _fail(folder, "offset / scale are not finite (clips, channels) arrays")
    if (scale < 0).any() or (scale * 65535 > 1e3).any():
        raise _fail(folder, "scale out of range")
    starts = np.concatenate([[0], np.cumsum(frames)]).astype(np.int64)
    clip = np.repeat(np.arange(n), frames)
    values = (q.astype(np.float64) + 32767.5) * scale[clip] + offset[clip]
    norms = np.linalg.norm(values[:, 3:].reshape(len(values), -1, 4), axis=-1)
    if not (np.abs(norms - 1.0) < 1e-3).all():
        raise _fail(folder, "rotations are not unit quaternions")
    pack.values, pack.starts = values, starts
    return pack


@functools.lru_cache(maxsize=1)
def _pack() -> _Pack:
    return _load_pack(resources.files(_PACKAGE))


def salsa_names() -> list[str]:
    """Names of the shipped salsa clips: ``["60_01", ..., "60_15"]`` (14 clips, no 60_08)."""
    return list(_pack().names)


def salsa_split() -> tuple[list[str], list[str]]:
    """The fixed quality split of the salsa clips: ``(training, held_out)`` names (10 and 4).

    Nothing tuned should look at the held-out clips."""
    train, held = _pack().split
    return list(train), list(held)


def salsa_credit() -> str:
    """The CMU acknowledgement and terms of the salsa data (the text of ``CREDIT.txt``)."""
    folder = resources.files(_PACKAGE)
    try:
        return folder.joinpath("CREDIT.txt").read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise _fail(folder, f"cannot read CREDIT.txt: {e}") from None


@overload
def load_salsa(name: str) -> Motion: ...
@overload
def load_salsa(name: None = None) -> list[Motion]: ...
def load_salsa(name: str | None = None) -> Motion | list[Motion]:
    """Load one shipped salsa clip by name (e.g. ``"60_01"``), or all 14 in order when ``name``
    is ``None``.

    The clips are the CMU BVH files of subject 60 resampled to 60 Hz (43 joints, lengths in
    metres, y up); also reachable as ``example:salsa/60_01`` wherever a motion source is read.

    Raises:
        ValueError: unknown name (the message lists the available ones), or damaged data.
    """
    pack = _pack()
    if name is None:
        return [pack.motion(i) for i in range(len(pack.names))]
    if name not in pack.names:
        raise ValueError(f"unknown salsa clip {name!r}; available: {', '.join(pack.names)}")
    return pack.motion(pack.names.index(name))
