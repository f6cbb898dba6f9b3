"""Block-banded SPD solver (issue 5 item 1): dense agreement, gradients, input checking, vmap,
and each of the solver's paths (fused single solve, factor-once many right-hand sides, vmap)."""

from __future__ import annotations

import re

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from jax.test_util import check_grads

from mtex_jax.linalg import (
    block_banded_matvec,
    block_banded_solve,
    block_banded_solve_status,
    block_tridiag_cholesky,
    block_tridiag_solve,
    tridiag_solve_rows,
)
from mtex_jax.linalg._blocktridiag import (
    block_tridiag_factor,
    solve_rows_fused,
    solve_rows_plain,
    solve_rows_unbatched,
    substitute_rows,
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


# --------------------------------------------------------------------------------------------
# the three solver paths (fused single, factor-once for many right-hand sides, vmapped
# matrices), the public block-tridiagonal factor/solve, derivatives through each path
# --------------------------------------------------------------------------------------------


def random_tridiag(rng: np.random.Generator, n: int, b: int, ridge: float = 0.5):
    """Random SPD block-tridiagonal matrix: dense and its blocks ``(n, b, b)``, ``(n−1, b, b)``."""
    N = n * b
    A = ridge * np.eye(N)
    for j in range(n):
        lo = max(j - 1, 0)
        G = rng.standard_normal((b, (j + 1 - lo) * b))
        A[lo * b : (j + 1) * b, lo * b : (j + 1) * b] += G.T @ G
    D = np.array([A[i * b : (i + 1) * b, i * b : (i + 1) * b] for i in range(n)])
    S = np.array([A[(i + 1) * b : (i + 2) * b, i * b : (i + 1) * b] for i in range(n - 1)])
    return A, D, S.reshape(n - 1, b, b)


def rows_of(x: np.ndarray, n: int, b: int) -> np.ndarray:
    """Dense ``(n·b, m)`` -> rows ``(n, m, b)``."""
    return np.swapaxes(x.reshape(n, b, -1), 1, 2)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7])
@pytest.mark.parametrize(("b", "m"), [(4, 1), (6, 3), (6, 200), (40, 1)])
def test_tridiag_paths_match_dense(n, b, m):
    """Fused path ((b+m)·b ≤ 1000), factor-once path (larger), chunked trsm (b = 40)."""
    rng = np.random.default_rng(100 * n + b + m)
    A, D, S = random_tridiag(rng, n, b)
    R = rng.standard_normal((n * b, m))
    ref = np.linalg.solve(A, R)
    for fn in (solve_rows_unbatched, solve_rows_fused, solve_rows_plain, tridiag_solve_rows):
        x, ok, bad = jax.jit(fn)(D, S, rows_of(R, n, b))
        assert bool(ok) and int(bad) == -1
        x = np.swapaxes(np.asarray(x), 1, 2).reshape(n * b, m)
        assert np.linalg.norm(x - ref) <= 1e-9 * np.linalg.norm(ref), fn.__name__


@pytest.mark.parametrize("n", [1, 2, 5])
def test_public_block_tridiag_factor_and_solve(n):
    rng = np.random.default_rng(n)
    b = 40  # the inverse's triangular solve is split into several LAPACK calls
    A, D, S = random_tridiag(rng, n, b)
    fac = jax.jit(block_tridiag_cholesky)(D, S)
    assert bool(fac.ok) and int(fac.first_bad) == -1
    L = np.linalg.cholesky(A)
    for i in range(n):
        blk = L[i * b : (i + 1) * b, i * b : (i + 1) * b]
        np.testing.assert_allclose(np.asarray(fac.Linv[i]) @ blk, np.eye(b), atol=1e-10)
        if i + 1 < n:
            sub = L[(i + 1) * b : (i + 2) * b, i * b : (i + 1) * b]
            np.testing.assert_allclose(np.asarray(fac.M[i]), sub, atol=1e-10)
    R = rng.standard_normal((n, b, 3))
    x = np.asarray(jax.jit(block_tridiag_solve)(fac, R)).reshape(n * b, 3)
    ref = np.linalg.solve(A, R.reshape(n * b, 3))
    assert np.linalg.norm(x - ref) <= 1e-9 * np.linalg.norm(ref)


def _lapack_operand_shapes(jaxpr) -> list[tuple[str, tuple[int, ...]]]:
    """(primitive, operand shape) of every Cholesky / triangular solve, sub-jaxprs included."""
    out = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name in ("cholesky", "triangular_solve"):
            out.append((eqn.primitive.name, tuple(eqn.invars[0].aval.shape)))
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            out.extend(_lapack_operand_shapes(sub))
    return out


def test_vmap_over_rhs_factorises_once_and_matches():
    """Only the right-hand side batched: one unbatched factorisation, batch folded into rows."""
    rng = np.random.default_rng(7)
    n, b, nrhs = 6, 4, 37
    A, D, S = random_tridiag(rng, n, b)
    R = rng.standard_normal((nrhs, n, 1, b))
    f = jax.vmap(tridiag_solve_rows, in_axes=(None, None, 0))
    x, ok, bad = jax.jit(f)(D, S, R)
    assert x.shape == R.shape and bool(np.all(np.asarray(ok))) and np.all(np.asarray(bad) == -1)
    ref = np.linalg.solve(A, R.reshape(nrhs, n * b).T).T
    np.testing.assert_allclose(np.asarray(x).reshape(nrhs, n * b), ref, rtol=1e-10, atol=1e-12)
    shapes = _lapack_operand_shapes(jax.make_jaxpr(f)(D, S, R).jaxpr)
    assert shapes and all(len(s) == 2 for _, s in shapes), shapes  # no batched LAPACK call
    # the whole banded solve vmapped over right-hand sides, and over matrices (batched)
    Ab, Db, Sb = zip(*(random_tridiag(rng, n, b) for _ in range(3)), strict=True)
    xb, okb, _ = jax.jit(jax.vmap(tridiag_solve_rows))(np.stack(Db), np.stack(Sb), R[:3])
    assert okb.shape == (3,) and bool(np.all(np.asarray(okb)))
    for i in range(3):
        refb = np.linalg.solve(Ab[i], R[i].reshape(n * b))
        np.testing.assert_allclose(np.asarray(xb[i]).reshape(-1), refb, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("path", ["fused", "vmap-rhs", "many-rhs"])
def test_check_grads_every_path(path):
    rng = np.random.default_rng(11)
    n, b = 4, 3
    _, D, S = random_tridiag(rng, n, b, ridge=1.0)
    if path == "fused":
        R = rng.standard_normal((n, 2, b))
        f = lambda d, s, r: tridiag_solve_rows(d, s, r)[0]
    elif path == "vmap-rhs":
        R = rng.standard_normal((3, n, 1, b))
        f = lambda d, s, r: jax.vmap(tridiag_solve_rows, in_axes=(None, None, 0))(d, s, r)[0]
    else:
        R = rng.standard_normal((n, 120, b))  # (b + m)·b > 1000: factor-once path
        f = lambda d, s, r: tridiag_solve_rows(d, s, r)[0]
    sym = lambda d: 0.5 * (d + np.swapaxes(d, -1, -2))
    g = jax.jit(lambda d, s, r: f(0.5 * (d + jnp.swapaxes(d, -1, -2)), s, r))
    check_grads(g, (sym(D), S, R), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("path", ["fused", "many-rhs", "vmap-rhs"])
def test_non_pd_status_every_path(path):
    rng = np.random.default_rng(12)
    n, b = 6, 4
    _, D, S = random_tridiag(rng, n, b)
    D = D.copy()
    D[3] -= 1e3 * np.eye(b)
    m = 1 if path != "many-rhs" else 300
    R = rng.standard_normal((n, m, b))
    if path == "vmap-rhs":
        x, ok, bad = jax.vmap(tridiag_solve_rows, in_axes=(None, None, 0))(D, S, R[None])
        ok, bad = ok[0], bad[0]
    else:
        x, ok, bad = jax.jit(tridiag_solve_rows)(D, S, R)
    assert not bool(ok) and int(bad) == 3
    assert np.isfinite(np.asarray(x)).all()


def test_float32_follows_input():
    rng = np.random.default_rng(13)
    A, diag, off1, off2 = random_band(rng, 9, 3, ridge=1.0)
    rhs = rng.standard_normal(27)
    f32 = lambda a: np.asarray(a, np.float32)
    sol = jax.jit(block_banded_solve_status)(f32(diag), f32(off1), f32(off2), f32(rhs))
    assert sol.x.dtype == jnp.float32 and bool(sol.ok)
    ref = np.linalg.solve(A, rhs)
    assert np.linalg.norm(np.asarray(sol.x) - ref) <= 1e-3 * np.linalg.norm(ref)


def test_in_place_loops_copy_no_buffer():
    """Performance guard: the loops update their per-block buffer in place. A defensive copy
    of the whole buffer per step (which XLA inserts when a write is not ordered after the
    read it replaces) made the solve 3-10x slower."""
    n, b, m = 8, 6, 1
    rng = np.random.default_rng(14)
    _, D, S = random_tridiag(rng, n, b)
    R = rng.standard_normal((n, m, b))
    hlo = jax.jit(solve_rows_fused).lower(D, S, R).compile().as_text()
    assert hlo is not None and f"f64[{n},{2 * b + m},{b}]" in hlo  # the buffer exists
    assert not re.search(rf"f64\[{n},{2 * b + m},{b}\]\{{[0-9,]+\}} copy\(", hlo)
    fac = block_tridiag_factor(jnp.asarray(D), jnp.asarray(S))
    Rm = rng.standard_normal((n, 50, b))
    hlo = jax.jit(substitute_rows).lower(fac.Linv, fac.M, Rm).compile().as_text()
    assert hlo is not None and f"f64[{n},50,{b}]" in hlo
    # the input (a jit parameter) may be copied once into the loop buffer, not per step
    assert len(re.findall(rf"f64\[{n},50,{b}\]\{{[0-9,]+\}} copy\(", hlo)) <= 1
