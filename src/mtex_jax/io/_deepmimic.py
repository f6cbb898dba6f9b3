"""Reader for the DeepMimic JSON motion format (humanoid3d character)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..core import (
    MAX_ABS_VALUE,
    MAX_FRAME_TIME,
    MAX_FRAMES,
    check_frame_time,
    load_json,
    read_input,
)
from ..motion import Motion, Skeleton, slerp_frames

__all__ = ["HUMANOID3D", "parse_deepmimic", "read_deepmimic"]

_ROT = ("Zrotation", "Yrotation", "Xrotation")
_ROOT = ("Xposition", "Yposition", "Zposition", *_ROT)
_HINGE = ("Zrotation",)

# The humanoid3d character of DeepMimic (y up, x forward, z to the character's right), its
# joints listed depth-first. Offsets are the joint attachment points of the character file, in
# metres. Knees and elbows are revolute joints about the local z axis. End sites: the head
# centre, the wrists (hand centres) and the toes.
HUMANOID3D = Skeleton(
    names=(
        "root",
        "chest",
        "neck",
        "right_shoulder",
        "right_elbow",
        "left_shoulder",
        "left_elbow",
        "right_hip",
        "right_knee",
        "right_ankle",
        "left_hip",
        "left_knee",
        "left_ankle",
    ),
    parents=(-1, 0, 1, 1, 3, 1, 5, 0, 7, 8, 0, 10, 11),
    offsets=(
        (0.0, 0.0, 0.0),
        (0.0, 0.236151, 0.0),
        (0.0, 0.223894, 0.0),
        (-0.02405, 0.2435, 0.18311),
        (0.0, -0.274788, 0.0),
        (-0.02405, 0.2435, -0.18311),
        (0.0, -0.274788, 0.0),
        (0.0, 0.0, 0.084887),
        (0.0, -0.421546, 0.0),
        (0.0, -0.40987, 0.0),
        (0.0, 0.0, -0.084887),
        (0.0, -0.421546, 0.0),
        (0.0, -0.40987, 0.0),
    ),
    channels=(
        _ROOT,
        _ROT,
        _ROT,
        _ROT,
        _HINGE,
        _ROT,
        _HINGE,
        _ROT,
        _HINGE,
        _ROT,
        _ROT,
        _HINGE,
        _ROT,
    ),
    end_sites=(
        (2, (0.0, 0.175, 0.0)),
        (4, (0.0, -0.258947, 0.0)),
        (6, (0.0, -0.258947, 0.0)),
        (9, (0.13, -0.05, 0.0)),
        (12, (0.13, -0.05, 0.0)),
    ),
    up_axis=1,
)

# Layout of a frame: (joint name, kind) after the duration and root position.
_LAYOUT = (
    ("root", "quat"),
    ("chest", "quat"),
    ("neck", "quat"),
    ("right_hip", "quat"),
    ("right_knee", "angle"),
    ("right_ankle", "quat"),
    ("right_shoulder", "quat"),
    ("right_elbow", "angle"),
    ("left_hip", "quat"),
    ("left_knee", "angle"),
    ("left_ankle", "quat"),
    ("left_shoulder", "quat"),
    ("left_elbow", "angle"),
)
FRAME_SIZE = 1 + 3 + sum(4 if k == "quat" else 1 for _, k in _LAYOUT)  # 44


def _frame_lines(text: str) -> list[int]:
    """1-based line number where each frame's opening bracket appears (depth-2 '[')."""
    lines: list[int] = []
    depth = 0
    line = 1
    in_str = False
    esc = False
    for ch in text:
        if ch == "\n":
            line += 1
        if in_str:
            if esc:
                esc = False
            elif ch == "\\":
                esc = True
            elif ch == '"':
                in_str = False
            continue
        if ch == '"':
            in_str = True
        elif ch in "[{":
            depth += 1
            if ch == "[" and depth == 3:
                lines.append(line)
        elif ch in "]}":
            depth -= 1
    return lines


def parse_deepmimic(text: str, source: str = "<string>", *, max_frames: int = MAX_FRAMES) -> Motion:
    """Parse DeepMimic JSON motion text (see :func:`read_deepmimic`); a leading UTF-8
    byte-order mark is skipped."""
    text = text.removeprefix("\ufeff")
    # numbers no float holds (a 401-digit integer, 1e400) and NaN / Infinity: refused, with
    # the line; JSON nested too deeply: refused before parsing
    doc = load_json(text, source)
    if not isinstance(doc, dict) or "Frames" not in doc:
        raise ValueError(f"{source}:1: not a DeepMimic motion (no 'Frames' list)")
    frames = doc["Frames"]
    if not isinstance(frames, list) or len(frames) == 0:
        raise ValueError(f"{source}:1: zero frames")
    if len(frames) > max_frames:
        raise ValueError(f"{source}:1: {len(frames):,} frames exceed the limit of {max_frames:,}")
    lines: list[int] | None = None

    def where(k: int) -> int:
        nonlocal lines
        if lines is None:
            lines = _frame_lines(text)
        return lines[k] if k < len(lines) else 1

    for k, fr in enumerate(frames):
        if not isinstance(fr, list) or len(fr) != FRAME_SIZE:
            n = len(fr) if isinstance(fr, list) else type(fr).__name__
            raise ValueError(
                f"{source}:{where(k)}: frame {k} has {n} values, expected {FRAME_SIZE}"
            )
        for v in fr:
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ValueError(f"{source}:{where(k)}: non-numeric value {v!r} in frame {k}")
            if isinstance(v, int) and abs(v) > MAX_ABS_VALUE:  # also no float holds it
                raise ValueError(
                    f"{source}:{where(k)}: a {len(str(abs(v)))}-digit integer in frame {k} "
                    f"exceeds {MAX_ABS_VALUE:g} in magnitude"
                )
    data = np.asarray(frames, dtype=np.float64)
    bad = ~np.all(np.isfinite(data), axis=1)
    if bad.any():
        k = int(np.nonzero(bad)[0][0])
        raise ValueError(f"{source}:{where(k)}: non-finite value in frame {k}")
    big = np.nonzero((np.abs(data) > MAX_ABS_VALUE).any(axis=1))[0]
    if big.size:
        k = int(big[0])
        raise ValueError(
            f"{source}:{where(k)}: value in frame {k} exceeds {MAX_ABS_VALUE:g} in magnitude"
        )
    dt = data[:, 0]
    # Durations: every keyframe but the last must last > 0 s (the last conventionally 0).
    body = dt[:-1] if len(dt) > 1 else dt
    nonpos = np.nonzero(~(body > 0))[0]
    if nonpos.size:
        k = int(nonpos[0])
        raise ValueError(
            f"{source}:{where(k)}: inconsistent frame time: frame {k} lasts {body[k]:g} s "
            "(durations must be positive)"
        )
    if len(dt) > 1 and dt[-1] < 0:
        k = len(dt) - 1
        raise ValueError(f"{source}:{where(k)}: inconsistent frame time: negative duration")
    vals, counts = np.unique(np.round(body, 9), return_counts=True)
    step = float(vals[np.argmax(counts)])
    check_frame_time(step, f"{source}:{where(int(np.argmin(np.abs(body - step))))}")
    long = np.nonzero(body > MAX_FRAME_TIME)[0]
    if long.size:
        k = int(long[0])
        raise ValueError(
            f"{source}:{where(k)}: keyframe {k} lasts {body[k]:g} s (limit {MAX_FRAME_TIME:g} s)"
        )
    total = float(body.sum()) if len(dt) > 1 else 0.0
    if total / step + 1 > max_frames:
        k = int(np.argmax(body))
        raise ValueError(
            f"{source}:{where(k)}: the keyframes last {total:g} s (frame {k}: {body[k]:g} s); "
            f"resampled every {step:g} s that is {total / step + 1:,.0f} frames, more than the "
            f"limit of {max_frames:,}"
        )
    fps = 1.0 / step
    if abs(fps - round(fps)) < 1e-3 * fps:
        fps = float(round(fps))
    sk = HUMANOID3D
    t = data.shape[0]
    rot = np.zeros((t, sk.n_joints, 4))
    col = 4
    for name, kind in _LAYOUT:
        j = sk.index(name)
        if kind == "quat":
            q = data[:, col : col + 4]
            n = np.linalg.norm(q, axis=1)
            badq = np.nonzero((n < 0.1) | (n > 10.0))[0]
            if badq.size:
                k = int(badq[0])
                raise ValueError(
                    f"{source}:{where(k)}: quaternion of {name!r} in frame {k} has norm "
                    f"{n[k]:.4g}; not a rotation"
                )
            rot[:, j] = q / n[:, None]
            col += 4
        else:
            half = 0.5 * data[:, col]
            rot[:, j, 0] = np.cos(half)
            rot[:, j, 3] = np.sin(half)  # revolute about local z
            col += 1
    motion = Motion(sk, fps, data[:, 1:4].copy(), rot)
    if np.any(np.abs(body - step) > 1e-6 * step):
        # non-uniform keyframes: resample to the most common duration (slerp / linear)
        times = np.concatenate([[0.0], np.cumsum(body)])[: len(dt)]
        motion = _resample_keyframes(motion, times, fps)
    return motion


def _resample_keyframes(motion: Motion, times: np.ndarray, fps: float) -> Motion:
    n_new = int(np.floor(times[-1] * fps + 1e-6)) + 1
    tn = np.arange(n_new) / fps
    i0 = np.clip(np.searchsorted(times, tn, side="right") - 1, 0, len(times) - 2)
    frac = np.clip((tn - times[i0]) / (times[i0 + 1] - times[i0]), 0.0, 1.0)
    rp = np.asarray(motion.root_positions)
    rot = np.asarray(motion.rotations)
    rp_new = rp[i0] + (rp[i0 + 1] - rp[i0]) * frac[:, None]
    rot_new = slerp_frames(rot, i0, frac)
    return Motion(motion.skeleton, fps, rp_new, rot_new)


def read_deepmimic(path: str | os.PathLike[str], *, max_frames: int = MAX_FRAMES) -> Motion:
    """Read a DeepMimic humanoid3d motion file (JSON).

    Each frame is ``[duration, root xyz, root quat wxyz, chest quat, neck quat, right hip
    quat, right knee angle, right ankle quat, right shoulder quat, right elbow angle, left
    hip quat, left knee angle, left ankle quat, left shoulder quat, left elbow angle]``, 44
    numbers; y is up. Quaternions are renormalised (the shipped clips have norms from 0.58 to
    1.12; a norm below 0.1 or above 10 is an error); revolute angles become rotations about
    the joint's local z axis. Keyframes of unequal duration (``humanoid3d_roll`` has one) are
    resampled to the most common duration by slerp. The frame rate is the inverse of that
    duration, snapped to the nearest integer when within 0.1 % (0.033332 s → 30 Hz). The skeleton is
    :data:`HUMANOID3D` (joints in depth-first order, so :func:`write_bvh` round-trips).

    Numbers: a number no float64 holds (a 401-digit integer, ``1e400``, which Python's
    ``json`` reads as inf) and ``NaN``, ``Infinity`` or ``-Infinity`` anywhere in the file are
    refused with the line (other spellings, ``nan`` or ``inf``, are not JSON); a denormal
    (``4e-320``) is read as its value (a duration is then checked like any other), ``-0.0``
    as zero.

    Raises:
        ValueError: naming the file and line for invalid JSON, a frame of the wrong length, a
            non-numeric or non-finite value, a number no float holds, zero frames, or an
            inconsistent frame duration;
            and on input beyond the limits of :mod:`mtex_jax.core`: a file larger than
            ``MAX_INPUT_BYTES`` or not a regular file, JSON nested deeper than
            ``MAX_DEPTH`` (refused before parsing, without recursion), more than
            ``max_frames`` frames after resampling (a keyframe lasting 1e6 s), a frame time
            outside ``[MIN_FRAME_TIME, MAX_FRAME_TIME]``, a number beyond ``MAX_ABS_VALUE``.
    """
    p = Path(path)
    try:
        text = read_input(p, "DeepMimic file").decode("utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"{p}: cannot read DeepMimic file: {e}") from None
    return parse_deepmimic(text, str(p), max_frames=max_frames)
