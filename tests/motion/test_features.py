"""Observation features (design §1): invertibility, invariances, continuity, serialisation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import mtex_jax as mj
from mtex_jax.motion import raw_features, unwrap_expmaps


def _rel_err(a: mj.Motion, b: mj.Motion) -> float:
    pa = np.asarray(mj.forward_kinematics(a, end_sites=True))
    pb = np.asarray(mj.forward_kinematics(b, end_sites=True))
    return float(np.max(np.abs(pa - pb)) / a.skeleton.size)


def _turn_and_shift(m: mj.Motion, angle: float, shift: np.ndarray) -> mj.Motion:
    up = np.eye(3)[m.skeleton.up_axis]
    r = Rotation.from_rotvec(angle * up)
    xyzw = r.as_quat()
    qy = np.concatenate([xyzw[3:], xyzw[:3]])
    rot = np.asarray(m.rotations).copy()
    rot[:, 0] = np.asarray(mj.motion.quat_mul(qy, rot[:, 0]))
    rp = r.apply(np.asarray(m.root_positions)) + shift
    return mj.Motion(m.skeleton, m.fps, rp, rot)


def test_decode_encode_identity_on_real_clips(cmu_motions):
    clips = [m.resample(60.0) for m in cmu_motions[:4]]
    fm = mj.FeatureMap.fit(clips)
    assert fm.dim < len(fm.channel_names)  # the fingers and eyes never move: dropped
    dropped = set(fm.channel_names) - set(fm.active_names)
    assert "lThumb1.rx" in dropped and "root.dyaw" not in dropped
    for m in clips:
        y = fm.encode(m)
        assert y.shape == (m.n_frames, fm.dim)
        assert np.all(np.isfinite(np.asarray(y)))
        back = fm.decode(y, *fm.start_of(m))
        assert _rel_err(m, back) < 1e-6
    # z-scored over the training set
    ally = np.concatenate([np.asarray(fm.encode(m)) for m in clips])
    np.testing.assert_allclose(ally.mean(0), 0.0, atol=1e-9)
    np.testing.assert_allclose(ally.std(0), 1.0, atol=1e-9)


def test_decode_encode_identity_on_embedded_clips():
    for name in ["dance_a", "backflip", "roll", "getup_facedown"]:
        m = mj.load_example(name)
        fm = mj.FeatureMap.fit(m)
        back = fm.decode(fm.encode(m), *fm.start_of(m))
        assert _rel_err(m, back) < 1e-6, name


def test_encode_invariant_to_vertical_rotation_and_floor_translation(cmu_motions):
    m = cmu_motions[5][:600]
    fm = mj.FeatureMap.fit(m)
    y = np.asarray(fm.encode(m))
    for angle, shift in [(0.7, [1.3, 0.0, -2.0]), (-2.9, [-5.0, 0.0, 0.25]), (np.pi, [0, 0, 0])]:
        y2 = np.asarray(fm.encode(_turn_and_shift(m, angle, np.asarray(shift))))
        np.testing.assert_allclose(y2, y, rtol=0, atol=1e-9)
    # a vertical shift is not invisible: the height is absolute
    y3 = np.asarray(fm.encode(_turn_and_shift(m, 0.0, np.array([0.0, 0.1, 0.0]))))
    assert np.max(np.abs(y3 - y)) > 1e-3


def test_decode_places_the_clip_where_asked(cmu_motions):
    m = cmu_motions[0][:300]
    fm = mj.FeatureMap.fit(m)
    y = fm.encode(m)
    moved = _turn_and_shift(m, 1.1, np.array([2.0, 0.0, 3.0]))
    back = fm.decode(y, *fm.start_of(moved))
    assert _rel_err(moved, back) < 1e-6
    # default start: origin, heading 0, absolute height kept
    d = fm.decode(y)
    rp = np.asarray(d.root_positions)
    assert abs(rp[0, 0]) < 1e-12 and abs(rp[0, 2]) < 1e-12
    np.testing.assert_allclose(rp[:, 1], np.asarray(m.root_positions)[:, 1], atol=1e-12)


def test_expmaps_have_no_2pi_jumps_on_a_turning_clip():
    # a joint spinning continuously for three full turns about a tilted axis, and a root
    # that keeps turning (spin clip): no 2π jumps in any exponential-map channel
    t = 400
    axis = np.array([0.3, 0.9, -0.3])
    axis /= np.linalg.norm(axis)
    ang = np.linspace(0.0, 6 * np.pi, t)
    v = ang[:, None] * axis
    q = np.asarray(mj.motion.expmap_to_quat(v))
    em = np.asarray(unwrap_expmaps(np.asarray(mj.motion.quat_to_expmap(q))))
    steps = np.linalg.norm(np.diff(em, axis=0), axis=1)
    assert steps.max() < 2 * (ang[1] - ang[0]) + 1e-9
    np.testing.assert_allclose(em, v, atol=1e-9)  # it is the unwound rotation vector itself

    m = mj.load_example("spin")
    raw = np.asarray(raw_features(m.root_positions, m.rotations, up_axis=1))
    em_cols = raw[:, 4:]
    jumps = np.abs(np.diff(em_cols, axis=0)).max()
    assert jumps < 1.5, f"largest exp-map change between frames {jumps:.2f} rad"
    yaw_total = np.abs(np.sum(raw[1:, 3]))
    assert yaw_total > 2 * np.pi * 0.9  # the dancer really turns around


def test_feature_map_save_load_and_bad_files(tmp_path):
    m = mj.load_example("dance_a")
    fm = mj.FeatureMap.fit(m)
    p = tmp_path / "fm.npz"
    fm.save(p)
    fm2 = mj.load_feature_map(p)
    assert fm2.skeleton == fm.skeleton and fm2.active == fm.active and fm2.fps == fm.fps
    np.testing.assert_array_equal(np.asarray(fm2.encode(m)), np.asarray(fm.encode(m)))
    # truncated file
    bad = tmp_path / "trunc.npz"
    bad.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
    with pytest.raises(ValueError, match=r"trunc\.npz"):
        mj.load_feature_map(bad)
    # garbage
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip at all")
    with pytest.raises(ValueError, match=r"junk\.npz"):
        mj.load_feature_map(junk)
    # a pickled object array is refused, never unpickled
    evil = tmp_path / "evil.npz"
    np.savez(evil, offset=np.array([object()], dtype=object))
    with pytest.raises(ValueError, match=r"evil\.npz"):
        mj.load_feature_map(evil)
    with pytest.raises(ValueError, match="no such file"):
        mj.load_feature_map(tmp_path / "absent.npz")


def test_fit_encode_equals_fit_then_encode(cmu_motions):
    """The learner's one-pass fit_encode (raw channels once, every clip padded to the longest
    one's bucket) gives the map and observations of fit + encode exactly, on clips of
    different lengths (different buckets) and a clip cut short."""
    clips = [m.resample(60.0) for m in cmu_motions[:3]]
    clips.append(clips[0][:100])
    fm, ys = mj.FeatureMap.fit_encode(clips)
    ref = mj.FeatureMap.fit(clips)
    assert fm.active == ref.active
    np.testing.assert_array_equal(fm.offset, ref.offset)
    np.testing.assert_array_equal(fm.scale, ref.scale)
    assert len({m.n_frames for m in clips}) > 1
    for m, y in zip(clips, ys, strict=True):
        np.testing.assert_array_equal(y, np.asarray(ref.encode(m)))
    with pytest.raises(ValueError, match="no motions"):
        mj.FeatureMap.fit_encode([])
    with pytest.raises(TypeError, match="not a Motion"):
        mj.FeatureMap.fit_encode([clips[0], np.zeros((3, 3))])  # type: ignore[list-item]


def test_feature_map_input_checks(cmu_motions):
    dance = mj.load_example("dance_a")
    walk = mj.load_example("walk")  # 30 Hz
    with pytest.raises(ValueError, match="fps"):
        mj.FeatureMap.fit([dance, walk])
    with pytest.raises(ValueError, match="no motions"):
        mj.FeatureMap.fit([])
    with pytest.raises(ValueError, match="different skeleton"):
        mj.FeatureMap.fit([dance, cmu_motions[0].resample(60.0)])
    fm = mj.FeatureMap.fit(dance)
    # another frame rate is resampled to the map's (issue 43: one contract for every function
    # that takes motions)
    np.testing.assert_array_equal(fm.encode(walk), fm.encode(walk.resample(fm.fps)))
    with pytest.raises(ValueError, match="shape"):
        fm.decode(np.zeros((10, fm.dim + 1)))
    with pytest.raises(ValueError, match="start_position"):
        fm.decode(np.zeros((10, fm.dim)), start_position=np.zeros(2))


def test_decode_is_differentiable():
    import jax
    import jax.numpy as jnp
    from jax.test_util import check_grads

    m = mj.load_example("walk")[:12]
    fm = mj.FeatureMap.fit(mj.load_example("walk"))
    y = jnp.asarray(fm.encode(m))

    def hand_height(yy):
        p = fm.joint_positions(yy, end_sites=True)
        return p[:, -2, 1]  # an end site (wrist) height per frame

    check_grads(hand_height, (y,), order=1, modes=["fwd", "rev"], atol=1e-6, rtol=1e-6)
    g = jax.grad(lambda yy: jnp.sum(hand_height(yy)))(y)
    assert np.all(np.isfinite(np.asarray(g))) and np.any(np.asarray(g) != 0)


def test_constant_channels_do_not_depend_on_precision(cmu_motions):
    """float32 round-off must not turn a constant finger channel into a 'moving' one."""
    clips = [m.resample(60.0) for m in cmu_motions[:2]]
    f64 = mj.FeatureMap.fit(clips)
    as32 = [
        mj.Motion(
            m.skeleton,
            m.fps,
            np.asarray(m.root_positions, np.float32),
            np.asarray(m.rotations, np.float32),
        )
        for m in clips
    ]
    f32 = mj.FeatureMap.fit(as32)
    assert f32.active == f64.active
    y = f32.encode(as32[0])
    assert y.dtype == np.float32 and np.all(np.isfinite(np.asarray(y)))
