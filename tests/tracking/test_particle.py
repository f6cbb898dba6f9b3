"""Particle-filter tracking with the implicit prior vs constant velocity (IP §3, §6), and the
Gauss–Newton proposal against the bootstrap filter (design §12.4)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mtex_jax as mj
from mtex_jax.cli import main
from mtex_jax.implicit import ImplicitModel
from mtex_jax.motion import forward_kinematics_arrays
from mtex_jax.tracking import (
    Camera,
    ParticleFilter,
    decode_frame,
    default_joints,
    make_problem,
    systematic,
    track,
)
from mtex_jax.tracking._particle import gauss_newton_root, robust_loglik

WINDOW = 10
HELD_OUT = 2  # 60_03 is tracked; the database holds the other 13 clips


# salsa30, salsa30_chunks and salsa30_model: tests/conftest.py (shared with
# test_implicit, built once per process)
@pytest.fixture(scope="module")
def chunks(salsa30_chunks, salsa30_held_out):
    """128-frame chunks of every clip but ``HELD_OUT`` (one jit compilation of the features)."""
    assert salsa30_held_out == HELD_OUT
    return salsa30_chunks


@pytest.fixture(scope="module")
def model(chunks) -> ImplicitModel:
    """The paper's window distance (``recent_weight=0``), which learn's docstring recommends
    for tracking."""
    return mj.implicit.learn(chunks, WINDOW, recent_weight=0.0)


@pytest.fixture(scope="module")
def problem(model, salsa30):
    return make_problem(jax.random.PRNGKey(100), model, salsa30[HELD_OUT], n_frames=60, start=30)


def test_camera_projection():
    cam = Camera.look_at([0.0, 1.0, 4.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], focal=800.0)
    np.testing.assert_allclose(np.asarray(cam.project(jnp.array([0.0, 1.0, 0.0]))), [500, 500])
    up = np.asarray(cam.project(jnp.array([0.0, 1.5, 0.0])))
    assert up[1] < 500 and abs(up[0] - 500) < 1e-9  # up in the world is up in the image
    np.testing.assert_allclose(up[1], 500 - 800 * 0.5 / 4.0)
    # a point twice as far projects half as far from the centre (perspective)
    far = np.asarray(cam.project(jnp.array([0.0, 1.5, -4.0])))
    np.testing.assert_allclose(500 - far[1], (500 - up[1]) / 2)
    with pytest.raises(ValueError, match="coincide"):
        Camera.look_at([0, 0, 0], [0, 0, 0], [0, 1, 0])


def test_frame_by_frame_decoding_reproduces_the_truth(model, salsa30, problem):
    """Integrating the true pose vectors from the true initial state gives the true joints:
    decode_frame agrees with FeatureMap.decode (an oracle particle has zero error)."""
    fm = model.feature_map
    clip = salsa30[HELD_OUT][30 : 30 + WINDOW + 1 + problem.n_frames]
    y = model.pose_vectors(clip)[WINDOW:, : fm.dim]
    pos, head = problem.init_position, problem.init_heading
    jidx = np.asarray(problem.joints)
    for t in range(problem.n_frames):
        pos, head, rot, lp = decode_frame(fm, jnp.asarray(y[t]), pos, head)
        x = forward_kinematics_arrays(fm.skeleton, pos, rot, lp)[jidx]
        np.testing.assert_allclose(np.asarray(x), np.asarray(problem.truth[t]), atol=1e-9)


def test_problem_observations(model, problem):
    k = len(problem.joints)
    assert problem.joints == default_joints(model.feature_map)
    assert problem.joints[0] == 0 and k == 17
    assert problem.observations.shape == (60, k, 2)
    assert problem.truth.shape == (60, k, 3)
    assert problem.init_window.shape == (WINDOW, model.database.pose_dim)
    resid = np.asarray(problem.observations - problem.camera.project(problem.truth))
    assert abs(resid.std() - 2.0) < 0.15 and abs(resid.mean()) < 0.2  # 2 px Gaussian noise


def test_systematic_resampling_counts():
    w = jnp.array([0.5, 0.25, 0.125, 0.125, 0.0])
    for seed in range(5):
        idx = np.asarray(systematic(jax.random.PRNGKey(seed), w))
        counts = np.bincount(idx, minlength=5)
        expected = 5 * np.asarray(w)  # N = 5 particles: each index N·w_i times, ± 1
        assert np.all(np.abs(counts - expected) < 1.0 + 1e-9)
        assert counts[4] == 0


def test_implicit_prior_beats_constant_velocity_with_300_particles(model, problem, salsa30_model):
    """The small version of the benchmark: same observations, 300 particles each, two seeds;
    the default database (recent weight 32, chosen for synthesis) beats constant velocity too,
    by less."""
    priors = ("implicit", "constant_velocity")
    err: dict[str, list[float]] = {p: [] for p in priors}
    rel: dict[str, list[float]] = {p: [] for p in priors}
    for seed in (0, 1):
        for prior in priors:
            r = track(jax.random.PRNGKey(seed), model, problem, dynamics=prior, n_particles=300)
            assert r.mean_joints.shape == problem.truth.shape
            assert np.all(np.isfinite(np.asarray(r.error)))
            err[prior].append(r.mean_error)
            rel[prior].append(float(np.mean(np.asarray(r.error_root_relative))))
    e_imp, e_cv = np.mean(err["implicit"]), np.mean(err["constant_velocity"])
    print(
        f"\nmean 3-D joint error (mm): implicit {1000 * e_imp:.0f}, const. vel. {1000 * e_cv:.0f}"
    )
    assert e_imp < 0.75 * e_cv
    assert np.mean(rel["implicit"]) < np.mean(rel["constant_velocity"])
    default = salsa30_model  # mj.implicit.learn(chunks, WINDOW): learned once (conftest.py)
    assert default.database.window == WINDOW and default.database.recent_weight > 0
    e_def = np.mean(
        [track(jax.random.PRNGKey(s), default, problem, n_particles=300).mean_error for s in (0, 1)]
    )
    assert e_def < e_cv


@pytest.mark.slow
def test_constant_velocity_needs_many_more_particles(model, problem):
    """Constant velocity with 3,000 particles is still not better than the implicit prior with
    300 (the paper: it needs about 10× more particles)."""
    imp = track(jax.random.PRNGKey(0), model, problem, dynamics="implicit", n_particles=300)
    cv = track(
        jax.random.PRNGKey(0), model, problem, dynamics="constant_velocity", n_particles=3000
    )
    assert imp.mean_error < cv.mean_error


def test_tracking_bad_input(model, problem, salsa30):
    key = jax.random.PRNGKey(0)
    with pytest.raises(ValueError, match="dynamics"):
        track(key, model, problem, dynamics="kalman")
    with pytest.raises(TypeError, match="beside a method"):
        track(key, model, problem, ParticleFilter(), n_particles=10)
    with pytest.raises(TypeError, match="MotionTexture or an ImplicitModel"):
        track(key, object(), problem)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="n_particles"):
        track(key, model, problem, n_particles=0)
    with pytest.raises(ValueError, match="beta"):
        track(key, model, problem, beta=0.0)
    with pytest.raises(ValueError, match="no frame to track"):
        make_problem(key, model, salsa30[0][: WINDOW + 1])
    with pytest.raises(ValueError, match="n_frames"):
        make_problem(key, model, salsa30[0], n_frames=10_000)
    with pytest.raises(ValueError, match="fps"):
        make_problem(key, model, salsa30[0][::2])


# --------------------------------------------------------------------------- the proposal
def _rotate_about(v, axis, angle):
    """Rodrigues' rotation of vectors ``v`` (numpy)."""
    c, s = np.cos(angle), np.sin(angle)
    return v * c + np.cross(axis, v) * s + np.outer(v @ axis, axis) * (1 - c)


def _tiny_root_problem():
    """Five joints seen by a camera 4 m away, their pixels made by a known root move, with
    one outlier and one missing joint (whose pixel is NaN)."""
    rng = np.random.default_rng(0)
    cam = Camera.look_at([0.0, 1.0, 4.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0])
    root = np.array([0.1, 1.0, 0.2])
    x = root + rng.normal(scale=0.4, size=(5, 3))
    up = np.array([0.0, 1.0, 0.0])
    move = np.array([0.05, -0.02, 0.3, 0.1])  # 30 cm in depth, 0.1 rad of heading
    xt = root + _rotate_about(x - root, up, move[3]) + move[:3]
    obs = np.asarray(cam.project(jnp.asarray(xt))) + rng.normal(scale=2.0, size=(5, 2))
    obs[1] += [60.0, -40.0]  # an outlier
    obs[4] = np.nan  # missing
    conf = np.array([1.0, 1.0, 0.7, 1.0, 0.0])
    return cam, x, root, up, obs, conf


def _dense_objective(cam, x, root, up, obs, conf, prec, sigma, dof):
    """Numpy reference: the residual function, its finite-difference Jacobian, the IRLS
    weights and the objective ``−log p(o | θ) + ½ θᵀ P θ`` of the Student-t likelihood."""
    r_mat, t_vec, f, c = (
        np.asarray(a) for a in (cam.rotation, cam.translation, cam.focal, cam.center)
    )
    on = conf > 0

    def resid(th):
        xm = root + _rotate_about(x - root, up, th[3]) + th[:3]
        xc = xm @ r_mat.T + t_vec
        px = f * xc[:, :2] / xc[:, 2:3] + c
        return np.where(on[:, None], (px - np.where(on[:, None], obs, 0.0)) / sigma, 0.0)

    def jac(th, h=1e-6):
        cols = [(resid(th + h * e) - resid(th - h * e)) / (2 * h) for e in np.eye(4)]
        return np.stack(cols, axis=-1)  # (K, 2, 4)

    def weights(r):
        return conf * (dof + 2) / (dof + np.sum(r * r, axis=-1))

    def objective(th):
        r2 = np.sum(resid(th) ** 2, axis=-1)
        return 0.5 * (dof + 2) * np.sum(conf * np.log1p(r2 / dof)) + 0.5 * th @ (prec * th)

    return resid, jac, weights, objective


def test_gauss_newton_root_step_matches_a_dense_reference():
    """One Gauss–Newton (IRLS) step of the rigid root move against numpy with a
    finite-difference Jacobian; many steps reach a stationary point of the robust objective
    (its finite-difference gradient vanishes) near the true move; the missing joint's NaN
    pixel changes nothing."""
    cam, x, root, up, obs, conf = _tiny_root_problem()
    prec = np.array([1.0, 1.0, 1.0, 4.0])  # weak prior: 1 m, 0.5 rad
    sigma, dof = 10.0, 4.0
    resid, jac, weights, objective = _dense_objective(cam, x, root, up, obs, conf, prec, sigma, dof)
    args = (cam, jnp.asarray(obs), jnp.asarray(conf), jnp.asarray(x), jnp.asarray(root))
    rest = (jnp.asarray(prec), jnp.asarray(sigma), jnp.asarray(up))

    th0 = np.zeros(4)
    r, j, w = resid(th0), jac(th0), weights(resid(th0))
    h_ref = np.einsum("k,kai,kaj->ij", w, j, j) + np.diag(prec)
    step_ref = -np.linalg.solve(h_ref, np.einsum("k,kai,ka->i", w, j, r))
    th1, h1 = gauss_newton_root(*args, *rest, 1, "student_t", dof)
    np.testing.assert_allclose(np.asarray(th1), step_ref, rtol=1e-6, atol=1e-9)
    j1 = jac(step_ref)
    h_at = np.einsum("k,kai,kaj->ij", weights(resid(step_ref)), j1, j1) + np.diag(prec)
    np.testing.assert_allclose(np.asarray(h1), h_at, rtol=1e-6)

    th, _ = gauss_newton_root(*args, *rest, 30, "student_t", dof)
    th = np.asarray(th)
    grad = [(objective(th + 1e-6 * e) - objective(th - 1e-6 * e)) / 2e-6 for e in np.eye(4)]
    np.testing.assert_allclose(grad, 0.0, atol=1e-5)
    np.testing.assert_allclose(th, [0.05, -0.02, 0.3, 0.1], atol=0.05)  # depth recovered
    keep = conf > 0  # the missing joint left out altogether: the same move
    kept = (cam, jnp.asarray(obs[keep]), jnp.asarray(conf[keep]), jnp.asarray(x[keep]))
    th_k, _ = gauss_newton_root(*kept, jnp.asarray(root), *rest, 30, "student_t", dof)
    np.testing.assert_allclose(np.asarray(th_k), th, rtol=1e-9, atol=1e-12)
    # the Student-t's IRLS weights: the outlier down-weighted, the missing joint at 0
    _, w_t = robust_loglik(jnp.asarray(resid(th)), jnp.asarray(conf), "student_t", dof)
    assert float(w_t[1]) < 0.2 * float(w_t[0]) and float(w_t[4]) == 0.0


@pytest.fixture(scope="module")
def hard_problem(model, salsa30):
    """The test's problem with 10 % of the joints missing and 5 % thrown 50–200 px off."""
    clip = salsa30[HELD_OUT]
    key = jax.random.PRNGKey(100)
    return make_problem(key, model, clip, n_frames=60, start=30, missing=0.1, outliers=0.05)


GN = ParticleFilter(n_particles=100, proposal="gauss_newton")


@pytest.fixture(scope="module")
def gn_and_bootstrap(model, hard_problem):
    """Seeds 0 and 1 of the Gauss–Newton proposal with 100 particles and of the bootstrap
    filter with 300."""
    boot = ParticleFilter(n_particles=300)
    return {
        name: [track(jax.random.PRNGKey(s), model, hard_problem, pf) for s in (0, 1)]
        for name, pf in (("gn", GN), ("bootstrap", boot))
    }


def test_gauss_newton_proposal_beats_the_bootstrap_filter_with_a_third_of_the_particles(
    gn_and_bootstrap,
):
    runs = gn_and_bootstrap
    err = {k: np.mean([r.mean_error for r in v]) for k, v in runs.items()}
    worst = {k: np.mean([float(jnp.max(r.error)) for r in v]) for k, v in runs.items()}
    gn, boot = 1000 * err["gn"], 1000 * err["bootstrap"]
    print(f"\nmean 3-D joint error (mm): gauss_newton/100 {gn:.0f}, bootstrap/300 {boot:.0f}")
    assert err["gn"] < 0.85 * err["bootstrap"]
    assert worst["gn"] < worst["bootstrap"]
    assert all(np.all(np.isfinite(np.asarray(r.ess))) for r in runs["gn"])


def test_missing_joints_do_not_change_the_estimate(model, hard_problem, gn_and_bootstrap):
    """Garbage (huge, NaN) in the pixels of joints with confidence 0 leaves both filters'
    output exactly as it was."""
    conf = np.asarray(hard_problem.confidence)
    assert 0 < (conf == 0).mean() < 0.2
    obs = np.asarray(hard_problem.observations).copy()
    miss = np.argwhere(conf == 0)
    obs[miss[::2, 0], miss[::2, 1]] = 1e250
    obs[miss[1::2, 0], miss[1::2, 1]] = np.nan
    garbage = eqx.tree_at(lambda p: p.observations, hard_problem, jnp.asarray(obs))
    for name, pf in (("gn", GN), ("bootstrap", ParticleFilter(n_particles=300))):
        r = track(jax.random.PRNGKey(0), model, garbage, pf)
        ref = gn_and_bootstrap[name][0]
        np.testing.assert_array_equal(np.asarray(r.mean_joints), np.asarray(ref.mean_joints))
        np.testing.assert_array_equal(np.asarray(r.ess), np.asarray(ref.ess))


def test_particle_filter_options():
    """The proposal's defaults, and bad options named in the error."""
    boot, gn = ParticleFilter(), ParticleFilter(proposal="gauss_newton")
    names = ("likelihood", "likelihood_sigma", "root_noise", "heading_noise")
    assert [boot.setting(k) for k in names] == ["gaussian", 20.0, 0.0, 0.0]  # the paper's
    assert gn.setting("likelihood") == "student_t" and gn.setting("root_noise") > 0
    assert (
        ParticleFilter(likelihood_sigma=5.0, proposal="gauss_newton").setting("likelihood_sigma")
        == 5.0
    )
    bad = {
        "proposal": "annealed?",
        "likelihood": "cauchy",
        "dof": 0.0,
        "gn_steps": 0,
        "root_noise": -0.1,
        "heading_noise": float("nan"),
        "likelihood_sigma": 0.0,
    }
    for name, value in bad.items():
        with pytest.raises(ValueError, match=name):
            ParticleFilter(**{name: value})
    with pytest.raises(ValueError, match="gn_steps"):
        ParticleFilter(proposal="gauss_newton", gn_steps=1.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"root_noise.*gauss_newton"):
        ParticleFilter(proposal="gauss_newton", root_noise=0.0)


def test_cli_track(tmp_path, capsys):
    plot = tmp_path / "err.png"
    rc = main(
        [
            "track",
            "example:dance_a",
            "--test",
            "example:dance_b",
            "--particles",
            "50",
            "--frames",
            "12",
            "--window",
            "5",
            "--seed",
            "1",
            "--plot",
            str(plot),
        ]
    )
    assert rc == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln[:8].strip().isdigit()]
    assert len(lines) == 12  # one row per tracked frame: frame, implicit, const. vel.
    assert all(len(ln.split()) == 3 for ln in lines)
    assert plot.exists() and plot.stat().st_size > 1000
    assert main(["track", "example:walk", "--test", "example:run", "--particles", "0"]) == 2
    assert "particles" in capsys.readouterr().err
    assert main(["track", "example:walk", "--test", "example:run", "--frames", "500"]) == 2
    assert "n_frames" in capsys.readouterr().err


def test_the_filter_tracks_with_a_given_skeleton(model, salsa30):
    """With the person's skeleton given (``known_bones=True``) the filter's particles carry
    its bones: in the mean joints, each long bone between two observed joints is longer or
    shorter than in the same run with the model's skeleton by the given change (within 30 %:
    the particles' mean shortens a bone whose particles bend differently, in both runs)."""
    key = jax.random.PRNGKey(7)
    kw = dict(n_frames=20, start=30, bone_scale=(0.9, 1.1))
    given = make_problem(key, model, salsa30[HELD_OUT], known_bones=True, **kw)
    unknown = make_problem(key, model, salsa30[HELD_OUT], **kw)
    pf = ParticleFilter(n_particles=64)
    P_g = np.asarray(mj.track(jax.random.PRNGKey(1), model, given, pf).mean_joints)
    P_u = np.asarray(mj.track(jax.random.PRNGKey(1), model, unknown, pf).mean_joints)
    sk = model.feature_map.skeleton
    bs = np.asarray(given.bone_scale)
    length = np.linalg.norm(np.asarray(sk.offsets), axis=1)
    ix = given.joints.index
    checked = 0
    for j in given.joints:
        p = sk.parents[j]
        if p not in given.joints or length[j] < 0.15 or abs(bs[j] - 1) < 0.03:
            continue
        g, u = (np.median(np.linalg.norm(P[:, ix(j)] - P[:, ix(p)], axis=-1)) for P in (P_g, P_u))
        change, expected = g - u, length[j] * (bs[j] - 1)
        assert abs(change - expected) < 0.3 * abs(expected), (sk.names[j], change, expected)
        checked += 1
    assert checked >= 2
