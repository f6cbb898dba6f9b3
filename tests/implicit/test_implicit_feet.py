"""The implicit model's foot lock and recent-pose weighting (issue 18): the lock against its
defining property (planted feet move as in the example), the contact weights and the weighted
window distance against NumPy re-derivations."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import mtex_jax as mj

WINDOW = 8


@pytest.fixture(scope="module")
def db(cmu_motions):
    """Three salsa clips at 30 Hz, 400 frames each: the first is the probe, the others the
    database."""
    clips = [c.resample(30.0)[:400] for c in cmu_motions[3:6]]
    return clips, mj.implicit.learn(clips[1:], WINDOW)


def test_foot_lock_makes_planted_feet_move_as_in_the_example(db):
    """lock_root with strength 1 and no smoothing: a fully planted foot's horizontal
    displacement equals the example's; with both feet planted, the mean of their excess
    displacements is zero. The rest of the pose is untouched."""
    from mtex_jax.implicit._feet import lock_root, root_channels

    model = db[1]
    fm = model.feature_map
    dim = fm.dim
    succ = np.asarray(model.database.successors)
    _, h0, h1 = mj.motion.ground_axes(fm.skeleton.up_axis)
    hz = [h0, h1]
    chans = root_channels(fm)
    assert chans is not None and len(model.database.feet) == 2
    rng = np.random.default_rng(0)
    for _ in range(4):
        i, j = rng.integers(0, model.database.n_examples, 2)
        ex_new, ex_last = succ[i, :dim], succ[i, :dim] - succ[i, dim:]
        last = succ[j, :dim]
        new = ex_new + 0.3 * rng.standard_normal(dim)  # an offset dragging the feet
        for c in ([1.0, 0.0], [0.0, 1.0], [1.0, 1.0]):
            got, _ = lock_root(
                fm, model.database.feet, chans, jnp.asarray(last), jnp.asarray(new),
                jnp.asarray(ex_last), jnp.asarray(ex_new), jnp.asarray(c), jnp.zeros(3), 1.0, 0.0,
            )  # fmt: skip
            got = np.asarray(got)
            keep = np.ones(dim, bool)
            keep[list(chans)] = False
            np.testing.assert_array_equal(got[keep], new[keep])
            g = np.asarray(fm.joint_positions(np.stack([last, got])))[:, model.database.feet]
            e = np.asarray(fm.joint_positions(np.stack([ex_last, ex_new])))[:, model.database.feet]
            excess = ((g[1] - g[0]) - (e[1] - e[0]))[:, hz]
            np.testing.assert_allclose(np.asarray(c) @ excess, 0.0, atol=1e-9)


def test_foot_contact_against_numpy(db):
    """c = 1 − min(s / median s, 1) with s the 5-frame moving average of the foot speed at
    each example's successor frame."""
    clips, model = db
    from mtex_jax.motion import joint_positions

    feet = list(model.database.feet)
    assert [model.feature_map.skeleton.names[f] for f in feet] == ["rFoot", "lFoot"]
    speeds = []
    for c in clips[1:]:
        p = joint_positions(c)[0][:, feet]
        s = np.linalg.norm(np.diff(p, axis=0), axis=-1) * c.fps
        pad = np.pad(s, ((2, 2), (0, 0)), mode="edge")
        speeds.append(
            np.stack([np.convolve(pad[:, k], np.ones(5) / 5, "valid") for k in (0, 1)], 1)
        )
    med = np.median(np.concatenate(speeds), axis=0)
    ref = np.concatenate([1 - np.minimum(s[WINDOW:] / med, 1) for s in speeds])
    np.testing.assert_allclose(np.asarray(model.database.foot_contact), ref, atol=1e-9)
    assert 0.1 < float(np.mean(ref > 0)) < 0.9


def test_recent_weight_adds_the_newest_pose_distance(db):
    """Model coordinates with recent weight w: ‖Ψ − Φ‖² = ‖Ψ − Φ‖²_{w=0} + w ‖ψ − φ‖² (newest
    pose vectors), and γ does not depend on w."""
    clips, model = db
    m0 = mj.implicit.learn(clips[1:], WINDOW, recent_weight=0.0, feature_map=model.feature_map)
    w = model.database.recent_weight
    assert w > 0 and m0.database.recent_weight == 0.0
    np.testing.assert_allclose(
        np.asarray(m0.database.gamma), np.asarray(model.database.gamma), rtol=1e-12
    )
    probe0, probe = m0.windows_of(clips[0])[3], model.windows_of(clips[0])[3]
    idx = np.arange(0, model.database.n_examples, 7)
    d0 = np.asarray(m0.distance2(np.broadcast_to(probe0, (len(idx), probe0.size)), idx))
    d1 = np.asarray(model.distance2(np.broadcast_to(probe, (len(idx), probe.size)), idx))
    p = model.database.pose_dim
    new = ((np.asarray(m0.database.windows)[idx, -p:] - np.asarray(probe0)[-p:]) ** 2).sum(-1)
    np.testing.assert_allclose(d1, d0 + w * new, rtol=1e-9)
