"""Student-t dynamics innovations of full-dimensional textons (``Texton.dof``,
``LearnConfig.dof``): the IRLS fit against an independent numpy re-derivation, the per-frame
terms against scipy's multivariate t, sampling against the t's moments, and the learner."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats as st
from jax.test_util import check_grads

import mtex_jax as mj
from mtex_jax.texture import (
    FullObservation,
    LearnConfig,
    exact_log_likelihood,
    fit_texton,
    frame_terms,
    load_texture,
    sample_texton,
    segment_log_likelihood,
    stack_textons,
)
from mtex_jax.texture._scoring.frame_terms_ref import frame_terms_per_texton


def _heavy(rng, T, D, nu=4.0):
    """An AR(2) on ``y`` driven by Student-t noise (heavy tails: rare large innovations)."""
    A1, A2 = 0.6 * np.eye(D), -0.2 * np.eye(D)
    L = np.tril(rng.normal(size=(D, D))) * 0.2 + 0.3 * np.eye(D)
    Y = np.zeros((T, D))
    for t in range(2, T):
        e = L @ rng.normal(size=D) / np.sqrt(rng.chisquare(nu) / nu)
        Y[t] = A1 @ Y[t - 1] + A2 @ Y[t - 2] + 0.1 + e
    return Y


def _irls_numpy(Y, nu, steps):
    """Least squares, then ``steps`` reweightings of the t's parameter-expanded EM, in
    observation coordinates (``y_t = W [y_{t−1}; y_{t−2}; 1] + e_t``, ``e_t ~ t_ν(0, S)``)."""
    T, D = Y.shape
    X = np.concatenate([Y[1:-1], Y[:-2], np.ones((T - 2, 1))], axis=1)
    Yt = Y[2:]
    w = np.ones(T - 2)
    for _ in range(steps + 1):
        Xw = X * w[:, None]
        W = np.linalg.solve(Xw.T @ X, Xw.T @ Yt)
        E = Yt - X @ W
        S = (E * w[:, None]).T @ E / w.sum()
        q = np.einsum("ti,ij,tj->t", E, np.linalg.inv(S), E)
        w = (nu + D) / (nu + q)
    return W, S


@pytest.mark.parametrize("nu", [3.0, 10.0])
def test_fit_texton_student_equals_numpy_irls(nu):
    rng = np.random.default_rng(0)
    D = 3
    Y = _heavy(rng, 500, D)
    tex = fit_texton(
        jnp.asarray(Y), state_dim=D, observation=FullObservation(), dof=nu, ridge=0.0, q_floor=1e-12
    )
    W, S = _irls_numpy(Y, nu, 10)
    C = np.asarray(tex.C)  # the texton's state is x = Cᵀ(y − μ): rotate back to y
    np.testing.assert_allclose(C @ np.asarray(tex.A1) @ C.T, W[:D].T, atol=1e-9)
    np.testing.assert_allclose(C @ np.asarray(tex.A2) @ C.T, W[D : 2 * D].T, atol=1e-9)
    np.testing.assert_allclose(C @ np.asarray(tex.Q) @ C.T, S, atol=1e-9)
    assert tex.dof == nu
    # the Gaussian fit's Q is inflated by the rare large innovations; the t's scale is not
    gauss = fit_texton(jnp.asarray(Y), state_dim=D, observation=FullObservation())
    assert np.trace(np.asarray(tex.Q)) < 0.8 * np.trace(np.asarray(gauss.Q))


def test_irls_steps_reach_the_t_maximum_likelihood():
    # at the t's maximum-likelihood fit the mean weight is 1 (the PX-EM fixed point) and one
    # more reweighting changes nothing
    rng = np.random.default_rng(1)
    Y = _heavy(rng, 800, 3)
    _, S10 = _irls_numpy(Y, 4.0, 10)
    _, S40 = _irls_numpy(Y, 4.0, 40)
    tex = fit_texton(jnp.asarray(Y), state_dim=3, observation=FullObservation(), dof=4.0)
    C = np.asarray(tex.C)
    np.testing.assert_allclose(C @ np.asarray(tex.Q) @ C.T, S40, rtol=2e-3, atol=1e-6)
    assert np.abs(S10 - S40).max() < 2e-3 * np.abs(S40).max()


def test_student_terms_equal_scipy_multivariate_t():
    rng = np.random.default_rng(2)
    T, D, nu = 50, 3, 4.0
    Y = _heavy(rng, T, D)
    tex = fit_texton(jnp.asarray(Y[:40]), state_dim=D, observation=FullObservation(), dof=nu)
    X = (Y - np.asarray(tex.mu)) @ np.asarray(tex.C)
    A1, A2, d, Q = (np.asarray(a) for a in (tex.A1, tex.A2, tex.d, tex.Q))
    dyn_ref = np.array(
        [
            st.multivariate_t(A1 @ X[t - 1] + A2 @ X[t - 2] + d, Q, df=nu).logpdf(X[t])
            for t in range(2, T)
        ]
    )
    init_ref = st.multivariate_normal(np.asarray(tex.m0), np.asarray(tex.S0)).logpdf(
        np.r_[X[0], X[1]]
    )
    got = float(segment_log_likelihood(tex, jnp.asarray(Y)))
    np.testing.assert_allclose(got, init_ref + dyn_ref.sum(), rtol=1e-10)
    stack = stack_textons(
        [tex, fit_texton(jnp.asarray(Y[10:]), state_dim=D, observation=FullObservation(), dof=nu)]
    )
    dyn, obs = frame_terms(stack, jnp.asarray(Y))  # the blocked full-dimensional kernel
    np.testing.assert_allclose(np.asarray(dyn)[0, 2:], dyn_ref, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(obs), 0.0)
    ref = frame_terms_per_texton(stack, jnp.asarray(Y))  # the per-texton reference
    np.testing.assert_allclose(np.asarray(dyn), np.asarray(ref[0]), rtol=1e-10, atol=1e-10)
    with pytest.raises(ValueError, match="Student-t"):
        exact_log_likelihood(tex, jnp.asarray(Y))


def test_student_segment_log_likelihood_gradients():
    rng = np.random.default_rng(3)
    Y = jnp.asarray(_heavy(rng, 30, 2))
    tex = fit_texton(Y, state_dim=2, observation=FullObservation(), dof=5.0)
    check_grads(lambda y: segment_log_likelihood(tex, y), (Y,), order=1, modes=("rev",))


def _whitened_innovations(tex, x):
    x = np.asarray(x)
    E = x[2:] - x[1:-1] @ np.asarray(tex.A1).T - x[:-2] @ np.asarray(tex.A2).T - np.asarray(tex.d)
    return np.linalg.solve(np.asarray(tex.B), E.T).T


def test_sample_texton_draws_t_innovations():
    # B v / √g with g ~ Gamma(ν/2, rate ν/2): the whitened innovations u have ‖u‖²/k ~
    # F(k, ν) and each component ~ t_ν; a Gaussian texton's have ‖u‖² ~ χ²_k
    rng = np.random.default_rng(4)
    D, nu = 2, 4.0
    tex = fit_texton(
        jnp.asarray(_heavy(rng, 400, D)), state_dim=D, observation=FullObservation(), dof=nu
    )
    x, _ = sample_texton(jax.random.key(0), tex, 20_000, observation_noise=False)
    U = _whitened_innovations(tex, x)
    q = np.sum(U * U, axis=1)
    assert st.kstest(q / D, st.f(D, nu).cdf).pvalue > 1e-3
    assert st.kstest(U[:, 0], st.t(nu).cdf).pvalue > 1e-3
    assert st.kstest(q, st.chi2(D).cdf).pvalue < 1e-6  # the test tells the two apart
    g = dataclasses.replace(tex, dof=None)
    xg, _ = sample_texton(jax.random.key(0), g, 20_000, observation_noise=False)
    qg = np.sum(_whitened_innovations(g, xg) ** 2, axis=1)
    assert st.kstest(qg, st.chi2(D).cdf).pvalue > 1e-3
    assert st.kstest(qg / D, st.f(D, nu).cdf).pvalue < 1e-6


def test_student_config_checks():
    for bad in (0, -1.0, float("nan"), float("inf"), True, "4"):
        with pytest.raises(ValueError, match="dof"):
            LearnConfig(observation="full", dof=bad)
    assert LearnConfig().dof == 4.0 and LearnConfig.paper().dof is None
    rng = np.random.default_rng(5)
    with pytest.raises(ValueError, match=r"model that takes them \(full, tied\), got 'paper'"):
        fit_texton(jnp.asarray(_heavy(rng, 100, 3)), state_dim=2, dof=4.0)
    tex = fit_texton(jnp.asarray(_heavy(rng, 100, 3)), state_dim=3, observation=FullObservation())
    with pytest.raises(ValueError, match="dof"):
        stack_textons([tex, dataclasses.replace(tex, dof=4.0)])


def _clips(seed):
    rng = np.random.default_rng(seed)
    return [_heavy(rng, 300, 4, nu=2.5) for _ in range(3)]


def test_learn_student_textons_round_trip(tmp_path):
    ys = _clips(6)
    cfg = LearnConfig(tmin=20, tmax=60, observation="full", dof=4.0, max_iter=4)
    tex = mj.learn(ys, cfg)
    assert tex.textons.dof == 4.0 and tex.config.dof == 4.0
    ll_t = tex.log_likelihood(ys[0])
    gauss = mj.learn(ys, dataclasses.replace(cfg, dof=None))
    assert gauss.textons.dof is None
    # on heavy-tailed data (ν = 2.5) the t model explains every clip better than the
    # Gaussian one (both learn one texton here)
    for y in ys:
        assert tex.log_likelihood(y) > gauss.log_likelihood(y) + 100
    path = tmp_path / "t.npz"
    tex.save(path)
    back = load_texture(path)
    assert back.textons.dof == 4.0 and back.config.dof == 4.0
    assert back.log_likelihood(ys[0]) == pytest.approx(ll_t, rel=1e-12)
    syn = mj.synthesize(jax.random.key(1), back, n_frames=200)
    assert np.isfinite(np.asarray(syn.Y)).all()


def test_dof_applies_to_full_dimensional_textons_only():
    ys = _clips(9)
    cfg = LearnConfig(tmin=20, tmax=60, max_iter=2)  # dof = 4 by default
    full = mj.learn(ys, dataclasses.replace(cfg, observation="full"))
    assert full.textons.dof == 4.0 and full.config.dof == 4.0
    for obs in ("paper", "residual"):
        low = mj.learn(ys, dataclasses.replace(cfg, observation=obs, state_dim=2))
        assert low.textons.dof is None and low.config.dof is None


def test_student_float32_smoke():
    ys = [y.astype(np.float32) for y in _clips(8)]
    tex = fit_texton(jnp.asarray(ys[0]), state_dim=4, observation=FullObservation(), dof=4.0)
    assert tex.A1.dtype == jnp.float32
    ll = segment_log_likelihood(tex, jnp.asarray(ys[1]))
    assert ll.dtype == jnp.float32 and np.isfinite(float(ll))
    model = mj.learn(ys, LearnConfig(tmin=20, tmax=60, observation="full", dof=4.0, max_iter=2))
    assert model.textons.A1.dtype == jnp.float32
    assert np.isfinite(model.log_likelihood(ys[0]))


def test_warm_started_m_step_is_one_weighted_least_squares():
    """EM's later M-steps start from the E-step's textons: one reweighting, i.e. weights
    ``(ν + D)/(ν + q_t)`` under ``prev`` and the weighted closed form, here against a numpy
    weighted least squares on each texton's segments (in observation coordinates)."""
    from mtex_jax.texture._learning.mstep import fit_all
    from mtex_jax.texture._scoring.rows import row_chunks
    from mtex_jax.texture._texton.options import SolveOptions

    rng = np.random.default_rng(10)
    D, nu, S, T = 3, 4.0, 2, 300
    Y = np.stack([_heavy(rng, T, D, nu=3.0) for _ in range(S)])
    rows = np.array([(s, b, 50, (s + b // 50) % 2) for s in range(S) for b in range(0, T, 50)])
    labels, groups = row_chunks(rows[:, 3], 8)
    chunks = (jnp.asarray(labels), jnp.asarray(groups))
    opts = SolveOptions.make(0.0, 1e-12, None, 4.0, FullObservation(), 1e-6, dof=nu)
    prev = stack_textons(
        [
            fit_texton(
                jnp.asarray(_heavy(rng, 400, D)), state_dim=D, observation=FullObservation(), dof=nu
            )
        ]
        * 2
    )
    got = fit_all(jnp.asarray(Y), jnp.asarray(rows), chunks, 2, 50, D, 1e-6, opts, prev)
    for i in range(2):
        p = prev[i]
        C, mu = np.asarray(p.C), np.asarray(p.mu)
        A1, A2, d, B = (np.asarray(a) for a in (p.A1, p.A2, p.d, p.B))
        X, Yt, w = [], [], []
        for s, b, n, lab in rows:
            if lab != i:
                continue
            seg = Y[s, b : b + n]
            Z = (seg - mu) @ C
            E = Z[2:] - Z[1:-1] @ A1.T - Z[:-2] @ A2.T - d
            q = np.sum(np.linalg.solve(B, E.T) ** 2, axis=0)
            w.append((nu + D) / (nu + q))
            X.append(np.concatenate([seg[1:-1], seg[:-2], np.ones((n - 2, 1))], axis=1))
            Yt.append(seg[2:])
        X, Yt, w = np.concatenate(X), np.concatenate(Yt), np.concatenate(w)
        W = np.linalg.solve((X * w[:, None]).T @ X, (X * w[:, None]).T @ Yt)
        E = Yt - X @ W
        Sig = (E * w[:, None]).T @ E / w.sum()
        one = got[i]
        Cg = np.asarray(one.C)
        np.testing.assert_allclose(Cg @ np.asarray(one.A1) @ Cg.T, W[:D].T, atol=1e-9)
        np.testing.assert_allclose(Cg @ np.asarray(one.A2) @ Cg.T, W[D : 2 * D].T, atol=1e-9)
        np.testing.assert_allclose(Cg @ np.asarray(one.Q) @ Cg.T, Sig, atol=1e-9)


def test_cold_and_warm_m_steps_share_one_program():
    """With ``cold`` given, ``fit_all`` is one program for EM's first M-step (the Gaussian fit
    and ``irls_steps`` reweightings; ``prev`` only a placeholder) and its later ones (one
    reweighting from ``prev``): each branch equals the separate path, and switching between
    them does not trace again."""
    from mtex_jax.texture._learning.mstep import _fit_all_impl
    from mtex_jax.texture._scoring.rows import row_chunks
    from mtex_jax.texture._texton.options import SolveOptions

    rng = np.random.default_rng(11)
    D, nu, S, T = 3, 4.0, 2, 300
    Y = jnp.asarray(np.stack([_heavy(rng, T, D, nu=3.0) for _ in range(S)]))
    rows = np.array([(s, b, 50, (s + b // 50) % 2) for s in range(S) for b in range(0, T, 50)])
    labels, groups = row_chunks(rows[:, 3], 8)
    chunks = (jnp.asarray(labels), jnp.asarray(groups))
    opts = SolveOptions.make(0.0, 1e-12, None, 4.0, FullObservation(), 1e-6, dof=nu)
    args = (Y, jnp.asarray(rows), chunks, 2, 50, D, 1e-6, opts)
    fit = eqx.filter_jit(_fit_all_impl)
    cold_sep = fit(*args)
    warm_sep = fit(*args, cold_sep)
    shared = eqx.filter_jit(eqx.debug.assert_max_traces(_fit_all_impl, max_traces=1))
    placeholder = jax.tree.map(jnp.zeros_like, cold_sep)
    cold = shared(*args, placeholder, jnp.asarray(True))
    warm = shared(*args, cold, jnp.asarray(False))
    for a, b in ((cold, cold_sep), (warm, warm_sep)):
        for f in ("mu", "C", "A1", "A2", "d", "B"):
            np.testing.assert_allclose(getattr(a, f), getattr(b, f), rtol=1e-12, atol=1e-12)
    # the warm step moved the fit (it is not the cold fit returned again)
    assert float(jnp.max(jnp.abs(warm.B - cold.B))) > 1e-8
