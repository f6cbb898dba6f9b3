"""Rotation algebra: unit quaternions (w-first), rotation matrices, exponential maps.

All functions are pure JAX, broadcast over leading axes, keep the input dtype and are
differentiable everywhere (small-angle branches use the "double where" trick so that gradients
at the identity are finite and exact).

Conventions:
    * A quaternion is ``(w, x, y, z)`` with ``w`` first; it rotates column vectors,
      ``v' = q v q*``.
    * ``quat_mul(a, b)`` is the rotation "first ``b``, then ``a``" (like ``R_a @ R_b``).
    * An exponential map (rotation vector) ``v`` has angle ``|v|`` about axis ``v / |v|``.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = [
    "expmap_to_quat",
    "quat_conj",
    "quat_from_axis_angle",
    "quat_mul",
    "quat_normalize",
    "quat_rotate",
    "quat_to_expmap",
    "quat_to_matrix",
    "quat_twist",
    "yaw_quat",
]

_SMALL = 1e-6


def quat_mul(a: Float[ArrayLike, "... 4"], b: Float[ArrayLike, "... 4"]) -> Float[Array, "... 4"]:
    """Hamilton product ``a ⊗ b`` (apply ``b`` first, then ``a``)."""
    a = jnp.asarray(a)
    b = jnp.asarray(b)
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conj(q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 4"]:
    """Conjugate (the inverse rotation for a unit quaternion)."""
    q = jnp.asarray(q)
    return q * jnp.asarray([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def quat_normalize(q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 4"]:
    """Scale to unit norm (the zero quaternion maps to the identity)."""
    q = jnp.asarray(q)
    n = jnp.linalg.norm(q, axis=-1, keepdims=True)
    ident = jnp.zeros_like(q).at[..., 0].set(1.0)
    safe_n = jnp.where(n > 0, n, 1.0)
    return jnp.where(n > 0, q / safe_n, ident)


def quat_to_matrix(q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 3 3"]:
    """Rotation matrix of a unit quaternion, ``R[..., i, j]`` so that ``v' = R @ v``."""
    q = jnp.asarray(q)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [
        jnp.stack([1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)], axis=-1),
        jnp.stack([2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)], axis=-1),
        jnp.stack([2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)], axis=-1),
    ]
    return jnp.stack(rows, axis=-2)


def quat_rotate(
    q: Float[ArrayLike, "... 4"], v: Float[ArrayLike, "... 3"]
) -> Float[Array, "... 3"]:
    """Rotate vectors ``v`` by unit quaternions ``q`` (``q v q*``)."""
    q = jnp.asarray(q)
    v = jnp.asarray(v)
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * jnp.cross(u, v)
    return v + w * t + jnp.cross(u, t)


def quat_from_axis_angle(
    axis: Float[ArrayLike, "... 3"], angle: Float[ArrayLike, ...]
) -> Float[Array, "... 4"]:
    """Quaternion of a rotation by ``angle`` (radians) about the unit vector ``axis``."""
    axis = jnp.asarray(axis)
    half = 0.5 * jnp.asarray(angle)[..., None]
    return jnp.concatenate([jnp.cos(half), jnp.sin(half) * axis], axis=-1)


def expmap_to_quat(v: Float[ArrayLike, "... 3"]) -> Float[Array, "... 4"]:
    """Exponential map (rotation vector) to unit quaternion.

    ``q = (cos(θ/2), sin(θ/2) v/θ)`` with ``θ = |v|``; for ``θ < 1e-6`` the Taylor series
    ``sin(θ/2)/θ ≈ 1/2 − θ²/48`` is used, so values and gradients at ``v = 0`` are exact.
    """
    v = jnp.asarray(v)
    th2 = jnp.sum(v * v, axis=-1, keepdims=True)
    small = th2 < _SMALL**2
    th2_safe = jnp.where(small, 1.0, th2)
    th = jnp.sqrt(th2_safe)
    scale = jnp.where(small, 0.5 - th2 / 48.0, jnp.sin(0.5 * th) / th)
    w = jnp.where(small, 1.0 - th2 / 8.0, jnp.cos(0.5 * th))
    return jnp.concatenate([w, scale * v], axis=-1)


def quat_to_expmap(q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 3"]:
    """Unit quaternion to exponential map with angle in ``[0, π]``.

    The quaternion is first moved to the ``w ≥ 0`` hemisphere, then
    ``v = 2 atan2(|u|, w) u/|u|`` with ``u = (x, y, z)``; for ``|u| < 1e-6`` the series
    ``v ≈ (2/w)(1 − |u|²/(3w²)) u`` is used.
    """
    q = jnp.asarray(q)
    q = jnp.where(q[..., :1] < 0, -q, q)
    w = q[..., :1]
    u = q[..., 1:]
    s2 = jnp.sum(u * u, axis=-1, keepdims=True)
    small = s2 < _SMALL**2
    s = jnp.sqrt(jnp.where(small, 1.0, s2))
    w_safe = jnp.where(small, jnp.maximum(w, 0.5), w)
    scale = jnp.where(
        small,
        (2.0 / w_safe) * (1.0 - s2 / (3.0 * w_safe * w_safe)),
        2.0 * jnp.arctan2(s, w) / s,
    )
    return scale * u


def quat_twist(q: Float[ArrayLike, "... 4"], axis: Float[ArrayLike, 3]) -> Float[Array, ...]:
    """Angle of the twist of ``q`` about the unit ``axis`` (swing–twist decomposition).

    With ``q = twist(ψ) ⊗ swing`` (or ``swing ⊗ twist``; the twist angle is the same), returns
    ``ψ = 2 atan2(u·axis, w)`` wrapped to ``(−π, π]``. Undefined only for a swing of exactly π.
    """
    q = jnp.asarray(q)
    axis = jnp.asarray(axis, dtype=q.dtype)
    proj = jnp.sum(q[..., 1:] * axis, axis=-1)
    ang = 2.0 * jnp.arctan2(proj, q[..., 0])
    return wrap_angle(ang)


def yaw_quat(angle: Float[ArrayLike, ...], axis: Float[ArrayLike, 3]) -> Float[Array, "... 4"]:
    """Quaternion of a rotation by ``angle`` about a fixed unit ``axis`` (broadcast)."""
    angle = jnp.asarray(angle)
    axis = jnp.asarray(
        axis, dtype=angle.dtype if jnp.issubdtype(angle.dtype, jnp.floating) else None
    )
    return quat_from_axis_angle(jnp.broadcast_to(axis, (*angle.shape, 3)), angle)


def wrap_angle(a: Float[ArrayLike, ...]) -> Float[Array, ...]:
    """Wrap angles to ``(−π, π]``."""
    a = jnp.asarray(a)
    return a - 2.0 * jnp.pi * jnp.ceil((a - jnp.pi) / (2.0 * jnp.pi))
