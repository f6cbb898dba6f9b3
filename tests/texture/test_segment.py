"""The segmentation DP against brute-force enumeration on tiny problems."""

from __future__ import annotations

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dp_problems import compositions, small_textons
from mtex_jax.texture import segment, segment_log_likelihood
from mtex_jax.texture._scoring.packing import pack_clips
from mtex_jax.texture._segmentation.segment import segment_batch


def brute_force(textons, log_M, log_pi, Y, tmin, tmax):
    T = Y.shape[0]
    n_t = log_pi.shape[0]
    cache = {}

    def seg(b, L, i):
        key = (b, L, i)
        if key not in cache:
            cache[key] = float(segment_log_likelihood(textons[i], Y[b : b + L]))
        return cache[key]

    best, arg = -np.inf, None
    for comp in compositions(T, tmin, tmax):
        starts = np.concatenate([[0], np.cumsum(comp)[:-1]])
        for labels in itertools.product(range(n_t), repeat=len(comp)):
            s = log_pi[labels[0]] + sum(log_M[a, b] for a, b in itertools.pairwise(labels))
            s += sum(seg(int(b), L, i) for b, L, i in zip(starts, comp, labels, strict=True))
            if s > best:
                best, arg = (
                    s,
                    [(int(b), L, i) for b, L, i in zip(starts, comp, labels, strict=True)],
                )
    return best, arg


@pytest.mark.parametrize(
    ("T", "n_t", "tmin", "tmax"),
    [(9, 2, 3, 4), (12, 3, 3, 6), (14, 2, 4, 7), (13, 3, 3, None), (10, 1, 3, 10)],
)
def test_dp_equals_brute_force(T, n_t, tmin, tmax):
    rng = np.random.default_rng(T * 10 + n_t)
    tex = small_textons(rng, n_t)
    M = rng.dirichlet(np.ones(n_t), size=n_t)
    pi = rng.dirichlet(np.ones(n_t))
    log_M, log_pi = np.log(M), np.log(pi)
    # data: pieces of the textons' own training-like signals so several labels compete
    Y = np.concatenate(
        [
            np.stack([np.sin(0.2 * (j % n_t + 1) * np.arange(4) + d) for d in range(4)], 1)
            + j % n_t
            for j in range(T // 4 + 1)
        ]
    )[:T] + 0.2 * rng.normal(size=(T, 4))
    seg = segment(tex, log_M, log_pi, jnp.asarray(Y), tmin, tmax)
    best, arg = brute_force(tex, log_M, log_pi, Y, tmin, T if tmax is None else tmax)
    assert np.isfinite(best)
    np.testing.assert_allclose(float(seg.score), best, rtol=1e-9, atol=1e-9)
    assert seg.to_list() == arg


def test_bounded_dp_with_large_tmax_equals_unbounded():
    rng = np.random.default_rng(3)
    tex = small_textons(rng, 3)
    M = rng.dirichlet(np.ones(3), size=3)
    pi = rng.dirichlet(np.ones(3))
    Y = jnp.asarray(rng.normal(size=(40, 4)))
    a = segment(tex, np.log(M), np.log(pi), Y, 5, None)
    b = segment(tex, np.log(M), np.log(pi), Y, 5, 40)
    c = segment(tex, np.log(M), np.log(pi), Y, 5, 55)
    assert a.to_list() == b.to_list() == c.to_list()
    np.testing.assert_allclose(float(a.score), float(b.score), rtol=1e-12)


def test_batched_padded_sequences_equal_single_runs():
    rng = np.random.default_rng(4)
    tex = small_textons(rng, 2)
    M = rng.dirichlet(np.ones(2), size=2)
    pi = rng.dirichlet(np.ones(2))
    lens = [30, 22, 17]
    Ys = [rng.normal(size=(L, 4)) for L in lens]
    pad = np.zeros((3, 30, 4))
    for k, y in enumerate(Ys):
        pad[k, : len(y)] = y
        pad[k, len(y) :] = 1e3  # garbage in the padding must not matter
    batch = segment(tex, np.log(M), np.log(pi), jnp.asarray(pad), 4, 9, n_frames=lens)
    for k, y in enumerate(Ys):
        single = segment(tex, np.log(M), np.log(pi), jnp.asarray(y), 4, 9)
        assert batch[k].to_list() == single.to_list()
        np.testing.assert_allclose(float(batch[k].score), float(single.score), rtol=1e-9)
        assert sum(L for _, L, _ in batch[k].to_list()) == lens[k]
    # the learner's E-step: clips packed (real frames only) in batches of 1, 2 (one empty
    # slot) or 3, in sequence
    log_d = np.log(rng.dirichlet(np.ones(6), size=2))
    args = (tex, jnp.log(M), jnp.log(pi), jnp.asarray(pad), jnp.asarray(lens), 4, 9)
    whole = segment_batch(*args, jnp.asarray(log_d))[0]
    for c in (1, 2, 3):
        packing = pack_clips(np.asarray(lens), 30, c)
        packed = segment_batch(*args, jnp.asarray(log_d), packing)[0]
        for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(packed), strict=True):
            assert a.shape == b.shape
            if jnp.issubdtype(a.dtype, jnp.integer):  # the segmentations: equal
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
            else:  # the scores: the frames are centred on each batch's mean, so to rounding
                np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9)


def test_pack_clips_balances_batches_and_keeps_every_frame():
    rng = np.random.default_rng(7)
    nf = rng.integers(40, 300, size=11)
    T = int(nf.max())
    p = pack_clips(nf, T, 4)
    frames, where, n, order = (np.asarray(a) for a in (p.frames, p.where, p.n, p.order))
    assert frames.shape[0] == 3 and where.shape == (3, 4, T) and frames.shape[1] % 16 == 0
    assert sorted(order.tolist()) == sorted(set(order.tolist()))  # one slot per clip
    for s, L in enumerate(nf):  # every real frame of every clip, in order, exactly once
        b, j = divmod(int(order[s]), 4)
        assert n[b, j] == L
        np.testing.assert_array_equal(frames[b, where[b, j, :L]], s * T + np.arange(L))
    totals = np.bincount(order // 4, weights=nf, minlength=3)
    assert totals.max() - totals.min() <= nf.max()  # longest first into the lightest batch
    assert frames.shape[1] < 4 * T
    with pytest.raises(ValueError, match="pack_clips"):
        pack_clips(np.array([10, 0]), 10, 2)


def test_segment_input_checks_and_no_retrace():
    rng = np.random.default_rng(5)
    tex = small_textons(rng, 2)
    lm, lp = np.log(np.full((2, 2), 0.5)), np.log(np.full(2, 0.5))
    Y = jnp.asarray(rng.normal(size=(20, 4)))
    with pytest.raises(ValueError, match="tmin"):
        segment(tex, lm, lp, Y, 2, 5)
    with pytest.raises(ValueError, match="tmax"):
        segment(tex, lm, lp, Y, 5, 4)
    with pytest.raises(ValueError, match="shorter than tmin"):
        segment(tex, lm, lp, Y[:4], 5, 8)
    with pytest.raises(ValueError, match="log_M"):
        segment(tex, lm[:1], lp, Y, 3, 5)
    # infeasible: 7 frames cannot be cut into pieces of exactly 3
    seg = segment(tex, lm, lp, Y[:7], 3, 3)
    assert int(seg.n_segments) == 0 and float(seg.score) == -np.inf
    from mtex_jax.texture import segment_scores, viterbi_segments

    f = eqx.debug.assert_max_traces(viterbi_segments.__wrapped__, max_traces=1)  # type: ignore[attr-defined]
    g = eqx.filter_jit(f)
    for _ in range(3):
        y = jnp.asarray(rng.normal(size=(20, 4)))
        g(segment_scores(tex, y), jnp.asarray(lm), jnp.asarray(lp), jnp.asarray(20), 3, 6)
