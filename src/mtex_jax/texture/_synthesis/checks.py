"""The argument checks of whole-sequence synthesis and the choreographer (design §5), and the
rescaling of texton lengths to a requested number of frames."""

from __future__ import annotations

from typing import Any

import numpy as np

from ...core import check_count, check_size
from .._model import MotionTexture

__all__ = [
    "DEFAULT_TRANSITION",
    "check_lengths",
    "check_n_frames",
    "check_options",
    "check_pair",
    "check_texture",
    "scale_lengths",
    "transition_decay",
]

#: Default time constant (seconds) of the bend towards the next key poses (design §10.11).
DEFAULT_TRANSITION = 0.25


def check_texture(texture: MotionTexture) -> None:
    if not isinstance(texture, MotionTexture):
        raise TypeError(f"expected a MotionTexture, got {type(texture).__name__}")
    labels = np.asarray(texture.key_pose_labels)
    missing = np.setdiff1d(np.arange(texture.n_textons), labels)
    if missing.size:
        raise ValueError(
            f"texton(s) {missing.tolist()} have no training segments (no key poses to start from)"
        )
    short = np.flatnonzero(np.asarray(texture.segment_lengths) < 2)
    if short.size:
        raise ValueError(
            f"training segments {short[:5].tolist()} are shorter than 2 frames "
            "(MotionTexture.segment_lengths)"
        )


def check_options(weighting: Any, residual: Any, replay: Any = "aligned") -> None:
    if weighting not in ("whitened", "paper"):
        raise ValueError(f"weighting must be 'whitened' or 'paper', got {weighting!r}")
    if residual not in ("blend", "subspace"):
        raise ValueError(f"residual must be 'blend' or 'subspace', got {residual!r}")
    if replay not in ("aligned", "shuffled"):
        raise ValueError(f"replay must be 'aligned' or 'shuffled', got {replay!r}")


def check_n_frames(n_frames: Any) -> int:
    if isinstance(n_frames, bool) or not isinstance(n_frames, int | np.integer):
        raise TypeError(f"n_frames must be an int, got {n_frames!r}")
    return check_count(n_frames, "n_frames", "MAX_GENERATED_FRAMES", low=4)


def check_pair(name: str, pose: Any, D: int) -> np.ndarray:
    try:
        p = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise TypeError(f"{name} must be a (2, {D}) array of observation frames") from e
    if p.shape != (2, D):
        raise ValueError(f"{name} must have shape (2, {D}) (two observation frames), got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"{name} contains NaN or inf")
    return p


def check_lengths(lengths: Any, n: int) -> np.ndarray:
    arr = np.asarray(lengths)
    if arr.shape != (n,) or not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(
            f"lengths must be {n} integers (one per texton), got {arr.dtype} {arr.shape}"
        )
    longest = int(arr.max()) if arr.size else 0
    check_size(longest, "synthesize: a texton's length", "MAX_GENERATED_FRAMES")
    check_size(
        int(arr.astype(np.int64).sum()), "synthesize: sum of lengths", "MAX_GENERATED_FRAMES"
    )
    return arr.astype(np.int64)


def scale_lengths(lengths: np.ndarray, total: int, min_len: np.ndarray) -> np.ndarray:
    """Integer lengths proportional to ``lengths`` that sum to ``total`` (each ≥ its minimum)."""
    if total < int(min_len.sum()):
        raise ValueError(
            f"{total} frames are too few for {lengths.size} textons (need >= {int(min_len.sum())})"
        )
    out = np.maximum(np.floor(lengths * total / lengths.sum()).astype(np.int64), min_len)
    while out.sum() != total:  # at most n corrections
        diff = total - int(out.sum())
        if diff > 0:
            out[np.argmax(lengths * total / lengths.sum() - out)] += 1
        else:
            slack = np.where(out > min_len, out - lengths * total / lengths.sum(), -np.inf)
            out[np.argmax(slack)] -= 1
    return out


def transition_decay(texture: MotionTexture, transition: Any) -> float | None:
    """``1 / τ`` in frames of the bend towards the next key poses (design §10.11), or ``None``
    (the exact conditional sample: every equation weighted 1).

    ``transition``: ``"auto"`` (:data:`DEFAULT_TRANSITION` seconds when the texture knows its
    frame rate, i.e. was learned from motions, else ``None``), ``None``, or a positive number
    of seconds (at least one frame).
    """
    fm = texture.feature_map
    if isinstance(transition, str):
        if transition != "auto":
            raise ValueError(f"transition must be 'auto', None or seconds, got {transition!r}")
        if fm is None:
            return None
        transition = DEFAULT_TRANSITION
    if transition is None:
        return None
    if isinstance(transition, bool) or not isinstance(transition, int | float | np.number):
        raise TypeError(f"transition must be 'auto', None or seconds, got {transition!r}")
    if fm is None:
        raise ValueError(
            "transition in seconds needs a texture with a frame rate (learned from motions); "
            "use transition=None"
        )
    frames = float(transition) * float(fm.fps)
    if not (np.isfinite(frames) and frames >= 1.0):
        raise ValueError(
            f"transition must be finite and at least one frame (1/{fm.fps:g} s), got {transition!r}"
        )
    return 1.0 / frames
