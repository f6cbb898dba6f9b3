"""Real keypoints in: 2-D detections and cameras from the files a user brings (design §12.1).

Keypoint files (:func:`read_keypoints`, :func:`write_keypoints`; COCO keypoints are given
joints by :func:`coco_joint_map`), camera files (:func:`read_camera`), and the tracker's
problem (:func:`problem_from_keypoints`). Every error of a file is a ``ValueError`` naming the
file and the problem; nothing is unpickled.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import zipfile
from collections.abc import Callable, Mapping
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, Float

from ..core import (
    atomic_write,
    check_real,
    check_size,
    describe_kind,
    file_kind,
    json_value_line,
    limit,
    load_json,
    read_input,
)
from ..motion import Skeleton, ground_axes
from ._camera import Camera
from ._problem import TrackingProblem

__all__ = [
    "COCO17_NAMES",
    "Keypoints",
    "coco_joint_map",
    "problem_from_keypoints",
    "read_camera",
    "read_keypoints",
    "write_keypoints",
]

#: The 17 keypoints of COCO, in COCO's order.
COCO17_NAMES: tuple[str, ...] = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
)  # fmt: skip

_SIDES = ("left", "right")
_LIMBS = ("shoulder", "elbow", "hip", "knee", "ankle")  # a known skeleton has all of these
_SECOND_LIFE = {"shoulder": "Shldr", "elbow": "ForeArm", "wrist": "Hand", "hip": "Thigh"}
_SECOND_LIFE |= {"knee": "Shin", "ankle": "Foot"}
# kind -> COCO name -> the joint whose origin is the keypoint (a hip: the thigh joint); the
# nose -> the joint that carries the head; wrists where the skeleton has them
_KINDS: dict[str, dict[str, str]] = {
    "CMU salsa (Second Life names)": {"nose": "head"}
    | {f"{s}_{a}": s[0] + b for s in _SIDES for a, b in _SECOND_LIFE.items()},
    "DeepMimic humanoid": {"nose": "neck"}
    | {f"{s}_{a}": f"{s}_{a}" for s in _SIDES for a in (*_LIMBS, "wrist")},
}


def _table(skeleton: Skeleton) -> dict[str, str] | None:
    names = set(skeleton.names)
    for table in _KINDS.values():
        if all(table[f"{s}_{a}"] in names for s in _SIDES for a in _LIMBS):
            return {c: j for c, j in table.items() if j in names}
    return None


def coco_joint_map(skeleton: Skeleton) -> dict[str, str]:
    """COCO keypoint name → joint name of ``skeleton``, found by the joints' names.

    Known skeletons: the CMU salsa clips (Second Life names ``lShldr``, ``lForeArm``, ``lHand``,
    ``lThigh``, ``lShin``, ``lFoot``; the nose → ``head``) and the DeepMimic humanoid (its own
    COCO-like names; the nose → ``neck``; no wrists). A keypoint is observed at its joint's
    origin (design §12.1): the hip at the thigh joint, the nose for the head; eyes and ears
    are left out (no joint lies there).

    Raises:
        ValueError: the skeleton is of neither kind (the message lists its joints).
    """
    if (table := _table(skeleton)) is not None:
        return table
    msg = f"not a {' or '.join(_KINDS)} skeleton (give a mapping); {_its_joints(skeleton)}"
    raise ValueError(f"coco_joint_map: {msg}")


def _its_joints(skeleton: Skeleton) -> str:
    return "its joints: " + ", ".join(skeleton.names)


class Keypoints(eqx.Module):
    """2-D keypoints of ``K`` skeleton joints over ``T`` frames (design §12.1).

    Attributes:
        joints: the skeleton joint index of each keypoint (static).
        pixels: ``(T, K, 2)`` pixel positions (any value where ``confidence`` is 0).
        confidence: ``(T, K)`` in ``[0, 1]``; ``0``: missing.
        names: the name of each keypoint in its source (a COCO or a joint name; static).
        fps: frames per second, where known (static).
    """

    joints: tuple[int, ...] = eqx.field(static=True, converter=lambda j: tuple(map(int, j)))
    pixels: Float[Array, "T K 2"] = eqx.field(converter=jnp.asarray)
    confidence: Float[Array, "T K"] = eqx.field(converter=jnp.asarray)
    names: tuple[str, ...] = eqx.field(static=True, converter=tuple)
    fps: float | None = eqx.field(static=True, default=None)

    def __check_init__(self) -> None:
        K, shape = len(self.joints), self.pixels.shape
        T = shape[0] if len(shape) == 3 else 0
        if K < 1 or T < 1 or shape != (T, K, 2) or self.confidence.shape != (T, K):
            raise ValueError(f"Keypoints: pixels (T, {K}, 2), confidence (T, {K}) for {K} joints")
        if len(self.names) != K or len(set(self.joints)) != K or min(self.joints) < 0:
            raise ValueError(f"Keypoints: {K} distinct joints (>= 0) and {K} names are needed")
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"Keypoints: fps must be positive and finite, got {self.fps}")
        c = None if isinstance(self.confidence, Tracer) else np.asarray(self.confidence)
        if c is not None and not (np.isfinite(c).all() and ((c >= 0) & (c <= 1)).all()):
            raise ValueError("Keypoints: confidence must be finite and in [0, 1]")

    @property
    def n_frames(self) -> int:
        return int(self.pixels.shape[0])


# --------------------------------------------------------------------------- reading
def _numbers(flat: list, src: str, where: str) -> np.ndarray:
    """JSON numbers (``null``: NaN) as float64, refusing strings, booleans and huge integers."""
    for v in flat:
        if v is not None and (isinstance(v, bool) or not isinstance(v, int | float)):
            raise ValueError(f"{src}: {where}: {v!r:.40} is not a number")
    try:
        return np.asarray([np.nan if v is None else v for v in flat], dtype=np.float64)
    except OverflowError:
        n = max(len(str(v)) for v in flat if isinstance(v, int))
        raise ValueError(f"{src}: {where}: a {n}-digit integer is too large for a float") from None


def _id_key(i: Any) -> Any:
    """Sort key of an image id: integers by value, strings in natural order (``f2 < f10``)."""
    if isinstance(i, str):
        return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", i)), i
    return i


# ":LINE" of the value at a JSON path of the file read ("" when there is none)
_Line = Callable[[tuple[str | int, ...]], str]


def _non_finite(v: Any) -> bool:
    return isinstance(v, float) and not math.isfinite(v)


def _coco(dets: list, src: str, line: _Line) -> tuple:
    """``(T, 17, 3)``: the best-scoring person detection of each image; the image ids; and the
    JSON path of each frame's values (``path(t, i)``: value ``i`` of frame ``t``)."""
    best: dict[Any, tuple[float, np.ndarray | None]] = {}
    index: dict[Any, int] = {}  # the detection of each image's best
    for n, d in enumerate(dets):
        if not isinstance(d, dict) or "image_id" not in d or "keypoints" not in d:
            raise ValueError(f"{src}: detection {n} is not an object with image_id and keypoints")
        i, kp = d["image_id"], d["keypoints"]
        if isinstance(i, bool) or not isinstance(i, int | str):
            raise ValueError(f"{src}: detection {n}: image_id {i!r:.40} is not an int or string")
        where = f"detection {n} (image_id {i!r})"
        best.setdefault(i, (-math.inf, None))
        if _non_finite(d.get("category_id")):
            raise ValueError(f"{src}{line((n, 'category_id'))}: {where}: category_id is not finite")
        if d.get("category_id", 1) != 1 or kp == []:  # not a person, or no one found
            continue
        if not isinstance(kp, list) or len(kp) != 51:
            k = f"{len(kp) / 3:g} keypoints ({len(kp)} values)" if isinstance(kp, list) else "none"
            raise ValueError(f"{src}: {where} has {k}; COCO-17 has 17 (51 values x, y, score)")
        v = _numbers(kp, src, where).reshape(17, 3)
        s = d.get("score", np.mean(np.clip(np.nan_to_num(v[:, 2]), 0, 1)))
        s = float(_numbers([s], src, f"{where}: score")[0])
        if not math.isfinite(s):
            at = line((n, "score"))
            raise ValueError(f"{src}{at}: {where}: the detection score {s} is not finite")
        if best[i][1] is None or s > best[i][0]:
            best[i] = (s, v)
            index[i] = n
    if len({type(i) for i in best}) > 1:
        raise ValueError(f"{src}: image ids mix integers and strings; they cannot be ordered")
    if not best:
        raise ValueError(f"{src}: no detections (an empty COCO results list)")
    ids = sorted(best, key=_id_key)
    none = np.zeros((17, 3))  # an image without a detection: every keypoint missing
    v = np.stack([none if (r := best[i][1]) is None else r for i in ids])

    def path(t: int, i: int) -> tuple[str | int, ...]:
        return (index[ids[t]], "keypoints", i) if ids[t] in index else ()

    return v, None, None, ids, path


def _mtex_json(doc: dict, src: str, line: _Line) -> tuple:
    names, frames = doc.get("names"), doc.get("frames")
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise ValueError(f"{src}: 'names' must be a non-empty list of joint names")
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{src}: 'frames' must be a non-empty list of frames")
    K = len(names)
    for t, fr in enumerate(frames):
        ok = isinstance(fr, list) and len(fr) == K
        if not ok or any(not isinstance(p, list) or len(p) != 3 for p in fr):
            n = f"{len(fr)} keypoints" if isinstance(fr, list) else "no list"
            raise ValueError(f"{src}: frame {t} has {n}; expected {K} (one per name) [x, y, s]")
    v = _numbers([x for fr in frames for p in fr for x in p], src, "frames")
    if _non_finite(fps := doc.get("fps")):
        raise ValueError(f"{src}{line(('fps',))}: fps must be finite, got {fps}")

    def path(t: int, i: int) -> tuple[str | int, ...]:
        return ("frames", t, i // 3, i % 3)

    return v.reshape(len(frames), K, 3), tuple(names), fps, None, path


def _from_json(data: bytes, src: str) -> tuple:
    """``(values (T, K, 3), names or None for COCO-17, fps, image ids or None, line of a
    value)``: ``line(t, i)`` is ``":LINE"`` of value ``i`` (x, y, score of each keypoint) of
    frame ``t`` in the file.

    NaN and Infinity are read (a missing keypoint's pixel may be anything); a number no float
    holds (a 401-digit integer, ``1e400``) is refused with the line.
    """
    try:
        text = data.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError:
        kind = describe_kind(file_kind(src) or "other")
        raise ValueError(f"{src}: a {kind}, not a keypoint file (JSON or .npz)") from None
    if text.lstrip()[:9].upper() == "HIERARCHY":
        raise ValueError(f"{src}: a BVH motion file, not a keypoint file")
    doc = load_json(text, src, what="keypoint file", nonfinite=True)

    def line(path: tuple[str | int, ...]) -> str:
        n = json_value_line(text, path) if path else None
        return "" if n is None else f":{n}"

    if isinstance(doc, list) or (isinstance(doc, dict) and doc.get("format") == "mtex-keypoints"):
        read = _coco(doc, src, line) if isinstance(doc, list) else _mtex_json(doc, src, line)
        v, names, fps, ids, path = read
        return v, names, fps, ids, lambda t, i: line(path(t, i))
    what = f"a JSON {type(doc).__name__}"
    if isinstance(doc, dict):
        keys = ", ".join(map(repr, list(doc)[:8]))
        what = "a DeepMimic motion file" if "Frames" in doc else f"JSON with keys {keys}"
    raise ValueError(f"{src}: {what}, not a keypoint file (COCO results or mtex-keypoints)")


def _from_npz(data: bytes, src: str) -> tuple:
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            sizes = {i.filename.removesuffix(".npy"): i.file_size for i in zf.infolist()}
    except (OSError, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"{src}: unreadable NumPy archive: {e}") from None
    if "__meta_json__" in sizes:
        kind = describe_kind(file_kind(src) or "npz")
        raise ValueError(f"{src}: a {kind} (an mtex_jax model file), not a keypoint file")
    if "keypoints" not in sizes:
        have = ", ".join(sorted(sizes)) or "nothing"
        raise ValueError(f"{src}: a NumPy archive of {have}, not a keypoint file (no 'keypoints')")
    if max(sizes.values()) > limit("MAX_MEMBER_BYTES"):
        raise ValueError(f"{src}: an array is larger than MAX_MEMBER_BYTES unpacked")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            kp, names, fps = z["keypoints"], z.get("names"), z.get("fps")
    except (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile) as e:
        raise ValueError(f"{src}: unreadable NumPy archive: {e}") from None  # object arrays too
    if kp.dtype.kind not in "biuf" or kp.ndim != 3 or kp.shape[2] != 3 or kp.shape[0] < 1:
        raise ValueError(f"{src}: 'keypoints' must be numbers (T, K, 3): {kp.dtype} {kp.shape}")
    if names is not None:
        if names.dtype.kind not in "US" or names.shape != (kp.shape[1],):
            raise ValueError(f"{src}: 'names' must be {kp.shape[1]} strings, one per keypoint")
        names = tuple(str(n) for n in names.astype(str))
    if fps is not None:
        fps = fps.item() if fps.shape == () and fps.dtype.kind in "iuf" else repr(fps)
    return kp.astype(np.float64), names, fps, None, lambda t, i: ""


def _resolve(
    names: tuple[str, ...] | None, skeleton: Skeleton, mapping: Mapping[str, str] | None, src: str
) -> tuple[list[int], list[str], list[int]]:
    """The columns kept, their source names and their joints (``names=None``: COCO-17)."""
    joints = list(skeleton.names)
    if mapping is not None:
        mapping = dict(mapping)
        if bad := [j for j in mapping.values() if j not in joints]:
            raise ValueError(f"{src}: the mapping names {bad}, not joints; {_its_joints(skeleton)}")
        if names is None and (bad := [c for c in mapping if c not in COCO17_NAMES]):
            raise ValueError(f"{src}: the mapping's keys {bad} are not COCO-17 keypoints")
    elif names is None:
        try:
            mapping = coco_joint_map(skeleton)
        except ValueError as e:
            raise ValueError(f"{src}: {e}") from None
    else:  # joint names, or COCO names of a known skeleton
        mapping = _table(skeleton) or {}
    cols, kept, idx = [], [], {}
    for c, n in enumerate(COCO17_NAMES if names is None else names):
        j = mapping.get(n, None if names is None else n)
        if j is None:
            continue  # a COCO keypoint without a joint (eyes, ears)
        if j not in joints:
            raise ValueError(f"{src}: unknown joint name {n!r}; {_its_joints(skeleton)}")
        if j in idx:
            raise ValueError(f"{src}: keypoints {idx[j]!r} and {n!r} both name the joint {j!r}")
        cols.append(c)
        kept.append(n)
        idx[j] = n
    if not cols:
        raise ValueError(f"{src}: no keypoint maps to a joint of the skeleton")
    return cols, kept, [joints.index(j) for j in idx]


def read_keypoints(
    path: str | os.PathLike[str],
    skeleton: Skeleton,
    *,
    mapping: Mapping[str, str] | None = None,
    fps: float | None = None,
) -> Keypoints:
    """Read 2-D keypoints of ``skeleton``'s joints from a file (design §12.1).

    Formats, found from the content: COCO results JSON, ``[{"image_id", "category_id": 1,
    "keypoints": [x1, y1, s1, …, x17, y17, s17], "score"}, ...]``, one frame per distinct
    ``image_id`` (integers by value, strings in natural order), the detection of highest
    ``score`` (default: the mean keypoint score), an image with only other categories or
    ``"keypoints": []`` a frame of missing keypoints; an ``.npz`` with ``keypoints (T, 17,
    3)`` (x, y, score) and optional ``fps``; the skeleton's own joints, an ``.npz`` with
    ``keypoints (T, K, 3)`` and ``names`` (K joint names), or JSON ``{"format":
    "mtex-keypoints", "names": [...], "fps": 30, "frames": [[[x, y, s], ...], ...]}``. A score
    of 0 marks a missing keypoint (its pixel may be anything, NaN or null too); scores above 1
    (COCO's visibility flag 2) count as 1.

    Args:
        path: the file.
        skeleton: the tracked skeleton.
        mapping: keypoint name → joint name, replacing the default: :func:`coco_joint_map`
            for COCO files (keypoints it leaves out are dropped); for named files the names
            are joints, or COCO names of a known skeleton.
        fps: frames per second (overrides the file's; COCO files have none).

    Raises:
        ValueError: naming the file and the problem: empty, another kind of file, a wrong
            keypoint count, a non-finite pixel with a positive score (frame and keypoint
            named), bad scores, unknown joint names, numbers no float can hold. In a JSON file
            the line is named too: ``NaN`` and ``Infinity`` are read only as the pixel of a
            missing keypoint (anywhere else, a score, ``fps``, ``category_id``, they are
            refused); a number no float64 holds (a 401-digit integer, ``1e400``) is refused
            anywhere; a denormal (``4e-320``) is read as its value, ``-0.0`` as zero.
    """
    src = str(path)
    data = read_input(path, "keypoint file")
    if not data.strip():
        raise ValueError(f"{src}: empty file; expected a keypoint file (COCO JSON or .npz)")
    read = _from_npz if data.startswith(b"PK\x03\x04") else _from_json
    v, names, file_fps, ids, line = read(data, src)
    T, K = v.shape[:2]
    if names is None and K != 17:
        raise ValueError(f"{src}: {K} keypoints per frame; COCO-17 has 17 (or give 'names')")
    check_size(T, f"{src}: frames", "MAX_FRAMES")
    fps = file_fps if fps is None else fps
    if fps is not None and (fps := float(_reals(fps, (), src, "fps"))) <= 0:
        raise ValueError(f"{src}: fps must be positive, got {fps:g}")
    cols, kept, joints = _resolve(names, skeleton, mapping, src)
    xy, s = v[:, cols, :2], v[:, cols, 2]

    def refuse(bad: np.ndarray, what: str, value: int | np.ndarray) -> None:
        """Refuse the first keypoint of ``bad``, with the line of its score (``value`` 2) or
        of its first pixel coordinate ``value`` marks (``(T, K, 2)``)."""
        if bad.any():
            t, k = (int(i) for i in np.argwhere(bad)[0])
            frame = f"frame {t}" + ("" if ids is None else f" (image_id {ids[t]!r})")
            at = f"pixel {tuple(xy[t, k].tolist())}, score {s[t, k]}; {int(bad.sum())} such"
            j = value if isinstance(value, int) else int(np.argmax(value[t, k]))
            where = line(t, 3 * cols[k] + j)
            raise ValueError(f"{src}{where}: {frame}, keypoint {kept[k]!r}: {what} ({at})")

    big = limit("MAX_ABS_VALUE")
    refuse(~np.isfinite(s), "the score is not finite", 2)
    refuse(s < 0, "the score is negative", 2)
    nan_px = ~np.isfinite(xy)
    refuse((s > 0) & nan_px.any(-1), "NaN/inf pixel with a positive score (0: missing)", nan_px)
    big_px = np.abs(xy) > big
    refuse((s > 0) & big_px.any(-1), f"a pixel beyond ±{big:g}", big_px)
    return Keypoints(
        joints=tuple(joints),
        pixels=np.where((s > 0)[..., None], xy, 0.0),
        confidence=np.minimum(s, 1.0),
        names=tuple(kept),
        fps=fps,
    )


def write_keypoints(
    path: str | os.PathLike[str], keypoints: Keypoints, format: str = "coco"
) -> None:
    """Write ``keypoints`` as JSON, atomically; :func:`read_keypoints` reads it back.

    Args:
        path: the file.
        keypoints: for ``"coco"``, named by COCO names.
        format: ``"coco"`` (COCO results: one detection per frame, ``image_id`` the frame,
            missing keypoints ``0, 0, 0``; no fps) or ``"mtex-keypoints"``.

    Raises:
        ValueError: an unknown format, non-COCO names for ``"coco"``, non-finite pixels.
    """
    if not isinstance(keypoints, Keypoints):
        raise TypeError(f"write_keypoints: expected Keypoints, got {type(keypoints).__name__}")
    if format not in ("coco", "mtex-keypoints"):
        raise ValueError(f"write_keypoints: format must be 'coco' or 'mtex-keypoints': {format!r}")
    conf = np.asarray(keypoints.confidence, dtype=np.float64)
    xy = np.asarray(keypoints.pixels, dtype=np.float64)
    if not np.isfinite(xy[conf > 0]).all():
        raise ValueError("write_keypoints: a pixel with a positive confidence is not finite")
    v = np.concatenate([np.where(conf[..., None] > 0, xy, 0.0), conf[..., None]], axis=-1)
    doc: Any = {"format": format, "names": list(keypoints.names), "fps": keypoints.fps}
    doc["frames"] = v.tolist()
    if format == "coco":
        if bad := [n for n in keypoints.names if n not in COCO17_NAMES]:
            raise ValueError(f"write_keypoints: {bad} are not COCO keypoints (use mtex-keypoints)")
        full = np.zeros((len(v), 17, 3))
        full[:, [COCO17_NAMES.index(n) for n in keypoints.names]] = v
        doc = [
            {"image_id": t, "category_id": 1, "keypoints": full[t].ravel().tolist(), "score": c}
            for t, c in enumerate(conf.mean(axis=1).tolist())
        ]
    with atomic_write(path, "w", encoding="utf-8") as fh:
        json.dump(doc, fh, allow_nan=False)


# --------------------------------------------------------------------------- camera
_CAMERA = ("focal", "fx", "fy", "center", "cx", "cy", "rotation", "translation", "width", "height")


def _reals(v: Any, shape: tuple[int, ...], src: str, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=object) if isinstance(v, list | int | float) else None
    if a is None or a.shape != shape:
        raise ValueError(f"{src}: '{what}' must be {shape or 'a number'} numbers, got {v!r:.40}")
    try:
        return np.array([check_real(x, what) for x in a.reshape(-1)]).reshape(shape)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{src}: {e}") from None


def read_camera(path: str | os.PathLike[str], up_axis: int = 1) -> tuple[Camera, bool]:
    """A pin-hole :class:`Camera` from JSON (design §12.1), and whether its pose was given.

    Fields: the focal length in pixels, ``"focal"`` or ``"fx"`` and ``"fy"`` (within 1 %: only
    square pixels are modelled); the principal point ``"center": [cx, cy]`` or ``"cx"``,
    ``"cy"``; optionally the pose, ``"rotation"`` (3 x 3, world to camera) with
    ``"translation"`` (3,); ``"width"``, ``"height"``; no other field (a misspelt pose must not
    pass unnoticed). Without a pose the camera is *level at the world origin*: the up axis is
    up in the image and it looks along the second horizontal axis of
    :func:`~mtex_jax.motion.ground_axes`; the tracker then estimates the floor.

    Args:
        path: the JSON file.
        up_axis: the skeleton's up axis (``Skeleton.up_axis``).

    Raises:
        ValueError: naming the file: not a JSON object, unknown or missing fields, a focal
            length not positive and finite, non-square pixels, a rotation that is not one
            (orthonormal within 1e-3, determinant +1; it is then made exact); with the line,
            invalid JSON, ``NaN`` or ``Infinity`` and numbers no float64 holds (a 401-digit
            integer, ``1e400``). A denormal (``4e-320``) is read as its value, ``-0.0`` as
            zero.
    """
    src = str(path)
    if isinstance(up_axis, bool) or up_axis not in (0, 1, 2):
        raise ValueError(f"read_camera: up_axis must be 0, 1 or 2, got {up_axis!r}")
    text = read_input(path, "camera file").decode("utf-8", "replace").removeprefix("\ufeff")
    doc = load_json(text, src, what="camera file")  # NaN, Infinity, 1e400 refused, with the line
    if not isinstance(doc, dict):
        raise ValueError(f"{src}: not a camera file: expected a JSON object with 'focal' etc.")
    if unknown := sorted(set(doc) - set(_CAMERA)):
        raise ValueError(f"{src}: unknown camera fields {unknown}; the fields are {_CAMERA}")
    if ("focal" in doc) == ("fx" in doc or "fy" in doc):
        raise ValueError(f"{src}: give the focal length once: 'focal', or 'fx' and 'fy'")
    keys = ("focal", "focal") if "focal" in doc else ("fx", "fy")
    fx, fy = (float(_reals(doc.get(k), (), src, k)) for k in keys)
    if not (fx > 0 and fy > 0):
        raise ValueError(f"{src}: the focal length must be positive, got {fx:g}, {fy:g}")
    if abs(fx - fy) > 0.01 * max(fx, fy):
        raise ValueError(f"{src}: fx, fy differ by > 1 %; only square pixels are modelled")
    if ("center" in doc) == ("cx" in doc or "cy" in doc):
        raise ValueError(f"{src}: give the principal point once: 'center', or 'cx' and 'cy'")
    c = doc["center"] if "center" in doc else [doc.get("cx"), doc.get("cy")]
    focal, (cx, cy) = 0.5 * (fx + fy), _reals(c, (2,), src, "center").tolist()
    if ("rotation" in doc) != ("translation" in doc):
        raise ValueError(f"{src}: 'rotation' and 'translation' are given together (or neither)")
    if "rotation" not in doc:
        u, _, h1 = ground_axes(up_axis)
        e = np.eye(3)
        return Camera.look_at(0 * e[0], e[h1], e[u], focal=focal, center=(cx, cy)), False
    R = _reals(doc["rotation"], (3, 3), src, "rotation")
    t = _reals(doc["translation"], (3,), src, "translation")
    if np.max(np.abs(R @ R.T - np.eye(3))) > 1e-3 or np.linalg.det(R) <= 0:
        raise ValueError(f"{src}: 'rotation' is not a rotation matrix (orthonormal, det +1)")
    w, _, vt = np.linalg.svd(R)  # the nearest rotation: the file's rounded digits made exact
    rot, trans, center = jnp.asarray(w @ vt), jnp.asarray(t), jnp.asarray([cx, cy])
    return Camera(rotation=rot, translation=trans, focal=jnp.asarray(focal), center=center), True


def problem_from_keypoints(
    keypoints: Keypoints, camera: Camera, *, pixel_noise: float = 2.0
) -> TrackingProblem:
    """The :class:`TrackingProblem` of real keypoints (design §12.1): frames ``0 … T-1``, no
    initial state, no ground truth.

    Args:
        keypoints: from :func:`read_keypoints`.
        camera: from :func:`read_camera` (or :meth:`Camera.look_at`).
        pixel_noise: standard deviation (pixels) of the detections' noise.
    """
    if not isinstance(keypoints, Keypoints) or not isinstance(camera, Camera):
        raise TypeError("problem_from_keypoints: expected Keypoints and a Camera")
    sigma = check_real(pixel_noise, "problem_from_keypoints: pixel_noise", low=0.0, open_low=True)
    obs, conf = keypoints.pixels, keypoints.confidence
    return TrackingProblem(
        joints=keypoints.joints,
        frames=tuple(range(keypoints.n_frames)),
        camera=camera,
        pixel_noise=jnp.asarray(sigma, obs.dtype),
        observations=jnp.where(conf[..., None] > 0, obs, 0.0),
        confidence=conf,
    )
