"""Block-banded symmetric positive definite solver in JAX (design §5, MT §5.4).

JAX has no banded solver. The normal matrix of constrained texton synthesis is symmetric
positive definite and *block pentadiagonal* in frames (block bandwidth 2: blocks ``(i, i)``,
``(i+1, i)``, ``(i+2, i)`` of size ``k × k``). Grouping frames in pairs ``(2I, 2I+1)`` makes it
block *tridiagonal* with ``b × b`` blocks, ``b = 2k``,

.. code-block:: text

    Â_II     = [[A_{2I,2I},   A_{2I+1,2I}ᵀ], [A_{2I+1,2I},   A_{2I+1,2I+1}]]
    Â_{I+1,I} = [[A_{2I+2,2I}, A_{2I+2,2I+1}], [0,             A_{2I+3,2I+1}]]

which is factorised by the block Cholesky recursion over the ``n`` pair blocks (cost
``O(n·b³)``)

.. code-block:: text

    P_0 = Â_00,   L_I L_Iᵀ = P_I,   M_I = Â_{I+1,I} L_I⁻ᵀ,   P_{I+1} = Â_{I+1,I+1} − M_I M_Iᵀ

and solved by block forward and backward substitution (``O(n·b²·m)`` for ``m`` right-hand sides)

.. code-block:: text

    z_I = L_I⁻¹ (r_I − M_{I−1} z_{I−1}),        x_I = L_I⁻ᵀ (z_I − M_Iᵀ x_{I+1}).

Performance design (CPU; design §5.4–§5.5). The recursion is
sequential and its ``30 × 30`` kernels are small, so a step costs a few microseconds of which
most is the per-call cost of small LAPACK kernels (Cholesky, triangular solve) and of the small
matrix products; what matters is the number of kernel calls per step:

* *Not batched* (one synthesis, few right-hand sides, ``solve_rows_fused``): the forward
  substitution rides along the factorisation. With ``X_I = [M_I; z_Iᵀ]`` one product gives the
  next pivot and the next forward right-hand side together, one Cholesky factors the pivot and
  one triangular solve gives ``X_I = [Â_{I+1,I}; y_Iᵀ] L_I⁻ᵀ``; the backward pass is one
  product and one triangular solve per step. The loops write into one per-block buffer in
  place, so no stacked outputs are allocated and zero-filled.
* *Many right-hand sides with one matrix* (``vmap`` over the noise of a synthesis, or many
  columns, ``solve_rows_plain``): the factorisation is computed once and stores ``L_I⁻¹``
  (:func:`block_tridiag_cholesky`); the substitution is matrix products only, with the
  right-hand sides as the rows of one GEMM per step, updated in place.
  ``tridiag_solve_rows`` takes this path through :func:`jax.custom_batching.custom_vmap` when
  only the right-hand side is batched: the batch is folded into the GEMM rows, the
  factorisation is not repeated per batch element and no LAPACK kernel sees a batch.
  Derivatives come from a :func:`jax.custom_jvp` rule, ``dx = A⁻¹(dr − dA x)``, whose tangent
  solve uses the plain path (autodiff-transparent, hence transposable for reverse mode).
* When the *matrix* is batched by the caller's ``vmap`` (different matrices), each element is
  factorised with the plain path under ``vmap`` (LAPACK then sees a batch, as it would for any
  vmapped factorisation).
* Triangular solves are split so that no LAPACK call gets 1024 or more right-hand-side entries:
  the OpenBLAS behind jaxlib's CPU LAPACK multithreads ``trsm`` from that size, which on a
  shared 2-core machine made a ``30 × 35`` solve 3–30× slower than a ``30 × 34`` one.

Only the lower blocks are read, and diagonal blocks are symmetrised, ``(A + Aᵀ)/2``: the
matrix is assumed symmetric. A failed pivot (not positive definite, or non-finite) makes the
recursion non-finite from there on; it is detected from the pivots after the loop and reported
by a status flag (the returned solution is then finite but meaningless).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float, Int


def sym(M: Array) -> Array:
    """The symmetric part ``(M + Mᵀ)/2`` of a (batch of) square matrices."""
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


# Largest number of right-hand-side entries per LAPACK triangular solve (see module notes).
_TRSM_MAX_ENTRIES = 1000


class BlockTridiagCholesky(eqx.Module):
    """Block Cholesky factor of a block-tridiagonal SPD matrix with ``n`` blocks of size ``b``.

    The factor is ``L`` with diagonal blocks ``L_I`` and sub-diagonal blocks ``M_I``; the
    inverses ``L_I⁻¹`` are stored so that substitution is matrix products only.

    Attributes:
        Linv: ``(n, b, b)`` inverses ``L_I⁻¹`` of the lower-triangular diagonal factor blocks.
        M: ``(n−1, b, b)`` sub-diagonal factor blocks ``M_I = A_{I+1,I} L_I⁻ᵀ``.
        ok: ``()`` bool, every pivot block was finite and positive definite.
        first_bad: ``()`` int, index of the first failed pivot block, ``-1`` if ``ok``.
    """

    Linv: Float[Array, "n b b"]
    M: Float[Array, "n1 b b"]
    ok: Bool[Array, ""]
    first_bad: Int[Array, ""]


class BandedSolution(eqx.Module):
    """Solution of a block-banded SPD system with its status (for traced code).

    Attributes:
        x: solution, same shape as the right-hand side.
        ok: ``()`` bool, the factorisation succeeded (all pivots finite, positive definite).
        first_bad_frame: ``()`` int, first frame block whose pivot failed (``-1`` if ``ok``);
            the failing pivot is the pair block of frames ``2·(f//2)`` and ``2·(f//2)+1``.
    """

    x: Float[Array, ...]
    ok: Bool[Array, ""]
    first_bad_frame: Int[Array, ""]


# --------------------------------------------------------------------------------------------
# small kernels
# --------------------------------------------------------------------------------------------


def tri_right(L: Array, B: Array, *, transpose: bool) -> Array:
    """``X`` with ``X Lᵀ = B`` (``transpose``) or ``X L = B``; ``L`` lower triangular ``(b, b)``.

    ``B`` is ``(rows, b)``; it is split into row chunks of at most ``_TRSM_MAX_ENTRIES``
    entries so that every LAPACK call stays single-threaded (see the module notes).
    """
    rows, b = B.shape[-2], B.shape[-1]
    step = max(1, _TRSM_MAX_ENTRIES // max(b, 1))
    solve = lambda Bc: lax.linalg.triangular_solve(
        L, Bc, left_side=False, lower=True, transpose_a=transpose
    )
    if rows <= step:
        return solve(B)
    return jnp.concatenate([solve(B[i : i + step]) for i in range(0, rows, step)], axis=0)


def _row(a: Array, i: Array) -> Array:
    """``a[i]`` for a traced, in-range ``i`` (no negative-index normalisation)."""
    return lax.dynamic_index_in_dim(a, i, axis=0, keepdims=False)


def _put(a: Array, v: Array, i: Array, *offsets: int) -> Array:
    """``a[i, offsets…] = v`` (block update in place of a loop-carried buffer)."""
    start = (i, *offsets, *([0] * (a.ndim - 1 - len(offsets))))
    return lax.dynamic_update_slice(a, v[None].astype(a.dtype), start)


def pivot_status(diag_of_factor: Array) -> tuple[Array, Array, Array]:
    """From ``(n, b)`` pivot diagonals: per-block ``good``, overall ``ok``, ``first_bad``."""
    good = jnp.all(jnp.isfinite(diag_of_factor) & (diag_of_factor > 0), axis=-1)
    ok = jnp.all(good)
    first_bad = jnp.where(ok, -1, jnp.argmin(good)).astype(jnp.int32)
    return good, ok, first_bad


# --------------------------------------------------------------------------------------------
# block-tridiagonal core (public)
# --------------------------------------------------------------------------------------------


def block_tridiag_factor(diag: Array, sub: Array) -> BlockTridiagCholesky:
    """:func:`block_tridiag_cholesky` for already symmetric ``diag``."""
    b = diag.shape[-1]
    dt = diag.dtype
    eye = jnp.eye(b, dtype=dt)
    sub_prev = jnp.concatenate([jnp.zeros((1, b, b), dt), sub], axis=0)

    def step(Linv_prev: Array, blocks: tuple[Array, Array]) -> tuple[Array, tuple[Array, Array]]:
        D, S = blocks
        Mp = S @ Linv_prev.T  # M_{I−1} = A_{I,I−1} L_{I−1}⁻ᵀ
        L = lax.linalg.cholesky(D - Mp @ Mp.T, symmetrize_input=False)
        Linv = tri_right(L, eye, transpose=True).T  # (I L⁻ᵀ)ᵀ = L⁻¹
        return Linv, (Linv, Mp)

    _, (Linv, Mp) = lax.scan(step, jnp.zeros((b, b), dt), (diag, sub_prev))
    good, ok, first_bad = pivot_status(jnp.diagonal(Linv, axis1=-2, axis2=-1))
    Linv = jnp.where(good[:, None, None], Linv, 0.0)
    M = jnp.where(good[:-1, None, None], Mp[1:], 0.0)
    return BlockTridiagCholesky(Linv=Linv, M=M, ok=ok, first_bad=first_bad)


def block_tridiag_cholesky(
    diag: Float[Array, "n b b"], sub: Float[Array, "n1 b b"]
) -> BlockTridiagCholesky:
    """Block Cholesky factorisation of a symmetric block-tridiagonal matrix.

    One ``lax.scan`` step per block: ``M_{I−1} = A_{I,I−1} L_{I−1}⁻ᵀ`` (a product with the
    stored inverse), ``L_I = chol(A_II − M_{I−1} M_{I−1}ᵀ)`` and ``L_I⁻¹`` (one triangular
    solve), ``O(n·b³)``.

    Args:
        diag: ``(n, b, b)`` diagonal blocks ``A_II`` (symmetrised, ``(A_II + A_IIᵀ)/2``).
        sub: ``(n−1, b, b)`` sub-diagonal blocks ``A_{I+1,I}``.

    Returns:
        The factor; ``ok`` is ``False`` (and ``first_bad`` the first failing block) if a
        pivot ``A_II − M_{I−1} M_{I−1}ᵀ`` is not positive definite or not finite; the factor
        blocks from the failing one on are then set to zero. No error is raised here, so this
        works under ``jit``/``vmap``/``grad``.
    """
    return block_tridiag_factor(sym(diag), sub)


def substitute_rows(Linv: Array, M: Array, r: Array) -> Array:
    """Forward and backward substitution with stored inverses; right-hand sides as rows.

    ``r`` is ``(n, m, b)`` (row ``j`` of block ``I`` is the ``j``-th right-hand side restricted
    to block ``I``), so each step is one ``(m, b) × (b, b)`` product per pass, a GEMM over all
    ``m`` right-hand sides (and over a ``vmap`` batch, which is folded into the rows).
    Row form of the substitution: ``z_I = (r_I − z_{I−1} M_{I−1}ᵀ) L_I⁻ᵀ``,
    ``x_I = (z_I − x_{I+1} M_I) L_I⁻¹``. Both passes overwrite their input in place (a loop
    carry updated with ``dynamic_update_slice``) instead of stacking a new output, so no
    ``(n, m, b)`` buffer is allocated and zero-filled per pass.
    """
    n, m, b = r.shape
    zero_blk = jnp.zeros((1, b, b), M.dtype)
    M_prev = jnp.concatenate([zero_blk, M], axis=0)
    M_next = jnp.concatenate([M, zero_blk], axis=0)

    def fwd(i: Array, carry: tuple[Array, Array]) -> tuple[Array, Array]:
        z_prev, R = carry
        z = (_row(R, i) - z_prev @ _row(M_prev, i).T) @ _row(Linv, i).T
        return z, _put(R, z, i)

    def bwd(j: Array, carry: tuple[Array, Array]) -> tuple[Array, Array]:
        i = n - 1 - j
        x_next, R = carry
        x = (_row(R, i) - x_next @ _row(M_next, i)) @ _row(Linv, i)
        return x, _put(R, x, i)

    zero = jnp.zeros((m, b), r.dtype)
    _, z = lax.fori_loop(0, n, fwd, (zero, r))
    _, x = lax.fori_loop(0, n, bwd, (zero, z))
    return x


def block_tridiag_solve(
    factor: BlockTridiagCholesky, rhs: Float[Array, "n b m"]
) -> Float[Array, "n b m"]:
    """Solve ``A X = R`` given the block Cholesky factor of ``A`` (two ``lax.scan`` passes).

    ``z_I = L_I⁻¹(r_I − M_{I−1} z_{I−1})``, then ``x_I = L_I⁻ᵀ(z_I − M_Iᵀ x_{I+1})``; matrix
    products only, ``O(n·b²·m)``.

    Args:
        factor: result of :func:`block_tridiag_cholesky` for ``n`` blocks of size ``b``.
        rhs: ``(n, b, m)`` right-hand sides, block ``I`` first.

    Returns:
        ``(n, b, m)`` solution.
    """
    r = jnp.swapaxes(rhs, -1, -2)  # (n, m, b): right-hand sides as rows
    return jnp.swapaxes(substitute_rows(factor.Linv, factor.M, r), -1, -2)


# --------------------------------------------------------------------------------------------
# block-tridiagonal solve with status: fused (single) and factor-once (batched) paths
# --------------------------------------------------------------------------------------------


def solve_rows_plain(D: Array, S: Array, r: Array) -> tuple[Array, Array, Array]:
    """Factor once (storing ``L_I⁻¹``), then GEMM substitution. Autodiff-transparent.

    A failed factorisation has its blocks zeroed from the failing one on, so ``x`` stays
    finite (for finite ``r``) without a pass over it.
    """
    fac = block_tridiag_factor(D, S)
    return substitute_rows(fac.Linv, fac.M, r), fac.ok, fac.first_bad


def solve_rows_fused(D: Array, S: Array, r: Array) -> tuple[Array, Array, Array]:
    """Factorisation with the forward substitution fused into its triangular solve.

    With ``X_{I−1} = [M_{I−1}; z_{I−1}]`` (``(b+m, b)``, rows) carried, step ``I`` is

    .. code-block:: text

        [P_I; y_I] = [D_I; r_I] − X_{I−1} M_{I−1}ᵀ      (one product: P_I and y_I together)
        L_I = chol(P_I),   X_I = [M_I; z_I] = [S_I; y_I] L_I⁻ᵀ      (one Cholesky, one trsm)

    (``P_I = D_I − M_{I−1} M_{I−1}ᵀ``, ``y_I = r_I − z_{I−1} M_{I−1}ᵀ``), then the backward pass
    ``x_I = (z_I − x_{I+1} M_I) L_I⁻¹`` (one trsm per step). Both loops write in place into
    one per-block buffer, over the entries they have just read (``[S_I; 0; 0]`` becomes
    ``[M_I; z_I; L_I]``, then ``z_I`` becomes ``x_I``): no stacked output is allocated and
    zero-filled, and as every write depends on the read it replaces, XLA needs no defensive
    copy of the buffer.
    """
    n, m, b = r.shape
    dt = D.dtype
    DR = jnp.concatenate([D, r], axis=1)  # (n, b+m, b): [D_I; r_I], read only
    # per block (2b+m, b): [A_{I+1,I}; 0; 0] (0 after the last block), overwritten by
    # [X_I; L_I] = [M_I; z_I; L_I] in the forward pass and by [M_I; x_I; L_I] in the backward
    SXL = jnp.concatenate([S, jnp.zeros((1, b, b), dt)], axis=0)
    SXL = jnp.concatenate([SXL, jnp.zeros((n, b + m, b), dt)], axis=1)

    def fwd(i: Array, carry: tuple[Array, Array]) -> tuple[Array, Array]:
        X, SXLb = carry
        G = _row(DR, i) - X @ X[:b].T
        L = lax.linalg.cholesky(G[:b], symmetrize_input=False)
        X = tri_right(L, jnp.concatenate([_row(SXLb, i)[:b], G[b:]], axis=0), transpose=True)
        return X, _put(SXLb, jnp.concatenate([X, L], axis=0), i)

    _, SXL = lax.fori_loop(0, n, fwd, (jnp.zeros((b + m, b), dt), SXL))

    def bwd(j: Array, carry: tuple[Array, Array]) -> tuple[Array, Array]:
        i = n - 1 - j
        x_next, SXLb = carry
        blk = _row(SXLb, i)
        x = tri_right(blk[b + m :], blk[b : b + m] - x_next @ blk[:b], transpose=False)
        return x, _put(SXLb, x, i, b)

    _, SXL = lax.fori_loop(0, n, bwd, (jnp.zeros((m, b), r.dtype), SXL))
    _, ok, first_bad = pivot_status(jnp.diagonal(SXL[:, b + m :], axis1=-2, axis2=-1))
    return jnp.where(ok, SXL[:, b : b + m], 0.0), ok, first_bad


def solve_rows_unbatched(D: Array, S: Array, r: Array) -> tuple[Array, Array, Array]:
    b, m = D.shape[-1], r.shape[1]
    if (b + m) * b <= _TRSM_MAX_ENTRIES:  # the fused triangular solve stays one small call
        return solve_rows_fused(D, S, r)
    return solve_rows_plain(D, S, r)


def _rows_batched(
    axis_size: int, D: Array, S: Array, r: Array, r_b: bool
) -> tuple[Array, Array, Array]:
    """One matrix, batched right-hand sides: factor once, the batch folded into GEMM rows.

    Returns ``x`` with the batch axis first; ``ok``, ``first_bad`` unbatched.
    """
    n, b = D.shape[0], D.shape[-1]
    fac = block_tridiag_factor(D, S)
    if r_b:
        m = r.shape[2]
        rows = jnp.moveaxis(r, 0, 1).reshape(n, axis_size * m, b)
    else:  # nothing batched (cannot happen through vmap, kept total)
        m = r.shape[1]
        rows = jnp.tile(r, (1, axis_size, 1))
    x = substitute_rows(fac.Linv, fac.M, rows)
    x = jnp.moveaxis(x.reshape(n, axis_size, m, b), 1, 0)
    return x, fac.ok, fac.first_bad


@jax.custom_batching.custom_vmap
def _solve_rows_vmappable(D: Array, S: Array, r: Array) -> tuple[Array, Array, Array]:
    return solve_rows_unbatched(D, S, r)


@_solve_rows_vmappable.def_vmap
def _solve_rows_vmap_rule(
    axis_size: int, in_batched: list[Any], D: Array, S: Array, r: Array
) -> tuple[tuple[Array, Array, Array], tuple[bool, bool, bool]]:
    D_b, S_b, r_b = in_batched
    if not D_b and not S_b:
        # one matrix, a batch of right-hand sides: factor once, the batch becomes GEMM rows
        return _rows_batched(axis_size, D, S, r, r_b), (True, False, False)
    # the matrix itself is batched: every element needs its own factorisation
    bcast = lambda a, batched: a if batched else jnp.broadcast_to(a, (axis_size, *a.shape))
    out = jax.vmap(solve_rows_plain)(bcast(D, D_b), bcast(S, S_b), bcast(r, r_b))
    return out, (True, True, True)


def _tridiag_matvec_rows(D: Array, S: Array, x: Array) -> Array:
    """``(A x)`` in row form for block-tridiagonal ``A`` (``D`` symmetric, ``S_I = A_{I+1,I}``).

    ``(A x)_I = x_I D_Iᵀ + x_{I−1} S_{I−1}ᵀ + x_{I+1} S_I`` with ``x`` ``(n, m, b)``.
    """
    y = x @ jnp.swapaxes(D, -1, -2)
    if S.shape[0] > 0:
        pad = lambda a, lo, hi: jnp.pad(a, ((lo, hi), (0, 0), (0, 0)))
        y = y + pad(x[:-1] @ jnp.swapaxes(S, -1, -2), 1, 0) + pad(x[1:] @ S, 0, 1)
    return y


@jax.custom_jvp
def tridiag_solve_rows(D: Array, S: Array, r: Array) -> tuple[Array, Array, Array]:
    """Solve the block-tridiagonal SPD system for right-hand-side rows, with status.

    Args:
        D: ``(n, b, b)`` symmetric diagonal blocks.
        S: ``(n−1, b, b)`` sub-diagonal blocks ``A_{I+1,I}``.
        r: ``(n, m, b)`` right-hand sides as rows.

    Returns:
        ``x`` ``(n, m, b)`` (finite but meaningless if not ``ok``), ``ok``, ``first_bad``
        (first failing pair block, ``-1`` if ``ok``).

    Derivatives (``custom_jvp``): ``dx = A⁻¹(dr − dA x)``; only the lower triangles of ``D``
    are read, so tangents of ``D`` are assumed symmetric.
    """
    return _solve_rows_vmappable(D, S, r)


@tridiag_solve_rows.defjvp
def _tridiag_solve_rows_jvp(
    primals: tuple[Array, Array, Array], tangents: tuple[Array, Array, Array]
) -> tuple[tuple[Array, Array, Array], tuple[Array, Any, Any]]:
    D, S, r = primals
    dD, dS, dr = tangents
    x, ok, first_bad = tridiag_solve_rows(D, S, r)
    # A dx = dr − dA x; the plain path is linear in its right-hand side and transposable
    dx, _, _ = solve_rows_plain(D, S, dr - _tridiag_matvec_rows(dD, dS, x))
    float0 = lambda a: np.zeros(np.shape(a), dtype=jax.dtypes.float0)
    return (x, ok, first_bad), (dx, float0(ok), float0(first_bad))
