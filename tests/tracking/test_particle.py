"""Particle-filter tracking with the implicit prior vs constant velocity (IP §3, §6)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mtex_jax as mj
from mtex_jax.cli import main
from mtex_jax.implicit import ImplicitModel
from mtex_jax.tracking import (
    Camera,
    ParticleFilter,
    decode_frame,
    default_joints,
    make_problem,
    systematic,
    track,
)
from mtex_jax.motion import forward_kinematics_arrays

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
    assert problem.init_window.shape == (WINDOW, model.pose_dim)
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
            rel[prior].append(float(jnp.mean(r.error_root_relative)))
    e_imp, e_cv = np.mean(err["implicit"]), np.mean(err["constant_velocity"])
    print(
        f"\nmean 3-D joint error (mm): implicit {1000 * e_imp:.0f}, const. vel. {1000 * e_cv:.0f}"
    )
    assert e_imp < 0.75 * e_cv
    assert np.mean(rel["implicit"]) < np.mean(rel["constant_velocity"])
    default = salsa30_model  # mj.implicit.learn(chunks, WINDOW): learned once (conftest.py)
    assert default.window == WINDOW and default.recent_weight > 0
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
