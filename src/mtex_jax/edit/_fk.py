"""Forward kinematics of the joints an edit sees, without ``dot_general``.

:func:`mtex_jax.motion.forward_kinematics_arrays` composes rotations with batched matrix
products. Under ``vmap`` over motions that product gets three batch dimensions, and XLA (jax
0.10.2, CPU) rewrites it into a ``dot`` whose layout its own HLO verifier rejects ("Expected
instruction to have shape f64[3,2,90,3,3], actual shape is f64[90,3,2,3,3]"). Here the
``3 × 3`` products are written as broadcast multiply-adds, which XLA fuses into elementwise
loops (as fast for ``3 × 3`` blocks) and which batch under ``vmap`` without that rewrite.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..motion import Skeleton, quat_to_matrix

__all__ = ["fk_positions"]


def _mm(a: Array, b: Array) -> Array:
    """``a @ b`` for stacks of ``3 × 3`` matrices, as multiply-adds."""
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def _mv(a: Array, v: Array) -> Array:
    """``a @ v`` for stacks of ``3 × 3`` matrices and 3-vectors, as multiply-adds."""
    return jnp.sum(a * v[..., None, :], axis=-1)


def fk_positions(
    skeleton: Skeleton,
    root_positions: Float[ArrayLike, "T 3"],
    rotations: Float[ArrayLike, "T J 4"],
    local_positions: Float[ArrayLike, "T J 3"] | None = None,
) -> Float[Array, "T J 3"]:
    """World joint positions, as :func:`mtex_jax.motion.forward_kinematics_arrays` (one tree
    level at a time; dtype follows the input), safe under ``vmap``."""
    rotations = jnp.asarray(rotations)
    T, J = rotations.shape[:2]
    R = quat_to_matrix(rotations)  # (T, J, 3, 3)
    if local_positions is None:
        off = jnp.asarray(skeleton.offsets_array, rotations.dtype)
        trans = jnp.broadcast_to(off, (T, J, 3))
    else:
        trans = jnp.asarray(local_positions, rotations.dtype)
    parents = np.asarray(skeleton.parents)
    depth = np.asarray(skeleton.depth())
    world_r: list[Array] = [R[:, 0]] * J  # filled level by level (parents come first)
    world_p: list[Array] = [jnp.asarray(root_positions, rotations.dtype)] * J
    for d in range(1, int(depth.max(initial=0)) + 1):
        idx = np.nonzero(depth == d)[0]
        par = parents[idx]
        pr = jnp.stack([world_r[p] for p in par], axis=1)  # (T, k, 3, 3)
        pp = jnp.stack([world_p[p] for p in par], axis=1)
        pos = pp + _mv(pr, trans[:, idx])
        rot = _mm(pr, R[:, idx])
        for i, j in enumerate(idx):
            world_p[j], world_r[j] = pos[:, i], rot[:, i]
    return jnp.stack(world_p, axis=1)
