"""Texton paths: Dijkstra vs scipy, path of a given length vs brute force, random walks."""

from __future__ import annotations

import itertools

import jax
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.sparse.csgraph import dijkstra

import mtex_jax as mj


def random_markov(rng: np.random.Generator, n: int, sparsity: float = 0.0) -> np.ndarray:
    M = rng.gamma(0.5, size=(n, n)) * (rng.random((n, n)) >= sparsity)
    M[np.arange(n), np.arange(n)] += 0.1  # every row has mass, and no off-diagonal M_ij = 1
    return M / M.sum(axis=1, keepdims=True)


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 12), st.floats(0.0, 0.7), st.integers(0, 2**31 - 1))
def test_shortest_path_equals_scipy_dijkstra(n, sparsity, seed):
    rng = np.random.default_rng(seed)
    M = random_markov(rng, n, sparsity)
    W = np.where(M > 0, -np.log(np.where(M > 0, M, 1.0)), np.inf)
    np.fill_diagonal(W, np.inf)
    # scipy's dense input treats 0 as "no edge"; every off-diagonal weight here is > 0
    # because each row also has mass on its diagonal
    dist, pred = dijkstra(np.where(np.isfinite(W), W, 0.0), directed=True, return_predecessors=True)
    for u in range(n):
        for v in range(n):
            if u != v and not np.isfinite(dist[u, v]):
                with pytest.raises(ValueError, match="not reachable"):
                    mj.texture.shortest_path(M, u, v)
                continue
            p = mj.texture.shortest_path(M, u, v)
            assert p[0] == u and p[-1] == v and len(set(p.tolist())) == len(p)
            np.testing.assert_allclose(
                mj.texture.path_cost(M, p), dist[u, v], rtol=1e-12, atol=1e-12
            )
            # same path as scipy's predecessor tree (ties have probability zero here)
            ref = [v]
            while ref[-1] != u:
                ref.append(int(pred[u, ref[-1]]))
            assert p.tolist() == ref[::-1]


def test_shortest_path_self_repeats_follow_the_self_transition_probability():
    rng = np.random.default_rng(0)
    M = random_markov(rng, 4)
    M[1, :] = [0.1, 0.6, 0.3, 0.0]
    M[0, :] = [0.2, 0.7, 0.05, 0.05]
    base = mj.texture.shortest_path(M, 0, 2)
    assert base.tolist() == [0, 1, 2]
    reps = {0: [], 1: [], 2: []}
    for s in range(3000):
        p = mj.texture.shortest_path(M, 0, 2, key=jax.random.key(s))
        assert p[0] == 0 and p[-1] == 2
        for lab in reps:
            reps[lab].append(int(np.sum(p == lab)) - 1)
    for lab in reps:  # E[extra repeats] of a geometric law = M_ii / (1 − M_ii)
        m = M[lab, lab] / (1 - M[lab, lab])
        se = np.sqrt(M[lab, lab]) / (1 - M[lab, lab]) / np.sqrt(3000)
        assert abs(np.mean(reps[lab]) - m) < 5 * se + 1e-3, (lab, np.mean(reps[lab]), m)


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 4), st.integers(1, 5), st.floats(0.0, 0.6), st.integers(0, 2**31 - 1))
def test_path_of_length_equals_brute_force(n, L, sparsity, seed):
    rng = np.random.default_rng(seed)
    M = random_markov(rng, n, sparsity)
    with np.errstate(divide="ignore"):
        logM = np.log(M)
    for u, v in itertools.product(range(n), repeat=2):
        best, arg = -np.inf, None
        for mid in itertools.product(range(n), repeat=max(L - 2, 0)):
            p = (u,) if L == 1 else (u, *mid, v)
            if L == 1 and u != v:
                break
            s = sum(logM[a, b] for a, b in itertools.pairwise(p))
            if s > best:
                best, arg = s, p
        if not np.isfinite(best):
            with pytest.raises(ValueError):
                mj.texture.path_of_length(M, u, v, L)
            continue
        p, score = mj.texture.path_of_length(M, u, v, L)
        assert len(p) == L and p[0] == u and p[-1] == v
        np.testing.assert_allclose(score, best, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(-mj.texture.path_cost(M, p), best, rtol=1e-12, atol=1e-12)
        assert arg is not None


def test_random_path_transition_frequencies_match_M():
    rng = np.random.default_rng(3)
    M = random_markov(rng, 5)
    p = mj.texture.random_path(jax.random.key(0), M, 40_000, start=2)
    assert p[0] == 2 and p.dtype == np.int64
    counts = np.zeros((5, 5))
    np.add.at(counts, (p[:-1], p[1:]), 1)
    freq = counts / counts.sum(axis=1, keepdims=True)
    se = np.sqrt(M * (1 - M) / counts.sum(axis=1, keepdims=True))
    assert np.all(np.abs(freq - M) <= 5 * se + 1e-3)
    # zero-probability transitions never happen
    M2 = M.copy()
    M2[:, 4] = 0
    M2 /= M2.sum(axis=1, keepdims=True)
    p2 = mj.texture.random_path(jax.random.key(1), M2, 2000, start=0)
    assert not np.any(p2[1:] == 4)


def test_path_errors():
    M = np.full((3, 3), 1 / 3)
    with pytest.raises(ValueError, match="not a texton index"):
        mj.texture.shortest_path(M, 0, 3)
    with pytest.raises(ValueError, match="square"):
        mj.texture.shortest_path(np.ones((2, 3)) / 3, 0, 1)
    with pytest.raises(ValueError, match="sums to"):
        mj.texture.random_path(jax.random.key(0), np.ones((3, 3)), 4)
    with pytest.raises(ValueError, match="negative or non-finite"):
        mj.texture.path_of_length(np.array([[np.nan, 1.0], [0.5, 0.5]]), 0, 1, 3)
    with pytest.raises(ValueError, match="L must be"):
        mj.texture.path_of_length(M, 0, 1, 0)
    with pytest.raises(ValueError, match="cannot go"):
        mj.texture.path_of_length(M, 0, 1, 1)
    with pytest.raises(TypeError, match="n_textons"):
        mj.texture.random_path(jax.random.key(0), M, 2.5)  # type: ignore[arg-type]
    disconnected = np.array([[1.0, 0.0], [0.5, 0.5]])
    with pytest.raises(ValueError, match="not reachable"):
        mj.texture.shortest_path(disconnected, 0, 1)
    with pytest.raises(ValueError, match="no path of exactly"):
        mj.texture.path_of_length(disconnected, 0, 1, 4)


def test_self_repeats_are_bounded_for_a_texton_that_always_follows_itself():
    """One texton with M = [[1]] (a texture learned on little data): the repeats stop at the
    documented bound instead of allocating terabytes."""
    from mtex_jax.texture import MAX_SELF_REPEATS, shortest_path

    path = shortest_path(np.ones((1, 1)), 0, 0, key=jax.random.key(0))
    assert path.tolist() == [0] * (1 + MAX_SELF_REPEATS)
