"""World joint positions of clips at one frame rate, and their finite-difference derivatives.

Every motion metric (design §10.4) starts here: the clips are checked (same skeleton, finite,
long enough), resampled to one common rate ``f`` and turned into world joint positions
``p_t ∈ R^{J×3}`` in metres by forward kinematics (:func:`mtex_jax.motion.as_motion_list` and
:func:`mtex_jax.motion.joint_positions`, re-exported here). The derivatives are forward
differences,

    v_t = (p_{t+1} − p_t) f,    a_t = (v_{t+1} − v_t) f,    j_t = (a_{t+1} − a_t) f,

so a clip of ``T`` frames has ``T − 1`` velocities, ``T − 2`` accelerations and ``T − 3`` jerks.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..motion import Motion, Skeleton, as_motion_list, joint_positions

__all__ = [
    "as_motion_list",
    "derivatives",
    "joint_positions",
    "joint_speeds",
    "moving_joints",
]


def _check_fps(fps: float, where: str) -> float:
    if not (isinstance(fps, int | float) and np.isfinite(fps) and fps > 0):
        raise ValueError(f"{where}: fps must be a positive finite number, got {fps!r}")
    return float(fps)


def derivatives(positions: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Velocity, acceleration and jerk of positions by forward differences.

    ``v_t = (p_{t+1} − p_t) f``, ``a_t = (v_{t+1} − v_t) f``, ``j_t = (a_{t+1} − a_t) f``.

    Args:
        positions: ``(T, ..., 3)`` positions in metres, ``T ≥ 4``.
        fps: frame rate ``f`` of the positions.

    Returns:
        ``v`` ``(T−1, ..., 3)`` in m/s, ``a`` ``(T−2, ..., 3)`` in m/s², ``j`` ``(T−3, ..., 3)``
        in m/s³.
    """
    f = _check_fps(fps, "derivatives")
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim < 2 or p.shape[0] < 4:
        raise ValueError(
            f"derivatives: need positions of shape (T, ..., 3) with T >= 4, got {p.shape}"
        )
    v = np.diff(p, axis=0) * f
    a = np.diff(v, axis=0) * f
    j = np.diff(a, axis=0) * f
    return v, a, j


def joint_speeds(positions: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Magnitudes ``|v_t|``, ``|a_t|``, ``|j_t|`` per frame and joint.

    Args:
        positions: ``(T, J, 3)`` world positions, ``T ≥ 4``.
        fps: their frame rate.

    Returns:
        ``(T−1, J)`` speed (m/s), ``(T−2, J)`` acceleration (m/s²), ``(T−3, J)`` jerk (m/s³).
    """
    v, a, j = derivatives(positions, fps)
    return (
        np.linalg.norm(v, axis=-1),
        np.linalg.norm(a, axis=-1),
        np.linalg.norm(j, axis=-1),
    )


def moving_joints(motions: Motion | Sequence[Motion], *, tol: float = 1e-6) -> np.ndarray:
    """Joints that carry motion of their own: all but the rigid appendages.

    A joint is *static* when its own local rotation (and local translation, if the clips have
    per-frame ones) is constant over every frame of ``motions`` and the same holds for all its
    descendants: it and everything below it are then rigidly attached to its parent (the
    uncaptured fingers and eyes of the CMU data). Such joints only repeat their parent's motion,
    so the metrics leave them out. Joints with a constant rotation but moving descendants (a
    collar bone) are kept. Decide the set on the *reference* clips and use the same set for every
    set compared with them.

    Args:
        motions: the clips the set is decided on.
        tol: largest peak-to-peak change of a quaternion or translation component that still
            counts as constant (the default ignores the rounding of angles written with six
            decimals of a degree, which moves the CMU fingers by about 10⁻⁸).

    Returns:
        ``(K,)`` int indices of the moving joints, increasing.
    """
    ms = as_motion_list(motions, "moving_joints")
    sk: Skeleton = ms[0].skeleton
    j = sk.n_joints
    own = np.zeros(j, dtype=bool)
    for m in ms:
        q = np.asarray(m.rotations, dtype=np.float64)
        # q and −q are one rotation: fix the sign of each frame by its first quaternion
        sign = np.where(np.sum(q * q[:1], axis=-1, keepdims=True) < 0, -1.0, 1.0)
        own |= np.ptp(q * sign, axis=0).max(axis=-1) > tol
        if m.local_positions is not None:
            own |= np.ptp(np.asarray(m.local_positions), axis=0).max(axis=-1) > tol
    own[0] = True  # the root carries the trajectory
    moving = own.copy()
    for i in range(j - 1, 0, -1):  # children follow parents: propagate up the tree
        if moving[i]:
            moving[sk.parents[i]] = True
    return np.nonzero(moving)[0]
