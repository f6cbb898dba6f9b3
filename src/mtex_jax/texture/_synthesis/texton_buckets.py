"""Shape buckets of per-texton synthesis (design §11): the bucket of a length, the noise of a
segment drawn for its bucket with the values of a draw for the segment, and the end pair held
at its rows of the bucket.

:func:`~mtex_jax.texture.synthesize_texton` runs one program per bucket of lengths: ``l``
frames are computed in :func:`texton_bucket` ``(l)`` rows, the real length ``n_valid`` is an
array of the program, and the rows past it are cut on the host.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ...core import bucket_length
from .._noise.draws import sincos_turn
from .._texton.texton import Texton

#: Lengths up to this many frames are bucketed in multiples of :data:`SHORT_STEP` (a
#: texton's own segments: a few programs, and no call pays for a long bucket); longer ones
#: in multiples of :data:`~mtex_jax.core.BUCKET_FRAMES` (three programs over 200–3,000).
SHORT_MAX = 192
SHORT_STEP = 64


def texton_bucket(length: int) -> int:
    """Rows of the shape bucket of a synthesis of ``length`` frames: ``length`` rounded up to
    a multiple of 64 up to 192 frames, else of :data:`~mtex_jax.core.BUCKET_FRAMES`."""
    if length <= SHORT_MAX:
        return bucket_length(length, SHORT_STEP)
    return bucket_length(length)


def prefix_normal(key: Array, size: Array, rows: int, k: int, dtype) -> Float[Array, "rows k"]:
    """:func:`~mtex_jax.texture._noise.draws.standard_normal` ``(key, (size // k, k))`` for a
    traced ``size``, in ``(rows, k)`` (zeros after ``size`` entries).

    The draw for ``size`` entries is Box–Muller on ``u = uniform(key, (2h,))``,
    ``h = ⌈size/2⌉``: entry ``i < h`` is ``r(u_i) cos(2π u_{h+i})``, entry ``i ≥ h`` is
    ``r(u_{i−h}) sin(2π u_i)``. Uniform draws of the default ``threefry`` keys are
    prefix-stable (the first ``2h`` of a longer draw are the same numbers), so the entries
    are read from one draw for the bucket with the segment's offset ``h``: the same values,
    by the same elementwise operations.
    """
    S = rows * k
    u = jax.random.uniform(key, (2 * ((S + 1) // 2),), dtype)
    h = (size + 1) // 2
    i = jnp.arange(S)
    lo = i < h
    r = jnp.sqrt(-2.0 * jnp.log1p(-u[jnp.where(lo, i, i - h)]))  # 1 − u ∈ (0, 1]
    cos, sin = sincos_turn(u[jnp.where(lo, i + h, i)])
    z = jnp.where(lo, r * cos, r * sin)
    return jnp.where(i < size, z, 0.0).reshape(rows, k)


def bucket_noise(tex: Texton, key: Array | None, n_valid: Array, rows: int) -> Array:
    """The noise ``v_j`` of a segment of ``n_valid`` frames in ``(rows − 2, k)``: rows up to
    ``n_valid − 2`` equal to :func:`~mtex_jax.texture._synthesis.texton_synthesis.draw_noise`
    ``(tex, key, n_valid)`` without a process (a Student-t texton's gamma scales are
    prefix-stable too), zeros after; zeros without a key."""
    k = tex.C.shape[-1]
    dt = tex.mu.dtype
    if key is None:
        return jnp.zeros((rows - 2, k), dt)
    size = (n_valid - 2) * k
    if tex.dof is None:
        return prefix_normal(key, size, rows - 2, k, dt)
    k_z, k_g = jax.random.split(key)
    z = prefix_normal(k_z, size, rows - 2, k, dt)
    g = jax.random.gamma(k_g, tex.dof / 2, (rows - 2,), dt) / (tex.dof / 2)
    return z / jnp.sqrt(g)[..., None]


def held_end(
    rows: int, n_valid: Array, end: Array, fixed: tuple[Array, Array] | None
) -> tuple[Array, Array]:
    """The held mask and poses ``(rows,)``, ``(rows, D)`` of a segment of ``n_valid`` frames
    in a bucket: the end pair at rows ``n_valid − 2, n_valid − 1``, the rows after it held at
    the last pose (their equations involve held frames only), and the edits ``fixed`` (padded
    with free rows) before it; the end pair overrides an edit of its rows, as without a
    bucket."""
    t = jnp.arange(rows)
    held = t >= n_valid - 2
    poses = jnp.where((t == n_valid - 2)[:, None], end[0], end[1])
    if fixed is not None:
        poses = jnp.where(held[:, None], poses, fixed[1])
        held = held | fixed[0]
    return held, poses
