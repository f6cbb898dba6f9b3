"""Pose vectors and motion windows of the implicit model (IP §3, design §7), and the checks of its
inputs."""

from __future__ import annotations

from typing import Any

import numpy as np
from jax.core import Tracer

from ..motion import FeatureMap, Motion

MAX_BITS = 30  # sign codes are int32


# --------------------------------------------------------------------------- helpers
def is_concrete(x: Any) -> bool:
    return not isinstance(x, Tracer)


def check_beta(beta: Any, fn: str) -> None:
    if is_concrete(beta):
        b = np.asarray(beta)
        if b.shape != ():
            raise ValueError(f"{fn}: beta must be a scalar, got shape {b.shape}")
        if not (np.isfinite(b) and b > 0):
            raise ValueError(f"{fn}: beta (temperature) must be positive and finite, got {b!r}")


def check_candidates(candidates: Any, fn: str) -> None:
    if isinstance(candidates, bool) or not isinstance(candidates, int | np.integer):
        raise ValueError(f"{fn}: candidates must be an integer, got {candidates!r}")
    if candidates < 1:
        raise ValueError(f"{fn}: candidates must be ≥ 1, got {candidates}")


def check_motion_values(m: Motion, what: str) -> None:
    for name in ("root_positions", "rotations"):
        a = np.asarray(getattr(m, name))
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{what}: non-finite values (NaN/inf) in {name}")


def encode_motion(fm: FeatureMap, motion: Motion) -> np.ndarray:
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
    check_motion_values(motion, "pose_vectors")
    y = encode_motion(fm, motion)
    return np.concatenate([y[1:], y[1:] - y[:-1]], axis=1)


def velocity_channels(fm: FeatureMap) -> tuple[int, ...]:
    """Indices (into ``y``) of the channels that are per-frame changes: the root's horizontal
    displacement and yaw change (names ``root.d…``)."""
    return tuple(i for i, name in enumerate(fm.active_names) if name.startswith("root.d"))


def time_weights(window: int, recent_weight: float) -> np.ndarray:
    """Per-pose-vector weights of a window, ``(d,)``: 1, except ``√(1 + w)`` for the newest,
    so that squared distances weigh the current pose and velocity ``1 + w`` times."""
    tw = np.ones(window)
    tw[-1] = np.sqrt(1.0 + recent_weight)
    return tw


def window_view(psi: np.ndarray, d: int) -> np.ndarray:
    """All ``(T' − d + 1, d, P)`` windows of consecutive rows (oldest first)."""
    v = np.lib.stride_tricks.sliding_window_view(psi, d, axis=0)  # (n, P, d)
    return np.ascontiguousarray(np.moveaxis(v, -1, 1))


def joint_reach(fm: FeatureMap) -> np.ndarray:
    """Reach of each joint ``(J,)``: path length (skeleton units) from the joint to its farthest
    descendant joint or end site; the root's is the whole figure's largest reach."""
    sk = fm.skeleton
    parents = np.asarray(sk.parents)
    length = np.linalg.norm(np.asarray(sk.offsets, dtype=np.float64), axis=1)
    reach = np.zeros(sk.n_joints)
    for parent, off in sk.end_sites:
        reach[parent] = max(reach[parent], float(np.linalg.norm(off)))
    for _ in range(sk.n_joints):  # relax until every parent covers its children
        changed = False
        for j in range(1, sk.n_joints):
            p = parents[j]
            if p >= 0 and reach[j] + length[j] > reach[p]:
                reach[p] = reach[j] + length[j]
                changed = True
        if not changed:
            break
    return reach


def channel_importance(fm: FeatureMap) -> np.ndarray:
    """How far a unit change of each observation channel moves the body, ``(D,)``.

    ``y_c`` is z-scored, so one unit is ``scale_c`` raw units. A joint-rotation channel (radians)
    moves the joints below by up to ``scale_c · reach_j`` (:func:`joint_reach`); the root's
    heading and tilt channels move the figure by its largest reach; root displacement, height
    and local-position channels are lengths already (``scale_c``).
    """
    sk = fm.skeleton
    reach = joint_reach(fm)
    body = max(float(reach.max()), 1e-12)
    floor = 0.02 * body  # a joint whose rotation moves nothing still counts a little
    index = {name: j for j, name in enumerate(sk.names)}
    scale = np.asarray(fm.scale, dtype=np.float64)[np.asarray(fm.active, dtype=np.int64)]
    imp = np.empty(fm.dim)
    for c, name in enumerate(fm.active_names):
        joint, _, kind = name.rpartition(".")
        if name.startswith("root.dyaw") or name.startswith("root.tilt"):
            lever = body
        elif name.startswith("root."):
            lever = 1.0
        elif kind.startswith("r"):
            lever = max(float(reach[index[joint]]), floor)
        else:  # local position channel
            lever = 1.0
        imp[c] = scale[c] * lever
    return imp
