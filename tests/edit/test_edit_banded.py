"""mtex_jax.edit: the banded Gauss–Newton solver, the dot-free forward kinematics, the batched
(vmap) solve and cleaning with swing guidance (issue 17).

Same small DeepMimic texture as ``test_edit.py``; references are independent computations
(the motion package's forward kinematics, dense autodiff Jacobians, the Levenberg–Marquardt
solver of the same objective, the motion before editing)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import edit_setup
import mtex_jax as mj
from cpu_devices import run_with_cpu_devices
from mtex_jax import edit as E
from mtex_jax.edit._banded.normal import step_solve
from mtex_jax.edit._fk import fk_positions
from mtex_jax.edit._gn import join_points
from mtex_jax.edit._jacobians import (
    channel_colouring,
    frame_columns,
    frame_jacobians,
    kept_positions,
    root_free_channels,
)
from mtex_jax.edit._prior import WhitenedTextons, prior_residuals
from mtex_jax.edit._solve import sub_skeleton
from mtex_jax.edit._whiten import band_matvec, band_quad
from mtex_jax.motion import fit_contacts

FPS, T = edit_setup.FPS, edit_setup.T


@pytest.fixture(scope="module")
def tex():
    return edit_setup.texture()


@pytest.fixture(scope="module")
def contacts():
    return edit_setup.contacts()


@pytest.fixture(scope="module")
def syn(tex):
    return edit_setup.synthesis(tex)


_hand = edit_setup.hand


def _positions(tex, syn, Y):
    sp, sh = tex.feature_map.start_of(syn.motion)
    return np.asarray(tex.feature_map.joint_positions(Y, sp, sh))


def test_dot_free_kinematics_matches_the_motion_package_and_batches(syn):
    m = syn.motion
    ref = np.asarray(mj.forward_kinematics(m))
    got = fk_positions(m.skeleton, jnp.asarray(m.root_positions), jnp.asarray(m.rotations))
    np.testing.assert_allclose(np.asarray(got), ref, atol=1e-12)
    rot = jnp.stack([jnp.asarray(m.rotations)] * 2)
    root = jnp.stack([jnp.asarray(m.root_positions), jnp.asarray(m.root_positions) + 1.0])
    many = jax.jit(jax.vmap(lambda r, q: fk_positions(m.skeleton, r, q)))(root, rot)
    np.testing.assert_allclose(np.asarray(many[1]), ref + 1.0, atol=1e-12)
    f = lambda q: fk_positions(m.skeleton, jnp.asarray(m.root_positions[:4]), q)
    check_grads(f, (jnp.asarray(m.rotations[:4]),), order=1, modes=("fwd", "rev"), eps=1e-6)


@pytest.mark.slow  # 19 s on 2 cores (the default run is kept near 15 min)
def test_frame_jacobians_are_the_diagonal_blocks_of_the_dense_jacobian(tex, syn):
    fm = tex.feature_map
    sk = fm.skeleton
    keep = (sk.index(_hand(tex)), *fit_contacts([syn.motion]).feet)
    sub, order = sub_skeleton(sk, keep)
    sp, sh = (jnp.asarray(a) for a in fm.start_of(syn.motion))
    n = 6
    Y = jnp.asarray(syn.Y[:n])
    fn = lambda y: kept_positions(fm, sub, order, y, sp, sh)
    free = jnp.asarray(root_free_channels(fm))
    P, J = frame_jacobians(fn, Y, free)
    np.testing.assert_allclose(np.asarray(P), np.asarray(fn(Y)), atol=1e-12)
    # channels that move disjoint joints share one Jacobian-vector product: same columns
    col = channel_colouring(fm, order)
    assert col.n_colours < fm.dim / 2
    colour, support = np.asarray(col.colour), np.asarray(col.support)
    for c in range(col.n_colours):
        assert np.all(support[colour == c].sum(axis=0) <= 1)  # no joint moved by two of them
    Pc, Jc = frame_jacobians(fn, Y, free, col)
    np.testing.assert_allclose(np.asarray(Pc), np.asarray(P), atol=1e-12)
    np.testing.assert_allclose(np.asarray(Jc), np.asarray(J), atol=1e-12)
    dense = np.asarray(jax.jacfwd(fn)(Y))  # (n, K, 3, n, D)
    f = np.asarray(free).astype(bool)
    for t in range(n):
        for s in range(n):
            blk = dense[t, :, :, s][..., f]
            if s == t:
                np.testing.assert_allclose(np.asarray(J[t])[..., f], blk, atol=1e-10)
            else:  # frames do not interact through the free channels
                assert np.abs(blk).max() < 1e-12
    assert np.abs(np.asarray(J)[..., ~f]).max() == 0.0
    check_grads(fn, (Y,), order=1, modes=("fwd", "rev"), eps=1e-6)
    # the rows a Gauss–Newton step gathers equal the dense blocks' rows
    fc = frame_columns(fn, Y, free, col)
    frames, slots = jnp.array([0, 3, 5, 3]), jnp.array([0, 1, 2, 2])
    Jd = np.asarray(J)
    np.testing.assert_allclose(
        np.asarray(fc.rows(frames, slots)), Jd[np.asarray(frames), np.asarray(slots)], atol=1e-12
    )
    np.testing.assert_allclose(np.asarray(fc.axis(1)), Jd[:, :, 1, :], atol=1e-12)


def _dense_penta(A0, A1, A2):
    T, D, _ = A0.shape
    M = np.zeros((T * D, T * D))
    for t in range(T):
        M[t * D : (t + 1) * D, t * D : (t + 1) * D] = A0[t]
        for k, A in ((1, A1), (2, A2)):
            if t >= k:
                M[t * D : (t + 1) * D, (t - k) * D : (t - k + 1) * D] = A[t]
                M[(t - k) * D : (t - k + 1) * D, t * D : (t + 1) * D] = A[t].T
    return M


def test_band_matvec_and_quad_match_the_dense_matrix():
    rng = np.random.default_rng(11)
    T, D = 6, 3
    A0 = rng.standard_normal((T, D, D))
    A0 = A0 + np.swapaxes(A0, 1, 2)
    A1, A2 = rng.standard_normal((T, D, D)), rng.standard_normal((T, D, D))
    A1[0] = A2[0] = A2[1] = 0.0  # the band layout of prior_hessian
    M = _dense_penta(A0, A1, A2)
    v = rng.standard_normal((T, D))
    bands = tuple(jnp.asarray(a) for a in (A0, A1, A2))
    np.testing.assert_allclose(
        np.asarray(band_matvec(bands, jnp.asarray(v))).ravel(), M @ v.ravel(), rtol=1e-12
    )
    np.testing.assert_allclose(
        float(band_quad(bands, jnp.asarray(v))), v.ravel() @ M @ v.ravel(), rtol=1e-12
    )


def test_single_precision_step_factor_and_its_double_precision_fallback():
    rng = np.random.default_rng(3)
    T, D = 7, 4
    B = rng.standard_normal((T, D, D))
    A0 = np.einsum("tij,tkj->tik", B, B) + 6.0 * np.eye(D)
    A1, A2 = 0.5 * rng.standard_normal((T, D, D)), 0.3 * rng.standard_normal((T, D, D))
    M = _dense_penta(A0, A1, A2)
    r = rng.standard_normal((T, D))
    ref = np.linalg.solve(M, r.reshape(-1)).reshape(T, D)
    x, fac, ok = step_solve(
        lambda x: x, tuple(jnp.asarray(a) for a in (A0, A1, A2)), jnp.asarray(r)
    )
    # the factor is kept in single precision, the substitution runs in double
    assert bool(ok) and bool(fac.ok) and fac.Linv.dtype == jnp.float32
    assert x.dtype == jnp.float64
    x = np.asarray(x)
    # single precision: a step direction, not an exact solve
    assert 1e-12 < np.abs(x - ref).max() / np.abs(ref).max() < 1e-5
    # a pivot that single precision rounds to a singular block (eigenvalue 1e-10 of 2):
    # the step is factored again in double precision and solved exactly
    A0[2, :2, :2] = [[1.0, 1.0 - 1e-10], [1.0 - 1e-10, 1.0]]
    A0[2, 2:, :2] = A0[2, :2, 2:] = 0.0
    A1[2] = A1[3] = A2[2] = A2[3] = A2[4] = 0.0  # block 2 decoupled
    M = _dense_penta(A0, A1, A2)
    assert np.all(np.linalg.eigvalsh(M) > 0)
    ref = np.linalg.solve(M, r.reshape(-1)).reshape(T, D)
    x, fac, ok = step_solve(
        lambda x: x, tuple(jnp.asarray(a) for a in (A0, A1, A2)), jnp.asarray(r)
    )
    assert bool(ok)
    # the single-precision factor failed (the case is real) and is flagged for chord steps
    assert not bool(fac.ok)
    np.testing.assert_allclose(np.asarray(x), ref, rtol=1e-6, atol=1e-8 * np.abs(ref).max())


@pytest.mark.slow  # the default run's budget (about 15 min); CI runs it after
def test_gauss_newton_and_levenberg_marquardt_agree(tex, syn):
    sk = tex.feature_map.skeleton
    hand = _hand(tex)
    j, m = sk.index(hand), 45
    P0 = _positions(tex, syn, syn.Y)
    cons = E.make_constraints(
        sk, T, tex.obs_dim, positions=[(hand, m, P0[m, j] + np.array([0.06, 0.04, -0.03]))]
    )
    gn = E.edit(tex, syn, cons, solver="gn")
    lm = E.edit(tex, syn, cons, solver="lm")
    assert bool(gn.converged) and gn.met, gn.report()
    assert int(gn.steps) < int(lm.steps)
    # the same objective; the LM solver prices the root channels with a weight of 1e4
    np.testing.assert_allclose(np.asarray(gn.Y), np.asarray(lm.Y), atol=2e-3)
    Pg, Pl = _positions(tex, syn, gn.Y), _positions(tex, syn, lm.Y)
    assert np.abs(Pg - Pl).max() < 1e-3
    # the banded solver measures the prior cost as a quadratic form on the prior's bands;
    # it is ½‖w (r(Y) − r(Y₀))‖² of the prior's residuals
    tx = WhitenedTextons.of(tex.textons, jnp.float64)
    seg = E.segments_of(tex, syn)
    r1 = prior_residuals(tx, seg, jnp.asarray(gn.Y))
    r0 = prior_residuals(tx, seg, jnp.asarray(syn.Y))
    w = float(E.EditWeights().prior)
    ref = 0.5 * sum(float(jnp.sum((w * (a - b)) ** 2)) for a, b in zip(r1, r0, strict=True))
    assert ref > 0
    np.testing.assert_allclose(float(gn.prior_cost), ref, rtol=1e-9)


def test_no_constraint_leaves_the_motion_exactly_unchanged(tex, syn):
    sk = tex.feature_map.skeleton
    res = E.edit(tex, syn, E.make_constraints(sk, T, tex.obs_dim, floor=-10.0), solver="gn")
    assert bool(res.converged) and res.met
    np.testing.assert_array_equal(np.asarray(res.Y), np.asarray(syn.Y))


def test_velocity_targets_choose_levenberg_marquardt(tex, syn):
    sk = tex.feature_map.skeleton
    cons = E.make_constraints(sk, T, tex.obs_dim, velocities=[(_hand(tex), 20, [0.0, 0.0, 0.0])])
    with pytest.raises(ValueError, match="velocity"):
        E.edit(tex, syn, cons, solver="gn")
    with pytest.raises(ValueError, match="solver"):
        E.edit(tex, syn, cons, solver="newton")


def test_edit_many_is_a_vmap_batch_that_matches_single_edits(tex, syn):
    sk = tex.feature_map.skeleton
    hand = _hand(tex)
    others = [mj.synthesize(jax.random.key(k), tex, n_frames=T) for k in (7, 8)]
    motions = [syn, *others]
    cons = []
    for i, s in enumerate(motions):
        P0 = _positions(tex, s, s.Y)
        tgt = P0[40 + i, sk.index(hand)] + [0.0, 0.04, 0.02]
        cons.append(E.make_constraints(sk, T, tex.obs_dim, positions=[(hand, 40 + i, tgt)]))
    many = E.edit_many(tex, motions, cons)
    assert many.Y.shape == (3, T, tex.obs_dim)
    for i, (s, c) in enumerate(zip(motions, cons, strict=True)):
        one = E.edit(tex, s, c)
        np.testing.assert_allclose(np.asarray(many.Y[i]), np.asarray(one.Y), atol=1e-8)
        assert bool(many.converged[i]) == bool(one.converged)


def test_edit_many_rejects_bad_devices(tex, syn):
    cons = E.make_constraints(tex.feature_map.skeleton, T, tex.obs_dim)
    with pytest.raises(ValueError, match="devices is empty"):
        E.edit_many(tex, [syn, syn], [cons, cons], devices=[])
    with pytest.raises(TypeError, match="must be JAX devices"):
        E.edit_many(tex, [syn, syn], [cons, cons], devices=["cpu"])


@pytest.mark.slow  # a fresh process that learns and compiles again (about a minute)
def test_edit_many_split_over_two_devices_equals_one_device():
    """Two CPU devices (XLA flag, in a subprocess): a batch of 3 motions (padded to 4) split
    between them gives the one-device batch's results, on the first device."""
    script = """
        import os, sys
        import numpy as np
        import jax
        jax.config.update("jax_enable_x64", True)
        assert jax.device_count() == 2, jax.devices()
        sys.path.insert(0, os.environ["TESTS_DIR"])
        import edit_setup
        import mtex_jax as mj
        from mtex_jax import edit as E
        tex = edit_setup.texture()
        hand, sk, T = edit_setup.hand(tex), tex.feature_map.skeleton, edit_setup.T
        motions = [mj.synthesize(jax.random.key(k), tex, n_frames=T) for k in (1, 2, 3)]
        cons = []
        for i, s in enumerate(motions):
            sp, sh = tex.feature_map.start_of(s.motion)
            P0 = np.asarray(tex.feature_map.joint_positions(s.Y, sp, sh))
            tgt = P0[40 + i, sk.index(hand)] + [0.0, 0.04, 0.02]
            cons.append(E.make_constraints(sk, T, tex.obs_dim, positions=[(hand, 40 + i, tgt)]))
        two = E.edit_many(tex, motions, cons)
        one = E.edit_many(tex, motions, cons, devices=jax.devices()[:1])
        assert two.Y.shape == one.Y.shape == (3, T, tex.obs_dim)
        assert two.Y.devices() == {jax.devices()[0]}, two.Y.devices()
        for a, b in zip(jax.tree.leaves(two), jax.tree.leaves(one), strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-10)
        assert np.all(np.asarray(two.converged))
        print("SPLIT_OK", np.asarray(two.steps).tolist())
        """
    run_with_cpu_devices(script, "SPLIT_OK", timeout=900)


def test_float32_gauss_newton_edit(tex, syn):
    sk = tex.feature_map.skeleton
    hand = _hand(tex)
    P0 = _positions(tex, syn, syn.Y)
    sp, sh = tex.feature_map.start_of(syn.motion)
    cons = E.make_constraints(
        sk, T, tex.obs_dim, positions=[(hand, 45, P0[45, sk.index(hand)] + [0.0, 0.05, 0.0])]
    )
    res = E.edit(
        tex,
        jnp.asarray(syn.Y, jnp.float32),
        cons,
        segments=E.segments_of(tex, syn),
        start_position=sp,
        start_heading=sh,
        solver="gn",
    )
    assert res.Y.dtype == jnp.float32 and bool(res.finite)
    assert float(res.position_error[0]) < 0.005


def test_swing_guidance_is_continuous_and_meets_the_plants(tex, syn, contacts):
    P0 = _positions(tex, syn, syn.Y)
    labels, plants = E.contact_plants(contacts, syn.motion)
    tgt, swing = E.swing_guidance(contacts, P0, labels)
    up = tex.feature_map.skeleton.up_axis
    for foot, a, b, h in plants:
        k = contacts.feet.index(foot)
        assert not swing[a : b + 1, k].any()
        horiz = [i for i in range(3) if i != up]
        np.testing.assert_allclose(tgt[a : b + 1, k][:, horiz].std(axis=0), 0.0, atol=1e-12)
        np.testing.assert_allclose(tgt[a : b + 1, k, up], h, atol=1e-12)
    # guidance moves no faster than the original plus the correction's smooth blend
    for k, foot in enumerate(contacts.feet):
        jump = np.linalg.norm(np.diff(tgt[:, k], axis=0), axis=-1)
        orig = np.linalg.norm(np.diff(P0[:, foot], axis=0), axis=-1)
        assert np.isfinite(jump).all() and jump.max() < orig.max() + 0.05


def test_gauss_newton_clean_stops_the_planted_feet(tex, syn, contacts):
    res = E.clean(tex, syn, contacts)
    assert bool(res.edit.finite)
    ((_, s0),) = contacts.heights_and_speeds(syn.motion)
    ((_, s1),) = contacts.heights_and_speeds(res.motion)
    lab = res.labels
    assert lab.any()
    assert s1[lab].mean() < 0.2 * s0[lab].mean(), (s0[lab].mean(), s1[lab].mean())
    assert s1[lab].max() < 0.25 * s0[lab].max(), (s0[lab].max(), s1[lab].max())
    assert res.penetration_after.max_depth <= 0.01
    assert "converged" in res.edit.report()


def test_apply_shift_moves_the_decoded_root_by_the_offset(tex, syn):
    from mtex_jax.edit._gn import apply_shift, root_channels

    fm = tex.feature_map
    assert root_channels(fm) is not None
    _, h0, h1 = mj.motion.ground_axes(fm.skeleton.up_axis)
    sp, sh = (jnp.asarray(a) for a in fm.start_of(syn.motion))
    Y = jnp.asarray(syn.Y)
    t = np.arange(T) / FPS
    dx = jnp.asarray(np.stack([0.1 * np.sin(t), 0.05 * t], axis=1))
    Y2, sp2 = apply_shift(fm, Y, sp, sh, dx)
    a = np.asarray(fm.decode(Y, sp, sh).root_positions)
    b = np.asarray(fm.decode(Y2, sp2, sh).root_positions)
    want = a.copy()
    want[:, h0] += np.asarray(dx[:, 0])
    want[:, h1] += np.asarray(dx[:, 1])
    np.testing.assert_allclose(b, want, atol=1e-10)
    # only the two displacement channels changed
    changed = np.abs(np.asarray(Y2) - np.asarray(Y)).max(axis=0) > 0
    assert changed.sum() == 2


def test_clean_result_decodes_with_its_start_position(tex, syn, contacts):
    res = E.clean(tex, syn, contacts, loglik=False)
    fm = tex.feature_map
    sh = fm.start_of(syn.motion)[1]
    again = fm.decode(res.Y, res.edit.start_position, sh)
    np.testing.assert_allclose(
        np.asarray(again.root_positions), np.asarray(res.motion.root_positions), atol=1e-12
    )
    held = E.clean(tex, syn, contacts, loglik=False, move_root=False)
    np.testing.assert_allclose(
        np.asarray(held.edit.start_position), fm.start_of(syn.motion)[0], atol=1e-12
    )


def _toy_problem(rng, T, D, K, spread):
    """A small banded problem: ``K`` joints of ``tanh`` kinematics over ``D`` channels, a
    motion ``Y0`` of ``T`` frames and prior bands laid out as ``prior_hessian``'s."""
    W = jnp.asarray(rng.standard_normal((K, 3, D)) / np.sqrt(D))
    fn = lambda Y: jnp.tanh(jnp.einsum("kcd,td->tkc", W, Y))
    Y0 = jnp.asarray(spread * rng.standard_normal((T, D)))
    eye = np.broadcast_to(np.eye(D), (T, D, D))
    H1, H2 = -0.5 * eye.copy(), 0.1 * eye.copy()
    H1[0] = H2[0] = H2[1] = 0.0  # the band layout of prior_hessian
    return fn, Y0, (jnp.asarray(2.0 * eye), jnp.asarray(H1), jnp.asarray(H2))


def _toy_solve(
    fn, Y0, bands, points, lower, lw, *, anchor=None, exact=None, tol=0.0, shifted=True, **solver
):
    """The toy problem's banded solve: the point targets and the lower heights (up axis 2) as
    its terms, every channel free, nothing held."""
    D = Y0.shape[1]
    terms = (
        E.HeightBounds(lower=lower, weight=jnp.asarray(lw), up=2, exact=exact, tol=tol),
        dataclasses.replace(points, shifted=shifted),
    )
    pb = E.BandedProblem(
        positions=fn,
        Y0=Y0,
        bands=bands,
        anchor=jnp.ones(D) if anchor is None else anchor,
        free_ch=jnp.ones(D),
        terms=terms,
    )
    return E.solve_banded(pb, E.BandedGaussNewton(**solver))


def _toy_points(T, F, K, rng, per_frame):
    slots = rng.integers(0, K, F)
    return E.PointTargets(
        slot=jnp.asarray(np.tile(slots, T), jnp.int32),
        frame=jnp.asarray(np.repeat(np.arange(T), F), jnp.int32),
        target=jnp.asarray(0.3 * rng.standard_normal((T * F, 3))),
        weight=jnp.asarray(rng.uniform(0.0, 3.0, (T * F, 3))),
        exact=jnp.asarray(rng.uniform(size=T * F) < 0.3),
        n_sparse=0 if per_frame else None,
        per_frame=F if per_frame else 0,
    )


def test_frame_major_targets_solve_as_sparse_ones_and_join_per_frame():
    """Targets marked frame-major (assembled per frame) give the solve of the same targets
    assembled one by one; join_points merges frame-major sets frame by frame."""
    rng = np.random.default_rng(4)
    T, D, K, F = 12, 5, 3, 2
    fn, Y0, bands = _toy_problem(rng, T, D, K, 0.2)
    lower = jnp.full((T, K), -jnp.inf)
    sparse = _toy_points(T, F, K, np.random.default_rng(9), per_frame=False)
    dense = _toy_points(T, F, K, np.random.default_rng(9), per_frame=True)
    run = lambda p: _toy_solve(fn, Y0, bands, p, lower, 1.0, rounds=2)
    a, b = run(sparse), run(dense)
    assert int(a.steps) > 1 and bool(a.converged) and bool(b.converged)
    np.testing.assert_allclose(np.asarray(b.z), np.asarray(a.z), atol=1e-6)
    # a sparse set joined with two frame-major ones: sparse first, then per frame
    extra = _toy_points(T, 1, K, rng, per_frame=True)
    pos = E.PointTargets(
        slot=jnp.asarray([1], jnp.int32),
        frame=jnp.asarray([5], jnp.int32),
        target=jnp.zeros((1, 3)),
        weight=jnp.ones((1, 3)),
        exact=jnp.asarray([True]),
    )
    j = join_points(join_points(pos, dense), extra)
    assert j.sparse_count == 1 and j.per_frame == F + 1
    fr = np.asarray(j.frame)
    assert fr[0] == 5 and np.array_equal(fr[1:], np.repeat(np.arange(T), F + 1))
    tg = np.asarray(j.target)[1:].reshape(T, F + 1, 3)
    np.testing.assert_array_equal(tg[:, :F], np.asarray(dense.target).reshape(T, F, 3))
    np.testing.assert_array_equal(tg[:, F], np.asarray(extra.target))
    # the joined set solves as the same targets all assembled one by one
    flat = E.PointTargets(
        slot=j.slot, frame=j.frame, target=j.target, weight=j.weight, exact=j.exact
    )
    np.testing.assert_allclose(np.asarray(run(j).z), np.asarray(run(flat).z), atol=1e-6)


def test_contact_plants_rules_match_the_contact_model(syn, contacts):
    m = syn.motion
    ((h, _),) = contacts.heights_and_speeds(m)
    H = contacts.height_threshold
    low, plants = E.contact_plants(contacts, m, rule="low")
    np.testing.assert_array_equal(low, (h[:-1] < H) & (h[1:] < H))
    slow, _ = E.contact_plants(contacts, m, rule="low_and_slow")
    np.testing.assert_array_equal(slow, contacts.labels(m))
    assert slow.sum() <= low.sum()
    # every plant is a run of contact steps of its foot, at a height within [floor, H_f]
    feet = list(contacts.feet)
    for foot, a, b, height in plants:
        k = feet.index(foot)
        assert low[a:b, k].all()
        assert contacts.floor - 1e-12 <= height <= H[k] + 1e-12
    with pytest.raises(ValueError, match="rule"):
        E.contact_plants(contacts, m, rule="fast")


def test_exact_lower_rounds_meet_the_bound_as_a_constrained_solve():
    """With ``exact_lower`` the multiplier rounds solve the bound-constrained problem: the
    result equals scipy's SLSQP minimum of the same objective with ``h ≥ lower`` as hard
    constraints (the point targets stay penalties), where the plain penalty leaves the bound
    violated."""
    from scipy.optimize import minimize

    rng = np.random.default_rng(5)
    T, D, K, F = 10, 4, 3, 1
    fn, Y0, bands = _toy_problem(rng, T, D, K, 0.4)
    pts = _toy_points(T, F, K, np.random.default_rng(9), per_frame=True)
    h0 = np.asarray(fn(Y0))[..., 2]
    lower = jnp.asarray(np.where(h0 < np.median(h0), np.median(h0), -np.inf))  # half violated
    mask = jnp.isfinite(lower)
    lw = 10.0

    def run(**kw):
        return _toy_solve(fn, Y0, bands, pts, lower, lw, chord=False, **kw)

    rounds = dict(rounds=12, rtol=1e-12, early_rtol=1e-12, max_steps=30, shifted=False)
    al = run(**rounds, exact=mask, tol=1e-9)
    pen = run(rounds=1, rtol=1e-12, max_steps=30)
    M = _dense_penta(*(np.asarray(b) for b in bands)) + np.eye(T * D)  # band + unit anchor

    def f(z):
        P = fn(Y0 + z.reshape(T, D))
        r = P[pts.frame, pts.slot] - pts.target
        return 0.5 * (z @ M @ z + jnp.sum(pts.weight**2 * r * r))

    fj = jax.jit(jax.value_and_grad(lambda z: f(z)))
    hz = jax.jit(lambda z: fn(Y0 + z.reshape(T, D))[..., 2][np.asarray(mask)])
    hj = jax.jit(jax.jacobian(lambda z: fn(Y0 + z.reshape(T, D))[..., 2][np.asarray(mask)]))
    lo = np.asarray(lower)[np.asarray(mask)]
    ref = minimize(
        lambda z: tuple(np.asarray(v, np.float64) for v in fj(jnp.asarray(z))),
        np.zeros(T * D),
        jac=True,
        method="SLSQP",
        constraints=[
            {
                "type": "ineq",
                "fun": lambda z: np.asarray(hz(jnp.asarray(z))) - lo,
                "jac": lambda z: np.asarray(hj(jnp.asarray(z))),
            }
        ],
        options={"ftol": 1e-14, "maxiter": 500},
    )
    assert ref.success, ref.message
    h_al = np.asarray(fn(Y0 + al.z))[..., 2]
    h_pen = np.asarray(fn(Y0 + pen.z))[..., 2]
    assert np.max(np.asarray(lower) - h_pen) > 0.05  # the penalty alone leaves it violated
    assert np.max(np.asarray(lower) - h_al) < 1e-7
    np.testing.assert_allclose(np.asarray(al.z).ravel(), ref.x, atol=1e-5)
    # bounds met to lower_tol after the first round: no further round (the penalty's solve)
    met = run(**rounds, exact=mask, tol=1.0)
    assert int(met.steps) == int(pen.steps)
    np.testing.assert_array_equal(np.asarray(met.z), np.asarray(pen.z))
