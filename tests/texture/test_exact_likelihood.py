"""The exact Kalman likelihood of a texton (design §3.4) against the dense joint Gaussian,
its gradients, and the EM refinement (design §6.1)."""

from typing import Any

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from jax.test_util import check_grads

from mtex_jax.texture import (
    RefineReport,
    Texton,
    exact_log_likelihood,
    exact_log_likelihood_segments,
    fit_texton,
    refine_texton,
)
from mtex_jax.texture._texton.texton import TEXTON_FIELDS
from texton_cases import (
    anisotropic_data,
    assert_valid_texton,
    make_oscillator_system,
    random_texton_np,
    recovery_errors,
    runs_of,
    simulate,
    to_texton,
)

# --------------------------------------------------------------------------------------------
# Exact likelihood (Kalman filter) against the dense joint Gaussian
# --------------------------------------------------------------------------------------------


def dense_joint_logpdf(p, Y):
    """log N(vec(Y); mean, cov) of the full LDS built densely (small T)."""
    T, D = Y.shape
    k = p["A1"].shape[0]
    # x_{1:T} = G [x1; x2; v_3..v_T] + g  (affine map built by unrolling the recursion)
    n_in = 2 * k + (T - 2) * k
    G = np.zeros((T * k, n_in))
    g = np.zeros(T * k)
    G[:k, :k] = np.eye(k)
    G[k : 2 * k, k : 2 * k] = np.eye(k)
    for t in range(2, T):
        rows = slice(t * k, (t + 1) * k)
        G[rows] = p["A1"] @ G[(t - 1) * k : t * k] + p["A2"] @ G[(t - 2) * k : (t - 1) * k]
        G[rows, 2 * k + (t - 2) * k : 2 * k + (t - 1) * k] += p["B"]
        g[rows] = p["A1"] @ g[(t - 1) * k : t * k] + p["A2"] @ g[(t - 2) * k : (t - 1) * k] + p["d"]
    in_mean = np.concatenate([p["m0"], np.zeros((T - 2) * k)])
    in_cov = np.eye(n_in)
    in_cov[: 2 * k, : 2 * k] = p["S0"]
    mean_x = G @ in_mean + g
    cov_x = G @ in_cov @ G.T
    Cbig = np.kron(np.eye(T), p["C"])
    mean_y = np.tile(p["mu"], T) + Cbig @ mean_x
    cov_y = Cbig @ cov_x @ Cbig.T + p["sigma2"] * np.eye(T * D)
    return scipy.stats.multivariate_normal.logpdf(Y.reshape(-1), mean_y, cov_y)


@pytest.mark.parametrize(("T", "D", "k"), [(2, 5, 2), (3, 6, 2), (7, 8, 3), (6, 4, 4)])
def test_exact_log_likelihood_equals_dense_gaussian(T, D, k):
    rng = np.random.default_rng(13 + T)
    p = random_texton_np(rng, D, k)
    x, _ = simulate(rng, dict(p, sigma2=0.0), T, burn=0)
    Y = p["mu"] + x[0] @ p["C"].T + np.sqrt(p["sigma2"]) * rng.standard_normal((T, D))
    Y = Y + 0.3 * rng.standard_normal((T, D))  # also off-model data
    got = float(exact_log_likelihood(to_texton(p), Y))
    np.testing.assert_allclose(got, dense_joint_logpdf(p, Y), rtol=1e-10, atol=1e-8)


def test_exact_log_likelihood_of_fitted_texton_equals_dense_gaussian():
    rng = np.random.default_rng(14)
    Y = anisotropic_data(rng, 60, 6)
    tex = fit_texton(Y, state_dim=2)
    p: dict[str, Any] = {n: np.asarray(getattr(tex, n)) for n in TEXTON_FIELDS}
    np.testing.assert_allclose(
        float(exact_log_likelihood(tex, Y[:8])), dense_joint_logpdf(p, Y[:8]), atol=1e-8
    )


def test_exact_log_likelihood_gradients():
    rng = np.random.default_rng(15)
    D, k, T = 6, 2, 7
    p = random_texton_np(rng, D, k)
    Y = rng.standard_normal((T, D))
    L0 = np.linalg.cholesky(p["S0"])

    def f(A1, A2, d, B, log_s2, m0, L0, mu, Y):
        tex = Texton(
            mu=mu,
            C=jnp.asarray(p["C"]),
            A1=A1,
            A2=A2,
            d=d,
            B=B,
            sigma2=jnp.exp(log_s2),
            m0=m0,
            S0=L0 @ L0.T,
        )
        return exact_log_likelihood(tex, Y)

    args = tuple(
        jnp.asarray(a)
        for a in (p["A1"], p["A2"], p["d"], p["B"], np.log(p["sigma2"]), p["m0"], L0, p["mu"], Y)
    )
    check_grads(f, args, order=1, modes=("fwd", "rev"))
    g = jax.grad(f, argnums=tuple(range(9)))(*args)
    assert all(np.all(np.isfinite(np.asarray(a))) for a in g)


def test_fit_texton_gradients_wrt_data():
    rng = np.random.default_rng(16)
    Y = jnp.asarray(anisotropic_data(rng, 40, 6, decay=0.6))

    def f(Y):
        tex = fit_texton(Y, state_dim=2)
        return jnp.concatenate(
            [
                tex.mu,
                tex.C.ravel(),
                tex.A1.ravel(),
                tex.A2.ravel(),
                tex.d,
                tex.B.ravel(),
                tex.sigma2[None],
                tex.m0,
                tex.S0.ravel(),
            ]
        )

    check_grads(f, (Y,), order=1, modes=("fwd", "rev"))


def test_fit_gradients_finite_for_degenerate_discarded_spectrum():
    """Data exactly in a 2-D subspace of R^6: discarded eigenvalues all 0 (degenerate)."""
    rng = np.random.default_rng(17)
    basis = np.linalg.qr(rng.standard_normal((6, 2)))[0]
    Y = jnp.asarray(np.cumsum(rng.standard_normal((50, 2)), 0) * [2.0, 1.0] @ basis.T)
    g = jax.grad(lambda Y: jnp.sum(fit_texton(Y, state_dim=2).A1))(Y)
    assert np.all(np.isfinite(np.asarray(g)))


def test_exact_log_likelihood_segments_equals_sum_over_segments():
    rng = np.random.default_rng(25)
    D, k = 6, 2
    p = random_texton_np(rng, D, k)
    tex = to_texton(p)
    ids = np.array([0] * 7 + [1] * 5 + [-1] * 2 + [2] * 1 + [3] * 2 + [0] * 6 + [-1])
    Y = rng.standard_normal((len(ids), D)) + p["mu"]
    ref = 0.0
    for run in runs_of(ids):
        if len(run) >= 2:
            ref += float(exact_log_likelihood(tex, Y[run]))
        else:  # one frame: y ~ N(μ + C m0[:k], C S0[:k,:k] Cᵀ + σ² I)
            cov = p["C"] @ p["S0"][:k, :k] @ p["C"].T + p["sigma2"] * np.eye(D)
            mean = p["mu"] + p["C"] @ p["m0"][:k]
            ref += scipy.stats.multivariate_normal.logpdf(Y[run[0]], mean, cov)
    got = float(exact_log_likelihood_segments(tex, Y, ids))
    np.testing.assert_allclose(got, ref, rtol=1e-10)
    # one segment = exact_log_likelihood; batched sequences never connect
    np.testing.assert_allclose(
        float(exact_log_likelihood_segments(tex, Y[:7])),
        float(exact_log_likelihood(tex, Y[:7])),
        rtol=1e-11,
    )
    Yb = np.stack([Y[:12], Y[12:24]])
    mb = np.stack([ids[:12], ids[12:24]])
    cat = np.concatenate([ids[:12], np.where(ids[12:24] >= 0, ids[12:24] + 100, -1)])
    np.testing.assert_allclose(
        float(exact_log_likelihood_segments(tex, Yb, mb)),
        float(exact_log_likelihood_segments(tex, Y[:24], cat)),
        rtol=1e-11,
    )


@pytest.mark.slow
def test_refine_removes_errors_in_variables_bias():
    """With observation noise the closed form regresses noisy states (biased); maximising the
    exact likelihood must raise it and move A1, A2, Q towards the generating system."""
    rng = np.random.default_rng(1)
    k, D = 2, 6
    system = make_oscillator_system(rng, k, D, sigma2=0.01)
    _, Y = simulate(rng, system, 800)
    closed = fit_texton(Y[0], state_dim=k)
    refined, report = refine_texton(closed, Y[0])
    assert isinstance(report, RefineReport)
    assert bool(report.accepted) and bool(report.converged)
    before = float(exact_log_likelihood(closed, Y[0]))
    after = float(exact_log_likelihood(refined, Y[0]))
    np.testing.assert_allclose(float(report.log_likelihood_before), before, rtol=1e-10)
    np.testing.assert_allclose(float(report.log_likelihood_after), after, rtol=1e-10)
    assert after > before + 0.05 * 800  # > 0.05 nats per frame
    err_c, err_r = recovery_errors(closed, system), recovery_errors(refined, system)
    assert err_r["A"] < 0.5 * err_c["A"], (err_c, err_r)
    assert err_r["Q"] < 0.5 * err_c["Q"], (err_c, err_r)
    assert err_r["eig"] < err_c["eig"], (err_c, err_r)
    # μ, C, m0, S0 are kept; the result is a valid texton
    for name in ("mu", "C", "m0", "S0"):
        np.testing.assert_array_equal(getattr(refined, name), getattr(closed, name))
    assert_valid_texton(refined)
    # refining again (already at the optimum) does not decrease the likelihood
    again, rep2 = refine_texton(refined, Y[0])
    assert float(rep2.log_likelihood_after) >= float(rep2.log_likelihood_before)
    assert float(exact_log_likelihood(again, Y[0])) >= after - 1e-9
    with pytest.raises(ValueError, match="max_steps"):
        refine_texton(closed, Y[0], max_steps=0)
