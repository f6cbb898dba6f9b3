"""Forward kinematics: jit, vmap, gradients (also at zero rotation), rotation helpers."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.spatial.transform import Rotation

import mtex_jax as mj
from mtex_jax.motion import quat_rotate, quat_twist
from mtex_jax.motion._rotation import wrap_angle

SK = mj.io.HUMANOID3D


def _expmap_fk(root, em):
    return mj.motion.forward_kinematics_arrays(
        SK, root, mj.motion.expmap_to_quat(em), end_sites=True
    )


def test_rotation_helpers_match_scipy():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(50, 3)) * 1.5
    q = np.asarray(mj.motion.expmap_to_quat(v))
    r = Rotation.from_rotvec(v)
    xyzw = r.as_quat()
    ref = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    ref *= np.sign(ref[:, :1]) * np.sign(q[:, :1])
    np.testing.assert_allclose(q, ref, atol=1e-12)
    np.testing.assert_allclose(np.asarray(mj.motion.quat_to_matrix(q)), r.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(np.asarray(mj.motion.quat_to_expmap(q)), r.as_rotvec(), atol=1e-10)
    x = rng.normal(size=(50, 3))
    np.testing.assert_allclose(np.asarray(quat_rotate(q, x)), r.apply(x), atol=1e-12)
    q2 = np.asarray(mj.motion.expmap_to_quat(rng.normal(size=(50, 3))))
    r2 = Rotation.from_quat(np.concatenate([q2[:, 1:], q2[:, :1]], axis=1))
    prod = np.asarray(mj.motion.quat_mul(q, q2))
    np.testing.assert_allclose(
        np.asarray(mj.motion.quat_to_matrix(prod)), (r * r2).as_matrix(), atol=1e-12
    )
    # twist about y of a pure yaw is the yaw
    ang = rng.uniform(-np.pi, np.pi, size=20)
    qy = np.stack([np.cos(ang / 2), 0 * ang, np.sin(ang / 2), 0 * ang], axis=1)
    np.testing.assert_allclose(np.asarray(quat_twist(qy, np.array([0.0, 1.0, 0.0]))), ang)
    np.testing.assert_allclose(np.asarray(wrap_angle(ang + 4 * np.pi)), ang, atol=1e-12)


def test_small_angle_branches_are_exact():
    v = jnp.array([[0.0, 0.0, 0.0], [1e-8, -2e-8, 3e-9], [1e-3, 0.0, 0.0]])
    q = mj.motion.expmap_to_quat(v)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(q), axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(mj.motion.quat_to_expmap(q)), np.asarray(v), atol=1e-15)
    jac = jax.jacfwd(lambda x: mj.motion.expmap_to_quat(x))(jnp.zeros(3))
    np.testing.assert_allclose(np.asarray(jac), np.vstack([np.zeros(3), 0.5 * np.eye(3)]))
    jac2 = jax.jacfwd(lambda q: mj.motion.quat_to_expmap(q))(jnp.array([1.0, 0.0, 0.0, 0.0]))
    assert np.all(np.isfinite(np.asarray(jac2)))


@pytest.mark.slow  # 19 s on 2 cores (the default run is kept near 15 min)
def test_fk_check_grads_float64():
    rng = np.random.default_rng(1)
    root = jnp.asarray(rng.normal(size=(2, 3)))
    em = jnp.asarray(rng.normal(size=(2, SK.n_joints, 3)) * 0.6)
    check_grads(_expmap_fk, (root, em), order=1, modes=["fwd", "rev"], atol=1e-6, rtol=1e-6)
    # at exactly zero rotation (the small-angle branch), including second order
    zero = jnp.zeros((1, SK.n_joints, 3))
    check_grads(_expmap_fk, (root[:1], zero), order=2, modes=["rev"], atol=1e-6, rtol=1e-6)
    zero = jnp.zeros((2, SK.n_joints, 3))
    g = jax.grad(lambda e: jnp.sum(_expmap_fk(root, e) ** 2))(zero)
    assert np.all(np.isfinite(np.asarray(g)))
    # through quaternions directly
    q = mj.motion.expmap_to_quat(em)
    check_grads(
        lambda r, qq: mj.motion.forward_kinematics_arrays(SK, r, qq),
        (root, q),
        order=1,
        modes=["fwd", "rev"],
    )


def test_fk_vmap_jit_and_batch_axes():
    m = mj.load_example("walk")
    p = mj.forward_kinematics(m)
    assert p.shape == (m.n_frames, SK.n_joints, 3)
    per_frame = jax.vmap(lambda r, q: mj.motion.forward_kinematics_arrays(SK, r, q))(
        jnp.asarray(m.root_positions), jnp.asarray(m.rotations)
    )
    np.testing.assert_allclose(np.asarray(per_frame), np.asarray(p), atol=1e-12)
    batched = mj.motion.forward_kinematics_arrays(
        SK, jnp.stack([m.root_positions] * 2), jnp.stack([m.rotations] * 2)
    )
    assert batched.shape == (2, *p.shape)
    with_ends = mj.forward_kinematics(m, end_sites=True)
    assert with_ends.shape == (m.n_frames, SK.n_joints + len(SK.end_sites), 3)


def test_fk_does_not_recompile_for_new_data():
    m = mj.load_example("walk")

    @eqx.debug.assert_max_traces(max_traces=1)
    def fk(r, q):
        return mj.motion.forward_kinematics_arrays(SK, r, q)

    f = eqx.filter_jit(fk)
    f(jnp.asarray(m.root_positions), jnp.asarray(m.rotations))
    f(jnp.asarray(m.root_positions) + 1.0, jnp.asarray(m.rotations[::-1]))


def test_fk_float32_smoke():
    m = mj.load_example("walk")
    p = mj.motion.forward_kinematics_arrays(
        SK, np.asarray(m.root_positions, np.float32), np.asarray(m.rotations, np.float32)
    )
    assert p.dtype == jnp.float32
    ref = np.asarray(mj.forward_kinematics(m))
    np.testing.assert_allclose(np.asarray(p), ref, atol=1e-5)


def test_fk_rejects_bad_shapes():
    import pytest

    with pytest.raises(ValueError, match="rotations must have shape"):
        mj.motion.forward_kinematics_arrays(SK, jnp.zeros((2, 3)), jnp.zeros((2, 5, 4)))
    with pytest.raises(ValueError, match="root_positions"):
        mj.motion.forward_kinematics_arrays(SK, jnp.zeros((3, 3)), jnp.zeros((2, SK.n_joints, 4)))
    with pytest.raises(TypeError):
        mj.forward_kinematics(np.zeros((2, 3)))  # type: ignore[arg-type]
