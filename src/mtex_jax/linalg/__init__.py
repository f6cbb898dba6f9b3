"""Block-banded and block-tridiagonal linear algebra (the normal equations of constrained
synthesis and of edits; design §5): Cholesky factorisations and solves in ``O(T k³)``, written
as ``lax.scan`` over frame blocks, differentiable, with a status instead of NaN on a
non-positive-definite system.
"""

from ._banded import (
    block_banded_matvec as block_banded_matvec,
    block_banded_solve as block_banded_solve,
    block_banded_solve_status as block_banded_solve_status,
    pair_blocks as pair_blocks,
)
from ._blockpenta import (
    BlockPentaCholesky as BlockPentaCholesky,
    block_penta_cholesky as block_penta_cholesky,
    block_penta_factor as block_penta_factor,
    block_penta_solve as block_penta_solve,
)
from ._blocktridiag import (
    BandedSolution as BandedSolution,
    BlockTridiagCholesky as BlockTridiagCholesky,
    block_tridiag_cholesky as block_tridiag_cholesky,
    block_tridiag_solve as block_tridiag_solve,
    sym as sym,
    tridiag_solve_rows as tridiag_solve_rows,
)

__all__ = [
    "BandedSolution",
    "BlockPentaCholesky",
    "BlockTridiagCholesky",
    "block_banded_matvec",
    "block_banded_solve",
    "block_banded_solve_status",
    "block_penta_cholesky",
    "block_penta_factor",
    "block_penta_solve",
    "block_tridiag_cholesky",
    "block_tridiag_solve",
    "pair_blocks",
    "sym",
    "tridiag_solve_rows",
]
