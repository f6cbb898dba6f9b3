"""Block-banded SPD solver (issue 5 item 1): dense agreement, gradients, input checking, vmap."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

from mtex_jax._linalg import (
    block_banded_matvec,
    block_banded_solve,
    block_banded_solve_status,
)


def random_band(rng: np.random.Generator, n: int, k: int, ridge: float = 0.1):
    """Random SPD matrix of block bandwidth 2: ``Σ_j G_jᵀ G_j + ridge·I`` with ``G_j`` touching
    frames ``j−2, j−1, j`` (the structure of constrained synthesis). Returns dense and blocks."""
    N = n * k
    A = ridge * np.eye(N)
    for j in range(n):
        lo = max(j - 2, 0)
        G = rng.standard_normal((k, (j + 1 - lo) * k))
        A[lo * k : (j + 1) * k, lo * k : (j + 1) * k] += G.T @ G
    blk = lambda i, j: A[i * k : (i + 1) * k, j * k : (j + 1) * k]
    diag = np.array([blk(i, i) for i in range(n)]).reshape(n, k, k)
    off1 = np.array([blk(i + 1, i) for i in range(n - 1)]).reshape(n - 1, k, k)
    off2 = np.array([blk(i + 2, i) for i in range(n - 2)]).reshape(max(n - 2, 0), k, k)
    return A, diag, off1, off2


def dense_from_blocks(diag, off1, off2):
    n, k = diag.shape[0], diag.shape[1]
    A = np.zeros((n * k, n * k))
    for i in range(n):
        A[i * k : (i + 1) * k, i * k : (i + 1) * k] = diag[i]
    for s, off in ((1, off1), (2, off2)):
        for i in range(n - s):
            A[(i + s) * k : (i + s + 1) * k, i * k : (i + 1) * k] = off[i]
            A[i * k : (i + 1) * k, (i + s) * k : (i + s + 1) * k] = off[i].T
    return A


@settings(deadline=None, max_examples=12)
@given(
    n=st.integers(1, 10),
    k=st.integers(1, 3),
    m=st.integers(1, 2),
    seed=st.integers(0, 2**31 - 1),
)
def test_matches_dense_numpy_solve(n, k, m, seed):
    rng = np.random.default_rng(seed)
    A, diag, off1, off2 = random_band(rng, n, k)
    np.testing.assert_allclose(dense_from_blocks(diag, off1, off2), A, rtol=0, atol=1e-12)
    rhs = rng.standard_normal((n * k, m))
    x = np.asarray(block_banded_solve(diag, off1, off2, rhs))
    ref = np.linalg.solve(A, rhs)
    assert np.linalg.norm(x - ref) <= 1e-9 * np.linalg.norm(ref)


@pytest.mark.parametrize(("n", "k"), [(1, 2), (4, 1), (7, 3)])
def test_rhs_shapes(n, k):
    rng = np.random.default_rng(n * 10 + k)
    A, diag, off1, off2 = random_band(rng, n, k)
    rhs = rng.standard_normal((n * k, 1))
    ref = np.linalg.solve(A, rhs)
    x1 = np.asarray(block_banded_solve(diag, off1, off2, rhs[:, 0]))
    assert np.linalg.norm(x1 - ref[:, 0]) <= 1e-9 * np.linalg.norm(ref[:, 0])
    R = rng.standard_normal((2, 3, n * k, 2))
    XB = np.asarray(block_banded_solve(diag, off1, off2, R))
    refB = np.linalg.solve(A, R)
    assert XB.shape == R.shape
    assert np.linalg.norm(XB - refB) <= 1e-9 * np.linalg.norm(refB)


def test_matvec_matches_dense():
    rng = np.random.default_rng(1)
    A, diag, off1, off2 = random_band(rng, 7, 3)
    x = rng.standard_normal((7, 3, 2))
    y = np.asarray(block_banded_matvec(diag, off1, off2, x))
    np.testing.assert_allclose(y.reshape(21, 2), A @ x.reshape(21, 2), rtol=1e-12, atol=1e-12)


def test_check_grads():
    rng = np.random.default_rng(2)
    _, diag, off1, off2 = random_band(rng, 5, 2, ridge=1.0)
    rhs = rng.standard_normal((10, 2))
    f = jax.jit(lambda d, o1, o2, r: block_banded_solve_status(d, o1, o2, r).x)
    check_grads(f, (diag, off1, off2, rhs), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)


def test_non_pd_reported_eagerly_and_by_status():
    rng = np.random.default_rng(3)
    _, diag, off1, off2 = random_band(rng, 6, 2)
    bad = diag.copy()
    bad[4] -= 1e3 * np.eye(2)
    rhs = np.ones(12)
    with pytest.raises(ValueError, match=r"not positive definite.*frame blocks 4 and 5"):
        block_banded_solve(bad, off1, off2, rhs)
    sol = jax.jit(block_banded_solve_status)(bad, off1, off2, rhs)
    assert not bool(sol.ok)
    assert int(sol.first_bad_frame) == 4
    assert np.isfinite(np.asarray(sol.x)).all()  # no NaN leaks even on failure
    good = jax.jit(block_banded_solve_status)(diag, off1, off2, rhs)
    assert bool(good.ok) and int(good.first_bad_frame) == -1
    # traced public call: a run-time error, not NaN
    with pytest.raises(Exception, match="not positive definite"):
        jax.block_until_ready(jax.jit(block_banded_solve)(bad, off1, off2, rhs))


def test_non_finite_reported_with_block_name():
    rng = np.random.default_rng(4)
    _, diag, off1, off2 = random_band(rng, 6, 2)
    o1 = off1.copy()
    o1[2, 0, 1] = np.nan
    with pytest.raises(ValueError, match="off1 block 2 contains NaN"):
        block_banded_solve(diag, o1, off2, np.ones(12))
    with pytest.raises(ValueError, match="rhs contains NaN"):
        block_banded_solve(diag, off1, off2, np.full(12, np.inf))
    assert not bool(block_banded_solve_status(diag, o1, off2, np.ones(12)).ok)


def test_bad_shapes():
    with pytest.raises(ValueError, match="off1 must have shape"):
        block_banded_solve(np.ones((3, 2, 2)), np.ones((3, 2, 2)), np.ones((1, 2, 2)), np.ones(6))
    with pytest.raises(ValueError, match="rhs must have shape"):
        block_banded_solve(np.ones((3, 2, 2)), np.ones((2, 2, 2)), np.ones((1, 2, 2)), np.ones(5))


def test_vmap_over_1000_problems():
    rng = np.random.default_rng(5)
    n, k, nprob = 9, 3, 1000
    mats = [random_band(rng, n, k) for _ in range(nprob)]
    diag = np.stack([m[1] for m in mats])
    off1 = np.stack([m[2] for m in mats])
    off2 = np.stack([m[3] for m in mats])
    rhs = rng.standard_normal((nprob, n * k, 2))
    f = jax.jit(jax.vmap(block_banded_solve_status))
    sol = jax.block_until_ready(f(diag, off1, off2, rhs))
    assert bool(np.all(np.asarray(sol.ok)))
    ref = np.linalg.solve(np.stack([m[0] for m in mats]), rhs)
    err = np.linalg.norm(np.asarray(sol.x) - ref, axis=(1, 2)) / np.linalg.norm(ref, axis=(1, 2))
    assert err.max() <= 1e-9
    # one failing problem in the batch is flagged individually
    diag[17, 0] -= 1e4 * np.eye(k)
    sol = f(diag, off1, off2, rhs)
    ok = np.asarray(sol.ok)
    assert not ok[17] and ok.sum() == nprob - 1
