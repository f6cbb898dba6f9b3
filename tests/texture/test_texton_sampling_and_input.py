"""Sampling a texton (MT Fig. 4), degenerate and invalid input, and the float32 smoke test."""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np
import pytest

from mtex_jax.texture import (
    Texton,
    dynamics_stats,
    exact_log_likelihood,
    fit_texton,
    frame_stats,
    frame_terms,
    init_terms,
    sample_texton,
    segment_log_likelihood,
    segment_scores,
    stack_textons,
    subspace_from_stats,
)
from mtex_jax.texture._texton.texton import TEXTON_FIELDS
from texton_cases import (
    anisotropic_data,
    assert_valid_texton,
    make_oscillator_system,
    recovery_errors,
)

# --------------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------------


def test_sample_texton_round_trip():
    rng = np.random.default_rng(18)
    D, k = 12, 3
    system = make_oscillator_system(rng, k, D, sigma2=1e-4)
    true = Texton(
        mu=jnp.asarray(system["mu"]),
        C=jnp.asarray(system["C"]),
        A1=jnp.asarray(system["A1"]),
        A2=jnp.asarray(system["A2"]),
        d=jnp.asarray(system["d"]),
        B=jnp.asarray(system["B"]),
        sigma2=jnp.asarray(system["sigma2"]),
        m0=jnp.zeros(2 * k),
        S0=jnp.eye(2 * k),
    )
    x1, x2 = jnp.ones(k), -jnp.ones(k)
    states, obs = sample_texton(jax.random.key(0), true, 20000, x1, x2)
    assert states.shape == (20000, k) and obs.shape == (20000, D)
    np.testing.assert_array_equal(states[0], x1)
    np.testing.assert_array_equal(states[1], x2)
    # the state recursion holds exactly with the sampled noise being N(0, I) after whitening
    X = np.asarray(states)
    v = np.linalg.solve(
        system["B"], (X[2:] - X[1:-1] @ system["A1"].T - X[:-2] @ system["A2"].T - system["d"]).T
    )
    assert abs(v.mean()) < 0.02 and abs(v.std() - 1) < 0.02
    # refitting on the samples recovers the system
    err = recovery_errors(fit_texton(obs, state_dim=k), system)
    assert err["A"] < 0.05 and err["Q"] < 0.1 and err["subspace"] < 0.01, err
    # noise-free observations lie exactly on μ + C x
    _, clean = sample_texton(jax.random.key(1), true, 30, x1, x2, observation_noise=False)
    s_clean, _ = sample_texton(jax.random.key(1), true, 30, x1, x2, observation_noise=False)
    np.testing.assert_allclose(clean, system["mu"] + np.asarray(s_clean) @ system["C"].T)
    # initial states drawn from (m0, S0) when not given
    s_rand, _ = sample_texton(jax.random.key(2), true, 5)
    assert s_rand.shape == (5, k) and np.all(np.isfinite(np.asarray(s_rand)))
    with pytest.raises(ValueError, match="length"):
        sample_texton(jax.random.key(0), true, 1, x1, x2)
    with pytest.raises(ValueError, match="x1"):
        sample_texton(jax.random.key(0), true, 5, jnp.ones(k + 1), x2)
    with pytest.raises(ValueError, match="both"):
        sample_texton(jax.random.key(0), true, 5, x1)


# --------------------------------------------------------------------------------------------
# Degenerate and invalid input
# --------------------------------------------------------------------------------------------


def test_constant_segment_gives_finite_pd_texton():
    # (most tests here use Y of shape (40, 6) and k = 2 so that the fit compiles once)
    Y = np.tile(np.linspace(-1, 1, 6), (40, 1))
    tex = fit_texton(Y, state_dim=2)
    assert_valid_texton(tex)
    np.testing.assert_allclose(tex.mu, Y[0], atol=1e-12)
    np.testing.assert_allclose(float(tex.sigma2), 1e-6)  # the floor
    np.testing.assert_allclose(tex.Q, 1e-6 * np.eye(2), atol=1e-12)
    dyn, obs = frame_terms(tex, Y)
    assert np.all(np.isfinite(np.asarray(dyn))) and np.all(np.isfinite(np.asarray(obs)))
    assert np.isfinite(float(exact_log_likelihood(tex, Y[:5])))


def test_segment_of_exactly_tmin_frames():
    rng = np.random.default_rng(19)
    Y = rng.standard_normal((3, 6))
    tex = fit_texton(Y, state_dim=2)
    assert_valid_texton(tex)
    # one valid triple, and segments of 1 and 2 frames contribute no dynamics at all
    ids = np.array([0, 0, 0, 1, 2, 2])
    Y2 = rng.standard_normal((6, 6))
    tex2 = fit_texton(Y2, ids, state_dim=2)
    assert_valid_texton(tex2)
    sub = subspace_from_stats(frame_stats(Y2, ids), state_dim=2)
    ds = dynamics_stats(Y2, ids, sub)
    assert (float(ds.n3), float(ds.n2), float(ds.n_start)) == (1.0, 3.0, 2.0)


def test_duplicated_frames_and_rank_deficient_data():
    rng = np.random.default_rng(20)
    Y = np.repeat(rng.standard_normal((20, 6)), 2, axis=0)  # every frame twice
    tex = fit_texton(Y, state_dim=2)
    assert_valid_texton(tex)
    # data of rank 1 with k = 2
    Y1 = np.outer(np.sin(np.arange(40) * 0.3), rng.standard_normal(6))
    tex1 = fit_texton(Y1, state_dim=2)
    assert_valid_texton(tex1)


def test_no_usable_frames_and_too_short_input():
    rng = np.random.default_rng(21)
    Y = rng.standard_normal((40, 6))
    assert_valid_texton(fit_texton(Y, -np.ones(40, int), state_dim=2))  # nothing selected
    assert_valid_texton(fit_texton(Y[:2], state_dim=2))  # no triple at all
    assert_valid_texton(fit_texton(Y[:1], state_dim=2))  # a single frame
    tex = fit_texton(Y, state_dim=6)  # k = D: no residual dimensions
    assert_valid_texton(tex)
    _, obs = frame_terms(tex, Y)
    np.testing.assert_array_equal(obs, 0.0)


def test_invalid_input_raises_clear_value_errors():
    rng = np.random.default_rng(22)
    Y = rng.standard_normal((40, 6))
    with pytest.raises(ValueError, match=r"state_dim=7 .*D=6"):
        fit_texton(Y, state_dim=7)  # D < k
    with pytest.raises(ValueError, match="state_dim"):
        fit_texton(Y, state_dim=0)
    with pytest.raises(ValueError, match="state_dim"):
        fit_texton(Y, state_dim=2.0)  # type: ignore[arg-type]
    for bad_value in (np.nan, np.inf, -np.inf):
        Yb = Y.copy()
        Yb[7, 2] = bad_value
        with pytest.raises(ValueError, match=r"Y .*NaN or inf.*\(7, 2\)"):
            fit_texton(Yb, state_dim=2)
    with pytest.raises(ValueError, match="Y must have shape"):
        fit_texton(Y[0], state_dim=2)
    with pytest.raises(ValueError, match="Y must have shape"):
        fit_texton(Y[None, None], state_dim=2)
    with pytest.raises(ValueError, match=r"mask must have shape \(40,\)"):
        fit_texton(Y, np.zeros(39, int), state_dim=2)
    with pytest.raises(ValueError, match="mask must be an integer"):
        fit_texton(Y, np.zeros(40), state_dim=2)
    for name, kw in [
        ("ridge", dict(ridge=-1.0)),
        ("q_floor", dict(q_floor=0.0)),
        ("sigma2_floor", dict(sigma2_floor=np.nan)),
        ("init_prior_weight", dict(init_prior_weight=-2)),
    ]:
        with pytest.raises(ValueError, match=name):
            fit_texton(Y, state_dim=2, **kw)
    tex = fit_texton(Y, state_dim=2)
    st = stack_textons([tex, tex])
    with pytest.raises(ValueError, match="D=6"):
        frame_terms(st, rng.standard_normal((40, 5)))
    Yb = Y.copy()
    Yb[3, 0] = np.nan
    for fn in (frame_terms, init_terms, segment_scores):
        with pytest.raises(ValueError, match="NaN or inf"):
            fn(st, Yb)
    with pytest.raises(ValueError, match="NaN or inf"):
        exact_log_likelihood(tex, Yb)
    with pytest.raises(ValueError, match="NaN or inf"):
        segment_log_likelihood(tex, Yb)
    with pytest.raises(ValueError, match="at least 2 frames"):
        segment_log_likelihood(tex, Y[:1])
    with pytest.raises(ValueError, match="single texton"):
        exact_log_likelihood(st, Y)
    with pytest.raises(ValueError, match="must be a Texton"):
        frame_terms(np.zeros(3), Y)  # type: ignore[arg-type]


def test_nan_inside_jit_is_caught_by_error_if():
    rng = np.random.default_rng(23)
    Y = rng.standard_normal((40, 6))
    Yb = Y.copy()
    Yb[5, 1] = np.nan
    f = jax.jit(lambda Y: fit_texton(Y, state_dim=2).A1)
    f(jnp.asarray(Y))
    with pytest.raises(Exception, match="NaN or inf"):
        jax.block_until_ready(f(jnp.asarray(Yb)))


# --------------------------------------------------------------------------------------------
# float32
# --------------------------------------------------------------------------------------------


def test_float32_smoke():
    rng = np.random.default_rng(24)
    Y = anisotropic_data(rng, 300, 10).astype(np.float32)
    tex = fit_texton(Y, np.repeat(np.arange(3), 100), state_dim=4)
    for name in TEXTON_FIELDS:
        a = getattr(tex, name)
        assert a.dtype == jnp.float32, name
        assert np.all(np.isfinite(np.asarray(a))), name
    assert np.min(np.linalg.eigvalsh(np.asarray(tex.Q, np.float64))) > 0
    st = stack_textons([tex, jax.tree.map(lambda a: a * np.float32(1.01), tex)])
    dyn, obs = frame_terms(st, Y)
    assert dyn.dtype == obs.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(dyn))) and np.all(np.isfinite(np.asarray(obs)))
    sc = segment_scores(st, Y)
    s = sc.score(np.array([0, 10]), np.array([99, 50]), np.array([0, 1]))
    assert s.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(s)))
    ll = exact_log_likelihood(tex, Y[:50])
    assert ll.dtype == jnp.float32 and np.isfinite(float(ll))
    # float32 agrees with float64 to float32 accuracy
    tex64 = fit_texton(Y.astype(np.float64), np.repeat(np.arange(3), 100), state_dim=4)
    dyn64, _ = frame_terms(tex64, Y.astype(np.float64))
    d32, _ = frame_terms(tex, Y)
    np.testing.assert_allclose(np.asarray(d32), np.asarray(dyn64), rtol=2e-2, atol=2e-2)
