"""The normal equations of a banded Gauss–Newton step: factor and solve, one frame per block.

:class:`~mtex_jax.edit.BandedGaussNewton` forms, at each fresh step, the prior's band plus
the constraints' block-diagonal Gauss–Newton terms; this module factorises that matrix with
:func:`~mtex_jax.linalg.block_penta_factor` (single precision for a double-precision problem,
with a fallback) and solves for the step, under ``vmap`` one motion after the other.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array

from ...linalg import BlockPentaCholesky, block_penta_factor, block_penta_solve, sym
from .._whiten import band_matvec

__all__ = ["factor_dtype", "no_factor", "normal_solve", "step_solve"]


def no_factor(T: int, D: int, dt) -> BlockPentaCholesky:
    """A zero factor (a skipped factorisation) of a problem in precision ``dt``."""
    z = jnp.zeros((T, D, D), factor_dtype(dt))
    return BlockPentaCholesky(
        Linv=z, L1=z, L2=z, ok=jnp.asarray(True), first_bad=jnp.asarray(-1, jnp.int32)
    )


@jax.custom_batching.custom_vmap
def normal_solve(H0, A, H1, H2, var_ch, anchor, held, delta, linear, active):
    """The Gauss–Newton normal equations' solution, their factor and the step's status.

    The matrix is ``H + M A M + diag(anchor²)`` over the free frames (``A``: the
    constraints' block-diagonal ``Σ JᵀW²J``, ``M = diag(var_ch)``), with an identity block
    at each held frame, whose displacement is ``delta``; the right-hand side is
    ``−(linear + H δ)``. Factorised with one frame per block
    (:func:`~mtex_jax.linalg.block_penta_factor`, each block formed inside the recursion, so
    the matrix is never stored), by :func:`step_solve`. Returns ``(z, factor, ok)``: the
    factor (for chord steps) may be of lower precision than the problem, and ``ok`` says
    that the step was solved.

    ``active`` (a bool) says whether the caller will use the result: a motion of a ``vmap``
    batch that has already stopped (or takes a chord step) still runs the loop body until
    every motion has, and its factorisation is skipped (zeros returned). Without ``vmap`` the
    solve always runs.

    Under ``vmap`` the motions are factorised one after the other (``lax.map``, with
    ``lax.cond`` on ``active``): a batched block Cholesky hands LAPACK a batch of triangular
    solves, which XLA's CPU backend runs orders of magnitude slower (measured with the
    frame-pair factor's ``108 × 108`` pivot blocks: an inverse 0.09 ms alone, 21 ms in a
    batch of 4; a batch of 4 motions of 600 frames did not finish in 5 minutes, one took
    0.13 s); everything else in the solve stays batched."""
    del active
    D = H0.shape[-1]
    dt = H0.dtype
    f = (~held).astype(dt)
    b = linear + band_matvec((H0, H1, H2), delta)
    f1 = jnp.concatenate([jnp.zeros((1,), dt), f[:-1]])
    f2 = jnp.concatenate([jnp.zeros((2,), dt), f[:-2]])
    mm = var_ch[:, None] * var_ch[None, :]
    eye, ridge = jnp.eye(D, dtype=dt), jnp.diag(anchor**2)

    def blocks(x):
        h0, a, h1, h2, held_t, f_t, f_1, f_2 = x
        a0 = jnp.where(held_t, eye, sym(h0 + a * mm) + ridge)
        return a0, h1 * (f_t * f_1), h2 * (f_t * f_2)

    z_star, fac, ok = step_solve(blocks, (H0, A, H1, H2, held, f, f1, f2), -b * f[:, None])
    return z_star * f[:, None] + delta, fac, ok


def factor_dtype(dtype) -> jnp.dtype:
    """The precision of a step's factor: single for a double-precision problem."""
    return jnp.dtype(jnp.float32 if jnp.dtype(dtype) == jnp.float64 else dtype)


def step_solve(blocks, xs, rhs: Array) -> tuple[Array, BlockPentaCholesky, Array]:
    """A Gauss–Newton step's solve: the normal matrix (blocks ``blocks(x_t)`` of the frames'
    slices of ``xs``, :func:`~mtex_jax.linalg.block_penta_factor`) factored in single
    precision for a double-precision problem, the substitution in the problem's precision.

    The factor only chooses the step's direction: each step is accepted on the cost, computed
    in the problem's precision, and the iteration stops where the gradient does, so an
    inexact factor changes the path, not the solution (an inexact Gauss–Newton step). In
    single precision the factorisation takes about 35 % less time (measured, 1,280 frames of
    54 channels); each block is rounded inside the recursion and the factor stays in single
    precision (the substitution converts it block by block), so no converted copy of the
    matrix or the factor is made. If it fails (a matrix too ill-conditioned for single
    precision), the step is factored and solved again in the problem's precision; the
    returned factor then reports ``ok = False`` and is not used for chord steps.

    Returns:
        ``(x, factor, ok)``: the solution, the single-precision factor, whether either
        factorisation succeeded.
    """
    lo = block_penta_factor(blocks, xs, dtype=factor_dtype(rhs.dtype))
    if lo.Linv.dtype == rhs.dtype:
        return block_penta_solve(lo, rhs), lo, lo.ok

    def exact() -> tuple[Array, Array]:
        hi = block_penta_factor(blocks, xs)
        return block_penta_solve(hi, rhs), hi.ok

    x, ok = lax.cond(lo.ok, lambda: (block_penta_solve(lo, rhs), lo.ok), exact)
    return x, lo, ok


@normal_solve.def_vmap
def _normal_solve_vmap(axis_size: int, in_batched, *args):
    full = tuple(
        a if b else jnp.broadcast_to(a, (axis_size, *jnp.shape(a)))
        for a, b in zip(args, in_batched, strict=True)
    )

    def one(xs):
        *a, active = xs
        T, D = a[-1].shape
        skip = lambda *_: (
            jnp.zeros_like(a[-1]),
            no_factor(T, D, a[-1].dtype),
            jnp.asarray(True),
        )
        return lax.cond(active, lambda *b: normal_solve(*b, active), skip, *a)

    out = lax.map(one, full)
    return out, jax.tree.map(lambda _: True, out)
