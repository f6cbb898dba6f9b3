"""Block-banded systems in frame layout (bandwidth two frames, as in the normal equations of
second-order synthesis): matvec and solve by pairing frames into a block-tridiagonal system."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float

from ._blocktridiag import BandedSolution, sym, tridiag_solve_rows

# --------------------------------------------------------------------------------------------
# block bandwidth 2 in frames -> block tridiagonal in frame pairs
# --------------------------------------------------------------------------------------------


def pair_blocks(diag: Array, off1: Array, off2: Array) -> tuple[Array, Array]:
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
    """Core: rhs ``(n, k, m)``; returns frame-shaped solution and status.

    Frame blocks are grouped in pairs (:func:`pair_blocks`) and solved by
    ``tridiag_solve_rows`` with the right-hand sides as rows.
    """
    n, k, m = rhs.shape
    nb = (n + 1) // 2
    pdiag, psub = pair_blocks(diag, off1, off2)
    pdiag = sym(pdiag)
    finite_in = jnp.all(jnp.isfinite(pdiag), axis=(1, 2))
    if nb > 1:
        finite_sub = jnp.all(jnp.isfinite(psub), axis=(1, 2))
        finite_in = finite_in & jnp.concatenate([finite_sub, jnp.ones((1,), bool)])
        finite_in = finite_in & jnp.concatenate([jnp.ones((1,), bool), finite_sub])
    r = jnp.concatenate([rhs, jnp.zeros((2 * nb - n, k, m), rhs.dtype)], axis=0)
    r = jnp.swapaxes(r.reshape(nb, 2 * k, m), 1, 2)  # (nb, m, 2k) rows
    x, fac_ok, fac_bad = tridiag_solve_rows(pdiag, psub, r)
    x = jnp.swapaxes(x, 1, 2).reshape(2 * nb, k, m)[:n]
    good = jnp.all(finite_in) & fac_ok
    bad_pair = jnp.where(fac_ok, jnp.argmin(finite_in), fac_bad)
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
    ``vmap`` and inspect ``ok``. Differentiable (forward and reverse mode).

    Args:
        diag: ``(n, k, k)`` diagonal blocks ``A_ii`` (symmetrised, ``(A_ii + A_iiᵀ)/2``).
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
