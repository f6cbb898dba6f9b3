"""The semi-Markov forward algorithm (marginal likelihood, design §10.1) against brute-force
enumeration of every segmentation and labelling on tiny problems."""

from __future__ import annotations

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.special import logsumexp

from dp_problems import compositions, small_textons
from mtex_jax.texture import (
    forward_log_likelihood,
    log_likelihood,
    segment,
    segment_log_likelihood,
    segment_scores,
)
from paper_settings import UNTIED


def _data(rng, T, n_t, D=4):
    pieces = [
        np.stack([np.sin(0.2 * (j % n_t + 1) * np.arange(4) + d) for d in range(D)], 1) + j % n_t
        for j in range(T // 4 + 1)
    ]
    return np.concatenate(pieces)[:T] + 0.2 * rng.normal(size=(T, D))


def brute_force(textons, log_M, log_pi, Y, tmin, tmax, log_dur=None):
    """logsumexp over every segmentation and labelling, each segment scored by the direct
    per-segment likelihood (not the prefix sums the DP uses)."""
    T, n_t = Y.shape[0], log_pi.shape[0]
    tmax = T if tmax is None else tmax
    cache: dict = {}

    def seg(b, L, i):
        if (b, L, i) not in cache:
            val = float(segment_log_likelihood(textons[i], Y[b : b + L]))
            cache[(b, L, i)] = val + (0.0 if log_dur is None else log_dur[i, L - tmin])
        return cache[(b, L, i)]

    terms, best = [], -np.inf
    for comp in compositions(T, tmin, tmax):
        starts = np.concatenate([[0], np.cumsum(comp)[:-1]]).astype(int)
        for labels in itertools.product(range(n_t), repeat=len(comp)):
            s = log_pi[labels[0]] + sum(log_M[a, b] for a, b in itertools.pairwise(labels))
            s += sum(seg(b, L, i) for b, L, i in zip(starts, comp, labels, strict=True))
            terms.append(s)
            best = max(best, s)
    return float(logsumexp(terms)), best, len(terms)


def _problem(T, n_t, seed):
    rng = np.random.default_rng(seed)
    tex = small_textons(rng, n_t)
    log_M = np.log(rng.dirichlet(np.ones(n_t), size=n_t))
    log_pi = np.log(rng.dirichlet(np.ones(n_t)))
    return tex, log_M, log_pi, _data(rng, T, n_t)


@pytest.mark.parametrize(
    ("T", "n_t", "tmin", "tmax"),
    [(9, 2, 3, 4), (12, 3, 3, 6), (14, 2, 4, 7), (13, 3, 3, None), (10, 1, 3, 10), (11, 2, 3, 3)],
)
def test_forward_equals_brute_force(T, n_t, tmin, tmax):
    tex, log_M, log_pi, Y = _problem(T, n_t, T * 10 + n_t)
    want, best, n_paths = brute_force(tex, log_M, log_pi, Y, tmin, tmax)
    got = float(log_likelihood(tex, log_M, log_pi, jnp.asarray(Y), tmin, tmax))
    if not np.isfinite(want):  # no segmentation of T fits (e.g. T=11 with tmin=tmax=3)
        assert got == -np.inf
        return
    assert n_paths > 1
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-8 * max(1.0, abs(want)))
    viterbi = float(segment(tex, log_M, log_pi, jnp.asarray(Y), tmin, tmax).score)
    np.testing.assert_allclose(viterbi, best, atol=1e-8 * max(1.0, abs(best)))
    assert got >= viterbi - 1e-9


def test_forward_with_durations_equals_brute_force():
    T, n_t, tmin, tmax = 13, 2, 3, 6
    tex, log_M, log_pi, Y = _problem(T, n_t, 7)
    rng = np.random.default_rng(3)
    dur = np.log(rng.dirichlet(np.ones(tmax - tmin + 1), size=n_t))
    want, _, _ = brute_force(tex, log_M, log_pi, Y, tmin, tmax, dur)
    got = float(log_likelihood(tex, log_M, log_pi, jnp.asarray(Y), tmin, tmax, log_durations=dur))
    np.testing.assert_allclose(got, want, atol=1e-8 * abs(want))
    # flat durations of probability 1 are the paper's model
    flat = float(log_likelihood(tex, log_M, log_pi, jnp.asarray(Y), tmin, tmax))
    zero = np.zeros((n_t, tmax - tmin + 1))
    same = log_likelihood(tex, log_M, log_pi, jnp.asarray(Y), tmin, tmax, log_durations=zero)
    np.testing.assert_allclose(float(same), flat, rtol=1e-12)


def test_single_segment_is_logsumexp_of_initial_plus_segment():
    """With tmin = tmax = T there is one segment: log p = logsumexp_i(log π_i + s_i(Y))."""
    T, n_t = 17, 3
    tex, log_M, log_pi, Y = _problem(T, n_t, 11)
    got = float(log_likelihood(tex, log_M, log_pi, jnp.asarray(Y), T, T))
    seg = [float(segment_log_likelihood(tex[i], jnp.asarray(Y))) for i in range(n_t)]
    np.testing.assert_allclose(got, logsumexp(log_pi + np.array(seg)), rtol=1e-11)


def test_long_windows_are_chunked_exactly():
    """tmax = None on a longer sequence: the window is reduced in several chunks (small
    budget forced), which must agree with one chunk."""
    import mtex_jax.texture._segmentation.recursion as fwd

    T, n_t, tmin = 40, 2, 3
    tex, log_M, log_pi, Y = _problem(T, n_t, 5)
    one = float(log_likelihood(tex, log_M, log_pi, jnp.asarray(Y), tmin, None))
    old = fwd._GATHER_BUDGET
    try:
        fwd._GATHER_BUDGET = 16  # Wc = 16 // (3 * 2) = 2 starts per chunk
        many = float(log_likelihood(tex, log_M, log_pi, jnp.asarray(Y), tmin, None))
    finally:
        fwd._GATHER_BUDGET = old
    np.testing.assert_allclose(many, one, rtol=1e-12)
    viterbi = float(segment(tex, log_M, log_pi, jnp.asarray(Y), tmin, None).score)
    assert one >= viterbi


def test_gradients_in_float64():
    T, n_t, tmin, tmax = 10, 2, 3, 5
    tex, log_M, log_pi, Y = _problem(T, n_t, 2)

    def f(y):
        sc = segment_scores(tex, y)
        return forward_log_likelihood(sc, log_M, log_pi, jnp.asarray(T), tmin, tmax)

    check_grads(f, (jnp.asarray(Y),), order=1, modes=["rev"], atol=1e-5, rtol=1e-5)
    g = jax.grad(f)(jnp.asarray(Y))
    assert bool(jnp.all(jnp.isfinite(g)))


def test_padding_is_ignored_and_no_retrace():
    """A sequence padded to a longer T with n_valid set scores as the unpadded one, and new
    data of the same shapes does not compile again."""
    T, n_t, tmin, tmax = 12, 2, 3, 5
    tex, log_M, log_pi, Y = _problem(T, n_t, 9)
    want = float(log_likelihood(tex, log_M, log_pi, jnp.asarray(Y), tmin, tmax))
    Yp = np.concatenate([Y, Y[:5] + 3.0])
    sc = segment_scores(tex, jnp.asarray(Yp))
    got = forward_log_likelihood(sc, log_M, log_pi, jnp.asarray(T), tmin, tmax)
    np.testing.assert_allclose(float(got), want, rtol=1e-12)

    counted = eqx.debug.assert_max_traces(
        lambda s: forward_log_likelihood(s, log_M, log_pi, jnp.asarray(T), tmin, tmax),
        max_traces=1,
    )
    run = jax.jit(counted)
    run(sc)
    run(segment_scores(tex, jnp.asarray(Yp[::-1].copy())))


def test_float32_smoke():
    T, n_t, tmin, tmax = 12, 2, 3, 5
    tex, log_M, log_pi, Y = _problem(T, n_t, 4)
    want = float(log_likelihood(tex, log_M, log_pi, jnp.asarray(Y), tmin, tmax))
    tex32 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), tex)
    got = log_likelihood(
        tex32,
        jnp.asarray(log_M, jnp.float32),
        jnp.asarray(log_pi, jnp.float32),
        jnp.asarray(Y, jnp.float32),
        tmin,
        tmax,
    )
    assert got.dtype == jnp.float32
    np.testing.assert_allclose(float(got), want, rtol=1e-4)


def test_bad_input():
    tex, log_M, log_pi, Y = _problem(12, 2, 1)
    with pytest.raises(ValueError, match="log_durations"):
        log_likelihood(tex, log_M, log_pi, jnp.asarray(Y), 3, 5, log_durations=np.zeros((2, 2)))
    with pytest.raises(ValueError, match="shorter than tmin"):
        log_likelihood(tex, log_M, log_pi, jnp.asarray(Y[:4]), 5, 6)
    with pytest.raises(ValueError, match="log_M"):
        log_likelihood(tex, log_M[:1], log_pi, jnp.asarray(Y), 3, 5)
    with pytest.raises(ValueError, match="Y must"):
        log_likelihood(tex, log_M, log_pi, jnp.asarray(Y[0]), 3, 5)


@pytest.mark.slow  # the default run's budget (about 15 min); CI runs it after
def test_marginal_at_least_best_path_on_held_out_salsa(cmu_motions):
    """On real held-out clips the marginal log-likelihood is >= the best path's score, and the
    mean figures are the totals over the number of frames."""
    import mtex_jax as mj

    train = [m.resample(30.0) for m in cmu_motions[:3]]
    held = [m.resample(30.0)[:600] for m in cmu_motions[11:13]]
    cfg = mj.LearnConfig(
        tmin=30, tmax=90, state_dim=8, fps=30.0, threshold=0.3, max_iter=2, **UNTIED
    )
    tex = mj.learn(train, cfg)
    for m in held:
        ll = tex.log_likelihood(m)
        best = tex.best_path_log_likelihood(m)
        assert np.isfinite(ll) and np.isfinite(best)
        assert ll >= best - 1e-6 * abs(best)
        T = m.n_frames
        np.testing.assert_allclose(tex.log_likelihood(m, mean=True), ll / T, rtol=1e-12)
        np.testing.assert_allclose(float(tex.segment(m).score), best, rtol=1e-12)


def test_fallback_paths_agree_with_brute_force(monkeypatch):
    """The exact fallbacks (gathered windows; the N×N logsumexp of the transition) give the
    brute-force value, also with transition probabilities of e^-2000 (shifted per column)."""
    import mtex_jax.texture._segmentation.recursion as fwd

    T, n_t, tmin, tmax = 12, 3, 3, 6
    tex, log_M, log_pi, Y = _problem(T, n_t, 21)
    log_M = log_M.copy()
    log_M[0, 1] = log_M[2, 1] = -2000.0
    log_M[1, 1] = -2500.0  # column 1: every entry e^-2000 or below
    want, _, _ = brute_force(tex, log_M, log_pi, Y, tmin, tmax)
    fast = float(log_likelihood(tex, log_M, log_pi, jnp.asarray(Y), tmin, tmax))
    np.testing.assert_allclose(fast, want, atol=1e-8 * abs(want))
    monkeypatch.setattr(fwd, "_FORCE_EXACT", True)
    jax.clear_caches()
    slow = float(log_likelihood(tex, log_M, log_pi, jnp.asarray(Y), tmin, tmax))
    np.testing.assert_allclose(slow, want, atol=1e-8 * abs(want))
