"""Structured linear algebra: the block-banded SPD solver behind constrained synthesis.

JAX has no banded solver; these factor and solve symmetric positive definite matrices with block
bandwidth 2 (grouped into block-tridiagonal form) by ``lax.scan`` in ``O(n·k³)``.
"""

from ._linalg import (
    BandedSolution,
    BlockTridiagCholesky,
    block_banded_matvec,
    block_banded_solve,
    block_banded_solve_status,
    block_tridiag_cholesky,
    block_tridiag_solve,
)

__all__ = [
    "BandedSolution",
    "BlockTridiagCholesky",
    "block_banded_matvec",
    "block_banded_solve",
    "block_banded_solve_status",
    "block_tridiag_cholesky",
    "block_tridiag_solve",
]
