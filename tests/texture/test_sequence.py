"""Whole-sequence synthesis and the virtual choreographer on a texture learned from the
embedded clips (design §5)."""

from __future__ import annotations

import dataclasses
import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mtex_jax as mj
from mtex_jax.texture._synthesis import keyposes, sequence
from shared_textures import four_clip_texture


@pytest.fixture(scope="module")
def texture():
    return four_clip_texture()


def texton(tex, i):
    return jax.tree.map(lambda a: a[i], tex.textons)


def proj(t, y):
    mu, C = np.asarray(t.mu), np.asarray(t.C)
    return mu + (np.asarray(y) - mu) @ C @ C.T


def test_every_texton_equals_single_texton_synthesis(texture):
    """Texton m of the sequence = synthesize_texton held at its key poses and the next one's."""
    rng = np.random.default_rng(0)
    path = rng.integers(0, texture.n_textons, 5)
    lengths = rng.integers(12, 40, 5)
    s = mj.synthesize(
        None, texture, path=path, lengths=lengths, residual="subspace", transition=None
    )
    Y, st, kp = np.asarray(s.Y), np.asarray(s.starts), np.asarray(texture.key_poses)
    segs = np.asarray(s.key_segments)
    assert Y.shape == (lengths.sum(), texture.obs_dim) and st.tolist() == [
        0,
        *np.cumsum(lengths)[:-1],
    ]
    np.testing.assert_array_equal(np.asarray(s.path), path)
    assert np.all(np.asarray(texture.key_pose_labels)[segs] == path)
    for m in range(4):
        ref = mj.texture.synthesize_texton(
            None, texton(texture, path[m]), int(lengths[m]) + 2, kp[segs[m]], kp[segs[m + 1]]
        )
        got = Y[st[m] : st[m] + lengths[m]]
        np.testing.assert_allclose(got, np.asarray(ref)[: lengths[m]], rtol=1e-9, atol=1e-9)
    # the last texton starts at its own key poses too
    np.testing.assert_allclose(
        Y[st[4] : st[4] + 2], proj(texton(texture, path[4]), kp[segs[4]]), atol=1e-9
    )
    assert s.motion is not None and s.motion.n_frames == lengths.sum()
    np.testing.assert_array_equal(s.frame_labels(), np.repeat(path, lengths))


def test_blend_holds_exact_key_poses_and_random_paths_fill_n_frames(texture):
    for seed in range(3):
        s = mj.synthesize(jax.random.key(seed), texture, n_frames=257)
        assert s.n_frames == 257 and int(np.asarray(s.lengths).sum()) == 257
        Y, kp = np.asarray(s.Y), np.asarray(texture.key_poses)
        for m, (b, k) in enumerate(
            zip(np.asarray(s.starts), np.asarray(s.key_segments), strict=True)
        ):
            np.testing.assert_allclose(Y[b : b + 2], kp[k], rtol=0, atol=1e-9, err_msg=str(m))
        assert np.all(np.asarray(s.lengths) >= 2)
        assert np.isfinite(Y).all()
        # the decoded root moves continuously: no step at a boundary larger than the largest
        # step inside textons by more than 2x
        root = np.asarray(s.motion.root_positions)
        step = np.linalg.norm(np.diff(root, axis=0), axis=1)
        b = s.boundaries() - 1
        assert step[b].max() <= 2 * np.delete(step, b).max() + 1e-9


def _chain_cost_reference(texture, chain):
    """Σ cost of an instance chain, re-derived: distance of the frames that followed each
    segment in its training clip to the next key poses; the step's largest such distance
    where a segment ends its clip."""
    segs = np.asarray(texture.segments)
    kp = np.asarray(texture.key_poses).reshape(segs.shape[0], -1)
    lab = np.asarray(texture.key_pose_labels)

    def after(a):
        for j in range(segs.shape[0]):
            if segs[j, 0] == segs[a, 0] and segs[j, 1] == segs[a, 1] + segs[a, 2]:
                return j
        return None

    total = 0.0
    for a, b in itertools.pairwise(chain):
        ja = after(a)
        if ja is not None:
            total += float(np.sum((kp[ja] - kp[b]) ** 2))
        else:  # the largest cost of this step over the segments that have a successor
            worst = 0.0
            for a2 in np.flatnonzero(lab == lab[a]):
                j2 = after(a2)
                if j2 is not None:
                    for b2 in np.flatnonzero(lab == lab[b]):
                        worst = max(worst, float(np.sum((kp[j2] - kp[b2]) ** 2)))
            total += worst
    return total


def many_instances(texture, seed=0, n_seg=40):
    """The texture with a synthetic training table: 3 clips, several segments per texton
    (the embedded-clip texture has one segment per texton, so instance choice is trivial)."""
    rng = np.random.default_rng(seed)
    n_t, D = texture.n_textons, texture.obs_dim
    labels = rng.permutation(np.concatenate([np.arange(n_t), rng.integers(0, n_t, n_seg - n_t)]))
    lengths = rng.integers(12, 40, n_seg)
    clip = np.sort(rng.integers(0, 3, n_seg))
    start = np.zeros(n_seg, np.int64)
    for c in range(3):
        sel = np.flatnonzero(clip == c)
        start[sel] = np.concatenate([[0], np.cumsum(lengths[sel])[:-1]])
    segs = np.stack([clip, start, lengths, labels], axis=1)
    kp = texture.key_poses[:1] + rng.standard_normal((n_seg, 2, D))
    return eqx.tree_at(
        lambda t: (t.segments, t.segment_lengths, t.key_poses, t.key_pose_labels),
        texture,
        (jnp.asarray(segs), jnp.asarray(lengths), jnp.asarray(kp), jnp.asarray(labels)),
    )


def usable_reference(texture):
    """Key-pose pairs inside the box-plot fence of the within-pair joint jump, each pair
    decoded on its own."""
    fm, kp = texture.feature_map, np.asarray(texture.key_poses)
    jumps = np.array(
        [
            np.linalg.norm(np.diff(np.asarray(fm.joint_positions(p)), axis=0), axis=-1).max()
            for p in kp
        ]
    )
    q1, med, q3 = np.percentile(jumps, [25, 50, 75])
    return jumps <= max(q3 + 1.5 * (q3 - q1), 2 * med), jumps


def candidates(texture, path):
    """Instances of every texton on the path: its usable key poses (all if none is usable)."""
    lab = np.asarray(texture.key_pose_labels)
    usable, _ = usable_reference(texture)
    out = []
    for p in path:
        c = np.flatnonzero(lab == p)
        out.append(c[usable[c]] if usable[c].any() else c)
    return out


def test_key_pose_chain_is_the_minimum_cost_chain(texture):
    """The dynamic programme over instances equals brute-force enumeration of all chains."""
    texture = many_instances(texture)
    lab = np.asarray(texture.key_pose_labels)
    present = np.unique(lab)
    rng = np.random.default_rng(3)
    for _ in range(4):
        path = rng.choice(present, 4)
        got = keyposes.key_pose_instances(texture, None, path)
        assert np.all(lab[got] == path)
        cands = candidates(texture, path)
        best = min(_chain_cost_reference(texture, c) for c in itertools.product(*cands))
        assert _chain_cost_reference(texture, got) == pytest.approx(best, rel=1e-9, abs=1e-12)
        keyed = keyposes.key_pose_instances(texture, jax.random.key(1), path)
        assert _chain_cost_reference(texture, keyed) == pytest.approx(best, rel=1e-9, abs=1e-12)


def test_key_poses_replay_training_transitions_where_they_exist(texture):
    """A path of labels of consecutive training segments gets a chain of segments that were
    adjacent in training (cost zero)."""
    texture = many_instances(texture, seed=1)
    segs = np.asarray(texture.segments)
    nxt = keyposes.next_segments(texture)
    ok, _ = usable_reference(texture)
    nxt = np.where(ok[np.maximum(nxt, 0)], nxt, -1)  # runs of usable key poses only
    i = int(np.flatnonzero(ok & (nxt >= 0) & (nxt[np.maximum(nxt, 0)] >= 0))[0])
    run = [i, int(nxt[i]), int(nxt[nxt[i]])]
    path = segs[run, 3]
    got = keyposes.key_pose_instances(texture, None, path)
    assert all(nxt[a] == b for a, b in itertools.pairwise(got))
    assert np.all(segs[got, 3] == path)
    # paths of one and two textons
    assert keyposes.key_pose_instances(texture, None, path[:1]).shape == (1,)
    two = keyposes.key_pose_instances(texture, jax.random.key(0), path[:2])
    assert nxt[two[0]] == two[1]


def test_outlier_key_poses_are_used_only_when_nothing_else_is_there(texture):
    """A key-pose pair with a glitch (a jump far beyond the other pairs') is not chosen, even
    where it would replay a training transition; a texton with only glitches still gets one."""
    texture = many_instances(texture, seed=2)
    lab = np.asarray(texture.key_pose_labels)
    nxt = keyposes.next_segments(texture)
    kp = np.array(texture.key_poses)
    rng = np.random.default_rng(0)
    kp[:, 1] = kp[:, 0] + 0.05 * rng.standard_normal(kp[:, 0].shape)  # smooth pairs
    texture = eqx.tree_at(lambda t: t.key_poses, texture, jnp.asarray(kp))
    _, before = usable_reference(texture)
    # the successor of some segment in its clip becomes a glitch: the second frame of the pair
    # is the first one with every channel moved by one standard deviation
    a = int(np.flatnonzero((nxt >= 0) & (np.bincount(lab)[lab[np.maximum(nxt, 0)]] > 1))[0])
    g = int(nxt[a])
    kp[g, 1] = kp[g, 0] + 1.0
    tex = eqx.tree_at(lambda t: t.key_poses, texture, jnp.asarray(kp))
    usable, jumps = usable_reference(tex)
    np.testing.assert_allclose(keyposes.key_pair_jumps(tex), jumps, rtol=1e-9, atol=1e-12)
    assert not usable[g] and jumps[g] > 3 * np.max(before)
    path = lab[[a, g]]
    for key in (None, jax.random.key(0), jax.random.key(1)):
        got = keyposes.key_pose_instances(tex, key, path)
        assert got[1] != g and lab[got[1]] == lab[g]
    assert np.array_equal(keyposes.usable_key_poses(tex), usable)
    # every pair of that texton a glitch: they stay candidates
    for j in np.flatnonzero(lab == lab[g]):
        kp[j, 1] = kp[j, 0] + 1.0
    tex = eqx.tree_at(lambda t: t.key_poses, texture, jnp.asarray(kp))
    got = keyposes.key_pose_instances(tex, None, path)
    assert lab[got[1]] == lab[g] and not keyposes.usable_key_poses(tex)[got[1]]


def test_outlier_rule_without_feature_map_and_degenerate_jumps(texture):
    """Raw-array textures measure the jump in observation space; equal jumps, mostly static
    pairs and a NaN pair are handled (nothing flagged / nothing flagged / the NaN pair)."""
    texture = eqx.tree_at(lambda t: t.feature_map, many_instances(texture, seed=3), None)
    assert texture.feature_map is None
    kp = np.array(texture.key_poses)
    n, D = kp.shape[0], kp.shape[-1]
    rng = np.random.default_rng(5)
    step = rng.standard_normal((n, D))
    step /= np.linalg.norm(step, axis=1, keepdims=True)

    def with_jumps(j):
        k = kp.copy()
        k[:, 1] = k[:, 0] + j[:, None] * step
        return eqx.tree_at(lambda t: t.key_poses, texture, jnp.asarray(k))

    j = rng.uniform(0.5, 1.0, n)
    j[[3, 11]] = [4.0, 9.0]  # two glitches
    tex = with_jumps(j)
    np.testing.assert_allclose(keyposes.key_pair_jumps(tex), j, rtol=1e-9)
    assert np.flatnonzero(~keyposes.usable_key_poses(tex)).tolist() == [3, 11]
    assert keyposes.usable_key_poses(with_jumps(np.full(n, 0.7))).all()
    static = np.zeros(n)
    static[: n // 5] = 1e-6  # most pairs do not move: the moving ones are not outliers
    assert keyposes.usable_key_poses(with_jumps(static)).all()
    k = kp.copy()
    k[:, 1] = k[:, 0] + j[:, None] * step
    k[5, 1, 0] = np.nan
    usable = keyposes.usable_key_poses(eqx.tree_at(lambda t: t.key_poses, texture, jnp.asarray(k)))
    assert np.flatnonzero(~usable).tolist() == [3, 5, 11]


def test_given_path_with_n_frames_rescales_lengths(texture):
    path = [0, 1, 2]
    s = mj.synthesize(jax.random.key(1), texture, path=path, n_frames=100)
    assert int(np.asarray(s.lengths).sum()) == 100 and s.n_frames == 100
    with pytest.raises(ValueError, match="sum to"):
        mj.synthesize(None, texture, path=path, lengths=[10, 10, 10], n_frames=31)


def test_match_texton_is_the_two_frame_segment_likelihood(texture):
    pair = np.asarray(texture.key_poses)[3]
    best, score = mj.texture.match_texton(texture, pair)
    ref = [
        float(mj.texture.segment_log_likelihood(texton(texture, i), jnp.asarray(pair)))
        for i in range(texture.n_textons)
    ]
    np.testing.assert_allclose(score, ref, rtol=1e-9, atol=1e-9)
    assert best == int(np.argmax(ref))
    _, end_score = mj.texture.match_texton(texture, pair, role="end")
    _, obs = mj.texture.frame_terms(texture.textons, jnp.asarray(pair))
    np.testing.assert_allclose(end_score, np.asarray(obs).sum(axis=1), rtol=1e-12)


@pytest.mark.parametrize("n_frames", [None, 150])
def test_choreograph_starts_and_ends_at_the_given_poses(texture, n_frames):
    walk = mj.load_example("walk").resample(30.0)
    dance = mj.load_example("dance_b").resample(30.0)
    fm = texture.feature_map
    start = np.asarray(fm.encode(walk))[5:7]
    end = np.asarray(fm.encode(dance))[20:22]
    for residual in ("blend", "subspace"):
        s = mj.choreograph(jax.random.key(0), texture, start, end, n_frames, residual=residual)
        Y, path = np.asarray(s.Y), np.asarray(s.path)
        if n_frames is not None:
            assert s.n_frames == n_frames
        assert path[0] == mj.texture.match_texton(texture, start)[0]
        assert path[-1] == mj.texture.match_texton(texture, end, role="end")[0]
        if residual == "blend":
            np.testing.assert_allclose(Y[:2], start, atol=1e-9)
            np.testing.assert_allclose(Y[-2:], end, atol=1e-9)
        else:
            np.testing.assert_allclose(Y[:2], proj(texton(texture, path[0]), start), atol=1e-9)
            np.testing.assert_allclose(Y[-2:], proj(texton(texture, path[-1]), end), atol=1e-9)


def test_same_sizes_do_not_recompile(texture, monkeypatch):
    counted = eqx.filter_jit(eqx.debug.assert_max_traces(sequence.path_core, max_traces=1))
    monkeypatch.setattr("mtex_jax.texture._synthesis.sequence._path_core_jit", counted)
    for seed in range(3):  # different paths, same padded sizes
        mj.synthesize(jax.random.key(seed), texture, path=[0, 1, 2], lengths=[20, 21, 22])


def test_float32_texture_synthesises_in_float32(texture):
    t32 = jax.tree.map(
        lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a, texture
    )
    s = mj.synthesize(jax.random.key(0), t32, n_frames=60, decode=False)
    assert s.Y.dtype == jnp.float32 and np.isfinite(np.asarray(s.Y)).all() and s.motion is None


def test_errors(texture):
    D = texture.obs_dim
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="give a path or n_frames"):
        mj.synthesize(key, texture)
    with pytest.raises(ValueError, match="needs a key"):
        mj.synthesize(None, texture, n_frames=50)
    with pytest.raises(ValueError, match="labels outside"):
        mj.synthesize(key, texture, path=[0, texture.n_textons])
    with pytest.raises(ValueError, match="lengths must be"):
        mj.synthesize(key, texture, path=[0, 1], lengths=[10])
    with pytest.raises(ValueError, match=">= 2 frames"):
        mj.synthesize(key, texture, path=[0, 1], lengths=[10, 1])
    with pytest.raises(ValueError, match="n_frames must be >= 4"):
        mj.synthesize(key, texture, n_frames=3)
    with pytest.raises(ValueError, match=r"shape \(2, "):
        mj.synthesize(key, texture, n_frames=50, start=np.zeros((3, D)))
    with pytest.raises(ValueError, match="NaN"):
        mj.choreograph(key, texture, np.full((2, D), np.nan), np.zeros((2, D)))
    with pytest.raises(ValueError, match="weighting"):
        mj.synthesize(key, texture, n_frames=50, weighting="dense")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="residual"):
        mj.synthesize(key, texture, n_frames=50, residual="none")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="too few"):
        mj.choreograph(key, texture, np.zeros((2, D)), np.ones((2, D)), n_frames=5)
    with pytest.raises(TypeError, match="MotionTexture"):
        mj.synthesize(key, texture.M, n_frames=50)


def test_transition_default_and_bad_values(texture):
    """``transition="auto"`` is ``DEFAULT_TRANSITION`` seconds for a texture with a frame rate
    (design §10.11); it changes the motion but not the held key poses; bad values are
    rejected by name, and seconds need a frame rate."""
    key = jax.random.key(4)
    auto = mj.synthesize(key, texture, n_frames=300)
    same = mj.synthesize(key, texture, n_frames=300, transition=mj.texture.DEFAULT_TRANSITION)
    spread = mj.synthesize(key, texture, n_frames=300, transition=None)
    np.testing.assert_array_equal(np.asarray(auto.Y), np.asarray(same.Y))
    np.testing.assert_array_equal(np.asarray(auto.path), np.asarray(spread.path))
    assert not np.allclose(np.asarray(auto.Y), np.asarray(spread.Y), atol=1e-6)
    kp = np.asarray(texture.key_poses)
    for b, k in zip(np.asarray(auto.starts), np.asarray(auto.key_segments), strict=True):
        np.testing.assert_allclose(np.asarray(auto.Y)[b : b + 2], kp[k], rtol=0, atol=1e-9)
    for bad, err in [("slow", ValueError), (True, TypeError), ("0.2", ValueError)]:
        with pytest.raises(err, match="transition"):
            mj.synthesize(key, texture, n_frames=300, transition=bad)
    for bad in [0.0, -1.0, float("nan"), float("inf"), 0.5 / 30.0]:
        with pytest.raises(ValueError, match="transition"):
            mj.synthesize(key, texture, n_frames=300, transition=bad)
    raw = dataclasses.replace(texture, feature_map=None, contacts=None)
    with pytest.raises(ValueError, match="frame rate"):
        mj.synthesize(key, raw, n_frames=300, transition=0.25)
    # without a frame rate "auto" is the exact conditional sample
    np.testing.assert_allclose(
        np.asarray(mj.synthesize(key, raw, n_frames=300, decode=False).Y),
        np.asarray(spread.Y),
        rtol=1e-12,
        atol=1e-12,
    )
