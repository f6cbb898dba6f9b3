"""The one-frame-per-block Cholesky of a block-pentadiagonal matrix (the edit solver's normal
equations, design §6.5): against a dense numpy solve and reconstruction, status on a failed
pivot, dtype."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from test_linalg import random_band  # the random SPD band of the tridiagonal tests

from mtex_jax.linalg import (
    BlockPentaCholesky,
    block_penta_cholesky,
    block_penta_factor,
    block_penta_solve,
)


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


def test_lower_precision_factor_and_mixed_precision_solve():
    """A float32 factor of a float64 matrix (each block rounded inside the recursion) equals
    the factor of the rounded matrix; the solve with it runs in float64."""
    rng = np.random.default_rng(8)
    A, diag, off1, off2 = random_band(rng, 9, 4)
    blocks = lower_blocks(diag, off1, off2)
    f32 = block_penta_cholesky(*blocks, dtype=jnp.float32)
    assert f32.Linv.dtype == f32.L1.dtype == f32.L2.dtype == jnp.float32
    ref = block_penta_cholesky(*(b.astype(jnp.float32) for b in blocks))
    for a, b in zip((f32.Linv, f32.L1, f32.L2), (ref.Linv, ref.L1, ref.L2), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    r = rng.standard_normal((9, 4))
    x = block_penta_solve(f32, jnp.asarray(r))
    assert x.dtype == jnp.float64
    exact = np.linalg.solve(A, r.ravel()).reshape(9, 4)
    # as accurate as single precision allows, and no more (the factor is rounded)
    err = np.abs(np.asarray(x) - exact).max() / np.abs(exact).max()
    assert 1e-12 < err < 1e-4
    # the same substitution with the factor converted up front gives the same numbers
    up = BlockPentaCholesky(
        Linv=f32.Linv.astype(jnp.float64),
        L1=f32.L1.astype(jnp.float64),
        L2=f32.L2.astype(jnp.float64),
        ok=f32.ok,
        first_bad=f32.first_bad,
    )
    x_up = block_penta_solve(up, jnp.asarray(r))
    np.testing.assert_allclose(np.asarray(x_up), np.asarray(x), rtol=0, atol=1e-14)


def test_blocks_formed_inside_the_recursion_equal_stored_blocks():
    """block_penta_factor with blocks computed per frame from stored pieces (a masked sum,
    as the edit solver forms its normal matrix) is the factor of the stored matrix."""
    rng = np.random.default_rng(12)
    n, k = 8, 3
    _, diag, off1, off2 = random_band(rng, n, k)
    A0, A1, A2 = (np.asarray(a) for a in lower_blocks(diag, off1, off2))
    extra = rng.standard_normal((n, k, k))
    extra = np.einsum("tij,tkj->tik", extra, extra)  # PSD, keeps the matrix SPD
    m = rng.uniform(0.5, 1.0, n)

    def blocks(x):
        a0, e, a1, a2, mt = x
        return a0 + e, a1 * mt, a2 * mt

    xs = tuple(jnp.asarray(a) for a in (A0, extra, A1, A2, m))
    f = block_penta_factor(blocks, xs)
    ref = block_penta_cholesky(
        jnp.asarray(A0 + extra),
        jnp.asarray(A1 * m[:, None, None]),
        jnp.asarray(A2 * m[:, None, None]),
    )
    assert bool(f.ok)
    for a, b in zip((f.Linv, f.L1, f.L2), (ref.Linv, ref.L1, ref.L2), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)
