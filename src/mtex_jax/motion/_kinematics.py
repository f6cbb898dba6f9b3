"""Forward kinematics in JAX: world joint positions from local rotations."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._motion import Motion
from ._rotation import quat_to_matrix
from ._skeleton import Skeleton

__all__ = ["forward_kinematics", "forward_kinematics_arrays"]


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
    if local_positions is None:
        off = jnp.asarray(skeleton.offsets_array, dtype=rotations.dtype)
        trans = jnp.broadcast_to(off, (n, j, 3))
    else:
        trans = jnp.asarray(local_positions, dtype=rotations.dtype).reshape(n, j, 3)
    parents = np.asarray(skeleton.parents)
    world_r = jnp.zeros_like(local_r).at[:, 0].set(local_r[:, 0])
    world_p = jnp.zeros((n, j, 3), rotations.dtype).at[:, 0].set(root_positions.reshape(n, 3))
    for idx in _levels(skeleton):
        par = parents[idx]
        pr = world_r[:, par]
        world_p = world_p.at[:, idx].set(
            world_p[:, par] + jnp.einsum("nkij,nkj->nki", pr, trans[:, idx])
        )
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
