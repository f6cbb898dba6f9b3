"""Random draws of synthesis: standard normals by the Box–Muller transform and the
standardised innovations of textons (Gaussian or Student-t)."""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array


def sincos_turn(u: Array) -> tuple[Array, Array]:
    """``(cos 2πu, sin 2πu)`` for ``u ∈ [0, 1)``: quadrant from ``⌊4u⌋``, then Taylor
    polynomials of degree 24/25 on ``[0, π/2)`` (truncation below 1e-18; measured error
    ≤ 8e-16 in float64 against numpy). On CPU about 8× cheaper than ``jnp.cos`` and
    ``jnp.sin`` in float64, whose general range reduction is the cost of Box–Muller.
    """
    q4 = 4 * u
    q = jnp.floor(q4)
    phi = (q4 - q) * (np.pi / 2)
    x2 = phi * phi
    sp = jnp.zeros_like(phi)
    cp = jnp.zeros_like(phi)
    for j in range(12, -1, -1):  # Horner in φ²: Σ (−1)^j φ^{2j+1}/(2j+1)!, Σ (−1)^j φ^{2j}/(2j)!
        sp = sp * x2 + (-1) ** j / math.factorial(2 * j + 1)
        cp = cp * x2 + (-1) ** j / math.factorial(2 * j)
    sp = phi * sp
    quad = q.astype(jnp.int32) & 3  # rotate by quad · 90°
    cos = jnp.where(quad == 0, cp, jnp.where(quad == 1, -sp, jnp.where(quad == 2, -cp, sp)))
    sin = jnp.where(quad == 0, sp, jnp.where(quad == 1, cp, jnp.where(quad == 2, -sp, -cp)))
    return cos, sin


def standard_normal(key: Array, shape: tuple[int, ...], dtype: Any) -> Array:
    """Standard normal variates from ``key`` by the Box–Muller transform.

    ``z = √(−2 log(1 − u₁)) (cos 2πu₂, sin 2πu₂)`` for ``u = jax.random.uniform(key, (2, h))``
    (``h = ⌈size/2⌉``; the cosines first, then the sines, truncated to ``size``;
    :func:`sincos_turn`). Exactly ``N(0, 1)`` up to the resolution of the uniforms; on CPU
    about a third of the cost of ``jax.random.normal`` in float64, whose inverse error
    function dominated the time of a synthesis.
    """
    size = int(np.prod(shape))
    u = jax.random.uniform(key, (2, (size + 1) // 2), dtype)
    r = jnp.sqrt(-2.0 * jnp.log1p(-u[0]))  # 1 − u ∈ (0, 1]
    cos, sin = sincos_turn(u[1])
    return jnp.concatenate([r * cos, r * sin])[:size].reshape(shape)


def independent_innovations(
    key: Array, shape: tuple[int, ...], dtype: Any, dof: float | None
) -> Array:
    """Standardised innovations ``v (…, k)`` of textons with ``Texton.dof``: ``N(0, I)``
    (:func:`standard_normal`) for Gaussian textons; for Student-t ones the scale mixture
    ``v = z / √g``, ``z ~ N(0, I_k)``, ``g ~ Gamma(ν/2, rate ν/2)`` per row, so that
    ``B v ~ t_ν(0, B Bᵀ)``."""
    if dof is None:
        return standard_normal(key, shape, dtype)
    k_z, k_g = jax.random.split(key)
    z = standard_normal(k_z, shape, dtype)
    g = jax.random.gamma(k_g, dof / 2, shape[:-1], dtype) / (dof / 2)
    return z / jnp.sqrt(g)[..., None]
