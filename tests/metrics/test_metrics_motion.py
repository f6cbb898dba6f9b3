"""Motion metrics (design §10.4): kinematics, realism (W1), contacts, transitions, novelty.

Each metric is checked on a case with a known answer: W1 against scipy, a clip copied from the
training set (copy fraction 1), a foot sliding at a known speed, a clip lowered by 5 cm, a seam
of known size, a moved and turned copy (novelty 0).
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

import mtex_jax as mj
from mtex_jax import metrics as M
from mtex_jax.motion import Motion, Skeleton, forward_kinematics, quat_mul, yaw_quat

FPS = 60.0


@pytest.fixture(scope="module")
def clips(cmu_files) -> tuple[Motion, Motion]:
    """Two CMU salsa clips (120 Hz), cut to 5 s each."""
    a = mj.read_bvh(cmu_files[0])[:600]
    b = mj.read_bvh(cmu_files[1])[:600]
    return a, b


def _shifted(m: Motion, delta) -> Motion:
    return Motion(m.skeleton, m.fps, np.asarray(m.root_positions) + np.asarray(delta), m.rotations)


def _turned(m: Motion, angle: float, delta) -> Motion:
    """``m`` turned about the up axis by ``angle`` around the origin, then moved by ``delta``."""
    up = np.eye(3)[m.skeleton.up_axis]
    q = np.asarray(yaw_quat(np.asarray(angle), up))
    rot = np.asarray(m.rotations).copy()
    rot[:, 0] = np.asarray(quat_mul(np.broadcast_to(q, rot[:, 0].shape), rot[:, 0]))
    c, s = np.cos(angle), np.sin(angle)
    r = np.eye(3)
    _, h0, h1 = mj.motion.ground_axes(m.skeleton.up_axis)
    r[h0, h0], r[h0, h1], r[h1, h0], r[h1, h1] = c, -s, s, c
    root = np.asarray(m.root_positions) @ r.T + np.asarray(delta)
    return Motion(m.skeleton, m.fps, root, rot)


# ------------------------------------------------------------------ kinematics
def test_derivatives_of_a_cubic_are_exact():
    f = 30.0
    t = np.arange(10) / f
    p = np.stack([t**3, 2 * t, np.zeros_like(t)], axis=-1)[:, None, :]  # (T, 1, 3)
    v, a, j = M.derivatives(p, f)
    assert v.shape == (9, 1, 3) and a.shape == (8, 1, 3) and j.shape == (7, 1, 3)
    np.testing.assert_allclose(v[:, 0, 1], 2.0)
    np.testing.assert_allclose(j[:, 0, 0], 6.0, rtol=1e-9)  # third difference of t³ is exact
    sv, _, sj = M.joint_speeds(p, f)
    np.testing.assert_allclose(sv, np.linalg.norm(v, axis=-1))
    np.testing.assert_allclose(sj, 6.0, rtol=1e-9)


def test_joint_positions_match_forward_kinematics_and_resample(clips):
    a, _ = clips
    (p120,) = mj.motion.joint_positions([a])
    np.testing.assert_allclose(p120, np.asarray(forward_kinematics(a)), atol=1e-9)
    (p60,) = mj.motion.joint_positions(a, FPS)
    # 120 → 60 Hz keeps every second frame exactly
    np.testing.assert_allclose(p60, p120[::2][: p60.shape[0]], atol=1e-9)


def test_moving_joints_drop_fingers_and_eyes(clips):
    sk = clips[0].skeleton
    names = {sk.names[i] for i in M.moving_joints(list(clips))}
    assert {"hip", "head", "rHand", "lHand", "rFoot", "lFoot", "rCollar", "rButtock"} <= names
    assert not names & {"leftEye", "rightEye", "rThumb1", "rThumb2", "lPinky2", "lIndex1"}
    assert len(names) == 21


# ------------------------------------------------------------------ realism
@pytest.mark.parametrize("n,m", [(1, 1), (7, 7), (50, 13), (400, 1000)])
def test_wasserstein_matches_scipy(n, m):
    rng = np.random.default_rng(n + m)
    u = rng.gamma(2.0, size=n)
    v = rng.normal(1.0, 2.0, size=m) ** 2
    assert M.wasserstein_1d(u, v) == pytest.approx(scipy.stats.wasserstein_distance(u, v), 1e-12)
    assert M.wasserstein_1d(u, u + 0.25) == pytest.approx(0.25)
    assert M.wasserstein_1d(u, u[::-1]) == 0.0


def test_wasserstein_rejects_empty_and_nan():
    with pytest.raises(ValueError, match="non-empty"):
        M.wasserstein_1d([], [1.0])
    with pytest.raises(ValueError, match="NaN"):
        M.wasserstein_1d([np.nan], [1.0])


def test_realism_distances_by_hand_and_floor(clips):
    a, b = clips
    same = M.realism([a, b], [a, b], fps=FPS)
    assert same.distances == (0.0, 0.0, 0.0)
    r = M.realism(b, a, fps=FPS)
    ia = M.moving_joints(a)
    sv_a, _, sj_a = M.speed_samples(a, FPS)
    sv_b, _, sj_b = M.speed_samples(b, FPS)
    by_hand = np.mean([scipy.stats.wasserstein_distance(sv_b[:, j], sv_a[:, j]) for j in ia])
    assert r.speed == pytest.approx(by_hand, rel=1e-10)
    assert r.jerk == pytest.approx(
        np.mean([scipy.stats.wasserstein_distance(sj_b[:, j], sj_a[:, j]) for j in ia]), rel=1e-10
    )
    # a noisy copy of b (1 cm of root jitter) is far from real, the real pair is the floor
    rng = np.random.default_rng(0)
    noisy = _shifted(b, rng.normal(0.0, 0.01, size=(b.n_frames, 3)))
    bad = M.realism(noisy, a, fps=FPS, floor=r)
    assert bad.ratios is not None
    assert bad.acceleration_ratio is not None and bad.acceleration_ratio > 5
    assert bad.jerk_ratio is not None and bad.jerk_ratio > 10
    assert bad.jerk_ratio == pytest.approx(bad.jerk / r.jerk)
    assert M.realism(b, a, fps=FPS, floor=r).ratios == pytest.approx((1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="fps"):
        M.realism(noisy, a, fps=30.0, floor=r)
    with pytest.raises(ValueError, match="other joints"):
        M.realism(noisy, a, fps=FPS, floor=r, joints=["hip", "head"])


def test_bad_inputs_raise_value_errors_naming_the_problem(clips):
    a, b = clips
    with pytest.raises(ValueError, match="empty list"):
        M.realism([], [a])
    with pytest.raises(ValueError, match="empty list"):
        mj.motion.fit_contacts([])
    with pytest.raises(ValueError, match="too short"):
        M.realism([a[:5]], [a], fps=FPS)  # 3 frames at 60 Hz: no jerk
    with pytest.raises(ValueError, match="too short"):
        M.novelty(a[:50], [a], fps=FPS)  # shorter than a 1 s window
    bad_root = np.asarray(a.root_positions).copy()
    bad_root[7, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):  # such a clip cannot reach the metrics
        Motion(a.skeleton, a.fps, bad_root, a.rotations)
    humanoid = mj.io.load_example(mj.io.example_names()[0])
    with pytest.raises(ValueError, match="different skeleton"):
        M.realism([a, humanoid], [b])
    with pytest.raises(ValueError, match="different skeletons"):
        M.realism(humanoid, [a])
    with pytest.raises(ValueError, match="different skeletons"):
        M.novelty(humanoid, [a])
    model = mj.motion.fit_contacts([a], fps=FPS)
    with pytest.raises(ValueError, match="skeleton"):
        model.skating(humanoid)


# ------------------------------------------------------------------ contacts
def test_foot_joints_by_name_and_by_shape(clips):
    sk = clips[0].skeleton
    assert [sk.names[i] for i in mj.motion.foot_joints(sk)] == ["rFoot", "lFoot"]
    h = mj.io.HUMANOID3D
    assert [h.names[i] for i in mj.motion.foot_joints(h)] == ["right_ankle", "left_ankle"]
    assert mj.motion.foot_joints(sk, ["lShin"]) == (sk.index("lShin"),)
    # no usable names: the lowest leaf of each leg in the rest pose
    anon = Skeleton(
        names=("a", "b", "c", "d", "e", "f", "g"),
        parents=(-1, 0, 1, 0, 3, 0, 5),
        offsets=((0, 1, 0), (0.1, -0.4, 0), (0, -0.4, 0), (-0.1, -0.4, 0), (0, -0.45, 0),
                 (0, 0.3, 0), (0, 0.3, 0)),
        channels=(("Xrotation",),) * 7,
    )  # fmt: skip
    assert mj.motion.foot_joints(anon) == (2, 4)


def test_contact_model_thresholds_follow_the_documented_rules(clips):
    a, b = clips
    model = mj.motion.fit_contacts([a, b], fps=FPS)
    assert model.foot_names == ("rFoot", "lFoot")
    ps = mj.motion.joint_positions([a, b], FPS)
    h = np.concatenate([p[:, list(model.feet), 1] for p in ps])
    np.testing.assert_allclose(model.height_threshold, np.median(h, axis=0))
    assert model.floor == pytest.approx(h.min())
    assert np.all((model.speed_threshold > 0.05) & (model.speed_threshold < 2.0))


def _held_pose(m: Motion, frame: int, n: int, velocity: np.ndarray) -> Motion:
    """Frame ``frame`` of ``m`` held for ``n`` frames while the root moves at ``velocity``."""
    t = np.arange(n)[:, None] / m.fps
    root = np.asarray(m.root_positions)[frame] + t * velocity
    rot = np.repeat(np.asarray(m.rotations)[frame : frame + 1], n, axis=0)
    return Motion(m.skeleton, m.fps, root, rot)


@pytest.mark.parametrize("speed", [0.3, 1.0])
def test_a_foot_sliding_at_a_known_speed_gives_that_speed(clips, speed):
    a, b = clips
    model = mj.motion.fit_contacts([a, b], fps=FPS)
    lf = model.feet.index(a.skeleton.index("lFoot"))
    # a frame where the left foot is low
    (p,) = mj.motion.joint_positions(a)
    frame = int(np.argmin(p[:, a.skeleton.index("lFoot"), 1]))
    direction = np.array([0.6, 0.0, -0.8])
    slide = _held_pose(a, frame, 240, speed * direction)
    res = model.skating(slide)
    assert res.per_foot_median[lf] == pytest.approx(speed, rel=1e-9)
    assert res.per_foot_p95[lf] == pytest.approx(speed, rel=1e-9)
    assert res.median == pytest.approx(speed, rel=1e-9)
    labels = model.labels(slide)
    assert labels.shape == (slide.resample(FPS).n_frames - 1, len(model.feet))
    assert labels[:, lf].all() == (speed < model.speed_threshold[lf])
    still = model.skating(_held_pose(a, frame, 240, np.zeros(3)))
    assert still.median == pytest.approx(0.0, abs=1e-9)


def test_a_clip_lowered_by_5_cm_penetrates_5_cm(clips):
    a, b = clips
    model = mj.motion.fit_contacts([a, b], fps=FPS)
    assert model.penetration([a, b]).max_depth == 0.0
    assert model.penetration([a, b]).share == 0.0
    lowered = _shifted(a, [0.0, -0.05, 0.0])
    pen = model.penetration(lowered)
    (p,) = mj.motion.joint_positions(lowered, FPS)
    lowest = p[:, list(model.feet), 1].min(axis=1)
    assert pen.share == pytest.approx(np.mean(lowest < model.floor))
    assert pen.max_depth == pytest.approx(model.floor - lowest.min())
    # the clip holding the floor, lowered by 5 cm, goes exactly 5 cm below it
    holder = min(
        (a, b), key=lambda m: mj.motion.joint_positions(m, FPS)[0][:, list(model.feet), 1].min()
    )
    assert model.penetration(_shifted(holder, [0, -0.05, 0])).max_depth == pytest.approx(0.05)


# ------------------------------------------------------------------ transitions
def test_joint_jumps_and_a_seam_of_known_size(clips):
    a, b = clips
    (p,) = mj.motion.joint_positions(a, FPS)
    (jmp,) = M.joint_jumps(a, FPS)
    np.testing.assert_allclose(jmp, np.linalg.norm(p[1:] - p[:-1], axis=-1).max(axis=1))
    p99 = M.jump_p99([a, b], FPS)
    assert p99 == pytest.approx(np.quantile(np.concatenate(M.joint_jumps([a, b], FPS)), 0.99))
    # a seam: the second half of a moved 1 m sideways (boundary at frame 300 of 120 Hz)
    root = np.asarray(a.root_positions).copy()
    root[300:, 0] += 1.0
    seam = Motion(a.skeleton, a.fps, root, a.rotations)
    res = M.transitions(seam, np.array([300]), [a, b], fps=FPS)
    assert res.threshold == pytest.approx(p99)
    # at 60 Hz the boundary is frame 150, the jump is from 149 to 150: 1 m plus the motion
    step = p[150] - p[149] + np.array([1.0, 0.0, 0.0])
    assert res.boundary_max == pytest.approx(np.linalg.norm(step, axis=-1).max())
    assert res.boundary_share_above == 1.0
    smooth = M.transitions([a, b], [np.array([100, 200]), np.array([50])], [a, b], fps=FPS)
    assert smooth.boundary_jumps.shape == (3,)
    assert smooth.share_above == pytest.approx(0.01, abs=0.005)
    with pytest.raises(ValueError, match="boundary frames"):
        M.transitions(seam, np.array([600]), [a], fps=FPS)
    with pytest.raises(ValueError, match="2 boundary arrays for 1 clips"):
        M.transitions([seam], [np.array([3]), np.array([4])], [a], fps=FPS)


# ------------------------------------------------------------------ novelty and copying
def test_novelty_of_a_moved_and_turned_training_window_is_zero(clips):
    a, b = clips
    piece = _turned(a[240:420], 2.0, [3.0, 0.0, -1.5])
    res = M.novelty(piece, [a, b], window=1.0, fps=FPS)
    assert res.distances.shape == (90 - 60 + 1,)
    np.testing.assert_allclose(res.distances, 0.0, atol=1e-6)
    np.testing.assert_array_equal(res.nearest, 120 + np.arange(31))
    assert set(res.nearest_clip.tolist()) == {0}
    # real motion of another clip is not a copy: centimetres to decimetres away
    other = M.novelty(b[:300], [a], window=1.0, fps=FPS, hop=5)
    assert other.median > 0.03 and other.distances.shape == (19,)


def test_novelty_nearest_window_matches_brute_force(clips):
    a, b = clips
    rng = np.random.default_rng(1)
    noisy = _shifted(b[:200], rng.normal(0.0, 0.02, size=(200, 3)))
    res = M.novelty(noisy, [a], window=0.5, fps=FPS, sample_fps=20.0, hop=7)
    joints = M.moving_joints(a)

    def windows(m):  # straightforward re-implementation, one window at a time
        (p,) = mj.motion.joint_positions(m, FPS)
        q0 = np.asarray(m.resample(FPS).rotations)[:, 0]
        psi = 2 * np.arctan2(q0[:, 2], q0[:, 0])
        out = []
        for s in range(p.shape[0] - 30 + 1):
            x = p[s : s + 30 : 3, joints] - np.array([p[s, 0, 0], 0.0, p[s, 0, 2]])
            c, sn = np.cos(psi[s]), np.sin(psi[s])
            # up = y, (h0, h1) = (z, x): rotate by −ψ about y
            z, xx = c * x[..., 2] + sn * x[..., 0], -sn * x[..., 2] + c * x[..., 0]
            out.append(np.stack([z, xx, x[..., 1]], -1).ravel())
        return np.array(out)

    db, qs = windows(a), windows(noisy)[::7]
    d = np.sqrt(((qs[:, None] - db[None]) ** 2).sum(-1) / (db.shape[1] // 3))
    np.testing.assert_array_equal(res.nearest, d.argmin(axis=1))
    np.testing.assert_allclose(res.distances, d.min(axis=1), rtol=1e-9)


def test_a_copied_training_clip_has_copy_fraction_one(clips):
    a, b = clips
    copy = _turned(b[100:460], -1.0, [0.5, 0.0, 2.0])
    res = M.copying(copy, [a, b], fps=FPS)
    assert res.fraction == 1.0
    assert res.longest_run == pytest.approx((180 - 1) / FPS)
    np.testing.assert_array_equal(res.nearest, 300 + 50 + np.arange(180))
    rev = M.copying(copy[::-1], [a, b], fps=FPS)
    assert rev.fraction < 0.05
    perm = np.random.default_rng(0).permutation(copy.n_frames)
    shuffled = M.copying(copy[perm], [a, b], fps=FPS)
    assert shuffled.fraction < 0.05 and shuffled.longest_run < 0.1
    # two generated clips: no run across the join
    two = M.copying([copy, copy], [a, b], fps=FPS)
    assert two.fraction == 1.0 and two.longest_run == pytest.approx(179 / FPS)
    assert not two.verbatim[[0, 180]].any()


def test_copying_from_sampler_indices_by_hand():
    clip = np.array([0, 0, 0, 1, 1, 1, 1])
    frame = np.array([0, 1, 2, 0, 1, 2, 3])
    succ = M.successor_array(clip, frame)
    np.testing.assert_array_equal(succ, [1, 2, -1, 4, 5, 6, -1])
    perm = np.array([3, 0, 6, 1, 5, 2, 4])  # the same database, examples in another order
    inv = np.argsort(perm)
    np.testing.assert_array_equal(
        M.successor_array(clip[perm], frame[perm]), [inv[s] if s >= 0 else -1 for s in succ[perm]]
    )
    # steps: 0→1 yes, 1→2 yes, 2→3 no (end of clip), 3→4 yes, 4→4 no, 4→5 yes
    res = M.copying_from_indices(np.array([0, 1, 2, 3, 4, 4, 5]), succ, fps=10.0)
    np.testing.assert_array_equal(res.verbatim, [0, 1, 1, 0, 1, 0, 1])
    assert res.fraction == pytest.approx(4 / 6)
    assert res.longest_run == pytest.approx(0.2)
    per_clip = M.copying_from_indices([np.array([0, 1]), np.array([2, 3, 4, 5])], succ, fps=10.0)
    assert per_clip.fraction == pytest.approx(3 / 4)
    with pytest.raises(ValueError, match="indices must be integers"):
        M.copying_from_indices(np.array([0, 9]), succ, fps=10.0)
    with pytest.raises(ValueError, match="at least 2 steps"):
        M.copying_from_indices(np.array([0]), succ, fps=10.0)
