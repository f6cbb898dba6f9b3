"""Pose vectors and motion windows of the implicit model (IP §3, SPEC §7), and the checks of its
inputs."""

from __future__ import annotations

from typing import Any

import numpy as np
from jax.core import Tracer

from ..motion import FeatureMap, Motion

_MAX_BITS = 30  # sign codes are int32


# --------------------------------------------------------------------------- helpers
def _is_concrete(x: Any) -> bool:
    return not isinstance(x, Tracer)


def _check_beta(beta: Any, fn: str) -> None:
    if _is_concrete(beta):
        b = np.asarray(beta)
        if b.shape != ():
            raise ValueError(f"{fn}: beta must be a scalar, got shape {b.shape}")
        if not (np.isfinite(b) and b > 0):
            raise ValueError(f"{fn}: beta (temperature) must be positive and finite, got {b!r}")


def _check_candidates(candidates: Any, fn: str) -> None:
    if isinstance(candidates, bool) or not isinstance(candidates, int | np.integer):
        raise ValueError(f"{fn}: candidates must be an integer, got {candidates!r}")
    if candidates < 1:
        raise ValueError(f"{fn}: candidates must be ≥ 1, got {candidates}")


def _check_motion_values(m: Motion, what: str) -> None:
    for name in ("root_positions", "rotations"):
        a = np.asarray(getattr(m, name))
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{what}: non-finite values (NaN/inf) in {name}")


def _encode(fm: FeatureMap, motion: Motion) -> np.ndarray:
    """``fm.encode(motion)`` as NumPy, padded to a power-of-two length to share compilations.

    The observation channels of frame ``t`` depend only on frames ``≤ t`` (frame 0 on frame
    1), so appending copies of the last frame leaves the first ``T`` rows unchanged.
    """
    t = motion.n_frames
    length = max(64, 1 << (max(t, 2) - 1).bit_length())
    pad = length - t
    m = motion.numpy()
    if pad:
        rep = lambda a: np.concatenate([a, np.repeat(a[-1:], pad, axis=0)], axis=0)
        lp = None if m.local_positions is None else rep(m.local_positions)
        m = Motion(m.skeleton, m.fps, rep(m.root_positions), rep(m.rotations), lp)
    return np.asarray(fm.encode(m))[:t]


def pose_vectors(fm: FeatureMap, motion: Motion) -> np.ndarray:
    """Pose vectors ``ψ_t = [y_t, y_t − y_{t−1}]`` of frames ``1 … T−1`` of a clip.

    Args:
        fm: the feature map giving ``y_t`` (its units are the pose vector's units).
        motion: a clip with at least 2 frames at ``fm.fps``.

    Returns:
        ``(T − 1, 2D)`` NumPy array; row ``k`` belongs to frame ``k + 1``.
    """
    if motion.n_frames < 2:
        raise ValueError(f"pose_vectors: a clip needs at least 2 frames, got {motion.n_frames}")
    _check_motion_values(motion, "pose_vectors")
    y = _encode(fm, motion)
    return np.concatenate([y[1:], y[1:] - y[:-1]], axis=1)


def velocity_channels(fm: FeatureMap) -> tuple[int, ...]:
    """Indices (into ``y``) of the channels that are per-frame changes: the root's horizontal
    displacement and yaw change (names ``root.d…``)."""
    return tuple(i for i, name in enumerate(fm.active_names) if name.startswith("root.d"))


def _window_view(psi: np.ndarray, d: int) -> np.ndarray:
    """All ``(T' − d + 1, d, P)`` windows of consecutive rows (oldest first)."""
    v = np.lib.stride_tricks.sliding_window_view(psi, d, axis=0)  # (n, P, d)
    return np.ascontiguousarray(np.moveaxis(v, -1, 1))
