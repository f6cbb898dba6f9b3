"""Forward kinematics in JAX: world joint positions from local rotations."""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._motion import Motion
from ._rotation import quat_to_matrix
from ._skeleton import Skeleton

__all__ = ["as_motion_list", "forward_kinematics", "forward_kinematics_arrays", "joint_positions"]


def _levels(skeleton: Skeleton) -> list[np.ndarray]:
    depth = np.asarray(skeleton.depth())
    return [np.nonzero(depth == d)[0] for d in range(1, int(depth.max()) + 1)]


@eqx.filter_jit
def forward_kinematics_arrays(
    skeleton: Skeleton,
    root_positions: Float[ArrayLike, "*batch 3"],
    rotations: Float[ArrayLike, "*batch J 4"],
    local_positions: Float[ArrayLike, "*batch J 3"] | None = None,
    *,
    end_sites: bool = False,
) -> Float[Array, "*batch J_out 3"]:
    """World positions of all joints from root positions and local rotations.

    Implements ``R_j = R_parent(j) R(q_j)`` and ``p_j = p_parent(j) + R_parent(j) t_j`` with
    ``t_j`` the skeleton offset (or ``local_positions[..., j, :]``), the root at
    ``root_positions``. Joints of equal depth are processed together, so the work is one batched
    matrix product per tree level. Any leading batch axes are allowed (frames, particles, …);
    the function is differentiable and ``vmap``-able, and the dtype follows the input.

    Args:
        skeleton: the figure (static under ``jit``).
        root_positions: ``(*batch, 3)``.
        rotations: ``(*batch, J, 4)`` unit quaternions ``(w, x, y, z)``, local to the parent.
        local_positions: optional ``(*batch, J, 3)`` per-frame joint translations.
        end_sites: if true, the positions of ``skeleton.end_sites`` are appended after the
            ``J`` joints, in the order of ``skeleton.end_sites``.

    Returns:
        ``(*batch, J, 3)``, or ``(*batch, J + E, 3)`` with end sites.
    """
    rotations = jnp.asarray(rotations)
    root_positions = jnp.asarray(root_positions, dtype=rotations.dtype)
    j = skeleton.n_joints
    if rotations.shape[-2:] != (j, 4):
        raise ValueError(f"rotations must have shape (..., {j}, 4), got {rotations.shape}")
    if root_positions.shape[-1:] != (3,) or root_positions.shape[:-1] != rotations.shape[:-2]:
        raise ValueError(
            f"root_positions must have shape {(*rotations.shape[:-2], 3)}, "
            f"got {root_positions.shape}"
        )
    batch = rotations.shape[:-2]
    n = int(np.prod(batch)) if batch else 1
    local_r = quat_to_matrix(rotations.reshape(n, j, 4))  # (N, J, 3, 3)
    # the skeleton's offsets are one (J, 3) constant, never broadcast over the batch: XLA
    # would constant-fold each level's gather of the broadcast, seconds at a million particles
    off = None
    trans = None
    if local_positions is None:
        off = jnp.asarray(skeleton.offsets_array, dtype=rotations.dtype)
    else:
        trans = jnp.asarray(local_positions, dtype=rotations.dtype).reshape(n, j, 3)
    parents = np.asarray(skeleton.parents)
    world_r = jnp.zeros_like(local_r).at[:, 0].set(local_r[:, 0])
    world_p = jnp.zeros((n, j, 3), rotations.dtype).at[:, 0].set(root_positions.reshape(n, 3))
    for idx in _levels(skeleton):
        par = parents[idx]
        pr = world_r[:, par]
        if trans is None:
            assert off is not None
            step = jnp.einsum("nkij,kj->nki", pr, off[idx])
        else:
            step = jnp.einsum("nkij,nkj->nki", pr, trans[:, idx])
        world_p = world_p.at[:, idx].set(world_p[:, par] + step)
        world_r = world_r.at[:, idx].set(pr @ local_r[:, idx])
    if end_sites and skeleton.end_sites:
        ep = np.asarray(skeleton.end_site_parents)
        eo = jnp.asarray(skeleton.end_site_offsets_array, dtype=rotations.dtype)
        ends = world_p[:, ep] + jnp.einsum("nkij,kj->nki", world_r[:, ep], eo)
        world_p = jnp.concatenate([world_p, ends], axis=1)
    return world_p.reshape(*batch, world_p.shape[1], 3)


def forward_kinematics(motion: Motion, *, end_sites: bool = False) -> Float[Array, "T J_out 3"]:
    """World joint positions ``(T, J, 3)`` of a :class:`Motion` (joints in skeleton order).

    See :func:`forward_kinematics_arrays`; with ``end_sites=True`` the end sites follow the
    joints, giving ``(T, J + E, 3)``.
    """
    if not isinstance(motion, Motion):
        raise TypeError(f"forward_kinematics expects a Motion, got {type(motion).__name__}")
    return forward_kinematics_arrays(
        motion.skeleton,
        motion.root_positions,
        motion.rotations,
        motion.local_positions,
        end_sites=end_sites,
    )


# ---------------------------------------------------------------------------------------------
# world joint positions of clips at one frame rate (every motion metric, design §10.4)
# ---------------------------------------------------------------------------------------------
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
