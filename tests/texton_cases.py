"""Shared cases of the texton tests: random stable systems, their numpy re-derivations
and scipy references (design §2, §3)."""

from typing import Any

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np
import scipy.stats
from scipy.optimize import linear_sum_assignment

from mtex_jax.texture import (
    Texton,
)
from mtex_jax.texture._texton.texton import TEXTON_FIELDS

# --------------------------------------------------------------------------------------------
# helpers: random systems and numpy references
# --------------------------------------------------------------------------------------------


def np_companion(A1, A2):
    k = A1.shape[0]
    return np.block([[A1, A2], [np.eye(k), np.zeros((k, k))]])


def make_oscillator_system(rng, k, D, sigma2=1e-6) -> dict[str, Any]:
    """Random stable second-order LDS: k damped oscillators in a random (non-orthogonal) basis.

    Mode j has companion eigenvalues r_j exp(±iθ_j), r in [0.85, 0.98]; A1 = V diag(2r cosθ) V⁻¹,
    A2 = V diag(−r²) V⁻¹ with V a random well-conditioned matrix.
    """
    r = rng.uniform(0.85, 0.98, k)
    th = rng.uniform(0.05, 1.2, k)
    q1 = np.linalg.qr(rng.standard_normal((k, k)))[0]
    q2 = np.linalg.qr(rng.standard_normal((k, k)))[0]
    V = q1 @ np.diag(rng.uniform(0.7, 1.4, k)) @ q2
    Vi = np.linalg.inv(V)
    A1 = V @ np.diag(2 * r * np.cos(th)) @ Vi
    A2 = V @ np.diag(-r * r) @ Vi
    B = np.tril(0.05 * rng.standard_normal((k, k)), -1) + np.diag(rng.uniform(0.1, 0.3, k))
    C = np.linalg.qr(rng.standard_normal((D, k)))[0]
    return dict(
        A1=A1,
        A2=A2,
        B=B,
        C=C,
        mu=rng.standard_normal(D),
        d=0.1 * rng.standard_normal(k),
        sigma2=sigma2,
    )


def simulate(rng, system, T, reps=1, burn=500):
    """Simulate `reps` independent runs, returns states (reps, T, k) and Y (reps, T, D)."""
    A1, A2, B, d = system["A1"], system["A2"], system["B"], system["d"]
    k = A1.shape[0]
    D = system["C"].shape[0]
    x = np.zeros((reps, T + burn, k))
    drive = rng.standard_normal((reps, T + burn, k)) @ B.T + d
    for t in range(2, T + burn):
        x[:, t] = x[:, t - 1] @ A1.T + x[:, t - 2] @ A2.T + drive[:, t]
    x = x[:, burn:]
    noise = np.sqrt(system["sigma2"]) * rng.standard_normal((reps, T, D))
    Y = system["mu"] + x @ system["C"].T + noise
    return x, Y


def recovery_errors(tex, system):
    """Basis-free errors of a fitted texton against the generating system.

    With M = C_fitᵀ C_true and c = C_fitᵀ(μ_true − μ_fit), the fitted states are
    x_fit = M x_true + c, so the true system in the fitted basis is A_i' = M A_i M⁻¹,
    d' = M d + (I − A1' − A2') c, Q' = M Q Mᵀ.
    """
    C_f = np.asarray(tex.C)
    M = C_f.T @ system["C"]
    Mi = np.linalg.inv(M)
    c = C_f.T @ (system["mu"] - np.asarray(tex.mu))
    A1m = M @ system["A1"] @ Mi
    A2m = M @ system["A2"] @ Mi
    dm = M @ system["d"] + c - A1m @ c - A2m @ c
    Qm = M @ system["B"] @ system["B"].T @ M.T
    A1f, A2f, df, Qf = (np.asarray(a) for a in (tex.A1, tex.A2, tex.d, tex.Q))
    ev_t = np.linalg.eigvals(np_companion(system["A1"], system["A2"]))
    ev_f = np.linalg.eigvals(np_companion(A1f, A2f))
    cost = np.abs(ev_t[:, None] - ev_f[None, :])
    row, col = linear_sum_assignment(cost)
    A_true = np.hstack([A1m, A2m])
    return dict(
        eig=cost[row, col].max(),
        A=np.linalg.norm(np.hstack([A1f, A2f]) - A_true) / np.linalg.norm(A_true),
        d=np.linalg.norm(np.linalg.solve(np.linalg.cholesky(Qm), df - dm)),
        Q=np.linalg.norm(Qf - Qm) / np.linalg.norm(Qm),
        subspace=np.linalg.norm(C_f @ C_f.T - system["C"] @ system["C"].T),
    )


def random_texton_np(rng, D, k, rho=0.9) -> dict[str, Any]:
    """A random valid texton (numpy arrays) with stable dynamics and PD S0."""
    A1 = rng.standard_normal((k, k)) / np.sqrt(k)
    A2 = 0.5 * rng.standard_normal((k, k)) / np.sqrt(k)
    s = rho / np.max(np.abs(np.linalg.eigvals(np_companion(A1, A2))))
    A1, A2 = s * A1, s * s * A2
    B = np.tril(0.2 * rng.standard_normal((k, k)), -1) + np.diag(rng.uniform(0.3, 0.8, k))
    L0 = np.tril(0.3 * rng.standard_normal((2 * k, 2 * k)), -1) + np.diag(
        rng.uniform(0.5, 1.5, 2 * k)
    )
    return dict(
        mu=rng.standard_normal(D),
        C=np.linalg.qr(rng.standard_normal((D, k)))[0],
        A1=A1,
        A2=A2,
        d=0.3 * rng.standard_normal(k),
        B=B,
        sigma2=np.float64(rng.uniform(0.05, 0.3)),
        m0=rng.standard_normal(2 * k),
        S0=L0 @ L0.T,
    )


def to_texton(p):
    return Texton(**{name: jnp.asarray(v) for name, v in p.items()})


def runs_of(ids):
    """Maximal runs of equal non-negative ids: list of index arrays (numpy reference)."""
    runs, start = [], None
    for t in range(len(ids) + 1):
        if start is not None and (t == len(ids) or ids[t] != ids[start]):
            runs.append(np.arange(start, t))
            start = None
        if t < len(ids) and ids[t] >= 0 and start is None:
            start = t
    return runs


def sign_fix(V):
    idx = np.argmax(np.abs(V), axis=0)
    s = np.sign(V[idx, np.arange(V.shape[1])])
    return V * np.where(s == 0, 1, s)


def numpy_fit(Y, ids, k, q_floor, sigma2_floor, kappa) -> dict[str, Any]:
    """Independent re-derivation of the closed-form fit: SVD + per-segment least squares."""
    D = Y.shape[1]
    frames = Y[ids >= 0]
    n = frames.shape[0]
    mu = frames.mean(axis=0)
    _, s, Vt = np.linalg.svd(frames - mu, full_matrices=False)
    C = sign_fix(Vt[:k].T)
    sigma2 = max(np.sum(s[k:] ** 2) / (n * (D - k)), sigma2_floor)
    targets, regressors, starts, pairs = [], [], [], []
    for run in runs_of(ids):
        X = (Y[run] - mu) @ C
        for t in range(2, len(run)):  # drop the terms that cross segment boundaries
            targets.append(X[t])
            regressors.append(np.concatenate([X[t - 1], X[t - 2], [1.0]]))
        for t in range(1, len(run)):
            pairs.append(np.concatenate([X[t - 1], X[t]]))
        if len(run) >= 2:
            starts.append(np.concatenate([X[0], X[1]]))
    Ytg, Xrg = np.array(targets), np.array(regressors)
    coef = np.linalg.lstsq(Xrg, Ytg, rcond=None)[0].T  # (k, 2k+1)
    A1, A2, d = coef[:, :k], coef[:, k : 2 * k], coef[:, 2 * k]
    res = Ytg - Xrg @ coef.T
    Q = res.T @ res / len(res) + q_floor * np.eye(k)
    pairs, starts = np.array(pairs), np.array(starts)
    m_p = pairs.mean(axis=0)
    S_p = (pairs - m_p).T @ (pairs - m_p) / len(pairs)
    m0 = (starts.sum(axis=0) + kappa * m_p) / (len(starts) + kappa)
    dev = starts - m0
    S0 = (dev.T @ dev + kappa * (S_p + np.outer(m_p - m0, m_p - m0))) / (len(starts) + kappa)
    S0 = S0 + q_floor * np.eye(2 * k)
    return dict(mu=mu, C=C, A1=A1, A2=A2, d=d, Q=Q, sigma2=sigma2, m0=m0, S0=S0)


def anisotropic_data(rng, T, D, decay=0.8):
    """Smooth random data with a clearly separated PCA spectrum (distinct eigenvalues)."""
    scales = decay ** np.arange(D)
    Z = np.cumsum(rng.standard_normal((T, D)), axis=0) * 0.2 + rng.standard_normal((T, D))
    return Z * scales + rng.standard_normal(D)


def assert_valid_texton(tex):
    for name in TEXTON_FIELDS:
        assert np.all(np.isfinite(np.asarray(getattr(tex, name)))), name
    assert np.min(np.linalg.eigvalsh(np.asarray(tex.Q))) > 0
    assert np.min(np.linalg.eigvalsh(np.asarray(tex.S0))) > 0
    assert float(tex.sigma2) > 0
    C = np.asarray(tex.C)
    np.testing.assert_allclose(C.T @ C, np.eye(C.shape[1]), atol=1e-10)
    B = np.asarray(tex.B)
    np.testing.assert_array_equal(B, np.tril(B))


def scipy_segment_ll(p, Yseg):
    """Projected-state segment log-likelihood with scipy densities, term by term."""
    D, k = p["C"].shape
    X = (Yseg - p["mu"]) @ p["C"]
    Rr = (Yseg - p["mu"]) - X @ p["C"].T
    Q = p["B"] @ p["B"].T
    ll = scipy.stats.multivariate_normal.logpdf(np.concatenate([X[0], X[1]]), p["m0"], p["S0"])
    for t in range(2, len(Yseg)):
        mean = p["A1"] @ X[t - 1] + p["A2"] @ X[t - 2] + p["d"]
        ll += scipy.stats.multivariate_normal.logpdf(X[t], mean, Q)
    # residual: D−k dimensional Gaussian, written in an orthonormal basis of the complement
    U = np.linalg.svd(np.eye(D) - p["C"] @ p["C"].T)[0][:, : D - k]
    for t in range(len(Yseg)):
        ll += scipy.stats.multivariate_normal.logpdf(U.T @ Rr[t], np.zeros(D - k), p["sigma2"])
    return ll


def scipy_frame_terms(p, Y):
    """Direct per-frame terms of one texton: scipy densities of x_t and of the explicit r_t."""
    D, k = p["C"].shape
    T = Y.shape[0]
    X = (Y - p["mu"]) @ p["C"]
    dyn = np.zeros(T)
    for t in range(2, T):
        mean = p["A1"] @ X[t - 1] + p["A2"] @ X[t - 2] + p["d"]
        dyn[t] = scipy.stats.multivariate_normal.logpdf(X[t], mean, p["B"] @ p["B"].T)
    r = (Y - p["mu"]) - X @ p["C"].T
    obs = -0.5 * ((D - k) * np.log(2 * np.pi * p["sigma2"]) + (r**2).sum(1) / p["sigma2"])
    return dyn, obs if D > k else np.zeros(T)


def assert_terms_equal_reference(ps, Y, dyn, obs):
    """Rows of ``frame_terms`` of a stack equal ``scipy_frame_terms`` of each texton."""
    for i, p in enumerate(ps):
        ref_dyn, ref_obs = scipy_frame_terms(p, Y)
        np.testing.assert_allclose(dyn[i], ref_dyn, rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(obs[i], ref_obs, rtol=1e-11, atol=1e-12)
