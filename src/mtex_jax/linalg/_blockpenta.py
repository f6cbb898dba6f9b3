"""Block Cholesky of a symmetric block-*pentadiagonal* matrix with one frame per block.

The edit solver's normal matrix couples a frame with the two before it (blocks ``A_{t,t}``,
``A_{t,t−1}``, ``A_{t,t−2}`` of size ``D × D``). :mod:`._blocktridiag` factors such a matrix
after grouping frames in pairs (block-tridiagonal with ``2D × 2D`` blocks: about ``37 D³``
flops per pair of frames); the recursion here keeps one frame per block and two sub-diagonal
factor blocks (about ``11 D³`` flops per frame, ``22 D³`` per pair):

.. code-block:: text

    L_{t,t−2} = A_{t,t−2} L_{t−2}⁻ᵀ
    L_{t,t−1} = (A_{t,t−1} − L_{t,t−2} L_{t−1,t−2}ᵀ) L_{t−1}⁻ᵀ
    L_t L_tᵀ  = A_{t,t} − L_{t,t−2} L_{t,t−2}ᵀ − L_{t,t−1} L_{t,t−1}ᵀ

with the inverses ``L_t⁻¹`` stored, so that substitution is matrix products only:
``y_t = L_t⁻¹ (r_t − L_{t,t−1} y_{t−1} − L_{t,t−2} y_{t−2})`` forwards, then
``x_t = L_t⁻ᵀ (y_t − L_{t+1,t}ᵀ x_{t+1} − L_{t+2,t}ᵀ x_{t+2})`` backwards (design §6.5).
A failed pivot (not positive definite, or not finite) is reported by a status flag, as in
:mod:`._blocktridiag`; nothing is raised, so the factorisation works under ``jit`` and
``vmap``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from ._blocktridiag import pivot_status, tri_right

__all__ = [
    "BlockPentaCholesky",
    "block_penta_cholesky",
    "block_penta_factor",
    "block_penta_solve",
]


class BlockPentaCholesky(eqx.Module):
    """Block Cholesky factor of a block-pentadiagonal SPD matrix with ``T`` blocks of ``D``.

    Attributes:
        Linv: ``(T, D, D)`` inverses ``L_t⁻¹`` of the diagonal factor blocks.
        L1: ``(T, D, D)`` ``L_{t,t−1}`` (block 0 is zero).
        L2: ``(T, D, D)`` ``L_{t,t−2}`` (blocks 0 and 1 are zero).
        ok: ``()`` every pivot block was finite and positive definite.
        first_bad: ``()`` the first failed pivot block, ``-1`` if ``ok``.
    """

    Linv: Float[Array, "T D D"]
    L1: Float[Array, "T D D"]
    L2: Float[Array, "T D D"]
    ok: Bool[Array, ""]
    first_bad: Int[Array, ""]

    def __check_init__(self) -> None:
        shape = jnp.shape(self.Linv)
        if len(shape) != 3 or shape[1] != shape[2]:
            raise ValueError(f"BlockPentaCholesky.Linv must be (T, D, D), got {shape}")
        for name in ("L1", "L2"):
            if jnp.shape(getattr(self, name)) != shape:
                raise ValueError(f"BlockPentaCholesky.{name} must have shape {shape}")


def block_penta_cholesky(
    A0: Float[Array, "T D D"],
    A1: Float[Array, "T D D"],
    A2: Float[Array, "T D D"],
    *,
    dtype=None,
) -> BlockPentaCholesky:
    """Factor the symmetric block-pentadiagonal matrix given by its lower blocks.

    Args:
        A0: ``(T, D, D)`` diagonal blocks ``A_{t,t}`` (only the lower triangle is read by the
            Cholesky kernel; pass symmetric blocks).
        A1: ``(T, D, D)`` ``A_{t,t−1}`` (block 0 ignored).
        A2: ``(T, D, D)`` ``A_{t,t−2}`` (blocks 0 and 1 ignored).
        dtype: the precision of the factorisation and of the factor (default: ``A0``'s). Each
            block is converted inside the recursion, so no converted copy of the matrix is
            made (:func:`block_penta_solve` takes a factor of lower precision than its
            right-hand side).

    Returns:
        :class:`BlockPentaCholesky`; the factor blocks from a failed pivot on are zero.
    """
    return block_penta_factor(lambda x: x, (A0, A1, A2), dtype=A0.dtype if dtype is None else dtype)


def block_penta_factor(
    blocks: Callable[[Any], tuple[Array, Array, Array]], xs: Any, *, dtype=None
) -> BlockPentaCholesky:
    """:func:`block_penta_cholesky` of a matrix whose blocks are formed frame by frame.

    ``blocks(x_t) = (A_{t,t}, A_{t,t−1}, A_{t,t−2})`` from the ``t``-th slices of the arrays
    of ``xs`` (a pytree of arrays with a leading axis ``T``), inside the recursion: a matrix
    that is a sum or a masked copy of stored bands (the edit solver's normal matrix) is then
    never stored itself. ``dtype``: the factor's precision (default: the blocks').
    """
    leaves = jax.tree.leaves(xs)
    T = leaves[0].shape[0]
    a0, _, _ = jax.eval_shape(blocks, jax.tree.map(lambda v: v[0], xs))
    D = a0.shape[-1]
    dt = jnp.dtype(a0.dtype if dtype is None else dtype)
    eye = jnp.eye(D, dtype=dt)

    def step(carry, x):
        Linv_1, Linv_2, L1_prev, alive = carry  # L_{t−1}⁻¹, L_{t−2}⁻¹, L_{t−1,t−2}
        xt, t = x
        a0, a1, a2 = (a.astype(dt) for a in blocks(xt))
        a1 = jnp.where(t >= 1, a1, 0.0)
        a2 = jnp.where(t >= 2, a2, 0.0)
        l2 = a2 @ Linv_2.T
        l1 = (a1 - l2 @ L1_prev.T) @ Linv_1.T
        L = lax.linalg.cholesky(a0 - l2 @ l2.T - l1 @ l1.T, symmetrize_input=False)
        Linv = tri_right(L, eye, transpose=True).T  # (I L⁻ᵀ)ᵀ = L⁻¹
        good, _, _ = pivot_status(jnp.diagonal(Linv)[None])
        alive = alive & good[0]
        # from a failed pivot on, the blocks are zero (and so is what they feed)
        Linv, l1, l2 = (jnp.where(alive, a, 0.0) for a in (Linv, l1, l2))
        return (Linv, Linv_1, l1, alive), (Linv, l1, l2, alive)

    zero = jnp.zeros((D, D), dt)
    init = (zero, zero, zero, jnp.asarray(True))
    _, (Linv, L1, L2, alive) = lax.scan(step, init, (xs, jnp.arange(T)))
    ok = jnp.all(alive)
    first_bad = jnp.where(ok, -1, jnp.argmin(alive)).astype(jnp.int32)
    return BlockPentaCholesky(Linv=Linv, L1=L1, L2=L2, ok=ok, first_bad=first_bad)


def block_penta_solve(factor: BlockPentaCholesky, rhs: Float[Array, "T D"]) -> Float[Array, "T D"]:
    """Solve ``A x = r`` with the factor of :func:`block_penta_cholesky` (two ``lax.scan``
    passes of matrix-vector products, ``O(T·D²)``).

    The substitution runs in ``rhs``'s precision; a factor of lower precision (e.g. float32
    for a float64 right-hand side) is converted block by block. The backward pass carries
    the products ``L_{t+1,t}ᵀ x_{t+1}`` and ``L_{t+2,t}ᵀ x_{t+2}`` from the blocks it has
    just read, so it needs no shifted copy of the factor."""
    D = rhs.shape[1]
    dt = rhs.dtype
    zero = jnp.zeros((D,), dt)

    def fwd(carry, blk):
        y1, y2 = carry
        Li, l1, l2, r = blk
        Li, l1, l2 = Li.astype(dt), l1.astype(dt), l2.astype(dt)
        y = Li @ (r - l1 @ y1 - l2 @ y2)
        return (y, y1), y

    _, y = lax.scan(fwd, (zero, zero), (factor.Linv, factor.L1, factor.L2, rhs))

    def bwd(carry, blk):
        # a = L_{t+1,t}ᵀ x_{t+1}, c1 = L_{t+1,t−1}ᵀ x_{t+1}, c2 = L_{t+2,t}ᵀ x_{t+2}
        a, c1, c2 = carry
        Li, l1, l2, yt = blk
        Li, l1, l2 = Li.astype(dt), l1.astype(dt), l2.astype(dt)
        x = Li.T @ (yt - a - c2)
        return (l1.T @ x, l2.T @ x, c1), x

    _, x = lax.scan(bwd, (zero, zero, zero), (factor.Linv, factor.L1, factor.L2, y), reverse=True)
    return x
