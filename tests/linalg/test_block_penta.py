"""The one-frame-per-block Cholesky of a block-pentadiagonal matrix (the edit solver's normal
equations, design §6.5): against a dense numpy solve and reconstruction, status on a failed
pivot, dtype."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from test_linalg import random_band  # the random SPD band of the tridiagonal tests

from mtex_jax.linalg import BlockPentaCholesky, block_penta_cholesky, block_penta_solve


def lower_blocks(diag, off1, off2):
    n, k = diag.shape[:2]
    A1 = np.zeros((n, k, k))
    A2 = np.zeros((n, k, k))
    A1[1:] = off1
    A2[2:] = off2
    return jnp.asarray(diag), jnp.asarray(A1), jnp.asarray(A2)


def dense_factor(f: BlockPentaCholesky) -> np.ndarray:
    Linv, L1, L2 = (np.asarray(a) for a in (f.Linv, f.L1, f.L2))
    n, k = Linv.shape[:2]
    L = np.zeros((n * k, n * k))
    for t in range(n):
        L[t * k : (t + 1) * k, t * k : (t + 1) * k] = np.linalg.inv(Linv[t])
        if t >= 1:
            L[t * k : (t + 1) * k, (t - 1) * k : t * k] = L1[t]
        if t >= 2:
            L[t * k : (t + 1) * k, (t - 2) * k : (t - 1) * k] = L2[t]
    return L


@pytest.mark.parametrize(
    ("n", "k", "seed"), [(1, 3, 0), (2, 2, 1), (3, 1, 2), (7, 4, 3), (12, 5, 4)]
)
def test_matches_dense_cholesky_and_solve(n, k, seed):
    rng = np.random.default_rng(seed)
    A, diag, off1, off2 = random_band(rng, n, k)
    f = block_penta_cholesky(*lower_blocks(diag, off1, off2))
    assert bool(f.ok) and int(f.first_bad) == -1
    L = dense_factor(f)
    np.testing.assert_allclose(L, np.linalg.cholesky(A), atol=1e-10)
    r = rng.standard_normal((n, k))
    x = block_penta_solve(f, jnp.asarray(r))
    np.testing.assert_allclose(np.asarray(x).ravel(), np.linalg.solve(A, r.ravel()), atol=1e-9)


def test_failed_pivot_is_reported_not_raised():
    rng = np.random.default_rng(5)
    _, diag, off1, off2 = random_band(rng, 6, 3)
    diag = diag.copy()
    diag[3] = -np.eye(3)  # block 3 cannot be a pivot
    f = block_penta_cholesky(*lower_blocks(diag, off1, off2))
    assert not bool(f.ok)
    assert int(f.first_bad) == 3
    assert np.all(np.asarray(f.Linv)[3:] == 0.0)
    assert np.all(np.isfinite(np.asarray(f.Linv)))


def test_dtype_follows_input():
    rng = np.random.default_rng(6)
    _, diag, off1, off2 = random_band(rng, 5, 2)
    A0, A1, A2 = (a.astype(jnp.float32) for a in lower_blocks(diag, off1, off2))
    f = block_penta_cholesky(A0, A1, A2)
    x = block_penta_solve(f, jnp.ones((5, 2), jnp.float32))
    assert f.Linv.dtype == jnp.float32 and x.dtype == jnp.float32


def test_bad_factor_shapes():
    z = jnp.zeros((4, 2, 2))
    with pytest.raises(ValueError, match="L1"):
        BlockPentaCholesky(
            Linv=z, L1=jnp.zeros((3, 2, 2)), L2=z, ok=jnp.asarray(True), first_bad=jnp.asarray(-1)
        )
