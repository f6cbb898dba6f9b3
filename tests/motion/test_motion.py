"""The Motion container: validation, slicing, concatenation, slerp resampling."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

import mtex_jax as mj
from mtex_jax.motion import slerp


def test_motion_validates_shapes():
    sk = mj.io.HUMANOID3D
    j = sk.n_joints
    ok = mj.Motion(sk, 30.0, np.zeros((5, 3)), np.tile([1.0, 0, 0, 0], (5, j, 1)))
    assert ok.n_frames == 5 and abs(ok.duration - 4 / 30) < 1e-15
    with pytest.raises(ValueError, match="rotations must have shape"):
        mj.Motion(sk, 30.0, np.zeros((5, 3)), np.zeros((5, j - 1, 4)))
    with pytest.raises(ValueError, match="root_positions"):
        mj.Motion(sk, 30.0, np.zeros((5, 2)), np.zeros((5, j, 4)))
    with pytest.raises(ValueError, match="frames"):
        mj.Motion(sk, 30.0, np.zeros((4, 3)), np.zeros((5, j, 4)))
    with pytest.raises(ValueError, match="fps"):
        mj.Motion(sk, 0.0, np.zeros((5, 3)), np.zeros((5, j, 4)))
    with pytest.raises(ValueError, match="parents must precede"):
        mj.Skeleton(("a", "b"), (-1, 1), ((0, 0, 0), (0, 1, 0)), ((), ()))
    with pytest.raises(ValueError, match="unique"):
        mj.Skeleton(("a", "a"), (-1, 0), ((0, 0, 0), (0, 1, 0)), ((), ()))


def test_slicing_and_concatenation():
    m = mj.load_example("walk")
    a, b = m[:10], m[10:]
    assert a.n_frames == 10 and b.n_frames == m.n_frames - 10
    c = mj.motion.concatenate_motions([a, b])
    np.testing.assert_array_equal(np.asarray(c.rotations), np.asarray(m.rotations))
    half = m[::2]
    assert half.fps == m.fps / 2
    with pytest.raises(TypeError):
        m[3]  # type: ignore[index]
    with pytest.raises(ValueError, match="fps"):
        mj.motion.concatenate_motions([m, mj.load_example("dance_a")])


def test_resample_by_slerp_matches_scipy(cmu_motions):
    m = cmu_motions[0][:241]  # 2 s at 120 Hz
    down = m.resample(60.0)
    assert down.fps == 60.0 and down.n_frames == 121
    # downsampling by an integer factor picks frames exactly
    np.testing.assert_allclose(np.asarray(down.rotations), np.asarray(m.rotations)[::2], atol=1e-12)
    up = m[:25].resample(240.0)
    assert up.n_frames == 49
    # in-between frames equal SciPy's Slerp, joint by joint
    q = np.asarray(m.rotations)[:25]
    t_old = np.arange(25) / 120.0
    t_new = np.arange(49) / 240.0
    for j in [0, 5, 17]:
        rot = Rotation.from_quat(np.concatenate([q[:, j, 1:], q[:, j, :1]], axis=1))
        ref = Slerp(t_old, rot)(t_new).as_matrix()
        ours = np.asarray(mj.motion.quat_to_matrix(np.asarray(up.rotations)[:, j]))
        np.testing.assert_allclose(ours, ref, atol=1e-10)
    # not angle averaging: halfway between ±170° about one axis is 180°, not 0°
    q0 = np.array([np.cos(np.radians(85)), 0, 0, np.sin(np.radians(85))])
    q1 = np.array([np.cos(np.radians(-85)), 0, 0, np.sin(np.radians(-85))])
    mid = slerp(q0, q1, np.array(0.5))
    assert abs(abs(mid[3]) - 1.0) < 1e-12


def test_resample_rejects_bad_rate():
    m = mj.load_example("walk")
    with pytest.raises(ValueError, match="fps"):
        m.resample(-1.0)
