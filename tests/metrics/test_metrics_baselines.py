"""Baseline densities (AR(2), constant velocity, hold last) and the texture's one-step
prediction, against numpy/scipy re-derivations."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import multivariate_normal

from mtex_jax.metrics import (
    constant_velocity,
    fit_ar2,
    hold_last,
    prediction_error,
    texture_predict,
)
from shared_textures import salsa30_texture


def _ar2_data(rng, T, D, n_seq=3):
    A1 = 0.5 * np.eye(D) + 0.1 * rng.normal(size=(D, D))
    A2 = -0.3 * np.eye(D) + 0.05 * rng.normal(size=(D, D))
    c = rng.normal(size=D)
    L = np.tril(0.2 * rng.normal(size=(D, D)), -1) + np.diag(rng.uniform(0.2, 0.5, D))
    seqs = []
    for _ in range(n_seq):
        y = np.zeros((T, D))
        y[:2] = rng.normal(size=(2, D))
        for t in range(2, T):
            y[t] = A1 @ y[t - 1] + A2 @ y[t - 2] + c + L @ rng.normal(size=D)
        seqs.append(y)
    return seqs, (A1, A2, c, L @ L.T)


def test_ar2_fit_equals_least_squares_and_recovers_the_system():
    rng = np.random.default_rng(0)
    seqs, (A1, A2, _, Sigma) = _ar2_data(rng, 4000, 3)
    m = fit_ar2(seqs, ridge=0.0, floor=1e-12)
    # independent: numpy lstsq on the same frames
    Z = np.concatenate([np.c_[y[1:-1], y[:-2], np.ones(len(y) - 2)] for y in seqs])
    T = np.concatenate([y[2:] for y in seqs])
    W, *_ = np.linalg.lstsq(Z, T, rcond=None)
    np.testing.assert_allclose(np.asarray(m.A1), W[:3].T, atol=1e-9)
    np.testing.assert_allclose(np.asarray(m.A2), W[3:6].T, atol=1e-9)
    np.testing.assert_allclose(np.asarray(m.c), W[6], atol=1e-9)
    R = T - Z @ W
    np.testing.assert_allclose(np.asarray(m.chol @ m.chol.T), R.T @ R / len(R), atol=1e-9)
    # and the generating system, to sampling error
    np.testing.assert_allclose(np.asarray(m.A1), A1, atol=0.05)
    np.testing.assert_allclose(np.asarray(m.A2), A2, atol=0.05)
    np.testing.assert_allclose(np.asarray(m.chol @ m.chol.T), Sigma, atol=0.02)


def test_log_likelihood_equals_scipy():
    rng = np.random.default_rng(1)
    seqs, _ = _ar2_data(rng, 300, 4)
    y = seqs[0][:50]
    for model in (fit_ar2(seqs), constant_velocity(seqs), hold_last(seqs)):
        S = np.asarray(model.chol @ model.chol.T)
        S0 = np.asarray(model.chol0 @ model.chol0.T)
        pred = y[1:-1] @ np.asarray(model.A1).T + y[:-2] @ np.asarray(model.A2).T
        pred = pred + np.asarray(model.c)
        want = multivariate_normal(np.asarray(model.m0), S0).logpdf(np.r_[y[0], y[1]])
        want += multivariate_normal(np.zeros(4), S).logpdf(y[2:] - pred).sum()
        np.testing.assert_allclose(model.log_likelihood(y), want, rtol=1e-10)
        np.testing.assert_allclose(model.log_likelihood(y, mean=True), want / 50, rtol=1e-10)
        assert model.frame_log_density(y).shape == (49,)


def test_per_frame_log_likelihood_is_the_chain_rule_against_scipy():
    """``per_frame=True``: ``log p(y_0)``, ``log p(y_1 | y_0)`` (the first-pair Gaussian's
    marginal and conditional), then the one-step densities, each against scipy on a tiny
    input; the values sum to the total."""
    rng = np.random.default_rng(3)
    seqs, _ = _ar2_data(rng, 200, 3)
    y = seqs[1][:6]
    D = 3
    for model in (fit_ar2(seqs), hold_last(seqs)):
        S = np.asarray(model.chol @ model.chol.T)
        S0 = np.asarray(model.chol0 @ model.chol0.T)
        m0 = np.asarray(model.m0)
        A1, A2, c = (np.asarray(a) for a in (model.A1, model.A2, model.c))
        want = [multivariate_normal(m0[:D], S0[:D, :D]).logpdf(y[0])]
        gain = S0[D:, :D] @ np.linalg.inv(S0[:D, :D])  # y_1 | y_0
        cond = multivariate_normal(m0[D:] + gain @ (y[0] - m0[:D]), S0[D:, D:] - gain @ S0[:D, D:])
        want.append(cond.logpdf(y[1]))
        for t in range(2, len(y)):
            want.append(multivariate_normal(A1 @ y[t - 1] + A2 @ y[t - 2] + c, S).logpdf(y[t]))
        got = model.log_likelihood(y, per_frame=True)
        assert isinstance(got, np.ndarray) and got.shape == (6,)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(got.sum(), model.log_likelihood(y), rtol=1e-12)
        with pytest.raises(ValueError, match="exclude each other"):
            model.log_likelihood(y, per_frame=True, mean=True)


def test_fixed_predictors():
    rng = np.random.default_rng(2)
    seqs, _ = _ar2_data(rng, 100, 2)
    y = seqs[1]
    np.testing.assert_allclose(
        np.asarray(constant_velocity(seqs).predict(y)), 2 * y[1:-1] - y[:-2], atol=1e-12
    )
    np.testing.assert_allclose(np.asarray(hold_last(seqs).predict(y)), y[1:-1], atol=1e-12)
    assert prediction_error(y[1:-1], y[2:]) == pytest.approx(np.mean((y[1:-1] - y[2:]) ** 2))
    # the fitted AR(2) predicts its own process better than the fixed predictors
    ar = fit_ar2(seqs)
    e_ar = prediction_error(ar.predict(y), y[2:])
    assert e_ar < prediction_error(hold_last(seqs).predict(y), y[2:])
    assert ar.log_likelihood(y) > constant_velocity(seqs).log_likelihood(y)


def test_float32_follows_input():
    rng = np.random.default_rng(3)
    seqs, _ = _ar2_data(rng, 200, 3)
    m = fit_ar2([s.astype(np.float32) for s in seqs])
    assert m.A1.dtype == jnp.float32
    ll = m.log_likelihood(seqs[0].astype(np.float32))
    np.testing.assert_allclose(ll, fit_ar2(seqs).log_likelihood(seqs[0]), rtol=1e-3)


def test_bad_input():
    with pytest.raises(ValueError, match="non-empty"):
        fit_ar2([])
    with pytest.raises(ValueError, match=">= 3"):
        fit_ar2([np.zeros((2, 3))])
    with pytest.raises(ValueError, match="NaN"):
        fit_ar2([np.full((5, 2), np.nan)])
    with pytest.raises(ValueError, match="dimension"):
        fit_ar2([np.zeros((5, 2)), np.zeros((5, 3))])
    m = fit_ar2([np.random.default_rng(0).normal(size=(20, 2))])
    with pytest.raises(ValueError, match=r"\(T, 2\)"):
        m.log_likelihood(np.zeros((5, 3)))
    with pytest.raises(ValueError, match="ridge"):
        fit_ar2([np.zeros((5, 2))], ridge=-1.0)


def test_texture_prediction_equals_numpy(cmu_dir, cmu_motions):
    # a paper texture learned from the first three clips at 30 Hz (shared with test_evaluate)
    tex = salsa30_texture(cmu_dir)
    clip = cmu_motions[12].resample(30.0)[:200]
    pred, labels = texture_predict(tex, clip)
    Y = np.asarray(tex.feature_map.encode(clip))
    assert pred.shape == (198, Y.shape[1]) and labels.shape == (200,)
    for t in (2, 50, 137, 199):
        i = labels[t - 1]
        tx = jax.tree.map(lambda a, i=i: np.asarray(a[i]), tex.textons)
        x1 = tx.C.T @ (Y[t - 1] - tx.mu)
        x2 = tx.C.T @ (Y[t - 2] - tx.mu)
        want = tx.mu + tx.C @ (tx.A1 @ x1 + tx.A2 @ x2 + tx.d)
        np.testing.assert_allclose(np.asarray(pred[t - 2]), want, atol=1e-10)
