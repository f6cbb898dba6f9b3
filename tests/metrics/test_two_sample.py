"""The classifier two-sample test (design §10.4): its features against a numpy/scipy
re-derivation, their invariance, its power on motion that differs, and its errors."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import mtex_jax as mj
from mtex_jax.metrics import two_sample_auc, window_features


def _turned_and_moved(m: mj.Motion, angle: float, shift: np.ndarray) -> mj.Motion:
    """The clip rotated by ``angle`` about the up axis and moved by ``shift``."""
    up = np.zeros(3)
    up[m.skeleton.up_axis] = 1.0
    R = Rotation.from_rotvec(angle * up)
    root = R.apply(np.asarray(m.root_positions)) + shift
    q = np.asarray(m.rotations).copy()
    q_root = Rotation.from_quat(q[:, 0], scalar_first=True)
    q[:, 0] = (R * q_root).as_quat(scalar_first=True)
    return dataclasses.replace(m, root_positions=root, rotations=q)


def test_window_features_against_a_scipy_derivation(salsa30):
    clip = salsa30[0][:130]  # two 2 s windows at 30 Hz, and 10 frames left over
    X, clip_of = window_features(clip, window=2.0, samples=5)
    sk = clip.skeleton
    up, h0, h1 = mj.motion.ground_axes(sk.up_axis)
    P = np.asarray(mj.forward_kinematics(clip))
    J = sk.n_joints
    assert X.shape == (2, 5 * J * 3 + 2 * J) and clip_of.tolist() == [0, 0]
    for i, s in enumerate((0, 60)):
        q0 = np.asarray(clip.rotations)[s, 0]
        e0 = np.eye(3)[h0]
        fwd = Rotation.from_quat(q0, scalar_first=True).apply(e0)
        heading = np.arctan2(fwd[h1], fwd[h0])
        # rotation about the up axis taking the heading to h0 (h0, h1, up right-handed)
        undo = Rotation.from_rotvec(-heading * np.eye(3)[up])
        picks = [s + k for k in (0, 15, 30, 44, 59)]  # round(linspace(0, 59, 5))
        rel = P[picks] - P[picks, :1]
        poses = undo.apply(rel.reshape(-1, 3)).ravel()
        speed = np.linalg.norm(P[s + 1 : s + 60] - P[s : s + 59], axis=-1) * 30.0
        want = np.concatenate([poses, speed.mean(0), speed.std(0)])
        np.testing.assert_allclose(X[i], want, rtol=1e-9, atol=1e-9)


def test_features_do_not_see_where_the_dancer_is_or_which_way_they_face(salsa30):
    clip = salsa30[1][:240]
    moved = _turned_and_moved(clip, 2.1, np.array([3.0, 0.0, -1.5]))
    a, _ = window_features(clip)
    b, _ = window_features(moved)
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)


def test_the_test_tells_hurried_dancing_from_real_and_real_from_real_less(salsa30):
    """Dancing played twice as fast is told apart almost always; another take of real dancing
    is told apart far less often (the reference)."""
    real = salsa30[10:14]
    fast = [dataclasses.replace(m.resample(15.0), fps=30.0) for m in salsa30[:8]]
    res = two_sample_auc(real, fast, reference=salsa30[:8])
    assert res.auc > 0.95, res
    assert res.reference_auc is not None and res.reference_auc < 0.8, res
    assert res.auc > res.reference_auc + 0.15
    assert len(res.fold_aucs) == 5 and res.n_real == sum(m.n_frames // 60 for m in real)
    json.dumps(res.as_dict())
    # a fixed seed: the same folds and the same trees (on fewer clips: the property, not the
    # figures)
    small = two_sample_auc(real[:2], fast[:3], reference=salsa30[4:6])
    assert two_sample_auc(real[:2], fast[:3], reference=salsa30[4:6]) == small


def test_bad_input_is_named(salsa30, cmu_motions):
    real, gen = salsa30[10:12], salsa30[:2]
    with pytest.raises(ValueError, match="folds"):
        two_sample_auc(real, gen, folds=1)
    with pytest.raises(ValueError, match="Hz"):
        two_sample_auc(real, cmu_motions[:2])  # 60 Hz against 30 Hz
    with pytest.raises(ValueError, match="fewer than folds"):
        two_sample_auc(real, [salsa30[0][:130]])  # two windows
    with pytest.raises(ValueError, match="window"):
        two_sample_auc(real, gen, window=0.05)
    with pytest.raises(ValueError, match="window"):
        window_features(real, window=float("nan"))
    with pytest.raises(ValueError, match="samples"):
        window_features(real, samples=1)
    with pytest.raises(ValueError, match="no clip holds one window"):
        window_features(salsa30[0][:30])
