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

import equinox as eqx
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from ._blocktridiag import pivot_status, tri_right

__all__ = ["BlockPentaCholesky", "block_penta_cholesky", "block_penta_solve"]


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
    A0: Float[Array, "T D D"], A1: Float[Array, "T D D"], A2: Float[Array, "T D D"]
) -> BlockPentaCholesky:
    """Factor the symmetric block-pentadiagonal matrix given by its lower blocks.

    Args:
        A0: ``(T, D, D)`` diagonal blocks ``A_{t,t}`` (only the lower triangle is read by the
            Cholesky kernel; pass symmetric blocks).
        A1: ``(T, D, D)`` ``A_{t,t−1}`` (block 0 ignored).
        A2: ``(T, D, D)`` ``A_{t,t−2}`` (blocks 0 and 1 ignored).

    Returns:
        :class:`BlockPentaCholesky`; the factor blocks from a failed pivot on are zero.
    """
    T, D, _ = A0.shape
    dt = A0.dtype
    eye = jnp.eye(D, dtype=dt)
    first = jnp.arange(T)
    A1 = jnp.where((first >= 1)[:, None, None], A1, 0.0)
    A2 = jnp.where((first >= 2)[:, None, None], A2, 0.0)

    def step(carry, blocks):
        Linv_1, Linv_2, L1_prev = carry  # L_{t−1}⁻¹, L_{t−2}⁻¹, L_{t−1,t−2}
        a0, a1, a2 = blocks
        l2 = a2 @ Linv_2.T
        l1 = (a1 - l2 @ L1_prev.T) @ Linv_1.T
        L = lax.linalg.cholesky(a0 - l2 @ l2.T - l1 @ l1.T, symmetrize_input=False)
        Linv = tri_right(L, eye, transpose=True).T  # (I L⁻ᵀ)ᵀ = L⁻¹
        return (Linv, Linv_1, l1), (Linv, l1, l2)

    zero = jnp.zeros((D, D), dt)
    _, (Linv, L1, L2) = lax.scan(step, (zero, zero, zero), (A0, A1, A2))
    good, ok, first_bad = pivot_status(jnp.diagonal(Linv, axis1=-2, axis2=-1))
    keep = jnp.cumprod(good.astype(jnp.int32)).astype(bool)[:, None, None]
    return BlockPentaCholesky(
        Linv=jnp.where(keep, Linv, 0.0),
        L1=jnp.where(keep, L1, 0.0),
        L2=jnp.where(keep, L2, 0.0),
        ok=ok,
        first_bad=first_bad,
    )


def block_penta_solve(factor: BlockPentaCholesky, rhs: Float[Array, "T D"]) -> Float[Array, "T D"]:
    """Solve ``A x = r`` with the factor of :func:`block_penta_cholesky` (two ``lax.scan``
    passes of matrix-vector products, ``O(T·D²)``)."""
    T, D = rhs.shape
    dt = rhs.dtype
    zero = jnp.zeros((D,), dt)

    def fwd(carry, blk):
        y1, y2 = carry
        Li, l1, l2, r = blk
        y = Li @ (r - l1 @ y1 - l2 @ y2)
        return (y, y1), y

    _, y = lax.scan(fwd, (zero, zero), (factor.Linv, factor.L1, factor.L2, rhs))
    pad = lambda a, n: jnp.concatenate([a[n:], jnp.zeros((min(n, T), D, D), dt)], axis=0)
    L1n, L2n = pad(factor.L1, 1), pad(factor.L2, 2)  # L_{t+1,t}, L_{t+2,t}

    def bwd(carry, blk):
        x1, x2 = carry
        Li, l1n, l2n, yt = blk
        x = Li.T @ (yt - l1n.T @ x1 - l2n.T @ x2)
        return (x, x1), x

    _, x = lax.scan(bwd, (zero, zero), (factor.Linv, L1n, L2n, y), reverse=True)
    return x
