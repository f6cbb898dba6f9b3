"""The texture's MAP smoother (design §12.2-§12.3) against independent references: finite
differences, a dense minimisation of the same objective with scipy, the truth of noise-free
problems, and the trackers' checks of bad input."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import mtex_jax as mj
from mtex_jax.core import count_compiles
from mtex_jax.edit import WhitenedTextons, prior_residuals

# the subject of these tests: the smoother's pieces (the term's rows, one banded solve)
from mtex_jax.edit._banded.terms import residual_rows
from mtex_jax.edit._prior import _REL_FLOOR  # the whitening's ridge, re-derived below
from mtex_jax.io import load_salsa
from mtex_jax.motion import ground_axes
from mtex_jax.tracking import (
    Camera,
    Gaussian,
    Huber,
    MapSmoother,
    ParticleFilter,
    SmoothPrior,
    StudentT,
    TexturePrior,
    TrackingProblem,
    make_problem,
    track,
)
from mtex_jax.tracking._body import Body
from mtex_jax.tracking._priors import root_weights
from mtex_jax.tracking._reprojection import Reprojection
from mtex_jax.tracking._smoother import _bone_step, _floor_term, _Frame, _single, _solve
from shared_textures import salsa_tracking_texture


@pytest.fixture(scope="module")
def texture() -> mj.MotionTexture:
    return salsa_tracking_texture()


@pytest.fixture(scope="module")
def clip(texture) -> mj.Motion:
    return load_salsa("60_12").resample(texture.feature_map.fps)  # held out


@pytest.fixture(scope="module")
def problem(texture, clip) -> TrackingProblem:
    return make_problem(jax.random.key(0), texture, clip, n_frames=40, start=30)


def _truth_X(texture, clip, problem) -> tuple[Body, jax.Array]:
    """The tracker's coordinates of the true motion at the problem's frames."""
    fm = texture.feature_map
    body = Body.of(fm, problem.joints)
    seg = clip[problem.frames[0] : problem.frames[-1] + 1]
    return body, body.coordinates(fm.encode(seg), *map(jnp.asarray, fm.start_of(seg)))


def _frame(texture, body, problem, sigma, loss, T, floor_contact=True) -> _Frame:
    dt = jnp.float64
    fm = texture.feature_map
    rep = Reprojection(
        camera=problem.camera,
        slots=body.slots,
        observations=problem.observations[:T],
        confidence=problem.confidence[:T],
        sigma=jnp.asarray(sigma, dt),
        pixel_loss=loss,
    )
    return _Frame(
        body=body,
        tx=WhitenedTextons.of(texture.textons, dt),
        reproj=rep,
        root_w=jnp.asarray(root_weights(fm.dim, body.root_cols, fm.fps, 6.0, 60.0)),
        bone_scale=jnp.ones((fm.skeleton.n_joints,), dt),
        floor=jnp.zeros((), dt),
        contact=_floor_term(texture, body, T, dt) if floor_contact else None,
        fps=float(fm.fps),
    )


def test_body_coordinates_round_trip(texture, clip, problem):
    """X of a clip poses exactly its joints, and gives back its observation vectors."""
    body, X = _truth_X(texture, clip, problem)
    np.testing.assert_allclose(np.asarray(body.observed(X)), np.asarray(problem.truth), atol=1e-9)
    fm = texture.feature_map
    seg = clip[problem.frames[0] : problem.frames[-1] + 1]
    np.testing.assert_allclose(
        np.asarray(body.observations(X))[1:], np.asarray(fm.encode(seg))[1:], atol=1e-9
    )


@pytest.mark.parametrize("loss", [Gaussian(), StudentT(4.0), Huber(2.0)], ids=type)
def test_reprojection_rows_match_finite_differences(texture, clip, problem, loss):
    """The term's Gauss-Newton rows are the finite-difference Jacobian of its residual
    through the body's kinematics, and their IRLS weights give the loss's gradient."""
    body, X = _truth_X(texture, clip, problem)
    T = 6
    X = X[:T] + 0.05 * jax.random.normal(jax.random.key(1), X[:T].shape)
    term = _frame(texture, body, problem, 2.0, loss, T).reproj
    fn = lambda X: body.positions(X)
    P = fn(X)
    Jp = jax.vmap(jax.jacfwd(lambda x: fn(x[None])[0]))(X)  # (T, Ks, 3, D)
    rows, res = residual_rows(term, P, Jp)
    r = term.residual(P)
    sw = np.sqrt(np.asarray(term.weights(r)))
    D, eps = X.shape[1], 1e-6
    res_of = jax.jit(lambda X: term.residual(fn(X)))
    fd = np.zeros((T, r.shape[1], D))
    for d in range(D):  # one channel at every frame at once (frames do not interact)
        e = jnp.zeros_like(X).at[:, d].set(eps)
        fd[:, :, d] = (np.asarray(res_of(X + e)) - np.asarray(res_of(X - e))) / (2 * eps)
    np.testing.assert_allclose(np.asarray(rows), fd * sw[..., None], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(res), np.asarray(r) * sw, rtol=1e-12)
    # IRLS: the loss's gradient is Jᵀ (w ⊙ r), the rows' Jᵀ(√w √w r)
    g = jax.grad(lambda X: term.loss(term.residual(fn(X))))(X)
    np.testing.assert_allclose(
        np.asarray(g),
        np.einsum("trd,tr->td", np.asarray(rows), np.asarray(res)),
        rtol=1e-6,
        atol=1e-9,
    )


def test_map_solves_the_dense_objective(texture, clip, problem):
    """One banded solve of a tiny problem (8 frames, the default prior's textons) ends at the
    minimum of the objective written densely as one residual vector (the texture prior's
    residuals, the root's second differences, the anchor, the reprojection): scipy's exact
    Newton (trust region, the dense Hessian by autodiff), started there, converges within a few
    iterations to a point whose joints are within 1 mm and whose cost is the same to 1e-5
    (measured: 2 iterations, 0.54 mm, 2e-6). The objective is not convex: from the start
    itself Newton may end in another basin (a limb mirrored in depth), so the reference is
    the dense solver's own convergence from the banded answer."""
    body, Xt = _truth_X(texture, clip, problem)
    T = 8
    X0 = Xt[:T] + 0.03 * jax.random.normal(jax.random.key(2), Xt[:T].shape)
    fr = _frame(texture, body, problem, 2.0, Gaussian(), T, floor_contact=False)
    fr = eqx.tree_at(lambda f: f.tx, fr, TexturePrior().whitened(texture.textons, jnp.float64))
    seg = _single(1, T)
    n = jnp.asarray(T)
    # the solve's own fixed point is the subject, not its speed: enough steps to reach it (from
    # this start it needed 60–120 with the packages of 2026-12; the tracker's rounds use 12)
    X_map, _ = _solve(fr, TexturePrior(), seg, X0, jnp.zeros((T,), bool), None, n, 200)
    Y0 = body.observations(X0)
    keep = fr.root_w == 0
    rep = fr.reproj

    def cost(x: jax.Array) -> jax.Array:
        X = x.reshape(X0.shape)
        e, g, o = prior_residuals(fr.tx, seg, jnp.where(keep, X, Y0), n)
        d2 = (X[2:] - 2 * X[1:-1] + X[:-2]) * fr.root_w
        r = rep.residual(body.positions(X)) / rep.sigma
        parts = (e, g, o, d2, 1e-4 * (X - X0), r)
        return 0.5 * jnp.sum(jnp.stack([jnp.sum(a**2) for a in parts]))

    f, grad, hess = (jax.jit(h) for h in (cost, jax.grad(cost), jax.hessian(cost)))
    ref = scipy.optimize.minimize(
        lambda x: float(f(x)),
        np.asarray(X_map).ravel(),
        jac=lambda x: np.asarray(grad(x)),
        hess=lambda x: np.asarray(hess(x)),
        method="trust-exact",
        options={"gtol": 1e-6, "maxiter": 200},
    )
    g_ref = np.abs(np.asarray(grad(jnp.asarray(ref.x)))).max()
    assert g_ref < 1e-3, f"the dense reference did not converge: gradient {g_ref:.3g}"
    assert ref.nit <= 10, f"the dense Newton needed {ref.nit} iterations from the banded answer"
    c_map = float(f(X_map.ravel()))
    assert abs(c_map - ref.fun) <= 1e-5 * abs(ref.fun), f"cost {c_map:.8g} vs dense {ref.fun:.8g}"
    P_ref = body.observed(jnp.asarray(ref.x.reshape(X0.shape)))
    d = np.linalg.norm(np.asarray(body.observed(X_map)) - np.asarray(P_ref), axis=-1)
    assert d.max() < 1e-3, f"joints {1000 * d.max():.2f} mm from the dense minimum"


def test_noise_free_observations_recover_the_truth(texture, clip):
    """Noise-free pixels of the true skeleton, a precise reprojection (0.01 px) and a start 2 cm
    (z-scored) off with the root 6 cm and 0.05 rad off: three rounds of the solve (the prior
    re-expanded at each, as the smoother's rounds do) explain every pixel to 0.05 px and put
    95 % of the joint-frames within 1 mm of the truth (measured: 95.6 %, median 0.2 mm). The
    rest, one leg in a few frames, sits exactly on the same pixels (measured worst 26 mm): a
    thigh nearly square to its camera ray has a mirror pose in depth that one camera cannot
    tell apart (design §12.3), which no solver tolerance removes."""
    prob = make_problem(jax.random.key(0), texture, clip, n_frames=20, start=60, pixel_noise=0.0)
    body, Xt = _truth_X(texture, clip, prob)
    T = prob.n_frames
    fr = _frame(texture, body, prob, 0.01, Gaussian(), T, floor_contact=False)
    X = Xt + 0.02 * jax.random.normal(jax.random.key(3), Xt.shape)
    c0, c1, cy = body.root_cols
    X = X.at[:, c0].add(0.03).at[:, c1].add(-0.05).at[:, cy].add(0.05)
    seg = _single(1, T)
    for _ in range(3):
        X, _ = _solve(fr, TexturePrior(), seg, X, jnp.zeros((T,), bool), None, jnp.asarray(T), 40)
    P = body.observed(X)
    px = np.abs(np.asarray(prob.camera.project(P)) - np.asarray(prob.observations))
    assert px.max() < 0.05, f"largest pixel residual {px.max():.3f} px"
    err = np.linalg.norm(np.asarray(P) - np.asarray(prob.truth), axis=-1)
    assert np.median(err) < 5e-4, f"median joint error {1000 * np.median(err):.2f} mm"
    share = float((err < 1e-3).mean())
    assert share >= 0.95, f"{100 * share:.1f} % of the joint-frames within 1 mm"


def _true_bones(texture, prob, key):
    """The per-bone scales ``make_problem(key, …, bone_scale=(0.9, 1.1))`` drew, the model's
    bone lengths, and the bones between observed joints longer than 5 cm."""
    sk = texture.feature_map.skeleton
    k_bones = jax.random.fold_in(key, 1)
    bs = np.asarray(jax.random.uniform(k_bones, (sk.n_joints,), minval=0.9, maxval=1.1))
    length = np.linalg.norm(np.asarray(sk.offsets), axis=1)
    observed = set(prob.joints)
    bones = [j for j in prob.joints if sk.parents[j] in observed and length[j] > 0.05]
    return bs, length, bones


def test_bone_lengths_recovered_on_a_scaled_skeleton(texture, clip):
    """The bone step on a person with bones scaled 0.9-1.1 (noise-free pixels, the poses known)
    recovers the lengths of the bones between observed joints within 1 cm."""
    prob = make_problem(
        jax.random.key(5),
        texture,
        clip,
        n_frames=40,
        start=30,
        pixel_noise=0.0,
        bone_scale=(0.9, 1.1),
    )
    body, X = _truth_X(texture, clip, prob)
    sk = texture.feature_map.skeleton
    truth = prob.truth
    fr = _frame(texture, body, prob, 1.0, Gaussian(), prob.n_frames, floor_contact=False)
    # the true world root (the scaled body stands on the floor: its root was lifted)
    up = sk.up_axis
    lift = float(np.median(np.asarray(truth)[:, 0, up] - np.asarray(body.observed(X))[:, 0, up]))
    sc = float(np.asarray(texture.feature_map.scale)[np.asarray(texture.feature_map.active)][2])
    X = X.at[:, 2].add(lift / sc)
    sd = jnp.asarray([0.05, 0.05])
    for _ in range(2):
        fr, X = _bone_step(fr, X, jnp.ones((prob.n_frames,), bool), sd, False)
    est = np.asarray(fr.bone_scale)
    bs, length, bones = _true_bones(texture, prob, jax.random.key(5))
    assert len(bones) >= 8
    worst = max(abs(length[j] * (est[j] - bs[j])) for j in bones)
    assert worst < 0.01, f"a bone {1000 * worst:.1f} mm off"


def test_the_floor_settles_the_body_size(texture, clip):
    """A person 5 % larger than the model, noise-free pixels: the model-sized body 5 % nearer
    along every camera ray projects exactly alike, so the bone step started there with the
    pixels alone stays at the model's size; with the feet on the floor (the camera's height
    known) it finds the person's size (design §12.2, "Size and depth")."""
    fm = texture.feature_map
    sk = fm.skeleton
    prob = make_problem(
        jax.random.key(5),
        texture,
        clip,
        n_frames=40,
        start=30,
        pixel_noise=0.0,
        bone_scale=np.full(sk.n_joints, 1.05),
    )
    body, X = _truth_X(texture, clip, prob)
    up, h0, h1 = ground_axes(sk.up_axis)
    c0, c1, _ = body.root_cols
    sc = float(np.asarray(fm.scale)[np.asarray(fm.active)][2])
    off = float(np.asarray(fm.offset)[np.asarray(fm.active)][2])
    truth = np.asarray(prob.truth)
    lift = float(np.median(truth[:, 0, up] - np.asarray(body.observed(X))[:, 0, up]))
    X = X.at[:, 2].add(lift / sc)
    # the model-sized body that projects alike: every root 1/1.05 of the way along its ray
    cam = prob.camera
    centre = -np.asarray(cam.rotation).T @ np.asarray(cam.translation)
    k = 1 / 1.05
    X = X.at[:, c0].set(centre[h0] + k * (X[:, c0] - centre[h0]))
    X = X.at[:, c1].set(centre[h1] + k * (X[:, c1] - centre[h1]))
    u = centre[up] + k * (X[:, 2] * sc + off - centre[up])
    X = X.at[:, 2].set((u - off) / sc)
    px = np.asarray(jax.vmap(cam.project)(body.observed(X)))
    gap = np.linalg.norm(px - np.asarray(prob.observations), axis=-1)
    assert np.median(gap) < 1.0, f"the start does not project alike: {np.median(gap):.2f} px"
    used = np.asarray(body.order)
    sizes = {}
    for floor in (False, True):
        fr = _frame(texture, body, prob, 1.0, Gaussian(), prob.n_frames, floor_contact=floor)
        Xe = X
        for _ in range(2):
            sd = jnp.asarray([0.05, 0.05])
            fr, Xe = _bone_step(fr, Xe, jnp.ones((prob.n_frames,), bool), sd, False)
        sizes[floor] = float(np.mean(np.log(np.asarray(fr.bone_scale)[used])))
    print(f"\nsize {np.log(1.05):+.3f}: pixels {sizes[False]:+.3f}, floor {sizes[True]:+.3f}")
    assert abs(sizes[False]) < 0.01  # the pixels alone cannot move it
    assert abs(sizes[True] - np.log(1.05)) < 0.02  # measured +0.063: 60_12's ankles stand high


def test_fixed_lag_estimates_the_bones_after_a_known_window(texture, clip):
    """With a known initial window and ``bones=True`` the fixed-lag smoother estimates the
    person's bones (from the batch solve of its first ``bone_window`` seconds) and keeps them:
    on a skeleton scaled 0.9-1.1 per bone its bone lengths are nearer the truth than the
    model's, and the frames after the window are tracked with them."""
    prob = make_problem(
        jax.random.key(5), texture, clip, n_frames=45, start=30, bone_scale=(0.9, 1.1)
    )
    assert prob.has_init
    r = track(jax.random.key(0), texture, prob, MapSmoother(lag=6, bones=True, bone_window=1.0))
    assert r.bone_scale is not None
    est = np.asarray(r.bone_scale)
    bs, length, bones = _true_bones(texture, prob, jax.random.key(5))
    err_est = np.mean([abs(length[j] * (est[j] - bs[j])) for j in bones])
    err_model = np.mean([abs(length[j] * (1.0 - bs[j])) for j in bones])
    print(f"\nmean bone error: estimated {1000 * err_est:.1f} mm, model {1000 * err_model:.1f} mm")
    assert np.ptp(est[bones]) > 0.01  # estimated, not the model's
    assert err_est < 0.8 * err_model
    assert np.all(np.isfinite(np.asarray(r.mean_joints)))


def test_track_with_the_texture_beats_a_smoothness_prior(texture, problem):
    """The small version of bench_tracking: the texture's MAP on 40 held-out frames is within
    80 mm and better than the same smoother with a smoothness-only prior; the fixed-lag
    smoother within 1.5 × the batch one; the texton labels come with the result."""
    r = track(jax.random.key(0), texture, problem)
    s = track(jax.random.key(0), texture, problem, MapSmoother(prior=SmoothPrior()))
    lag = track(jax.random.key(0), texture, problem, MapSmoother(lag=10))
    e, es, el = r.mean_error, s.mean_error, lag.mean_error
    print(f"\nMAP {1000 * e:.1f} mm, smoothness {1000 * es:.1f}, fixed-lag {1000 * el:.1f}")
    assert e < 0.08 and e < es and el < 1.5 * e
    assert r.labels is not None and r.labels.shape == (problem.n_frames,)
    assert set(np.unique(np.asarray(r.labels))) <= set(range(texture.n_textons))
    assert r.motion is not None and r.motion.n_frames == problem.n_frames
    P = np.asarray(mj.forward_kinematics(r.motion))[:, list(problem.joints)]
    np.testing.assert_allclose(P, np.asarray(r.mean_joints), atol=1e-6)  # the BVH is the estimate
    for a in (r.error, r.error_root_relative, r.error_aligned):
        assert a is not None and np.all(np.isfinite(np.asarray(a)))


def test_fixed_lag_is_causal(texture, problem):
    """A fixed-lag frame is final L frames later: frames up to T − 1 − L of a clip cut at T
    are those of the whole clip."""
    T, L = 24, 4
    cut = dataclasses.replace(
        problem,
        frames=problem.frames[:T],
        observations=problem.observations[:T],
        confidence=problem.confidence[:T],
        truth=problem.truth[:T] if problem.truth is not None else None,
    )
    opts = MapSmoother(lag=L)
    a = np.asarray(track(jax.random.key(0), texture, cut, opts).mean_joints)
    b = np.asarray(track(jax.random.key(0), texture, problem, opts).mean_joints)
    np.testing.assert_allclose(a[: T - L], b[: T - L], atol=1e-9)
    assert not np.allclose(a[T - 1], b[T - 1], atol=1e-6)  # the last frames were not final


def test_missing_joints_and_outliers(texture, clip, problem):
    """Missing joints (confidence 0) with garbage pixels change nothing; a frame with every
    joint missing is carried by the prior; the robust loss shrugs off outliers."""
    r = track(jax.random.key(0), texture, problem)
    conf = np.asarray(problem.confidence).copy()
    obs = np.asarray(problem.observations).copy()
    conf[5, 3], obs[5, 3] = 0.0, np.nan  # declared missing: any value, NaN included
    conf[12, :], obs[12, :] = 0.0, 1e6  # a frame with nothing seen
    p2 = eqx.tree_at(lambda p: (p.observations, p.confidence), problem, (obs, conf))
    r2 = track(jax.random.key(0), texture, p2)
    assert np.all(np.isfinite(np.asarray(r2.mean_joints)))
    assert float(r2.error[12]) < 0.1  # the prior carries the frame
    obs_same = obs.copy()
    obs_same[5, 3], obs_same[12, :] = -3.0, 7.0  # other garbage at the same missing joints
    p3 = eqx.tree_at(lambda p: p.observations, p2, obs_same)
    np.testing.assert_allclose(
        np.asarray(track(jax.random.key(0), texture, p3).mean_joints),
        np.asarray(r2.mean_joints),
        atol=1e-9,
    )
    hard = make_problem(jax.random.key(0), texture, clip, n_frames=40, start=30, outliers=0.05)
    rh = track(jax.random.key(0), texture, hard)
    assert rh.mean_error < 1.5 * r.mean_error + 0.005


def test_bad_input_is_refused(texture, problem):
    key = jax.random.key(0)
    obs = np.asarray(problem.observations).copy()
    obs[3, 2] = np.nan
    with pytest.raises(ValueError, match="not declared missing"):
        track(key, texture, eqx.tree_at(lambda p: p.observations, problem, obs))
    with pytest.raises(ValueError, match="observations must have shape"):
        dataclasses.replace(problem, observations=problem.observations[:, :-1])
    cam = problem.camera
    with pytest.raises(ValueError, match="focal length"):
        track(key, texture, eqx.tree_at(lambda p: p.camera.focal, problem, jnp.asarray(0.0)))
    flip = jnp.asarray([-1.0, 1.0, -1.0])  # turned half round about its down axis
    behind = Camera(
        rotation=cam.rotation * flip[:, None],
        translation=cam.translation * flip,
        focal=cam.focal,
        center=cam.center,
    )
    with pytest.raises(ValueError, match="behind the subject"):
        track(key, texture, eqx.tree_at(lambda p: p.camera, problem, behind))
    conf = np.asarray(problem.confidence).copy()
    conf[0, 0] = 1.5
    with pytest.raises(ValueError, match="confidences"):
        track(key, texture, eqx.tree_at(lambda p: p.confidence, problem, conf))
    for bad in (
        dict(lag=0),
        dict(rounds=0),
        dict(root_accel=-1.0),
        dict(floor="guess"),
        dict(bone_window=-1.0),
    ):
        with pytest.raises(ValueError, match=next(iter(bad))):
            MapSmoother(**bad)
    with pytest.raises(ValueError, match="nu"):
        StudentT(0.0)
    with pytest.raises(TypeError, match="MotionTexture"):
        track(key, texture, problem, ParticleFilter())
    with pytest.raises(TypeError, match=r"ImplicitModel|MotionTexture"):
        track(key, object(), problem)  # type: ignore[arg-type]


def test_a_new_length_in_the_same_bucket_does_not_compile(texture, problem):
    """Clips of 40 and 37 frames share a shape bucket: the second compiles nothing."""
    track(jax.random.key(0), texture, problem)
    short = dataclasses.replace(
        problem,
        frames=problem.frames[:37],
        observations=problem.observations[:37],
        confidence=problem.confidence[:37],
        truth=problem.truth[:37] if problem.truth is not None else None,
    )
    with count_compiles() as c:
        track(jax.random.key(0), texture, short)
    assert c.programs == 0, f"{c.programs} programs compiled"


def test_float32_smoke(texture, problem):
    """A texture in single precision tracks in single precision, finitely."""
    t32 = jax.tree.map(lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, texture)
    p32 = jax.tree.map(lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, problem)
    r = track(jax.random.key(0), t32, p32)
    assert r.mean_joints.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(r.mean_joints))) and r.mean_error < 0.1


def test_process_noise_inflation_adds_to_every_noise_covariance(texture):
    """``WhitenedTextons.of(..., noise=ν)`` whitens with ``B Bᵀ + ν² I`` (innovations),
    ``S₀ + ν² I`` (initial pairs) and ``σ² + ν²`` (out of the subspace): numpy re-derivation."""
    t = texture.textons
    nu = 0.03
    tx = WhitenedTextons.of(t, jnp.float64, nu)
    B = np.tril(np.asarray(t.B))
    for i in range(B.shape[0]):
        k = B.shape[-1]
        Q = B[i] @ B[i].T + nu**2 * np.eye(k)
        W = np.asarray(tx.B_inv[i])
        np.testing.assert_allclose(W @ Q @ W.T, np.eye(k), atol=1e-8)
        S0 = 0.5 * (np.asarray(t.S0[i]) + np.asarray(t.S0[i]).T) + nu**2 * np.eye(2 * k)
        S0 = S0 + _REL_FLOOR * np.trace(S0) / (2 * k) * np.eye(2 * k)  # the whitening's ridge
        L = np.asarray(tx.L0_inv[i])
        np.testing.assert_allclose(L @ S0 @ L.T, np.eye(2 * k), atol=1e-8)
    np.testing.assert_allclose(
        np.asarray(tx.inv_sigma), 1 / np.sqrt(np.asarray(t.sigma2) + nu**2), rtol=1e-12
    )
    with pytest.raises(ValueError, match="noise"):
        WhitenedTextons.of(t, jnp.float64, -1.0)
    with pytest.raises(ValueError, match="noise"):
        TexturePrior(noise=float("nan"))


def test_smooth_prior_quadratic_is_its_cost(texture, clip, problem):
    """``SmoothPrior.quadratic`` (second differences plus each channel's training marginal)
    gives the Hessian and gradient of its cost written out directly (autodiff, dense)."""
    body, Xt = _truth_X(texture, clip, problem)
    fm = texture.feature_map
    T, D = 6, fm.dim
    X0 = Xt[:T]
    root_w = jnp.asarray(root_weights(D, body.root_cols, fm.fps, 6.0, 60.0))
    pr = SmoothPrior(pose_sd=0.7)
    tx = WhitenedTextons.of(texture.textons, jnp.float64)  # not read by this prior
    (H0, H1, H2), g = pr.quadratic(tx, _single(0, T), X0, X0, root_w, fm.fps, T)
    w = jnp.where(root_w > 0, root_w, fm.fps**2 / pr.accel)
    keep = (root_w == 0).astype(X0.dtype)

    def cost(X):
        d2 = (X[2:] - 2 * X[1:-1] + X[:-2]) * w
        return 0.5 * jnp.sum(d2**2) + 0.5 * jnp.sum(keep * (X / 0.7) ** 2)

    Hd = np.asarray(jax.hessian(cost)(X0)).reshape(T, D, T, D)
    np.testing.assert_allclose(np.asarray(g), np.asarray(jax.grad(cost)(X0)), atol=1e-9)
    for t in range(T):
        np.testing.assert_allclose(np.asarray(H0[t]), Hd[t, :, t], atol=1e-6)
        if t >= 1:
            np.testing.assert_allclose(np.asarray(H1[t]), Hd[t, :, t - 1], atol=1e-6)
        if t >= 2:
            np.testing.assert_allclose(np.asarray(H2[t]), Hd[t, :, t - 2], atol=1e-6)


def test_float32_tracks_a_whole_clip(texture, clip):
    """JAX's default precision tracks 150 frames of a dancer the texture never saw, batch and
    fixed-lag, as well as double precision (measured, both precisions: batch 26.6 mm mean,
    81 mm worst; fixed-lag 48.4 and 97 mm). Before the process-noise inflation of design §12.2
    the batch smoother diverged here in single precision (1,781 mm mean, 9.8 m worst)."""
    cast = lambda tree: jax.tree.map(
        lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, tree
    )
    prob = make_problem(jax.random.key(1), texture, clip, n_frames=150, start=30)
    t32, p32 = cast(texture), cast(prob)
    for method in (MapSmoother(), MapSmoother(lag=10)):
        r = track(jax.random.key(0), t32, p32, method)
        assert r.mean_joints.dtype == jnp.float32
        err = np.asarray(r.error)
        assert np.all(np.isfinite(err))
        assert err.mean() < 0.06, f"lag={method.lag}: mean error {1000 * err.mean():.1f} mm"
        assert err.max() < 0.3, f"lag={method.lag}: worst frame {1000 * err.max():.1f} mm"


def test_a_given_skeleton_is_kept(texture, clip):
    """A person's skeleton given with the problem (``known_bones=True``: measured beforehand) is
    the one ``make_problem`` drew, and the smoother tracks with it: every tracked bone between
    two observed joints has the given length at every frame, and the track is nearer the
    truth than the same problem tracked with the model's skeleton."""
    key = jax.random.key(5)
    kw = dict(n_frames=30, start=30, bone_scale=(0.9, 1.1))
    given = make_problem(key, texture, clip, known_bones=True, **kw)
    unknown = make_problem(key, texture, clip, **kw)
    assert unknown.bone_scale is None
    bs, length, bones = _true_bones(texture, given, key)
    np.testing.assert_allclose(np.asarray(given.bone_scale), bs, rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(given.observations), np.asarray(unknown.observations))
    r_g = track(jax.random.key(0), texture, given, MapSmoother())
    r_u = track(jax.random.key(0), texture, unknown, MapSmoother())
    np.testing.assert_allclose(np.asarray(r_g.bone_scale), bs, rtol=1e-12)
    assert r_u.bone_scale is None
    P = np.asarray(r_g.mean_joints)
    sk = texture.feature_map.skeleton
    for j in bones:
        k, kp = given.joints.index(j), given.joints.index(sk.parents[j])
        got = np.linalg.norm(P[:, k] - P[:, kp], axis=-1)
        np.testing.assert_allclose(got, length[j] * bs[j], rtol=1e-9)
    e_g, e_u = r_g.mean_error, r_u.mean_error
    print(f"\nglobal error: skeleton given {1000 * e_g:.1f} mm, model's {1000 * e_u:.1f} mm")
    assert e_g < e_u


def test_a_given_skeleton_is_checked(texture, clip, problem):
    """A given skeleton of the wrong length or with a non-positive bone is refused by name."""
    J = texture.feature_map.skeleton.n_joints
    bad_len = dataclasses.replace(problem, bone_scale=jnp.ones(J - 1))
    with pytest.raises(ValueError, match="bone_scale has shape"):
        track(jax.random.key(0), texture, bad_len, MapSmoother())
    with pytest.raises(ValueError, match="bone_scale must be positive"):
        dataclasses.replace(problem, bone_scale=jnp.zeros(J))
    with pytest.raises(TypeError, match="known_bones must be a bool"):
        make_problem(jax.random.key(0), texture, clip, n_frames=5, known_bones=1)
