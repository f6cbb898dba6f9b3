"""The raw channels of the observation vector (design §1): root velocity in the heading frame,
root height, joint rotations as unwrapped exponential maps, and their inverse, the decoding
with the root integrated from a start position and heading."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._rotation import (
    expmap_to_quat,
    quat_conj,
    quat_mul,
    quat_rotate,
    quat_to_expmap,
    quat_twist,
    wrap_angle,
    yaw_quat,
)
from ._skeleton import ground_axes

__all__ = ["decode_raw", "raw_features", "unit_axis", "unwrap_expmaps"]


def unit_axis(up: int) -> np.ndarray:
    e = np.zeros(3)
    e[up] = 1.0
    return e


def unwrap_expmaps(v: Float[ArrayLike, "T *n 3"]) -> Float[Array, "T *n 3"]:
    """Make a sequence of exponential maps continuous in time (``lax.scan`` over frames).

    For each frame, of the equivalent vectors ``(θ + 2πn) v/θ`` (``n`` integer) the one nearest
    the previous output is chosen: ``n = round((û·v_prev − θ) / 2π)``. At the identity
    (``θ < 1e-9``) the previous frame's axis is used.
    """
    v = jnp.asarray(v)

    def step(prev, cur):
        th = jnp.linalg.norm(cur, axis=-1, keepdims=True)
        pn = jnp.linalg.norm(prev, axis=-1, keepdims=True)
        ok = th > 1e-9
        # at the identity the axis is free: take the previous one (identity = 2πn about it)
        u_prev = jnp.where(pn > 1e-9, prev / jnp.where(pn > 1e-9, pn, 1.0), 0.0)
        u = jnp.where(ok, cur / jnp.where(ok, th, 1.0), u_prev)
        th = jnp.where(ok, th, 0.0)
        n = jnp.round((jnp.sum(u * prev, axis=-1, keepdims=True) - th) / (2 * jnp.pi))
        out = (th + 2 * jnp.pi * n) * u
        return out, out

    _, out = jax.lax.scan(step, v[0], v)
    return out


def raw_features(
    root_positions: Float[ArrayLike, "T 3"],
    rotations: Float[ArrayLike, "T J 4"],
    local_positions: Float[ArrayLike, "T J 3"] | None = None,
    *,
    up_axis: int = 1,
) -> Float[Array, "T R"]:
    """All raw observation channels of one clip (see the module docstring), ``(T, R)``."""
    rotations = jnp.asarray(rotations)
    p = jnp.asarray(root_positions, dtype=rotations.dtype)
    t = rotations.shape[0]
    u, h0, h1 = ground_axes(up_axis)
    up = jnp.asarray(unit_axis(up_axis), dtype=rotations.dtype)
    q_root = rotations[:, 0]
    psi = quat_twist(q_root, up)
    q_yaw = yaw_quat(psi, up)
    tilt = quat_mul(quat_conj(q_yaw), q_root)
    if t > 1:
        dp = p[1:] - p[:-1]
        local = quat_rotate(quat_conj(q_yaw[:-1]), dp)
        dh = jnp.stack([local[:, h0], local[:, h1]], axis=-1)
        dh = jnp.concatenate([dh[:1], dh], axis=0)
        dyaw = wrap_angle(psi[1:] - psi[:-1])
        dyaw = jnp.concatenate([dyaw[:1], dyaw], axis=0)
    else:
        dh = jnp.zeros((1, 2), rotations.dtype)
        dyaw = jnp.zeros((1,), rotations.dtype)
    rots = jnp.concatenate([tilt[:, None], rotations[:, 1:]], axis=1)  # (T, J, 4)
    em = unwrap_expmaps(quat_to_expmap(rots))
    parts = [dh, p[:, u : u + 1], dyaw[:, None], em.reshape(t, -1)]
    if local_positions is not None:
        lp = jnp.asarray(local_positions, dtype=rotations.dtype)
        parts.append(lp[:, 1:].reshape(t, -1))
    return jnp.concatenate(parts, axis=1)


def decode_raw(
    raw: Float[Array, "T R"],
    n_joints: int,
    has_lp: bool,
    up_axis: int,
    start_position: Float[Array, 3],
    start_heading: Float[Array, ""],
) -> tuple[Array, Array, Array | None, Array]:
    t = raw.shape[0]
    u, h0, h1 = ground_axes(up_axis)
    up = jnp.asarray(unit_axis(up_axis), dtype=raw.dtype)
    dh = raw[:, 0:2]
    height = raw[:, 2]
    dyaw = raw[:, 3]
    em = raw[:, 4 : 4 + 3 * n_joints].reshape(t, n_joints, 3)
    psi = start_heading + jnp.concatenate([jnp.zeros((1,), raw.dtype), jnp.cumsum(dyaw[1:])])
    q_yaw = yaw_quat(psi, up)
    q = expmap_to_quat(em)
    q_root = quat_mul(q_yaw, q[:, 0])
    rotations = q.at[:, 0].set(q_root)
    local = jnp.zeros((t, 3), raw.dtype).at[:, h0].set(dh[:, 0]).at[:, h1].set(dh[:, 1])
    world = quat_rotate(q_yaw[:-1], local[1:])  # displacement of frame s uses heading s−1
    horiz = jnp.concatenate([jnp.zeros((1, 3), raw.dtype), jnp.cumsum(world, axis=0)], axis=0)
    pos = horiz + start_position.at[u].set(0.0)
    pos = pos.at[:, u].set(height)
    lp = None
    if has_lp:
        lp_raw = raw[:, 4 + 3 * n_joints :].reshape(t, n_joints - 1, 3)
        lp = jnp.concatenate([jnp.zeros((t, 1, 3), raw.dtype), lp_raw], axis=1)
        lp = lp.at[:, 0].set(pos)
    return pos, rotations, lp, psi
