"""World joint positions of clips at one frame rate, and their finite-difference derivatives.

Every motion metric (design §10.4) starts here: the clips are checked (same skeleton, finite,
long enough), resampled to one common rate ``f`` and turned into world joint positions
``p_t ∈ R^{J×3}`` in metres by forward kinematics. The derivatives are forward differences,

    v_t = (p_{t+1} − p_t) f,    a_t = (v_{t+1} − v_t) f,    j_t = (a_{t+1} − a_t) f,

so a clip of ``T`` frames has ``T − 1`` velocities, ``T − 2`` accelerations and ``T − 3`` jerks.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..motion import Motion, Skeleton, forward_kinematics_arrays

__all__ = [
    "as_motion_list",
    "derivatives",
    "joint_positions",
    "joint_speeds",
    "moving_joints",
]

_BLOCK = 2048  # frames per forward-kinematics call: one compiled shape for every clip length


def as_motion_list(
    motions: Motion | Sequence[Motion], where: str, *, min_frames: int = 1
) -> list[Motion]:
    """Check a motion or a list of motions and return it as a list.

    Args:
        motions: one :class:`~mtex_jax.motion.Motion` or a non-empty sequence of them.
        where: name of the calling function, used in error messages.
        min_frames: fewest frames each clip must have at its own rate (callers that resample
            check the length again at the common rate).

    Returns:
        The motions as a list.

    Raises:
        ValueError: on an empty list, a non-``Motion`` item, clips whose skeletons differ in
            structure, a clip with fewer than ``min_frames`` frames, or a clip with NaN or
            infinite root positions or rotations.
    """
    ms = [motions] if isinstance(motions, Motion) else list(motions)
    if not ms:
        raise ValueError(f"{where}: empty list of motions")
    for i, m in enumerate(ms):
        if not isinstance(m, Motion):
            raise ValueError(f"{where}: item {i} is a {type(m).__name__}, not a Motion")
    first = ms[0].skeleton
    for i, m in enumerate(ms):
        if not m.skeleton.same_structure(first):
            raise ValueError(
                f"{where}: motion {i} has a different skeleton from motion 0 "
                f"({m.n_joints} vs {first.n_joints} joints, or other names/parents)"
            )
        if m.n_frames < min_frames:
            raise ValueError(
                f"{where}: motion {i} is too short: {m.n_frames} frames, need at least {min_frames}"
            )
        arrays = [m.root_positions, m.rotations]
        if m.local_positions is not None:
            arrays.append(m.local_positions)
        if not all(np.all(np.isfinite(np.asarray(a))) for a in arrays):
            raise ValueError(f"{where}: motion {i} has NaN or infinite values")
    return ms


def _check_fps(fps: float, where: str) -> float:
    if not (isinstance(fps, int | float) and np.isfinite(fps) and fps > 0):
        raise ValueError(f"{where}: fps must be a positive finite number, got {fps!r}")
    return float(fps)


def _positions_one(m: Motion) -> np.ndarray:
    """``(T, J, 3)`` float64 world positions of one clip.

    Forward kinematics runs with the root at the origin, in blocks of a fixed number of frames
    (one compilation for all clip lengths); the root trajectory is added afterwards in float64,
    so positions far from the origin keep their precision even when JAX computes in float32
    (jerk multiplies position rounding by about ``8 f³``).
    """
    sk = m.skeleton
    t = m.n_frames
    q = np.asarray(m.rotations, dtype=np.float64)
    lp = None if m.local_positions is None else np.asarray(m.local_positions, dtype=np.float64)
    out = np.empty((t, sk.n_joints, 3), dtype=np.float64)
    zeros = np.zeros((_BLOCK, 3))
    for s in range(0, t, _BLOCK):
        e = min(s + _BLOCK, t)
        qb = np.empty((_BLOCK, sk.n_joints, 4))
        qb[: e - s] = q[s:e]
        qb[e - s :] = (1.0, 0.0, 0.0, 0.0)
        lb = None
        if lp is not None:
            lb = np.zeros((_BLOCK, sk.n_joints, 3))
            lb[: e - s] = lp[s:e]
        pb = forward_kinematics_arrays(sk, zeros, qb, lb)
        out[s:e] = np.asarray(pb, dtype=np.float64)[: e - s]
    out += np.asarray(m.root_positions, dtype=np.float64)[:, None, :]
    return out


def joint_positions(
    motions: Motion | Sequence[Motion],
    fps: float | None = None,
    *,
    min_frames: int = 1,
    where: str = "joint_positions",
) -> list[np.ndarray]:
    """World joint positions of clips at one common frame rate.

    Each clip is resampled to ``fps`` (:meth:`Motion.resample`: linear root, slerp rotations)
    when its own rate differs, then ``p_t = FK(root_t, q_t)``.

    Args:
        motions: a motion or a non-empty list of motions of one skeleton structure.
        fps: the common frame rate; ``None`` uses the first clip's rate.
        min_frames: fewest frames a clip must have at ``fps`` (e.g. 4 for jerk).
        where: name used in error messages.

    Returns:
        One float64 array ``(T_i, J, 3)`` per clip, in metres (the file's unit).

    Raises:
        ValueError: see :func:`as_motion_list`; also a bad ``fps`` or a clip that is too short
            at ``fps``.
    """
    ms = as_motion_list(motions, where)
    f = ms[0].fps if fps is None else _check_fps(fps, where)
    out = []
    for i, m in enumerate(ms):
        r = m if m.fps == f else m.resample(f)
        if r.n_frames < min_frames:
            raise ValueError(
                f"{where}: motion {i} is too short: {r.n_frames} frames at {f:g} fps, "
                f"need at least {min_frames}"
            )
        out.append(_positions_one(r))
    return out


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
