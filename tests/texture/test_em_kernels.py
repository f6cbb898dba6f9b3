"""The batched kernels of EM against the per-sequence scorer: the E-step's segment scores of
sequences laid end to end (``batch_scores_impl``) and the objective's per-segment scores
(``rows_score``), for each observation model."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from mtex_jax.texture import (
    FullObservation,
    fit_texton,
    observation_model,
    segment_scores,
    stack_textons,
)
from mtex_jax.texture._learning.mstep import fit_all
from mtex_jax.texture._scoring.packing import pack_clips
from mtex_jax.texture._scoring.rows import CHUNK_ROWS, row_chunks, rows_score
from mtex_jax.texture._scoring.scores import batch_scores_impl
from mtex_jax.texture._segmentation.segment import segment_batch
from mtex_jax.texture._texton.options import SolveOptions


def _smooth(rng, T, D):
    t = np.arange(T)[:, None]
    y = np.sin(rng.uniform(0.05, 0.3, (1, D)) * t + rng.uniform(0, 6, (1, D)))
    return y + 0.05 * rng.normal(size=(T, D)) + np.cumsum(0.02 * rng.normal(size=(T, D)), 0)


def _data(observation: str):
    rng = np.random.default_rng(3)
    D = 6
    k = D if observation == "full" else 2
    texs = [
        fit_texton(
            jnp.asarray(_smooth(rng, 150, D)),
            state_dim=k,
            observation=observation_model(observation),
        )
        for _ in range(3)
    ]
    Y = np.zeros((3, 140, D))  # three sequences, two of them padded with zeros
    for s, n in enumerate([90, 140, 117]):
        Y[s, :n] = _smooth(rng, n, D)
    return stack_textons(texs), Y


@pytest.mark.parametrize("observation", ["paper", "residual", "full"])
def test_batch_scores_equal_per_sequence_scores(observation):
    tex, Y = _data(observation)
    batch = jax.jit(batch_scores_impl)(tex, jnp.asarray(Y))
    rng = np.random.default_rng(0)
    for s in range(Y.shape[0]):
        one = segment_scores(tex, jnp.asarray(Y[s]))
        sc = jax.tree.map(lambda a, s=s: a[s], batch)
        b = rng.integers(0, 120, 200)
        e = np.minimum(b + rng.integers(1, 60, 200), Y.shape[1] - 1)
        i = rng.integers(0, 3, 200)
        want, got = np.asarray(one.score(b, e, i)), np.asarray(sc.score(b, e, i))
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-8)
        # the initial term at the last frame has no successor frame: -inf, as per sequence
        assert np.all(np.isneginf(np.asarray(sc.init)[:, -1]))


@pytest.mark.parametrize("observation", ["paper", "residual", "full"])
def test_rows_score_is_the_sum_of_own_texton_segment_scores(observation):
    tex, Y = _data(observation)
    # the fifth row's 70-frame slab would overrun the sequence: it starts 25 frames earlier
    rows = np.array(
        [[0, 0, 40, 1], [0, 40, 50, 2], [1, 3, 60, 0], [2, 50, 67, 1], [1, 95, 45, 2], [0, 0, 2, 0]]
    )
    w = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 0.0])  # the last row is padding (weight 0)
    lab, grp = row_chunks(rows[:, 3], 6)  # padded with empty chunks
    chunks = (jnp.asarray(lab), jnp.asarray(grp))
    got = float(rows_score(tex, jnp.asarray(Y), jnp.asarray(rows), jnp.asarray(w), chunks, 70))
    want = 0.0
    for (s, b, n, i), wr in zip(rows, w, strict=True):
        if wr:
            want += float(segment_scores(tex, jnp.asarray(Y[s])).score(b, b + n - 1, i))
    np.testing.assert_allclose(got, want, rtol=1e-10)


@pytest.mark.parametrize("observation", ["paper", "full"])
@pytest.mark.parametrize("clip_batch", [None, 2])
def test_e_step_scores_given_segments_from_its_own_segment_scores(observation, clip_batch):
    # the M-step objective fused into the E-step: each clip's sum of the scores of given
    # segments (each by its own texton), from the E-step's frame terms, unpacked or packed
    tex, Y = _data(observation)
    nf = np.array([90, 140, 117])
    rows = [[(0, 40, 1), (40, 50, 2)], [(3, 60, 0), (95, 45, 2)], [(50, 67, 1)]]
    K = 4
    old = np.zeros((3, 3, K), dtype=np.int64)
    for s, segs in enumerate(rows):
        for j, (b, n, i) in enumerate(segs):
            old[:, s, j] = (b, n, i)
    M = np.full((3, 3), 1 / 3)
    packing = None if clip_batch is None else pack_clips(nf, 140, clip_batch)
    seg, got = segment_batch(
        tex,
        jnp.log(M),
        jnp.log(np.full(3, 1 / 3)),
        jnp.asarray(Y),
        jnp.asarray(nf),
        20,
        70,
        None,
        packing,
        tuple(jnp.asarray(a) for a in old),
    )
    for s, segs in enumerate(rows):
        sc = segment_scores(tex, jnp.asarray(Y[s, : nf[s]]))
        want = sum(float(sc.score(b, b + n - 1, i)) for b, n, i in segs)
        np.testing.assert_allclose(float(got[s]), want, rtol=1e-10)
    assert np.all(np.asarray(seg.n_segments) > 0)


def test_rows_score_with_many_rows_per_texton():
    """More rows per texton than one chunk holds, against the per-sequence scorer."""
    tex, Y = _data("residual")
    rng = np.random.default_rng(5)
    n_rows = 40
    s = rng.integers(0, 3, n_rows)
    lengths = rng.integers(2, 61, n_rows)
    T_s = np.array([90, 140, 117])[s]
    starts = np.array([rng.integers(0, t - m + 1) for t, m in zip(T_s, lengths, strict=True)])
    rows = np.stack([s, starts, lengths, rng.integers(0, 3, n_rows)], axis=1)
    w = rng.uniform(0.5, 2.0, n_rows)
    lab, grp = row_chunks(rows[:, 3])
    got = float(
        rows_score(
            tex,
            jnp.asarray(Y),
            jnp.asarray(rows),
            jnp.asarray(w),
            (jnp.asarray(lab), jnp.asarray(grp)),
            60,
        )
    )
    want = sum(
        wr * float(segment_scores(tex, jnp.asarray(Y[si])).score(b, b + n - 1, i))
        for (si, b, n, i), wr in zip(rows, w, strict=True)
    )
    np.testing.assert_allclose(got, want, rtol=1e-10)


@settings(deadline=None, max_examples=50)
@given(st.lists(st.integers(0, 5), min_size=1, max_size=60), st.integers(0, 5))
def test_row_chunks_hold_every_row_once_with_its_label(labels, extra):
    labels = np.asarray(labels)
    counts = np.bincount(labels)
    n = int(np.sum(-(-counts // CHUNK_ROWS)))
    lab, grp = row_chunks(labels, n + extra)
    assert lab.shape == (n + extra,) and grp.shape == (n + extra, CHUNK_ROWS)
    seen = grp[grp >= 0]
    np.testing.assert_array_equal(np.sort(seen), np.arange(len(labels)))
    for c in range(n + extra):
        rows = grp[c][grp[c] >= 0]
        assert np.all(labels[rows] == lab[c])
    assert np.all(grp[n:] == -1)


@pytest.mark.parametrize(("observation", "dof"), [("paper", None), ("full", None), ("full", 4.0)])
def test_chunked_m_step_equals_per_texton_fits(observation, dof):
    """The M-step's rows go in per-texton chunks of CHUNK_ROWS (36 rows: several chunks per
    texton, padding rows and empty chunks besides): each texton equals ``fit_texton`` on its
    own segments (a mask per sequence), the independent per-texton path; with Student-t
    innovations (``dof``) the IRLS steps too (fit_texton's IRLS is checked against numpy in
    test_student)."""
    rng = np.random.default_rng(11)
    D = 5
    k = D if observation == "full" else 2
    S, T = 4, 400
    Y = np.stack([_smooth(rng, T, D) for _ in range(S)])
    rows = []
    for s in range(S):  # consecutive segments of 6-14 frames, labels 0-2
        b = 0
        while b + 14 <= T and len(rows) < 36:
            n = int(rng.integers(6, 15))
            rows.append((s, b, n, int(rng.integers(0, 3))))
            b += n
    rows = np.asarray(rows)
    n_real = len(rows)
    cap = 40
    padded = np.zeros((cap, 4), dtype=np.int64)
    padded[:n_real] = rows
    labels, groups = row_chunks(rows[:, 3], 16)  # the real rows only, 16 chunks
    assert np.bincount(labels[groups[:, 0] >= 0]).min() >= 2  # several chunks per texton
    opts = SolveOptions.make(1e-6, 1e-6, None, 4.0, observation_model(observation), 1e-6, dof=dof)
    chunks = (jnp.asarray(labels), jnp.asarray(groups))
    got = fit_all(jnp.asarray(Y), jnp.asarray(padded), chunks, 3, 14, k, 1e-6, opts)
    assert got.dof == dof
    for i in range(3):
        mask = np.full((S, T), -1)
        for r, (s, b, n, lab) in enumerate(rows):
            if lab == i:
                mask[s, b : b + n] = r
        want = fit_texton(
            jnp.asarray(Y),
            jnp.asarray(mask),
            state_dim=k,
            observation=observation_model(observation),
            dof=dof,
        )
        one = jax.tree.map(lambda a, i=i: a[i], got)
        for name in ("mu", "A1", "A2", "d", "sigma2", "B", "m0", "S0"):
            np.testing.assert_allclose(
                np.asarray(getattr(one, name)),
                np.asarray(getattr(want, name)),
                rtol=1e-7,
                atol=1e-9,
                err_msg=f"texton {i}: {name}",
            )
        # C is defined up to the signs of its columns
        c_got, c_want = np.asarray(one.C), np.asarray(want.C)
        np.testing.assert_allclose(np.abs(c_got.T @ c_want), np.eye(k), atol=1e-7)


@pytest.mark.parametrize("cap", [8, 16, 24])
def test_e_step_skips_the_padding_textons_of_a_full_stack(cap):
    # the learner pads its stacks (copies of the last texton, never entered: log π and the
    # log M columns are -inf); with n_active the full-dimensional kernel skips the padding
    # groups (2 textons per group up to 8, 4 up to 16, else 8). The segmentation, its score and
    # the given segments' scores equal those of the unpadded stack.
    rng = np.random.default_rng(5)
    D = 6
    texs = [
        fit_texton(jnp.asarray(_smooth(rng, 150, D)), state_dim=D, observation=FullObservation())
        for _ in range(5)
    ]
    n = len(texs)
    Y = np.zeros((3, 140, D))
    nf = np.array([90, 140, 117])
    for s, m in enumerate(nf):
        Y[s, :m] = _smooth(rng, m, D)
    M = rng.dirichlet(np.ones(n), size=n)
    pi = rng.dirichlet(np.ones(n))
    old = np.zeros((3, 3, 4), dtype=np.int64)
    old[:, 0, 0], old[:, 1, 0], old[:, 2, 0] = (0, 40, 1), (3, 60, 4), (50, 67, 2)
    old_j = tuple(jnp.asarray(a) for a in old)
    packing = pack_clips(nf, 140, 2)
    lM = np.full((cap, cap), -np.inf)
    lM[:n, :n] = np.log(M)
    lpi = np.full(cap, -np.inf)
    lpi[:n] = np.log(pi)
    padded = stack_textons(texs + [texs[-1]] * (cap - n))
    args = (jnp.asarray(Y), jnp.asarray(nf), 20, 70, None, packing, old_j)
    want_seg, want_old = segment_batch(stack_textons(texs), jnp.log(M), jnp.log(pi), *args)
    for n_active in (jnp.asarray(n, jnp.int32), jnp.asarray(n), None):  # as the learner passes
        seg, got_old = segment_batch(padded, jnp.asarray(lM), jnp.asarray(lpi), *args, n_active)
        np.testing.assert_allclose(np.asarray(seg.score), np.asarray(want_seg.score), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(got_old), np.asarray(want_old), rtol=1e-12)
        for f in ("starts", "lengths", "labels", "n_segments"):
            np.testing.assert_array_equal(getattr(seg, f), getattr(want_seg, f))
