"""Learning a motion texture: recovery of a known texture, EM behaviour, real data, files."""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

import mtex_jax as mj
from cpu_devices import run_with_cpu_devices
from mtex_jax.texture import LearnConfig, MotionTexture, learn, load_texture
from paper_settings import PAPER, UNTIED


# ---------------------------------------------------------------------------------------------
# A known motion texture: 5 textons with distinct dynamics, D = 30, k = 4
# ---------------------------------------------------------------------------------------------
def make_textons(rng, n_t=5, D=30, k=4):
    out = []
    for i in range(n_t):
        freqs = rng.uniform(0.05, 0.4, size=k // 2) * (1 + 0.3 * i)
        A1 = np.zeros((k, k))
        A2 = np.zeros((k, k))
        r = 0.97
        for j, f in enumerate(freqs):  # damped oscillators: x_t = 2r cos ω x_{t−1} − r² x_{t−2}
            A1[2 * j, 2 * j] = 2 * r * np.cos(2 * np.pi * f)
            A1[2 * j + 1, 2 * j + 1] = 2 * r * np.cos(2 * np.pi * 1.3 * f)
            A2[2 * j, 2 * j] = A2[2 * j + 1, 2 * j + 1] = -r * r
        C, _ = np.linalg.qr(rng.normal(size=(D, k)))
        out.append((A1, A2, C, rng.normal(size=D)))
    return out


def sample_texture(rng, textons, n_seg=45, lo=40, hi=120):
    n_t = len(textons)
    k = textons[0][0].shape[0]
    M = rng.dirichlet(np.full(n_t, 0.5), size=n_t)
    np.fill_diagonal(M, 0.0)
    M /= M.sum(axis=1, keepdims=True)
    lab = int(rng.integers(n_t))
    ys, starts, labels, t = [], [], [], 0
    for _ in range(n_seg):
        L = int(rng.integers(lo, hi + 1))
        A1, A2, C, mu = textons[lab]
        x = np.zeros((L, k))
        x[0] = 2 * rng.normal(size=k)
        x[1] = 0.95 * x[0] + 0.3 * rng.normal(size=k)
        for i in range(2, L):
            x[i] = A1 @ x[i - 1] + A2 @ x[i - 2] + 0.15 * rng.normal(size=k)
        ys.append(mu + x @ C.T + 0.05 * rng.normal(size=(L, C.shape[0])))
        starts.append(t)
        labels.append(lab)
        t += L
        lab = int(rng.choice(n_t, p=M[lab]))
    return np.concatenate(ys), np.asarray(starts), np.asarray(labels)


def boundary_f1(pred, true, tol=3):
    pred, true = np.asarray(pred), np.asarray(true)
    precision = np.mean([np.min(np.abs(true - p)) <= tol for p in pred])
    recall = np.mean([np.min(np.abs(pred - t)) <= tol for t in true])
    return 2 * precision * recall / (precision + recall)


def label_accuracy(segs, starts, labels, T):
    truth = np.repeat(labels, np.diff(np.append(starts, T)))
    pred = np.full(T, -1)
    for _, b, L, i in segs:
        pred[b : b + L] = i
    C = np.zeros((pred.max() + 1, truth.max() + 1))
    np.add.at(C, (pred, truth), 1)
    r, c = linear_sum_assignment(-C)  # best one-to-one matching of texton ids
    return C[r, c].sum() / T


@pytest.mark.parametrize("seed", [0, 1])
def test_recovers_a_known_motion_texture(seed):
    rng = np.random.default_rng(seed)
    Y, starts, labels = sample_texture(rng, make_textons(rng))
    assert len(starts) >= 40 and len(set(labels.tolist())) == 5
    cfg = LearnConfig(tmin=40, tmax=120, state_dim=4, bic_thresholds=(0.1, 0.3, 1.0), **PAPER)
    mt = learn([Y], cfg)
    segs = np.asarray(mt.segments)
    f1 = boundary_f1(segs[:, 1], starts)
    acc = label_accuracy(segs, starts, labels, len(Y))
    assert f1 >= 0.9, f"boundary F1 {f1:.3f}"
    assert acc >= 0.95, f"label accuracy {acc:.3f}"
    assert np.all(segs[:, 2] >= 40) and np.all(segs[:, 2] <= 120)


@functools.cache
def _convergence_run(relabel_tol: float) -> tuple[int, LearnConfig, tuple[dict, ...]]:
    """Frames, config and the callback's figures of one learn with a coarse greedy threshold;
    cached, so that the run without a share (``relabel_tol=0``) is learned once for both cases
    of the test below."""
    rng = np.random.default_rng(3)
    Y, _, _ = sample_texture(rng, make_textons(rng))
    cfg = LearnConfig(
        tmin=40, tmax=120, state_dim=4, threshold=3.0, relabel_tol=relabel_tol, **PAPER
    )
    infos: list[dict] = []
    learn([Y], cfg, callback=infos.append)
    return len(Y), cfg, tuple(infos)


@pytest.mark.parametrize("relabel_tol", [0.0, 0.05])
def test_em_stops_at_its_convergence_test(relabel_tol):
    """EM stops at its first iteration where at most ``relabel_tol`` of the frames changed
    texton or the objective gained less than ``tol`` per frame (or at ``max_iter``), as the
    callback's figures show. With a coarse greedy threshold EM relabels 1014, 363, 50 and 0 of
    the 3,605 frames: a share of 0.05 stops it at the third iteration, on the same iterates."""
    n, cfg, infos = _convergence_run(relabel_tol)
    assert [i["iteration"] for i in infos] == list(range(len(infos)))  # one EM run
    assert all(i["pruned"] == 0 for i in infos)
    gains = np.diff([-np.inf] + [i["objective_e"] for i in infos])
    stop = [
        i["changed"] <= relabel_tol * n or g < cfg.tol * n
        for i, g in zip(infos, gains, strict=True)
    ]
    assert not any(stop[:-1])
    assert stop[-1] or infos[-1]["iteration"] == cfg.max_iter
    if relabel_tol > 0:  # the same iterates as without the share, stopped no later
        _, strict_cfg, strict = _convergence_run(0.0)  # the case above: learned once
        assert strict_cfg == dataclasses.replace(cfg, relabel_tol=0.0)
        assert len(strict) > len(infos)  # this share stops this run earlier
        want = [i["objective_e"] for i in strict[: len(infos)]]
        assert [i["objective_e"] for i in infos] == want


@pytest.mark.parametrize(
    ("field", "value"), [("tol", -1e-4), ("tol", float("nan")), ("relabel_tol", 1.0)]
)
def test_learn_config_rejects_bad_tolerances(field, value):
    with pytest.raises(ValueError, match=f"LearnConfig.{field}"):
        LearnConfig(**{field: value})


# ---------------------------------------------------------------------------------------------
# Real data
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def salsa_texture(cmu_motions):
    cfg = LearnConfig(tmin=60, tmax=180, state_dim=12, fps=60.0, threshold=0.3, max_iter=4, **PAPER)
    return learn(cmu_motions, cfg)


def test_learn_on_cmu_salsa(salsa_texture, cmu_motions):
    mt = salsa_texture
    segs = np.asarray(mt.segments)
    assert mt.n_textons >= 10
    assert np.all(segs[:, 2] >= 60) and np.all(segs[:, 2] <= 180)
    # every clip is covered exactly, in order
    for s, m in enumerate(cmu_motions):
        rows = segs[segs[:, 0] == s]
        assert rows[0, 1] == 0 and np.all(rows[1:, 1] == rows[:-1, 1] + rows[:-1, 2])
        assert rows[-1, 1] + rows[-1, 2] == m.resample(60.0).n_frames
    hist = np.asarray(mt.history)
    assert hist.ndim == 2 and hist.shape[1] == 2 and len(hist) >= 2
    # the returned model's objective (E-step) is at least the objective after initialisation
    assert hist[:, 1].max() >= hist[0, 0]
    np.testing.assert_allclose(np.asarray(mt.M).sum(axis=1), 1.0)
    assert np.all(np.asarray(mt.M) > 0)  # the pseudo-count keeps every transition possible
    assert abs(float(np.sum(np.asarray(mt.pi))) - 1.0) < 1e-12


def test_save_load_segment_round_trip(salsa_texture, cmu_motions, tmp_path):
    mt = salsa_texture
    p = tmp_path / "salsa.npz"
    mt.save(p)
    mt2 = load_texture(p)
    assert mt2.n_textons == mt.n_textons and mt2.config == mt.config
    clip = cmu_motions[3].resample(60.0)
    a = mt.segment(clip)
    b = mt2.segment(clip)
    assert a.to_list() == b.to_list()
    assert float(a.score) == float(b.score)
    # the learned segmentation of that clip is the model's optimal one
    rows = np.asarray(mt.segments)
    assert [tuple(r[1:]) for r in rows[rows[:, 0] == 3]] == a.to_list()


def test_model_file_errors(salsa_texture, tmp_path):
    p = tmp_path / "m.npz"
    salsa_texture.save(p)
    raw = p.read_bytes()
    trunc = tmp_path / "trunc.npz"
    trunc.write_bytes(raw[: len(raw) // 3])
    with pytest.raises(ValueError, match=r"trunc\.npz"):
        load_texture(trunc)
    fm_file = tmp_path / "fm.npz"
    salsa_texture.feature_map.save(fm_file)
    with pytest.raises(ValueError, match=r"expected a 'mtex_jax\.MotionTexture' file"):
        load_texture(fm_file)
    # wrong format version and a missing array, written with the same container
    from mtex_jax.core import load_arrays_json, save_arrays_json

    arrays, meta = load_arrays_json(p, kind="mtex_jax.MotionTexture")
    bad_meta = dict(meta, format_version=99)
    save_arrays_json(tmp_path / "v99.npz", arrays, bad_meta)
    with pytest.raises(ValueError, match="format version 99"):
        load_texture(tmp_path / "v99.npz")
    missing = {k: v for k, v in arrays.items() if k != "texton.A1"}
    save_arrays_json(tmp_path / "missing.npz", missing, meta)
    with pytest.raises(ValueError, match=r"texton\.A1"):
        load_texture(tmp_path / "missing.npz")


def test_learning_is_deterministic():
    rng = np.random.default_rng(7)
    Y, _, _ = sample_texture(rng, make_textons(rng), n_seg=20)
    cfg = LearnConfig(tmin=40, tmax=120, state_dim=4, threshold=0.5, max_iter=3, **PAPER)
    a = learn([Y[:900], Y[900:]], cfg)
    b = learn([Y[:900], Y[900:]], cfg)
    for x, y in zip(jax_leaves(a), jax_leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)


def jax_leaves(mt: MotionTexture) -> list[np.ndarray]:
    import jax

    return [np.asarray(v) for v in jax.tree.leaves(mt)]


def test_learn_input_errors():
    rng = np.random.default_rng(0)
    ok = rng.normal(size=(100, 6))
    cfg = LearnConfig(tmin=10, tmax=30, state_dim=2, **UNTIED)
    with pytest.raises(ValueError, match="empty"):
        learn([], cfg)
    with pytest.raises(ValueError, match="shorter than tmin"):
        learn([ok, ok[:5]], cfg)
    with pytest.raises(ValueError, match="D = 5"):
        learn([ok, ok[:, :5]], cfg)
    nan = ok.copy()
    nan[17, 2] = np.nan
    with pytest.raises(ValueError, match="NaN/inf in frame 17"):
        learn([ok, nan], cfg)
    with pytest.raises(ValueError, match="tmin"):
        LearnConfig(tmin=2)
    with pytest.raises(ValueError, match="tmax"):
        LearnConfig(tmin=10, tmax=9)
    with pytest.raises(ValueError, match="state_dim"):
        learn([ok], LearnConfig(tmin=10, tmax=30, state_dim=7, **UNTIED))
    with pytest.raises(ValueError, match="cannot be cut"):
        learn([ok[:25]], LearnConfig(tmin=10, tmax=12, state_dim=2, **UNTIED))
    with pytest.raises(TypeError, match="mixture"):
        learn([ok, mj.load_example("walk")], cfg)


@pytest.mark.slow  # the default run's budget (about 15 min); CI runs it after
def test_sharded_learning_equals_single_device(tmp_path):
    """Two CPU devices (XLA flag, in a subprocess): the same model as with one device."""
    script = """
        import os, sys
        import numpy as np
        import jax
        jax.config.update("jax_enable_x64", True)
        assert jax.device_count() == 2, jax.devices()
        sys.path[:0] = [os.environ["TESTS_DIR"], os.path.join(os.environ["TESTS_DIR"], "texture")]
        from test_learn import make_textons, sample_texture
        from mtex_jax.texture import LearnConfig, learn
        rng = np.random.default_rng(11)
        Y, _, _ = sample_texture(rng, make_textons(rng), n_seg=24)
        parts = [Y[:700], Y[700:1300], Y[1300:]]
        base = dict(tmin=40, tmax=120, state_dim=4, threshold=0.5, max_iter=3)
        base.update(observation="residual", init="greedy")
        one = learn(parts, LearnConfig(**base, shard=False))
        two = learn(parts, LearnConfig(**base, shard=True))
        assert np.array_equal(np.asarray(one.segments), np.asarray(two.segments))
        for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(two)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-9)
        print("SHARDED_OK", len(np.asarray(one.segments)))
        """
    run_with_cpu_devices(script, "SHARDED_OK", timeout=900)


def test_learn_does_not_shard_over_one_process_cpu_devices_by_default():
    """``LearnConfig.shard=None`` (default) keeps the data on one device when every device is
    a CPU device of this process (their collectives stalled a learn; see the slow test)."""
    import jax

    from mtex_jax.texture._learning.em import Runner

    ys = [np.zeros((50, 3)), np.zeros((40, 3))]
    cfg = LearnConfig(tmin=10, tmax=20, state_dim=2, **UNTIED)
    assert cfg.shard is None
    assert Runner(ys, cfg, devices=jax.devices() * 2).sharding is None


@pytest.mark.slow  # a fresh process (about a minute)
def test_learn_on_two_cpu_devices_finishes_and_equals_one(cmu_dir):
    """Two CPU devices (XLA flag, in a subprocess), two salsa clips, the default sharding: the
    learn finishes (with ``shard=True`` it stalled in an all-reduce that one device never
    joined) and gives the one-device model."""
    script = """
        import os, sys
        import numpy as np
        import jax
        jax.config.update("jax_enable_x64", True)
        assert jax.device_count() == 2, jax.devices()
        import mtex_jax as mj
        from mtex_jax.texture import LearnConfig, learn
        d = os.environ["CMU_DIR"]
        clips = [mj.io.read_bvh(os.path.join(d, f"60_0{i}.bvh")).resample(60.0) for i in (1, 2)]
        base = dict(
            tmin=60, tmax=180, state_dim=12, fps=60.0, min_segments=3, max_iter=3,
            observation="residual",
        )
        two = learn(clips, LearnConfig(**base))
        ref = learn(clips, LearnConfig(**base, shard=False))
        assert np.array_equal(np.asarray(two.segments), np.asarray(ref.segments))
        print("TWO_CPU_OK", two.n_textons)
        """
    run_with_cpu_devices(script, "TWO_CPU_OK", timeout=600, CMU_DIR=str(cmu_dir))


def test_learn_float32_smoke():
    """float32 in, float32 out, finite: short, very different clips stress the fits."""
    import jax
    import jax.numpy as jnp

    clips = [mj.load_example(n).resample(30.0) for n in ["crawl", "dance_a", "kick", "spin"]]
    fm = mj.FeatureMap.fit(clips)
    ys = [np.asarray(fm.encode(m), dtype=np.float32) for m in clips]
    mt = learn(ys, LearnConfig(tmin=18, tmax=54, state_dim=6, max_iter=2, **PAPER))
    assert mt.textons.B.dtype == jnp.float32
    for leaf in jax.tree.leaves(mt.textons):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert np.all(np.isfinite(np.asarray(mt.history)))


def _pruning_parts() -> list[np.ndarray]:
    """Two clips on which the greedy threshold 0.05 makes many textons of one or two
    segments."""
    rng = np.random.default_rng(3)
    Y, _, _ = sample_texture(rng, make_textons(rng), n_seg=30)
    return [Y[: len(Y) // 2], Y[len(Y) // 2 :]]


def _pruning_config(min_segments: int) -> LearnConfig:
    paper = {**PAPER, "min_segments": min_segments}
    return LearnConfig(tmin=40, tmax=120, state_dim=4, threshold=0.05, max_iter=6, **paper)


@functools.cache
def _pruned_texture(min_segments: int) -> MotionTexture:
    """``learn`` on :func:`_pruning_parts` (the default path), learned once for the two tests
    below that need it."""
    return learn(_pruning_parts(), _pruning_config(min_segments))


def test_min_segments_prunes_rarely_used_textons():
    parts = _pruning_parts()
    loose = _pruned_texture(1)
    tight = _pruned_texture(3)
    c_loose = np.bincount(np.asarray(loose.key_pose_labels))
    c_tight = np.bincount(np.asarray(tight.key_pose_labels), minlength=tight.n_textons)
    assert c_loose.min() < 3  # this setting does leave rarely used textons without pruning
    assert c_tight.min() >= 3 and tight.n_textons < loose.n_textons
    segs = np.asarray(tight.segments)
    for s, y in enumerate(parts):  # every frame is still segmented, in order
        mine = segs[segs[:, 0] == s]
        assert mine[:, 2].sum() == len(y)
        np.testing.assert_array_equal(mine[1:, 1], mine[:-1, 1] + mine[:-1, 2])
    np.testing.assert_allclose(np.asarray(tight.M).sum(axis=1), 1.0, rtol=1e-12)
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="min_segments"):
            LearnConfig(min_segments=bad)


def _learn_both_ways(monkeypatch, data, cfg, new=None):
    """``learn`` with the greedy textons of too few segments dropped before the first E-step
    (the default; ``new`` if given, a model learned so), and with them pruned only after it,
    as the E-step decides."""
    from mtex_jax.texture._learning import learn as _learn

    seen = []
    em = _learn.run_em

    def old_path(*args, prune_initial=False, **kwargs):
        seen.append(prune_initial)
        return em(*args, prune_initial=False, **kwargs)

    if new is None:
        new = learn(data, cfg)
    monkeypatch.setattr(_learn, "run_em", old_path)
    old = learn(data, cfg)
    assert any(seen)  # the greedy EM did ask for the early pruning
    return new, old


def _assert_same_texture(a, b):
    """Equal models; the first M-step objective of the early pruning covers only the kept
    textons' segments, so ``history[0, 0]`` is left out."""
    np.testing.assert_array_equal(np.asarray(a.segments), np.asarray(b.segments))
    ha, hb = np.asarray(a.history), np.asarray(b.history)
    np.testing.assert_allclose(ha[:, 1], hb[:, 1], rtol=1e-9)
    np.testing.assert_allclose(ha[1:, 0], hb[1:, 0], rtol=1e-9)
    a, b = (eqx.tree_at(lambda m: m.history, t, np.zeros(1)) for t in (a, b))
    for x, y in zip(jax_leaves(a), jax_leaves(b), strict=True):
        np.testing.assert_allclose(x.astype(float), y.astype(float), rtol=1e-9, atol=1e-12)


def test_pruning_the_greedy_textons_before_the_first_e_step_changes_nothing(monkeypatch):
    # threshold 0.05 makes many greedy textons of one or two segments (see the test above)
    parts = _pruning_parts()
    cfg = _pruning_config(3)
    from mtex_jax.texture._learning.init import greedy_init

    segs, n = greedy_init(parts, cfg, 0.05)
    assert np.sum(np.bincount(segs[:, 3], minlength=n) < cfg.min_segments) >= 3
    # the default path's model is the one the test above learned (the same clips and config)
    new, old = _learn_both_ways(monkeypatch, parts, cfg, new=_pruned_texture(3))
    _assert_same_texture(new, old)


@pytest.mark.slow
def test_pruning_the_greedy_textons_early_changes_nothing_on_salsa(monkeypatch, cmu_motions):
    # the untied learn (BIC selection, k = D) on the 14 clips at 60 Hz: 155 greedy textons, of
    # which 148 have fewer than 3 segments
    cfg = LearnConfig(tmin=60, tmax=180, fps=60.0, **UNTIED)
    new, old = _learn_both_ways(monkeypatch, cmu_motions, cfg)
    _assert_same_texture(new, old)


def test_greedy_prediction_errors_equal_the_direct_formula():
    """The greedy pass's stacked errors (two GEMMs and ‖p‖², C orthonormal) against the direct
    per-texton ‖y_t − μ − C(A1 x_{t−1} + A2 x_{t−2} + d)‖² / D in numpy, for fitted textons
    and a stack padded with copies of its last texton."""
    import jax

    from mtex_jax.texture import fit_texton
    from mtex_jax.texture._learning.init import _Bank, _bank_errors

    rng = np.random.default_rng(8)
    Y, _, _ = sample_texture(rng, make_textons(rng), n_seg=6)
    bank = _Bank()
    texs = [fit_texton(Y[b : b + 60], state_dim=3) for b in (0, 100, 200)]
    for t in texs:
        bank.add(t)
    win = Y[300:360]
    got = np.asarray(_bank_errors(bank.stacked(), jax.device_put(win)))
    assert got.shape[0] >= 3 and np.all(got[:, :2] == 0.0)
    for i, t in enumerate(texs):
        mu, C, A1, A2, d = (np.asarray(getattr(t, f)) for f in ("mu", "C", "A1", "A2", "d"))
        X = (win - mu) @ C
        yhat = mu + (X[1:-1] @ A1.T + X[:-2] @ A2.T + d) @ C.T
        want = np.sum((win[2:] - yhat) ** 2, axis=1) / win.shape[1]
        np.testing.assert_allclose(got[i, 2:], want, rtol=1e-9, atol=1e-12)
        one = np.asarray(_bank_errors(bank.one(i), jax.device_put(win)))[0]
        np.testing.assert_allclose(one, got[i], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(got[3:], np.broadcast_to(got[2], got[3:].shape), rtol=1e-12)


@pytest.mark.slow  # the default run has the same check on synthetic clips (test_observation_models)
def test_default_texture_of_the_training_clips_stays_in_range_when_noise_driven(cmu_dir):
    """Issue 16's stability criterion on real data: the default texture of the quality split's
    10 training clips (60 Hz), every texton run by its dynamics with sampled noise for 10,000
    frames from its own key poses, stays finite and within a small multiple of the key poses'
    range. (With ``rho_max=1`` one texton reached 27-29 times: a unit root keeps its drift.)"""
    from mtex_jax.texture import spectral_radius, synthesize_texton

    train = [f"60_{i:02d}" for i in (1, 2, 3, 4, 5, 6, 7, 9, 10, 11)]
    clips = [mj.read_bvh(cmu_dir / f"{n}.bvh")[4:] for n in train]
    tex = learn(clips, LearnConfig(tmin=60, tmax=180, fps=60.0))
    assert tex.config.rho_max == 0.999
    assert float(np.max(np.asarray(spectral_radius(tex.textons)))) <= 0.999 + 1e-12
    kp = np.asarray(tex.key_poses)
    lab = np.asarray(tex.segments)[:, 3]
    span = float(np.abs(kp).max())
    for i in range(tex.n_textons):
        run = np.asarray(
            synthesize_texton(jax.random.key(i), tex.textons[i], 10_000, kp[lab == i][0])
        )
        assert np.isfinite(run).all()
        assert np.abs(run).max() < 5 * span, (i, np.abs(run).max() / span)
