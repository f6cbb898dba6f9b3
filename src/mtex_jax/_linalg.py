"""Block-banded symmetric positive definite solver in JAX (SPEC §5, MT §5.4).

JAX has no banded solver. The normal matrix of constrained texton synthesis is symmetric
positive definite and *block pentadiagonal* in frames (block bandwidth 2: blocks ``(i, i)``,
``(i+1, i)``, ``(i+2, i)`` of size ``k × k``). Grouping frames in pairs ``(2I, 2I+1)`` makes it
block *tridiagonal* with ``2k × 2k`` blocks

.. code-block:: text

    Â_II     = [[A_{2I,2I},   A_{2I+1,2I}ᵀ], [A_{2I+1,2I},   A_{2I+1,2I+1}]]
    Â_{I+1,I} = [[A_{2I+2,2I}, A_{2I+2,2I+1}], [0,             A_{2I+3,2I+1}]]

which is factorised by the block Cholesky recursion (``lax.scan``, cost ``O(n·k³)``)

.. code-block:: text

    L_0 Lᵀ_0 = Â_00,   M_I = Â_{I+1,I} L_I⁻ᵀ,   L_{I+1} Lᵀ_{I+1} = Â_{I+1,I+1} − M_I M_Iᵀ

followed by block forward and backward substitution ``z_I = L_I⁻¹(r_I − M_{I−1} z_{I−1})``,
``x_I = L_I⁻ᵀ(z_I − M_Iᵀ x_{I+1})``. Each scan step makes one unbatched Cholesky and one
triangular inversion; everything else is matrix products, so batching with ``vmap`` adds no
concurrently running LAPACK calls.

Only the lower blocks are read: the matrix is assumed symmetric.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jax import lax
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Bool, Float, Int

__all__ = [
    "BandedSolution",
    "BlockTridiagCholesky",
    "block_banded_matvec",
    "block_banded_solve",
    "block_banded_solve_status",
    "block_tridiag_cholesky",
    "block_tridiag_solve",
]


_UNROLL = 1


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
# block-tridiagonal core
# --------------------------------------------------------------------------------------------


def block_tridiag_cholesky(
    diag: Float[Array, "n b b"], sub: Float[Array, "n1 b b"]
) -> BlockTridiagCholesky:
    """Block Cholesky factorisation of a symmetric block-tridiagonal matrix.

    Args:
        diag: ``(n, b, b)`` diagonal blocks ``A_II`` (symmetric; the lower triangle is used).
        sub: ``(n−1, b, b)`` sub-diagonal blocks ``A_{I+1,I}``.

    Returns:
        The factor; ``ok`` is ``False`` (and ``first_bad`` the first failing block) if a
        pivot ``A_II − M_{I−1} M_{I−1}ᵀ`` is not positive definite or not finite. No error is
        raised here, so this works under ``jit``/``vmap``/``grad``.
    """
    b = diag.shape[-1]
    eye = jnp.eye(b, dtype=diag.dtype)
    sub_prev = jnp.concatenate([jnp.zeros((1, b, b), diag.dtype), sub], axis=0)

    def step(Linv_prev: Array, blocks: tuple[Array, Array]) -> tuple[Array, tuple[Array, ...]]:
        D, S = blocks
        Mp = S @ Linv_prev.T  # M_{I−1} = A_{I,I−1} L_{I−1}⁻ᵀ
        P = D - Mp @ Mp.T
        P = 0.5 * (P + P.T)
        L = jnp.linalg.cholesky(P)
        pivots = jnp.diagonal(L)
        good = jnp.all(jnp.isfinite(L)) & jnp.all(pivots > 0)
        L_safe = jnp.where(good, L, eye)  # keep the recursion finite after a failure
        Linv = jsl.solve_triangular(L_safe, eye, lower=True)
        return Linv, (Linv, Mp, good)

    _, (Linv, Mp, good) = lax.scan(step, eye, (diag, sub_prev), unroll=_UNROLL)
    ok = jnp.all(good)
    first_bad = jnp.where(ok, -1, jnp.argmin(good)).astype(jnp.int32)
    return BlockTridiagCholesky(Linv=Linv, M=Mp[1:], ok=ok, first_bad=first_bad)


def block_tridiag_solve(
    factor: BlockTridiagCholesky, rhs: Float[Array, "n b m"]
) -> Float[Array, "n b m"]:
    """Solve ``A X = R`` given the block Cholesky factor of ``A`` (two ``lax.scan`` passes).

    Args:
        factor: result of :func:`block_tridiag_cholesky` for ``n`` blocks of size ``b``.
        rhs: ``(n, b, m)`` right-hand sides, block ``I`` first.

    Returns:
        ``(n, b, m)`` solution.
    """
    Linv, M = factor.Linv, factor.M
    b, m = rhs.shape[1], rhs.shape[2]
    zero = jnp.zeros((b, m), rhs.dtype)
    M_prev = jnp.concatenate([jnp.zeros((1, b, b), M.dtype), M], axis=0)

    def fwd(z_prev: Array, blocks: tuple[Array, Array, Array]) -> tuple[Array, Array]:
        Li, Mp, r = blocks
        z = Li @ (r - Mp @ z_prev)
        return z, z

    _, z = lax.scan(fwd, zero, (Linv, M_prev, rhs), unroll=_UNROLL)
    M_next = jnp.concatenate([M, jnp.zeros((1, b, b), M.dtype)], axis=0)

    def bwd(x_next: Array, blocks: tuple[Array, Array, Array]) -> tuple[Array, Array]:
        Li, Mn, zi = blocks
        x = Li.T @ (zi - Mn.T @ x_next)
        return x, x

    _, x = lax.scan(bwd, zero, (Linv, M_next, z), reverse=True, unroll=_UNROLL)
    return x


# --------------------------------------------------------------------------------------------
# block bandwidth 2 in frames -> block tridiagonal in frame pairs
# --------------------------------------------------------------------------------------------


def _pair_blocks(diag: Array, off1: Array, off2: Array) -> tuple[Array, Array]:
    """Frame blocks (bandwidth 2, size k) -> pair blocks (tridiagonal, size 2k)."""
    n, k = diag.shape[0], diag.shape[-1]
    nb = (n + 1) // 2
    pad = 2 * nb - n
    dt = diag.dtype
    eye = jnp.eye(k, dtype=dt)
    D = jnp.concatenate([diag, jnp.broadcast_to(eye, (pad, k, k))], axis=0)
    S1 = jnp.concatenate([off1, jnp.zeros((2 * nb - 1 - off1.shape[0], k, k), dt)], axis=0)
    S2 = jnp.concatenate([off2, jnp.zeros((max(2 * nb - 2, 0) - off2.shape[0], k, k), dt)])
    D0, D1 = D[0::2], D[1::2]
    S1e = S1[0::2]  # A_{2I+1,2I}
    top = jnp.concatenate([D0, jnp.swapaxes(S1e, -1, -2)], axis=-1)
    bot = jnp.concatenate([S1e, D1], axis=-1)
    pdiag = jnp.concatenate([top, bot], axis=-2)
    if nb == 1:
        return pdiag, jnp.zeros((0, 2 * k, 2 * k), dt)
    S2e, S2o = S2[0::2], S2[1::2]  # A_{2I+2,2I}, A_{2I+3,2I+1}
    S1o = S1[1::2][: nb - 1]  # A_{2I+2,2I+1}
    top = jnp.concatenate([S2e, S1o], axis=-1)
    bot = jnp.concatenate([jnp.zeros_like(S2o), S2o], axis=-1)
    psub = jnp.concatenate([top, bot], axis=-2)
    return pdiag, psub


def _check_band_shapes(diag: Array, off1: Array, off2: Array) -> tuple[int, int]:
    if diag.ndim != 3 or diag.shape[1] != diag.shape[2]:
        raise ValueError(f"diag must have shape (n, k, k), got {tuple(diag.shape)}")
    n, k = diag.shape[0], diag.shape[1]
    if n < 1:
        raise ValueError("diag must hold at least one block")
    for name, x, m in (("off1", off1, n - 1), ("off2", off2, max(n - 2, 0))):
        if tuple(x.shape) != (m, k, k):
            raise ValueError(f"{name} must have shape ({m}, {k}, {k}) for n={n}, got {x.shape}")
    return n, k


def _as_float(name: str, x: ArrayLike) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        raise ValueError(f"{name} must be a real floating array, got dtype {x.dtype}")
    return x


def block_banded_matvec(
    diag: Float[ArrayLike, "n k k"],
    off1: Float[ArrayLike, "n1 k k"],
    off2: Float[ArrayLike, "n2 k k"],
    x: Float[ArrayLike, "n k m"],
) -> Float[Array, "n k m"]:
    """``A x`` for the symmetric block-banded ``A`` (``O(n·k²·m)``).

    Args:
        diag: ``(n, k, k)`` blocks ``A_ii``.
        off1: ``(n−1, k, k)`` blocks ``A_{i+1,i}``.
        off2: ``(n−2, k, k)`` blocks ``A_{i+2,i}``.
        x: ``(n, k, m)``.

    Returns:
        ``(n, k, m)`` with
        ``(A x)_i = A_ii x_i + Σ_{j=1,2} (A_{i,i−j} x_{i−j} + A_{i+j,i}ᵀ x_{i+j})``.
    """
    diag, off1, off2, x = (jnp.asarray(a) for a in (diag, off1, off2, x))
    pad = lambda a, lo, hi: jnp.pad(a, ((lo, hi), (0, 0), (0, 0)))  # no scatter: vmap-fast
    y = diag @ x
    if off1.shape[0] > 0:
        y = y + pad(off1 @ x[:-1], 1, 0) + pad(jnp.swapaxes(off1, -1, -2) @ x[1:], 0, 1)
    if off2.shape[0] > 0:
        y = y + pad(off2 @ x[:-2], 2, 0) + pad(jnp.swapaxes(off2, -1, -2) @ x[2:], 0, 2)
    return y


def _solve_frames(diag: Array, off1: Array, off2: Array, rhs: Array) -> BandedSolution:
    """Core: rhs ``(n, k, m)``; returns frame-shaped solution and status."""
    n, k, m = rhs.shape
    nb = (n + 1) // 2
    pdiag, psub = _pair_blocks(diag, off1, off2)
    finite_in = jnp.all(jnp.isfinite(pdiag), axis=(1, 2))
    if nb > 1:
        finite_sub = jnp.all(jnp.isfinite(psub), axis=(1, 2))
        finite_in = finite_in & jnp.concatenate([finite_sub, jnp.ones((1,), bool)])
        finite_in = finite_in & jnp.concatenate([jnp.ones((1,), bool), finite_sub])
    fac = block_tridiag_cholesky(pdiag, psub)
    r = jnp.concatenate([rhs, jnp.zeros((2 * nb - n, k, m), rhs.dtype)], axis=0)
    r = r.reshape(nb, 2 * k, m)
    x = block_tridiag_solve(fac, r).reshape(2 * nb, k, m)[:n]
    good = jnp.all(finite_in) & fac.ok
    bad_pair = jnp.where(fac.ok, jnp.argmin(finite_in), fac.first_bad)
    first_bad = jnp.where(good, -1, 2 * bad_pair).astype(jnp.int32)
    return BandedSolution(x=x, ok=good, first_bad_frame=first_bad)


def _to_frames(rhs: Array, n: int, k: int) -> tuple[Array, tuple[int, ...]]:
    shape = tuple(rhs.shape)
    if rhs.ndim == 1:
        if shape != (n * k,):
            raise ValueError(f"rhs must have shape ({n * k},) or (..., {n * k}, m), got {shape}")
        return rhs.reshape(n, k, 1), shape
    if shape[-2] != n * k:
        raise ValueError(f"rhs must have shape ({n * k},) or (..., {n * k}, m), got {shape}")
    m = shape[-1]
    r = rhs.reshape(-1, n * k, m)  # (B, nk, m)
    r = jnp.moveaxis(r, 0, 1).reshape(n, k, -1)  # (n, k, B·m)
    return r, shape


def _from_frames(x: Array, shape: tuple[int, ...], n: int, k: int) -> Array:
    if len(shape) == 1:
        return x.reshape(n * k)
    m = shape[-1]
    x = x.reshape(n * k, -1, m)
    return jnp.moveaxis(x, 1, 0).reshape(shape)


def block_banded_solve_status(
    diag: Float[ArrayLike, "n k k"],
    off1: Float[ArrayLike, "n1 k k"],
    off2: Float[ArrayLike, "n2 k k"],
    rhs: Float[ArrayLike, "*batch nk m"],
) -> BandedSolution:
    """Solve ``A x = r`` for symmetric positive definite ``A`` of block bandwidth 2, with status.

    ``A`` has ``n × n`` blocks of size ``k × k``, nonzero only for ``|i − j| ≤ 2``. Frames are
    grouped in pairs and the block-tridiagonal system is solved by block Cholesky with
    ``lax.scan`` in ``O(n·k³ + n·k²·m)``. Never raises on values: use it under ``jit`` or
    ``vmap`` and inspect ``ok``. Differentiable (autodiff through the scans).

    Args:
        diag: ``(n, k, k)`` diagonal blocks ``A_ii`` (only the lower triangle is read).
        off1: ``(n−1, k, k)`` first sub-diagonal blocks ``A_{i+1,i}``.
        off2: ``(max(n−2, 0), k, k)`` second sub-diagonal blocks ``A_{i+2,i}``.
        rhs: ``(n·k,)`` or ``(*batch, n·k, m)`` right-hand sides.

    Returns:
        :class:`BandedSolution` with ``x`` of the shape of ``rhs``; if ``ok`` is ``False`` the
        values of ``x`` are meaningless (but finite where the input was finite).
    """
    diag, off1, off2 = (
        _as_float(nm, a) for nm, a in (("diag", diag), ("off1", off1), ("off2", off2))
    )
    rhs = _as_float("rhs", rhs)
    n, k = _check_band_shapes(diag, off1, off2)
    dt = jnp.result_type(diag, off1, off2, rhs)
    r, shape = _to_frames(rhs.astype(dt), n, k)
    sol = _solve_frames(diag.astype(dt), off1.astype(dt), off2.astype(dt), r)
    finite_rhs = jnp.all(jnp.isfinite(r))
    return BandedSolution(
        x=_from_frames(sol.x, shape, n, k),
        ok=sol.ok & finite_rhs,
        first_bad_frame=sol.first_bad_frame,
    )


def _first_nonfinite_block(name: str, x: Array) -> str | None:
    xn = np.asarray(x)
    bad = ~np.isfinite(xn.reshape(xn.shape[0], -1)).all(axis=1) if xn.shape[0] else np.zeros(0)
    if bad.any():
        return f"{name} block {int(np.argmax(bad))} contains NaN or inf"
    return None


def block_banded_solve(
    diag: Float[ArrayLike, "n k k"],
    off1: Float[ArrayLike, "n1 k k"],
    off2: Float[ArrayLike, "n2 k k"],
    rhs: Float[ArrayLike, "*batch nk m"],
) -> Float[Array, "*batch nk m"]:
    """Solve ``A x = r`` for SPD ``A`` of block bandwidth 2 (see :func:`block_banded_solve_status`).

    Input checking: called eagerly with concrete arrays, non-finite blocks or a matrix that
    is not positive definite raise ``ValueError`` naming the block. Under a trace
    (``jit``/``vmap``/``grad``) the same failures raise at run time through
    ``eqx.error_if``; use :func:`block_banded_solve_status` to get a status flag instead.

    Args:
        diag: ``(n, k, k)`` blocks ``A_ii``.
        off1: ``(n−1, k, k)`` blocks ``A_{i+1,i}``.
        off2: ``(max(n−2, 0), k, k)`` blocks ``A_{i+2,i}``.
        rhs: ``(n·k,)`` or ``(*batch, n·k, m)``.

    Returns:
        ``x`` with the shape of ``rhs``.

    Raises:
        ValueError: eager call with non-finite input or a non-positive-definite matrix.
    """
    arrays = {"diag": diag, "off1": off1, "off2": off2, "rhs": rhs}
    concrete = not any(isinstance(a, Tracer) for a in arrays.values())
    if concrete:
        for name in ("diag", "off1", "off2"):
            arr = _as_float(name, arrays[name])
            if arr.ndim == 3:
                msg = _first_nonfinite_block(name, arr)
                if msg is not None:
                    raise ValueError(f"block_banded_solve: {msg}")
        if not np.isfinite(np.asarray(rhs)).all():
            raise ValueError("block_banded_solve: rhs contains NaN or inf")
    sol = _solve_status_jit(diag, off1, off2, rhs)
    if concrete:
        if not bool(sol.ok):
            f = int(sol.first_bad_frame)
            raise ValueError(
                "block_banded_solve: the matrix is not positive definite: the Cholesky pivot of "
                f"frame blocks {f} and {f + 1} (pair block {f // 2}) failed, i.e. the leading "
                f"principal submatrix through frame block {f + 1} is not positive definite"
            )
        return sol.x
    return eqx.error_if(
        sol.x, ~sol.ok, "block_banded_solve: matrix not positive definite or input not finite"
    )


_solve_status_jit = eqx.filter_jit(block_banded_solve_status)
