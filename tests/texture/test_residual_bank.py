"""Synthesis innovations replayed from the training residuals (:class:`ResidualBank`): the
bank's rows against a per-frame numpy re-derivation, the glitch rule against scipy's F law,
the draws against the blocks they must be and a uniform choice of segment (scipy's
chi-square), the file format, path synthesis, bad input and float32."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats as st

import mtex_jax as mj
from mtex_jax.texture import (
    LearnConfig,
    ResidualBank,
    draw_residuals,
    load_texture,
    residual_bank,
    segment_innovations,
)
from mtex_jax.texture._learning.learn import with_innovations
from mtex_jax.texture._noise.residual_bank import _draw_impl


def _clips(n=3, T=200, D=3, seed=3):
    """AR(2) clips with two regimes (slow and fast oscillation) so that EM keeps 2 textons."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        y = np.zeros((T, D))
        for t in range(2, T):
            a1 = 1.6 if (t // 50) % 2 == 0 else 0.4
            y[t] = a1 * y[t - 1] - 0.8 * y[t - 2] + rng.standard_t(4, D) * 0.3
        out.append(y)
    out[0][GLITCH, 1] += 40.0  # a capture glitch: one frame of one channel, ~100 sd off
    return out


GLITCH = 101


@pytest.fixture(scope="module")
def learned():
    ys = _clips()
    cfg = LearnConfig(
        tmin=20,
        tmax=60,
        observation="full",
        init="greedy",
        max_iter=2,
        n_textons=2,
        selection="none",
        min_segments=1,
    )
    assert cfg.innovations == "residuals"  # the default
    return mj.learn(ys, cfg), ys


def _residual(tex, y, j, i):
    """Numpy: the whitened residual of frame ``j`` of clip ``y`` under texton ``i``."""
    t = tex.textons[int(i)]
    mu, C, A1, A2, d, B = (np.asarray(a) for a in (t.mu, t.C, t.A1, t.A2, t.d, t.B))
    x = (y[j - 2 : j + 1] - mu) @ C
    return np.linalg.solve(B, x[2] - A1 @ x[1] - A2 @ x[0] - d)


def _kept(tex, ys):
    """Numpy and scipy: the segments the glitch rule keeps, and their residuals."""
    k = tex.textons.C.shape[-1]
    limit = st.f.ppf(1 - 1e-6, k, tex.textons.dof)
    out = []
    for s, a, n, i in np.asarray(tex.segments):
        u = np.asarray([_residual(tex, ys[s], j, i) for j in range(a + 2, a + n)])
        if np.max(np.sum(u**2, axis=1)) / k <= limit:
            out.append(((s, a, n, i), u))
    return out


def test_bank_rows_are_the_plausible_segments_residuals(learned):
    tex, ys = learned
    bank = tex.residuals
    assert isinstance(bank, ResidualBank) and tex.innovations is not None
    rows = np.asarray(bank.rows)
    kept = _kept(tex, ys)
    segs = np.asarray(tex.segments)
    assert len(np.unique(segs[:, 3])) >= 2  # the test sees more than one texton
    # the glitch's segment (and only it) is left out
    hit = [(s, a, n) for s, a, n, _ in segs if s == 0 and a <= GLITCH < a + n]
    assert len(kept) == len(segs) - 1 and hit
    assert all(key[:3] != hit[0] for key, _ in kept)
    assert np.array_equal(np.asarray(bank.labels), [key[3] for key, _ in kept])
    assert np.array_equal(np.asarray(bank.lengths), [len(u) for _, u in kept])
    for start, (_, u) in zip(np.asarray(bank.starts), kept, strict=True):
        assert np.allclose(rows[start : start + len(u)], u, atol=1e-10)
    assert rows.shape == (sum(len(u) for _, u in kept), tex.textons.C.shape[-1])
    # and segment_innovations agrees on every kept segment
    within = segment_innovations(tex.textons, ys, np.asarray([key for key, _ in kept]))
    assert all(np.allclose(a, u, atol=1e-10) for a, (_, u) in zip(within, kept, strict=True))
    # tail = 0 keeps every segment; a texton whose segments all fail keeps its best one
    every = residual_bank(tex.textons, ys, segs, tail=0.0)
    assert np.asarray(every.labels).size == len(segs)
    strict = residual_bank(tex.textons, ys, segs, tail=0.999999)
    assert sorted(np.asarray(strict.labels).tolist()) == sorted(np.unique(segs[:, 3]).tolist())


def test_bank_records_the_segment_of_every_block(learned):
    tex, ys = learned
    bank = tex.residuals
    segs = [tuple(int(x) for x in r) for r in np.asarray(tex.segments)]
    kept = _kept(tex, ys)
    assert np.array_equal(np.asarray(bank.segments), [segs.index(key) for key, _ in kept])
    # the public builder numbers them the same way, short segments included
    again = residual_bank(tex.textons, ys, tex.segments)
    assert np.array_equal(np.asarray(again.segments), np.asarray(bank.segments))
    short = np.concatenate([np.asarray([[0, 0, 2, 0]]), np.asarray(tex.segments)])
    assert np.array_equal(
        np.asarray(residual_bank(tex.textons, ys, short).segments), np.asarray(bank.segments) + 1
    )


def test_aligned_draws_replay_the_instance_segment(learned):
    tex, ys = learned
    bank = tex.residuals
    rows, starts, lengths, labels, segments = (
        np.asarray(a) for a in (bank.rows, bank.starts, bank.lengths, bank.labels, bank.segments)
    )
    segs = np.asarray(tex.segments)
    L = 130
    left_out = np.setdiff1d(np.arange(len(segs)), segments)  # the glitch's segment
    assert left_out.size == 1
    inst = np.concatenate([segments, left_out, [-1]])
    lab = segs[np.maximum(inst, 0), 3]
    v = np.asarray(draw_residuals(jax.random.key(0), bank, lab, L, instances=inst))
    for m, j in enumerate(segments):  # numpy: the instance's own residuals, cyclically
        u = np.asarray(
            [
                _residual(tex, ys[segs[j, 0]], t, segs[j, 3])
                for t in range(segs[j, 1] + 2, segs[j, 1] + segs[j, 2])
            ]
        )
        assert np.allclose(v[m], u[np.arange(L) % len(u)], atol=1e-10)
    # a left-out instance, or none, draws a block of a segment of the texton
    blocks = [
        np.resize(rows[a : a + n], (L, rows.shape[1])) for a, n in zip(starts, lengths, strict=True)
    ]
    for m in (len(segments), len(segments) + 1):
        assert any(np.array_equal(v[m], blocks[j]) for j in np.flatnonzero(labels == lab[m]))
    # an instance of another texton is not used
    other = np.flatnonzero(labels != labels[0])[0]
    w = np.asarray(
        draw_residuals(jax.random.key(0), bank, [labels[0]], L, instances=[segments[other]])
    )
    assert not np.array_equal(w[0], blocks[other])
    # without instances (shuffled) the draws are those of the uniform choice
    assert np.array_equal(
        np.asarray(draw_residuals(jax.random.key(0), bank, lab, L)),
        np.asarray(draw_residuals(jax.random.key(0), bank, lab, L, instances=None)),
    )
    with pytest.raises(ValueError, match="instances"):
        draw_residuals(jax.random.key(0), bank, [0, 1], L, instances=[0])


def _dense_constrained(tex, i, start, end, length, v, weights=None):
    """Numpy: texton ``i`` held at ``start`` (frames 0, 1) and ``end`` (frames l−2, l−1),
    the free states minimising ``Σ_j ω_j ‖B⁻¹(x_j − A1 x_{j−1} − A2 x_{j−2} − d) − v_j‖²``
    by dense least squares (``weights`` ``ω_j`` for ``j = 2 … l−1``, default 1);
    observations ``μ + C x``."""
    t = tex.textons[int(i)]
    mu, C, A1, A2, d, B = (np.asarray(a) for a in (t.mu, t.C, t.A1, t.A2, t.d, t.B))
    k = C.shape[1]
    W = np.linalg.inv(B)
    held = {0: (start[0] - mu) @ C, 1: (start[1] - mu) @ C}
    held |= {length - 2: (end[0] - mu) @ C, length - 1: (end[1] - mu) @ C}
    free = [f for f in range(length) if f not in held]
    col = {f: n * k for n, f in enumerate(free)}
    G, c = np.zeros(((length - 2) * k, len(free) * k)), np.zeros((length - 2) * k)
    for j in range(2, length):
        r = slice((j - 2) * k, (j - 1) * k)
        c[r] = W @ d + v[j - 2]
        for f, M in ((j, W), (j - 1, -W @ A1), (j - 2, -W @ A2)):
            if f in held:
                c[r] -= M @ held[f]
            else:
                G[r, col[f] : col[f] + k] = M
    if weights is not None:
        root = np.repeat(np.sqrt(np.asarray(weights, dtype=np.float64)), k)
        G, c = G * root[:, None], c * root
    x = np.zeros((length, k))
    x[free] = np.linalg.lstsq(G, c, rcond=None)[0].reshape(len(free), k)
    for f, h in held.items():
        x[f] = h
    return mu + x @ C.T


def test_aligned_draws_past_the_segment_come_from_beyond(learned):
    """Aligned blocks: the instance's own residuals (numpy), then ``beyond``'s rows; blocks
    without an aligned instance, and shuffled draws, ignore ``beyond``."""
    tex, ys = learned
    bank = tex.residuals
    rows, starts, lengths, labels, segments = (
        np.asarray(a) for a in (bank.rows, bank.starts, bank.lengths, bank.labels, bank.segments)
    )
    segs = np.asarray(tex.segments)
    L, k = 130, rows.shape[1]
    left_out = np.setdiff1d(np.arange(len(segs)), segments)
    inst = np.concatenate([segments, left_out, [-1]])
    lab = segs[np.maximum(inst, 0), 3]
    far = np.random.default_rng(0).standard_normal((inst.size, L, k)) + 100.0
    key = jax.random.key(0)
    v = np.asarray(draw_residuals(key, bank, lab, L, instances=inst, beyond=far))
    assert (segs[segments, 2] - 2 < L).all()  # every block has rows past its segment
    for m, j in enumerate(segments):
        s0, a0, n0, i0 = segs[j]
        u = np.asarray([_residual(tex, ys[s0], t, i0) for t in range(a0 + 2, a0 + n0)])
        assert np.allclose(v[m, : n0 - 2], u, atol=1e-10)
        assert np.array_equal(v[m, n0 - 2 :], far[m, n0 - 2 :])
    # the left-out instance and the block without one: as without beyond (cyclic blocks)
    plain = np.asarray(draw_residuals(key, bank, lab, L, instances=inst))
    assert np.array_equal(v[len(segments) :], plain[len(segments) :])
    blocks = [np.resize(rows[a : a + n], (L, k)) for a, n in zip(starts, lengths, strict=True)]
    for m in (len(segments), len(segments) + 1):
        assert any(np.array_equal(v[m], blocks[j]) for j in np.flatnonzero(labels == lab[m]))
    # shuffled replay ignores beyond
    assert np.array_equal(
        np.asarray(draw_residuals(key, bank, lab, L, beyond=far)),
        np.asarray(draw_residuals(key, bank, lab, L)),
    )
    with pytest.raises(ValueError, match="beyond"):
        draw_residuals(key, bank, lab, L, instances=inst, beyond=far[:, :-1])


def test_tail_draws_are_the_process_per_row_and_padding_free(learned):
    """The rows past the aligned blocks: row ``m`` is the innovation process drawn with
    ``fold_in(key, m)`` for a multiple of 256 frames, so more path rows or frames (the
    padding) change none of them; without a process, independent Student-t draws."""
    from mtex_jax.texture import draw_innovations
    from mtex_jax.texture._noise.draws import independent_innovations
    from mtex_jax.texture._synthesis import path_noise as pn

    tex, _ = learned
    k, dof = int(tex.textons.C.shape[-1]), float(tex.textons.dof)
    key = jax.random.key(7)
    a = np.asarray(pn.tail_draws(key, tex.innovations, (5, 150, k), np.float64, dof))
    b = np.asarray(pn.tail_draws(key, tex.innovations, (9, 190, k), np.float64, dof))
    assert a.shape == (5, 150, k)
    assert np.array_equal(b[:5, :150], a)
    for m in (0, 4):
        kk = jax.random.fold_in(key, m)
        ref = draw_innovations(kk, tex.innovations, (256, k), np.float64, dof)
        assert np.allclose(a[m], np.asarray(ref)[:150], rtol=0, atol=1e-12)
    assert not np.allclose(a[0], a[1])
    white = np.asarray(pn.tail_draws(key, None, (5, 150, k), np.float64, dof))
    ref = independent_innovations(jax.random.fold_in(key, 3), (256, k), np.float64, dof)
    assert np.allclose(white[3], np.asarray(ref)[:150], rtol=0, atol=1e-12)


def _two_textons_of_clip_1(tex, ys, tau=None):
    """Two textons along clip 1's own segmentation (no glitch there), synthesised with aligned
    replay (``tau``: the bend's time constant in frames, ``None``: weights 1), checked texton
    by texton against the dense least squares (numpy) of its own instance's residuals and,
    for the two equations of its end frames past them, the tail draws of the innovation
    process, each equation ``j`` weighted ``exp(max(l − j, 0)/τ)`` (1 without ``tau``).
    Returns the synthesis, its arguments and the first texton's training frames."""
    from mtex_jax.texture._synthesis import path_noise as pn, sequence as seq
    from mtex_jax.texture._synthesis.sequence import synthesize_path

    segs = np.asarray(tex.segments)
    rows = np.flatnonzero(segs[:, 0] == 1)[:3]
    idx, path, lens = rows[:2], segs[rows[:2], 3], segs[rows[:2], 2]
    kp = np.asarray(tex.key_poses)
    plan = seq.PathPlan(path, lens.astype(np.int64), idx, None, kp[rows[2]], False)
    args = (plan, "whitened", "blend", "aligned")
    key = jax.random.key(3)
    decay = None if tau is None else 1.0 / tau
    Y = np.asarray(synthesize_path(tex, key, *args, decay=decay))
    k = int(tex.textons.C.shape[-1])
    l_pad = pn.round_up(int(max(lens.max(), tex.config.tmax)) + 2, seq._PAD_FRAMES)
    shape = (seq.path_capacity(tex, 2), l_pad - 2, k)
    tail = np.asarray(
        pn.tail_draws(
            jax.random.fold_in(key, 1), tex.innovations, shape, np.float64, float(tex.textons.dof)
        )
    )
    at = 0
    for m, j in enumerate(idx):
        s0, a0, n0, i0 = segs[j]
        u = np.asarray([_residual(tex, ys[s0], t, i0) for t in range(a0 + 2, a0 + n0)])
        v = np.concatenate([u, tail[m, n0 - 2 : n0]])
        omega = None
        if tau is not None:
            omega = np.exp(np.maximum(n0 - np.arange(2, n0 + 2), 0) / tau)
        ref = _dense_constrained(tex, i0, kp[j], kp[rows[m + 1]], n0 + 2, v, omega)
        assert np.allclose(Y[at : at + n0], ref[:n0], atol=1e-8)
        at += n0
    a0, n0 = segs[idx[0], 1], int(lens[0])
    return Y, args, ys[1][a0 : a0 + n0]


def test_aligned_synthesis_replays_each_textons_instance(learned):
    """Each texton is the dense least squares with its own instance's residuals (see
    ``_two_textons_of_clip_1``); the shuffled replay does not follow them."""
    from mtex_jax.texture._synthesis.sequence import synthesize_path

    tex, ys = learned
    Y, args, _ = _two_textons_of_clip_1(tex, ys)
    Z = np.asarray(synthesize_path(tex, jax.random.key(3), *args[:-1], "shuffled"))
    assert not np.allclose(Z, Y, atol=1e-3)


@pytest.mark.parametrize("tau", [4.0, 15.0])
def test_transition_weights_the_equations_towards_the_end(learned, tau):
    """The bend near the end (design §10.11): with ``decay = 1/τ`` each texton is the dense
    least squares with equation ``j`` weighted ``exp(max(l − j, 0)/τ)`` (``l`` = its length,
    the end pair at rows ``l, l + 1``), the same residuals replayed; its first frames stay
    closer to the training clip it replays than with the bend spread over the texton."""
    tex, ys = learned
    Y, _, real = _two_textons_of_clip_1(tex, ys, tau)
    Y1, _, _ = _two_textons_of_clip_1(tex, ys)
    assert not np.allclose(Y, Y1, atol=1e-3)  # it changes the motion
    early = slice(2, len(real) // 3)
    assert np.abs(Y[early] - real[early]).max() < np.abs(Y1[early] - real[early]).max()


def test_draws_are_blocks_from_a_uniformly_chosen_segment_of_the_texton(learned):
    tex, _ = learned
    bank = tex.residuals
    rows, starts, lengths, labels = (
        np.asarray(a) for a in (bank.rows, bank.starts, bank.lengths, bank.labels)
    )
    lab = np.asarray([int(labels[0])] * 3000 + [int(labels[-1])] * 5)
    L = 130  # longer than some segments: those repeat from their first row
    v = np.asarray(draw_residuals(jax.random.key(0), bank, lab, L))
    assert v.shape == (lab.size, L, rows.shape[1])
    k = rows.shape[1]
    blocks = [np.resize(rows[a : a + n], (L, k)) for a, n in zip(starts, lengths, strict=True)]
    found = []
    for m in range(lab.size):
        hit = [j for j in np.flatnonzero(labels == lab[m]) if np.array_equal(v[m], blocks[j])]
        assert hit, f"block {m} is not a block of texton {lab[m]}'s segments"
        found.append(hit[0])
    assert (lengths < L).any()
    # the segment is chosen uniformly among the texton's own
    cand = np.flatnonzero(labels == lab[0])
    counts = np.asarray([np.sum(np.asarray(found[:3000]) == j) for j in cand])
    assert st.chisquare(counts, np.full(cand.size, 3000 / cand.size)).pvalue > 1e-3
    # another key, other blocks; the same key, the same blocks
    w = np.asarray(draw_residuals(jax.random.key(1), bank, lab, L))
    assert not np.array_equal(v, w)
    assert np.array_equal(v, np.asarray(draw_residuals(jax.random.key(0), bank, lab, L)))


def test_draws_compile_once_per_shape(learned):
    bank = learned[0].residuals
    draw = eqx.filter_jit(eqx.debug.assert_max_traces(_draw_impl, max_traces=1))
    a = draw(jax.random.key(0), bank, jnp.asarray([0, 1, 0]), 30)
    b = draw(jax.random.key(1), bank, jnp.asarray([1, 1, 0]), 30)
    assert a.shape == b.shape == (3, 30, bank.rows.shape[1])


def test_synthesis_replays_the_bank_and_the_file_keeps_it(learned, tmp_path):
    tex, _ = learned
    a = mj.synthesize(jax.random.key(0), tex, n_frames=150).Y
    b = mj.synthesize(jax.random.key(0), tex, n_frames=150).Y
    c = mj.synthesize(jax.random.key(0), dataclasses.replace(tex, residuals=None), n_frames=150)
    assert np.isfinite(np.asarray(a)).all() and np.array_equal(np.asarray(a), np.asarray(b))
    assert not np.allclose(np.asarray(a), np.asarray(c.Y))
    # zero noise draws nothing
    z = mj.synthesize(None, tex, np.asarray([0]), lengths=[40]).Y
    z0 = mj.synthesize(
        None, dataclasses.replace(tex, residuals=None), np.asarray([0]), lengths=[40]
    )
    assert np.array_equal(np.asarray(z), np.asarray(z0.Y))
    tex.save(tmp_path / "t.npz")
    back = load_texture(tmp_path / "t.npz")
    assert back.config.innovations == "residuals" and back.residuals is not None
    for f in ("rows", "starts", "lengths", "labels"):
        assert np.array_equal(np.asarray(getattr(back.residuals, f)), getattr(tex.residuals, f))
    shuffled = lambda t: mj.synthesize(jax.random.key(0), t, n_frames=150, replay="shuffled").Y
    assert np.array_equal(np.asarray(shuffled(back)), np.asarray(shuffled(tex)))
    assert "training residuals" in mj.texture.texture_summary(back)
    with np.load(tmp_path / "t.npz") as f:
        arrays = {k: f[k] for k in f.files}
    half = {k: v for k, v in arrays.items() if k != "residuals.labels"}
    np.savez(tmp_path / "half.npz", **half)
    with pytest.raises(ValueError, match=r"half\.npz.*come together"):
        load_texture(tmp_path / "half.npz")
    for name, value, msg in (
        ("residuals.labels", arrays["residuals.labels"] + tex.n_textons, "outside"),
        ("residuals.starts", arrays["residuals.starts"] + 10**6, "(row ranges|outside)"),
    ):
        np.savez(tmp_path / "bad.npz", **{**arrays, name: value})
        with pytest.raises(ValueError, match=rf"bad\.npz.*{msg}"):
            load_texture(tmp_path / "bad.npz")


def test_file_keeps_the_alignment(learned, tmp_path):
    tex, _ = learned
    tex.save(tmp_path / "t.npz")
    back = load_texture(tmp_path / "t.npz")
    assert back.residuals.segments is not None
    assert np.array_equal(np.asarray(back.residuals.segments), tex.residuals.segments)
    a = mj.synthesize(jax.random.key(0), tex, n_frames=150).Y
    assert np.array_equal(np.asarray(mj.synthesize(jax.random.key(0), back, n_frames=150).Y), a)


def test_bad_input_is_rejected(learned):
    tex, ys = learned
    bank = tex.residuals
    key = jax.random.key(0)
    with pytest.raises(TypeError, match="ResidualBank"):
        draw_residuals(key, tex.innovations, [0], 5)  # type: ignore[arg-type]
    for labels in ([], [[0]], [0.5]):
        with pytest.raises(ValueError, match="labels"):
            draw_residuals(key, bank, np.asarray(labels), 5)
    for length in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="length"):
            draw_residuals(key, bank, [0], length)  # type: ignore[arg-type]
    one, two = jnp.ones(1, int), jnp.ones(2, int)
    with pytest.raises(ValueError, match="rows"):
        ResidualBank(rows=jnp.zeros((0, 3)), starts=one, lengths=one, labels=one)
    with pytest.raises(ValueError, match="one shape"):
        ResidualBank(rows=jnp.zeros((4, 3)), starts=two, lengths=one, labels=one)
    with pytest.raises(ValueError, match="row ranges"):
        ResidualBank(rows=jnp.zeros((4, 3)), starts=one * 2, lengths=one * 3, labels=one)
    with pytest.raises(ValueError, match="segments"):
        ResidualBank(rows=jnp.zeros((4, 3)), starts=one, lengths=one, labels=one, segments=two)
    segs = np.asarray(tex.segments)
    with pytest.raises(ValueError, match="lies outside clip"):
        residual_bank(tex.textons, ys, segs + np.asarray([0, 1000, 0, 0]))
    for tail in (1.0, -0.1):
        with pytest.raises(ValueError, match="tail"):
            residual_bank(tex.textons, ys, segs, tail=tail)
    with pytest.raises(ValueError, match="no segment of 3 frames"):
        residual_bank(tex.textons, ys, np.asarray([[0, 0, 2, 0]]))
    with pytest.raises(ValueError, match=r"clip 1 must have shape"):
        residual_bank(tex.textons, [ys[0], ys[1][:, :2], ys[2]], segs)
    with pytest.raises(ValueError, match="labels outside"):
        residual_bank(tex.textons, ys, segs + np.asarray([0, 0, 0, 9]))
    with pytest.raises(ValueError, match="'fitted', 'white' or 'residuals'"):
        LearnConfig(innovations="bootstrap")
    # a share of the clips (distributed learning) needs every process's residuals
    with pytest.raises(ValueError, match="needs gather"):
        with_innovations(tex, ys, offset=0, reduce=lambda s: s)
    # a bank whose labels name no texton of the model
    wrong = ResidualBank(bank.rows, bank.starts, bank.lengths, bank.labels + tex.n_textons)
    with pytest.raises(ValueError, match=r"residuals\.labels outside"):
        dataclasses.replace(tex, residuals=wrong)
    with pytest.raises(ValueError, match="columns"):
        dataclasses.replace(
            tex, residuals=ResidualBank(bank.rows[:, :1], *[bank.starts, bank.lengths, bank.labels])
        )


def test_float32_smoke(learned):
    tex, ys = learned
    t32 = jax.tree.map(
        lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a,
        tex.textons,
    )
    bank = residual_bank(t32, [y.astype(np.float32) for y in ys], tex.segments)
    v = draw_residuals(jax.random.key(0), bank, [0, 1], 16, jnp.float32)
    assert v.dtype == jnp.float32 and np.isfinite(np.asarray(v)).all()
    assert np.allclose(
        np.asarray(v),
        np.asarray(draw_residuals(jax.random.key(0), tex.residuals, [0, 1], 16)),
        atol=1e-3,
        rtol=1e-3,
    )
