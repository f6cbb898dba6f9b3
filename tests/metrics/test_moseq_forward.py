"""The likelihoods of the jax-moseq row (``benchmarks/quality/quality_moseq.py``): the HMM forward
algorithm against enumeration of every state path, the AR emission densities against scipy,
and the row's ``reason`` when jax-moseq is missing. jax-moseq itself is not needed."""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import multivariate_normal

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks" / "quality"))
from quality_moseq import (
    ar_frame_loglik,
    hmm_forward,
    hmm_forward_frames,
    marginal_loglik,
    moseq_row,
    score,
)


def _brute_force(log_lik, pi, p0):
    T, K = log_lik.shape
    total = 0.0
    for z in itertools.product(range(K), repeat=T):
        p = p0[z[0]] * np.exp(log_lik[0, z[0]])
        for t in range(1, T):
            p *= pi[z[t - 1], z[t]] * np.exp(log_lik[t, z[t]])
        total += p
    return np.log(total)


@pytest.mark.parametrize("K,T", [(1, 4), (2, 6), (3, 5)])
def test_forward_equals_enumeration(K, T):
    rng = np.random.default_rng(K * 10 + T)
    log_lik = rng.normal(scale=2.0, size=(T, K))
    pi = rng.dirichlet(np.ones(K), size=K)
    p0 = rng.dirichlet(np.ones(K))
    assert hmm_forward(log_lik, pi, p0) == pytest.approx(_brute_force(log_lik, pi, p0), rel=1e-12)
    uniform = np.full(K, 1.0 / K)
    assert hmm_forward(log_lik, pi) == pytest.approx(_brute_force(log_lik, pi, uniform), rel=1e-12)


def test_forward_with_zero_transitions_and_large_magnitudes():
    """Zero entries of ``pi`` (a sticky HDP draw can underflow) and emission log-densities
    far from 0 (hundreds per frame at D = 54) are handled without overflow."""
    rng = np.random.default_rng(1)
    pi = np.array([[0.9, 0.1, 0.0], [0.0, 0.5, 0.5], [0.3, 0.0, 0.7]])
    log_lik = rng.normal(size=(5, 3)) - 400.0
    p0 = np.full(3, 1 / 3)
    got = hmm_forward(log_lik, pi)
    assert np.isfinite(got)
    assert got == pytest.approx(_brute_force(log_lik + 400.0, pi, p0) - 5 * 400.0, rel=1e-12)


def test_ar_emissions_match_scipy_in_jax_moseq_layout():
    """``Ab`` acts on ``[y_{t-2}, y_{t-1}, 1]`` (jax-moseq's ``get_lags`` order)."""
    rng = np.random.default_rng(2)
    K, D, L, T = 3, 2, 2, 7
    y = rng.normal(size=(T, D))
    Ab = rng.normal(scale=0.5, size=(K, D, L * D + 1))
    A = rng.normal(size=(K, D, D))
    Q = A @ A.transpose(0, 2, 1) + 0.5 * np.eye(D)
    got = ar_frame_loglik(y, Ab, Q)
    assert got.shape == (T - L, K)
    for k in range(K):
        A2, A1, b = Ab[k][:, :D], Ab[k][:, D : 2 * D], Ab[k][:, -1]
        for t in range(L, T):
            mean = A1 @ y[t - 1] + A2 @ y[t - 2] + b
            want = multivariate_normal(mean, Q[k]).logpdf(y[t])
            assert got[t - L, k] == pytest.approx(want, rel=1e-12)


def test_marginal_with_one_state_is_the_ar_density():
    rng = np.random.default_rng(3)
    D = 3
    ys = [rng.normal(size=(n, D)) for n in (5, 9)]
    Ab = rng.normal(scale=0.3, size=(1, D, 2 * D + 1))
    Q = np.eye(D)[None] * 0.7
    got = marginal_loglik(ys, Ab, Q, np.ones((1, 1)))
    want = [ar_frame_loglik(y, Ab, Q).sum() for y in ys]
    np.testing.assert_allclose(got, want, rtol=1e-12)


def test_frame_terms_are_prefix_differences_and_predictions_are_the_prior_of_each_frame():
    """``frame[t] = log p(y_{0..t}) − log p(y_{0..t−1})`` by enumeration of each prefix, and
    ``predicted[t] = p(z_t | y_{<t})`` by enumeration of the paths to frame t − 1."""
    rng = np.random.default_rng(4)
    T, K = 5, 3
    log_lik = rng.normal(scale=2.0, size=(T, K))
    pi = rng.dirichlet(np.ones(K), size=K)
    p0 = rng.dirichlet(np.ones(K))
    frame, predicted = hmm_forward_frames(log_lik, pi, p0)
    prefix = [_brute_force(log_lik[: t + 1], pi, p0) for t in range(T)]
    np.testing.assert_allclose(np.cumsum(frame), prefix, rtol=1e-12)
    np.testing.assert_allclose(predicted[0], p0, rtol=1e-12)
    for t in range(1, T):
        # p(z_t = j | y_{<t}) ∝ Σ over paths to t−1 of their weight times pi[z_{t−1}, j]
        w = np.zeros(K)
        for z in itertools.product(range(K), repeat=t):
            p = p0[z[0]] * np.exp(log_lik[0, z[0]])
            for s in range(1, t):
                p *= pi[z[s - 1], z[s]] * np.exp(log_lik[s, z[s]])
            w += p * pi[z[-1]]
        np.testing.assert_allclose(predicted[t], w / w.sum(), rtol=1e-10)


def test_score_with_one_state_is_the_ar_model():
    """One state: the prediction is the AR mean, the frame terms its log-densities."""
    rng = np.random.default_rng(5)
    D = 2
    ys = [rng.normal(size=(n, D)) for n in (6, 8)]
    Ab = rng.normal(scale=0.3, size=(1, D, 2 * D + 1))
    Q = np.eye(D)[None] * 0.5
    got = score(ys, Ab, Q, np.ones((1, 1)))
    fr = np.concatenate([ar_frame_loglik(y, Ab, Q)[:, 0] for y in ys])
    assert got["frames"] == 4 + 6
    assert got["per_frame"] == pytest.approx(fr.mean(), rel=1e-12)
    assert got["median_frame"] == pytest.approx(np.median(fr), rel=1e-12)
    assert got["worst_frame"] == pytest.approx(fr.min(), rel=1e-12)
    A2, A1, b = Ab[0][:, :D], Ab[0][:, D : 2 * D], Ab[0][:, -1]
    err = [y[t] - (A1 @ y[t - 1] + A2 @ y[t - 2] + b) for y in ys for t in range(2, len(y))]
    assert got["prediction_mse"] == pytest.approx(np.mean(np.square(err)), rel=1e-12)


def test_row_says_why_without_jax_moseq(monkeypatch):
    monkeypatch.setitem(sys.modules, "jax_moseq", None)  # import fails as if not installed
    ys = [np.zeros((10, 2))]
    row = moseq_row(ys, ys, iters=1)
    assert row["package"] == "jax-moseq"
    assert "cannot be imported" in row["reason"]


def test_row_says_why_when_the_other_interpreter_fails(tmp_path):
    ys = [np.zeros((10, 2))]
    row = moseq_row(ys, ys, iters=1, python=tmp_path / "no-such-python")
    assert "cannot run" in row["reason"]
