"""Implicit-model synthesis extensions (issue 18): velocity form, blending, continuation,
look-ahead, run cap, leaf rules, body weighting of the database and the choice of ``b`` by
explained variance — each against a NumPy re-derivation or an exhaustive search."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import mtex_jax as mj
from mtex_jax.implicit import ImplicitModel, SynthesisConfig, fade_weight, pose_vectors
from mtex_jax.implicit._seams import seam_weights
from traces import count_traces

WINDOW = 6
N = 48


@pytest.fixture(scope="module")
def clips(cmu_motions):
    m = [c.resample(30.0) for c in cmu_motions[:3]]
    return [c[i : i + 128] for c in m for i in range(0, c.n_frames - 127, 128)]


@pytest.fixture(scope="module")
def model(clips) -> ImplicitModel:
    return mj.implicit.learn(clips[1:], WINDOW)


def _lock(model: ImplicitModel, cfg: SynthesisConfig, prev, new, ex_prev, ex_new, i, delta):
    """The foot lock of ``_feet``'s docstring in NumPy (FK through the feature map's decode)."""
    fm = model.feature_map
    feet = list(model.database.feet)
    g = np.asarray(fm.joint_positions(np.stack([prev, new])))[:, feet]
    e = np.asarray(fm.joint_positions(np.stack([ex_prev, ex_new])))[:, feet]
    slide = (g[1] - g[0]) - (e[1] - e[0])
    c = np.asarray(model.database.foot_contact)[i]
    delta = cfg.lock_smoothing * delta + (1 - cfg.lock_smoothing) * (
        (c[:, None] * slide).sum(0) / max(c.sum(), 1.0)
    )
    _, h0, h1 = mj.motion.ground_axes(fm.skeleton.up_axis)
    act = list(fm.active)
    new = new.copy()
    new[act.index(0)] -= cfg.foot_lock * delta[h0] / float(fm.scale[0])
    new[act.index(1)] -= cfg.foot_lock * delta[h1] / float(fm.scale[1])
    return new, delta


def _smooth_seams(raw, before, seams, width, keep):
    """``_seams``'s docstring frame by frame: the nearest seam by enumeration."""
    out, at = raw.copy(), np.flatnonzero(seams)
    for t in range(len(raw)):
        m = max(0.0, 1.0 - np.min(np.abs(at - t)) / width) if at.size else 0.0
        prev = raw[t - 1] if t > 0 else before
        nxt = raw[t + 1] if t + 1 < len(raw) else raw[t]
        out[t] = raw[t] + m * ((prev + 2 * raw[t] + nxt) / 4 - raw[t])
        out[t, keep] = raw[t, keep]
    return out


def _reference(model: ImplicitModel, seed_y, idx, cfg: SynthesisConfig) -> np.ndarray:
    """The generator of ``_synthesis``'s docstring in NumPy, for given example indices."""
    dim = model.feature_map.dim
    succ = np.asarray(model.database.successors)
    y_next, dy = succ[:, :dim], succ[:, dim:]
    clip = np.asarray(model.database.clip_index)
    vel = np.zeros(dim, bool)
    vel[list(mj.implicit.velocity_channels(model.feature_map))] = True
    prev, cur, off, age, out = seed_y[-1], -1, np.zeros(dim), 0, []
    delta, seams = np.zeros(3), []
    for i in idx:
        cont = cur >= 0 and i == cur + 1 and i < len(clip) and clip[i] == clip[cur]
        seams.append(not cont)
        if not cont:
            off = prev - (y_next[i] - dy[i]) if cfg.velocity else np.zeros(dim)
            age = 0
        age += 1
        if cfg.blend > 0:
            x = min(age / (cfg.blend + 1), 1.0)
            w = np.full(dim, 1 - (3 * x * x - 2 * x**3))
            if cfg.root_blend >= 0:  # root velocity channels: their own fade (0: none)
                xr = min(age / (cfg.root_blend + 1), 1.0)
                w[vel] = 1 - (3 * xr * xr - 2 * xr**3) if cfg.root_blend > 0 else 0.0
        else:
            w = np.where(vel, 0.0, 1.0)
        new = y_next[i] + w * off
        if cfg.foot_lock > 0:
            new, delta = _lock(model, cfg, prev, new, y_next[i] - dy[i], y_next[i], i, delta)
        prev = new
        out.append(prev)
        cur = i
    if cfg.seam_smoothing == 0:
        return np.asarray(out)
    return _smooth_seams(np.asarray(out), seed_y[-1], seams, cfg.seam_smoothing, vel)


_CONFIGS = [
    SynthesisConfig(),
    SynthesisConfig(blend=0, continuation=1, max_run=0, candidates=1, leaf="weighted"),
    SynthesisConfig(blend=7, continuation=3, lookahead=3, leaf="uniform", candidates=4),
    SynthesisConfig(leaf_cap=2, candidates=3),
    SynthesisConfig(root_blend=-1, seam_smoothing=4, continuation=2),
    SynthesisConfig(blend=4, root_blend=0, continuation=3, seam_smoothing=1),
    SynthesisConfig(foot_lock=0.0, seam_smoothing=0),
    SynthesisConfig(foot_lock=0.5, lock_smoothing=0.0, continuation=2),
    SynthesisConfig.paper(),
]
# every configuration with the tree sampler; with the exact sampler (the same generator, only
# the search differs) the defaults and the paper's in the default run, the rest when CI has time
_CASES = [pytest.param(c, "tree") for c in _CONFIGS] + [
    pytest.param(c, "exact", marks=() if i in (0, len(_CONFIGS) - 1) else pytest.mark.slow)
    for i, c in enumerate(_CONFIGS)
]


@pytest.mark.parametrize(("cfg", "sampler"), _CASES)
def test_poses_follow_the_numpy_rederivation(model, clips, cfg, sampler):
    y, idx = model.synthesize_poses(
        jax.random.PRNGKey(3), clips[0], N, 1.0, sampler=sampler, config=cfg
    )
    y, idx = np.asarray(y), np.asarray(idx)
    ref = _reference(model, y[:WINDOW], idx, cfg)
    np.testing.assert_allclose(y[WINDOW:], ref, atol=1e-9)


def test_velocity_form_applies_the_examples_change_of_pose(model, clips):
    """Pure velocity form (blend 0): every generated frame moves by the example's own change
    of pose, ŷ_{t+1} − ŷ_t = Δy(e) (pose channels), even across transitions."""
    cfg = SynthesisConfig(blend=0, continuation=1, max_run=0, seam_smoothing=0)
    y, idx = model.synthesize_poses(jax.random.PRNGKey(5), clips[0], N, 1.0, config=cfg)
    y, idx = np.asarray(y), np.asarray(idx)
    dim = model.feature_map.dim
    pose = np.ones(dim, bool)
    pose[list(mj.implicit.velocity_channels(model.feature_map))] = False
    step = np.diff(y[WINDOW - 1 :], axis=0)
    dy = np.asarray(model.database.successors)[idx, dim:]
    np.testing.assert_allclose(step[:, pose], dy[:, pose], atol=1e-9)
    assert len(set(idx.tolist())) > 5  # transitions happened


def test_blending_rejoins_the_example_after_blend_frames(model, clips):
    """With blend B, B + 1 frames after a transition the pose is the example's own pose."""
    b = 3
    cfg = SynthesisConfig(
        blend=b, continuation=8, lookahead=8, max_run=0, foot_lock=0.0, seam_smoothing=0
    )
    y, idx = model.synthesize_poses(jax.random.PRNGKey(2), clips[0], N, 1.0, config=cfg)
    y, idx = np.asarray(y)[WINDOW:], np.asarray(idx)
    dim = model.feature_map.dim
    succ_y = np.asarray(model.database.successors)[:, :dim]
    for t in range(0, N - b - 1, 8):  # searches at 0, 8, 16, …; 8 frames played from each
        np.testing.assert_allclose(y[t + b : t + 8], succ_y[idx[t + b : t + 8]], atol=1e-9)


def test_root_blend_fades_the_root_velocity_on_its_own(model, clips):
    """root_blend B_r: the root-velocity channels rejoin the example's values B_r + 1 frames
    after a transition while the pose channels still carry their offset (B_r = 0 and −1:
    ``test_poses_follow_the_numpy_rederivation``)."""
    dim = model.feature_map.dim
    vel = np.zeros(dim, bool)
    vel[list(mj.implicit.velocity_channels(model.feature_map))] = True
    succ_y = np.asarray(model.database.successors)[:, :dim]
    key = jax.random.PRNGKey(4)
    rb = 2
    cfg = SynthesisConfig(
        blend=6,
        root_blend=rb,
        continuation=8,
        lookahead=8,
        max_run=0,
        foot_lock=0.0,
        seam_smoothing=0,
    )
    y, idx = model.synthesize_poses(key, clips[0], N, 1.0, config=cfg)
    y, idx = np.asarray(y)[WINDOW:], np.asarray(idx)
    for t in range(0, N - 8, 8):  # a search every 8 frames
        got, ex = y[t + rb : t + 8], succ_y[idx[t + rb : t + 8]]
        np.testing.assert_allclose(got[:, vel], ex[:, vel], atol=1e-9)
    assert np.abs(y[:, ~vel] - succ_y[idx][:, ~vel]).max() > 1e-3  # pose offsets remain


def test_continuation_lookahead_and_run_cap(model, clips):
    """continuation c: a search every c frames, examples continue in between; look-ahead L:
    every searched example has ≥ L further frames in its clip; max_run caps verbatim runs."""
    c, la, cap = 4, 6, 8
    cfg = SynthesisConfig(continuation=c, lookahead=la, max_run=cap)
    _, idx = model.synthesize_poses(jax.random.PRNGKey(1), clips[0], 96, 1.0, config=cfg)
    idx = np.asarray(idx)
    clip = np.asarray(model.database.clip_index)
    remaining = np.array([np.sum(clip[i + 1 :] == clip[i]) for i in range(len(clip))])
    for t in range(1, len(idx)):
        if t % c:
            assert idx[t] == idx[t - 1] + 1
    assert np.all(remaining[idx[::c]] >= la)
    run, longest = 1, 1
    for t in range(1, len(idx)):
        run = run + 1 if idx[t] == idx[t - 1] + 1 and clip[idx[t]] == clip[idx[t - 1]] else 1
        longest = max(longest, run)
    assert longest <= cap


@pytest.mark.parametrize("leaf", ["uniform", "weighted", "exact"])
def test_tree_at_tiny_beta_agrees_with_exhaustive_search(model, clips, leaf):
    """From a database clip at β → 0 the exhaustive nearest window of each history is the
    clip's own next window; the tree (own leaf) with the exact leaf rule finds it too, so
    paper-style synthesis replays the clip. Uniform/weighted leaves may pick another member
    of the leaf, which must then share the sign code of the exhaustive answer."""
    cfg = SynthesisConfig(
        velocity=False,
        blend=0,
        leaf=leaf,
        lookahead=0,
        continuation=1,
        max_run=0,
        candidates=1,
        leaf_cap=0,
        hubness=0.0,
    )
    clip = clips[2]
    _, it = model.synthesize_poses(jax.random.PRNGKey(0), clip, 30, 1e-9, config=cfg)
    _, ie = model.synthesize_poses(
        jax.random.PRNGKey(0), clip, 30, 1e-9, config=cfg, sampler="exact"
    )
    it, ie = np.asarray(it), np.asarray(ie)
    w = np.asarray(model.database.windows)
    probes = np.asarray(model.windows_of(clip))[:30]
    brute = np.argmin(((probes[:, None] - w[None]) ** 2).sum(-1), axis=1)
    np.testing.assert_array_equal(ie[:1], brute[:1])
    first = model.database.clip_sizes[0]
    np.testing.assert_array_equal(ie, first + np.arange(30))
    codes = np.asarray(model.database.codes)
    if leaf == "exact":
        np.testing.assert_array_equal(it, ie)
    else:
        assert codes[it[0]] == codes[ie[0]]


def _brute_radius(w, clip, frame, d, k):
    out = np.zeros(len(w))
    for i in range(len(w)):
        d2 = ((w - w[i]) ** 2).sum(-1)
        ok = ~((clip == clip[i]) & (np.abs(frame - frame[i]) <= d))
        if ok.any():
            out[i] = np.sort(d2[ok])[:k].mean()
    return out


@settings(deadline=None, max_examples=15)
@given(st.integers(0, 2**31 - 1), st.integers(1, 4), st.integers(1, 6))
def test_neighbour_radius_against_brute_force(seed, n_clips, k):
    from mtex_jax.implicit._hubness import neighbour_radius

    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 40))
    w = rng.standard_normal((n, 5))
    clip = np.sort(rng.integers(0, n_clips, n))
    frame = np.concatenate([np.arange(np.sum(clip == c)) for c in np.unique(clip)])
    d = int(rng.integers(0, 4))
    np.testing.assert_allclose(
        neighbour_radius(w, clip, frame, d, k), _brute_radius(w, clip, frame, d, k), rtol=1e-4
    )


def test_model_neighbour_radius_and_hubness_kernel(model, clips):
    """The model's r_i is the mean squared distance to the 10 nearest non-overlapping windows,
    and the exact sampler at β → 0 picks argmin ‖Ψ_i − Φ‖² − h r_i over admissible examples."""
    w = np.asarray(model.database.windows)
    clip, frame = np.asarray(model.database.clip_index), np.asarray(model.database.frame_index)
    r = _brute_radius(w, clip, frame, WINDOW, 10)
    np.testing.assert_allclose(np.asarray(model.database.neighbour_radius), r, rtol=1e-4)
    probe = np.asarray(model.windows_of(clips[0]))[0]
    d2 = ((w - probe) ** 2).sum(-1)
    rem = np.array([np.sum(clip[i + 1 :] == clip[i]) for i in range(len(clip))])
    for h in (0.0, 0.2, 1.0):
        cfg = SynthesisConfig(continuation=1, lookahead=4, max_run=0, hubness=h)
        _, idx = model.synthesize_poses(
            jax.random.PRNGKey(0), clips[0], 1, 1e-9, config=cfg, sampler="exact"
        )
        score = np.where(rem >= 4, d2 - h * r, np.inf)
        assert int(idx[0]) == int(np.argmin(score)), h
    assert SynthesisConfig.paper().hubness == 0.0
    assert SynthesisConfig().hubness > 0.0


def test_no_recompile_for_new_keys_betas_and_starts(model, clips):
    cfg = SynthesisConfig()
    model.synthesize_poses(jax.random.PRNGKey(0), clips[0], 20, 1.0, config=cfg)
    with count_traces() as seen:
        for k in range(3):
            model.synthesize_poses(jax.random.PRNGKey(k), clips[k + 1], 20, 0.5 + k, config=cfg)
    assert seen["synthesize_scan"] == 0


def test_float32_smoke(clips):
    c32 = [
        mj.Motion(
            c.skeleton,
            c.fps,
            np.asarray(c.root_positions, np.float32),
            np.asarray(c.rotations, np.float32),
        )
        for c in clips[:3]
    ]
    m = mj.implicit.learn(c32, WINDOW)
    assert m.database.windows.dtype == np.float32
    out = m.synthesize(jax.random.PRNGKey(0), c32[0], 30, 1.0)
    assert np.asarray(out.rotations).dtype == np.float32
    assert np.all(np.isfinite(np.asarray(out.rotations)))


# --------------------------------------------------------------------------- database
def test_joint_reach_against_path_enumeration(model):
    sk = model.feature_map.skeleton
    off = np.linalg.norm(np.asarray(sk.offsets), axis=1)
    children = {
        j: [c for c in range(sk.n_joints) if sk.parents[c] == j] for j in range(sk.n_joints)
    }
    sites = {j: [np.linalg.norm(o) for p, o in sk.end_sites if p == j] for j in range(sk.n_joints)}

    def far(j):
        best = max(sites[j], default=0.0)
        return max([best] + [off[c] + far(c) for c in children[j]])

    np.testing.assert_allclose(
        mj.implicit.joint_reach(model.feature_map),
        np.array([far(j) for j in range(sk.n_joints)]),
        atol=1e-12,
    )


def test_body_weighting_whitens_pose_and_velocity_groups(model, clips):
    """γ_c · m_c is one number per group and the mean variance of ψ/γ over a group is 1."""
    psi = np.concatenate([pose_vectors(model.feature_map, c) for c in clips[1:]])
    gamma = np.asarray(model.database.gamma)
    imp = np.tile(mj.implicit.channel_importance(model.feature_map), 2)
    p = psi.shape[1]
    for half in (slice(0, p // 2), slice(p // 2, p)):
        g = gamma[half] * imp[half]
        np.testing.assert_allclose(g, g[0], rtol=1e-10)
        np.testing.assert_allclose(
            np.mean((psi[:, half] / gamma[half]).var(axis=0)), 1.0, rtol=1e-8
        )
    assert model.weighting == "body"


def test_min_explained_picks_the_fewest_components(model, clips):
    target = 0.6
    m = mj.implicit.learn(clips[1:], WINDOW, min_explained=target, feature_map=model.feature_map)
    w = np.asarray(m.database.windows)
    s = np.linalg.svd(w - w.mean(0), compute_uv=False)
    frac = np.cumsum(s**2) / np.sum(s**2)
    b = m.database.n_components
    assert frac[b - 1] >= target - 1e-9 > frac[b - 2]
    np.testing.assert_allclose(m.explained_variance, frac[b - 1], rtol=1e-8)


@settings(deadline=None, max_examples=30)
@given(st.integers(1, 20), st.integers(0, 40))
def test_fade_weight_is_a_smooth_step(blend, age):
    w = float(fade_weight(jnp.asarray(age, jnp.float64), blend))
    x = min(age / (blend + 1), 1.0)
    assert w == pytest.approx(1 - (3 * x * x - 2 * x**3), abs=1e-12)
    assert 0.0 <= w <= 1.0
    if age >= blend + 1:
        assert w == 0.0


@settings(deadline=None, max_examples=40)
@given(st.lists(st.booleans(), min_size=1, max_size=30), st.integers(1, 6))
def test_seam_weights_against_enumeration(seams, width):
    """m_t = max(0, 1 − |t − s(t)| / S) with s(t) the nearest seam, by enumeration."""
    got = np.asarray(seam_weights(jnp.asarray(seams), width))
    at = np.flatnonzero(seams)
    want = [
        max(0.0, 1.0 - np.min(np.abs(at - t)) / width) if at.size else 0.0
        for t in range(len(seams))
    ]
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_seam_smoothing_lowers_the_jerk_at_transitions(model, clips):
    """The same examples with and without seam smoothing: frames ≥ S from a seam are equal;
    the mean squared third difference of the pose channels at the seams drops."""
    key, n = jax.random.PRNGKey(8), 120
    on = SynthesisConfig()
    off = SynthesisConfig(seam_smoothing=0)
    y1, i1 = model.synthesize_poses(key, clips[0], n, 1.0, config=on)
    y0, i0 = model.synthesize_poses(key, clips[0], n, 1.0, config=off)
    np.testing.assert_array_equal(np.asarray(i1), np.asarray(i0))
    y1, y0, idx = np.asarray(y1)[WINDOW:], np.asarray(y0)[WINDOW:], np.asarray(i1)
    seams = np.r_[True, idx[1:] != idx[:-1] + 1]
    at = np.flatnonzero(seams)
    far = np.array([np.min(np.abs(at - t)) >= on.seam_smoothing for t in range(n)])
    np.testing.assert_array_equal(y1[far], y0[far])
    pose = np.ones(y0.shape[1], bool)
    pose[list(mj.implicit.velocity_channels(model.feature_map))] = False
    j1 = np.diff(y1[:, pose], n=3, axis=0)
    j0 = np.diff(y0[:, pose], n=3, axis=0)
    near = np.zeros(n - 3, bool)
    for s in at[(at >= 3) & (at < n - 3)]:
        near[s - 3 : s + 1] = True  # third differences that span the seam
    assert np.mean(j1[near] ** 2) < 0.7 * np.mean(j0[near] ** 2)


def test_bad_options_raise_clear_errors(model, clips):
    key = jax.random.PRNGKey(0)
    bad: tuple[tuple[dict[str, Any], str], ...] = (
        ({"blend": -1}, "blend"),
        ({"continuation": 0}, "continuation"),
        ({"lookahead": 1.5}, "lookahead"),
        ({"max_run": -2}, "max_run"),
        ({"candidates": 0}, "candidates"),
        ({"leaf_cap": -1}, "leaf_cap"),
        ({"hubness": -0.1}, "hubness"),
        ({"hubness": float("inf")}, "hubness"),
        ({"hubness": True}, "hubness"),
        ({"root_blend": -2}, "root_blend"),
        ({"root_blend": 1.5}, "root_blend"),
        ({"leaf": "nearest"}, "leaf"),
        ({"velocity": 1}, "velocity"),
        ({"velocity": False, "blend": 3}, "blend"),
        ({"foot_lock": 1.5}, "foot_lock"),
        ({"seam_smoothing": -1}, "seam_smoothing"),
        ({"seam_smoothing": 1.5}, "seam_smoothing"),
        ({"seam_smoothing": True}, "seam_smoothing"),
        ({"foot_lock": -0.1}, "foot_lock"),
        ({"foot_lock": True}, "foot_lock"),
        ({"lock_smoothing": 1.0}, "lock_smoothing"),
        ({"lock_smoothing": float("nan")}, "lock_smoothing"),
    )
    for kw, name in bad:
        with pytest.raises(ValueError, match=name):
            SynthesisConfig(**kw)
    with pytest.raises(ValueError, match="config"):
        model.synthesize(key, clips[0], 5, 1.0, config={"blend": 2})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="leaf"):
        model.synthesize(key, clips[0], 5, 1.0, leaf="nearest")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="weighting"):
        mj.implicit.learn(clips[1:3], WINDOW, weighting="joint")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="min_explained"):
        mj.implicit.learn(clips[1:3], WINDOW, min_explained=1.5)
    for bad_w in (-1.0, float("nan"), "3", True):
        with pytest.raises(ValueError, match="recent_weight"):
            mj.implicit.learn(clips[1:3], WINDOW, recent_weight=bad_w)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="not both"):
        mj.implicit.learn(clips[1:3], WINDOW, min_explained=0.5, n_components=4)


# --------------------------------------------------------------------------- CLI
def test_cli_synthesis_options(tmp_path, capsys):
    from mtex_jax.cli import main

    out = tmp_path / "s.bvh"
    base = [
        "implicit-synth",
        "example:walk",
        "example:run",
        "-o",
        str(out),
        "--frames",
        "20",
        "--window",
        "5",
    ]
    opts = [
        "--paper",
        "--leaf",
        "exact",
        "--continuation",
        "3",
        "--weighting",
        "channel",
        "--min-explained",
        "0.8",
        "--sampler",
        "exact",
        "--hubness",
        "0.3",
        "--root-blend",
        "2",
        "--recent-weight",
        "0",
        "--foot-lock",
        "0.5",
        "--seam-smoothing",
        "3",
    ]
    assert main(base + opts) == 0
    assert "wrote" in capsys.readouterr().out
    assert mj.read_bvh(out).n_frames == 25
    for bad, word in (
        (["--blend", "-1"], "blend"),
        (["--continuation", "0"], "continuation"),
        (["--min-explained", "2"], "min-explained"),
        (["--paper", "--blend", "3"], "blend"),
        (["--max-run", "-3"], "max-run"),
        (["--leaf-cap", "-1"], "leaf-cap"),
        (["--hubness", "-1"], "hubness"),
        (["--root-blend", "-2"], "root-blend"),
        (["--foot-lock", "1.5"], "foot-lock"),
        (["--seam-smoothing", "-1"], "seam-smoothing"),
        (["--recent-weight", "-1"], "recent-weight"),
    ):
        assert main(base + bad) == 2
        err = capsys.readouterr().err
        assert word in err and err.count("\n") == 1, (bad, err)
