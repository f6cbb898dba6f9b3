"""Tests for textons (issue 3): fitting, per-frame terms, segment scores, exact likelihood.

Every test compares against an independent reference (numpy/scipy re-derivations, dense
Gaussians, known generating systems) or checks a documented invariant that can fail.
"""

import threading
from typing import Any

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from jax.test_util import check_grads
from scipy.optimize import linear_sum_assignment

from mtex_jax import internal
from mtex_jax.texture import (
    DynamicsStats,
    FrameStats,
    RefineReport,
    SegmentScorer,
    Texton,
    dynamics_stats,
    exact_log_likelihood,
    exact_log_likelihood_segments,
    fit_texton,
    frame_stats,
    frame_terms,
    init_terms,
    refine_texton,
    sample_texton,
    segment_log_likelihood,
    segment_scores,
    spectral_radius,
    stack_textons,
    subspace_from_stats,
    texton_from_stats,
)

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
    for name in internal.TEXTON_FIELDS:
        assert np.all(np.isfinite(np.asarray(getattr(tex, name)))), name
    assert np.min(np.linalg.eigvalsh(np.asarray(tex.Q))) > 0
    assert np.min(np.linalg.eigvalsh(np.asarray(tex.S0))) > 0
    assert float(tex.sigma2) > 0
    C = np.asarray(tex.C)
    np.testing.assert_allclose(C.T @ C, np.eye(C.shape[1]), atol=1e-10)
    B = np.asarray(tex.B)
    np.testing.assert_array_equal(B, np.tril(B))


# --------------------------------------------------------------------------------------------
# Texton container
# --------------------------------------------------------------------------------------------


def test_texton_shapes_stack_and_index():
    rng = np.random.default_rng(0)
    ts = [to_texton(random_texton_np(rng, 9, 3)) for _ in range(4)]
    st = stack_textons(ts)
    assert (st.n_textons, st.state_dim, st.obs_dim, st.batch_shape) == (4, 3, 9, (4,))
    assert ts[0].n_textons == 1 and not ts[0].is_stacked
    np.testing.assert_array_equal(st[2].A1, ts[2].A1)
    np.testing.assert_array_equal(st[1:3].S0, jnp.stack([ts[1].S0, ts[2].S0]))
    np.testing.assert_allclose(st.Q[3], ts[3].B @ ts[3].B.T)
    with pytest.raises(TypeError):
        ts[0][0]


def test_texton_check_init_rejects_bad_shapes():
    p = random_texton_np(np.random.default_rng(1), 6, 2)
    for name, bad in [
        ("C", np.zeros((6, 3))),
        ("A2", np.zeros((2, 3))),
        ("d", np.zeros(3)),
        ("B", np.zeros((2,))),
        ("sigma2", np.zeros(2)),
        ("m0", np.zeros(2)),
        ("S0", np.zeros((2, 2))),
        ("mu", np.zeros(5)),
    ]:
        q = dict(p, **{name: bad})
        with pytest.raises(ValueError, match=f"Texton.{name}|Texton.C"):
            to_texton(q)
    with pytest.raises(ValueError, match="k=4"):  # k > D
        Texton(
            mu=jnp.zeros(3),
            C=jnp.zeros((3, 4)),
            A1=jnp.zeros((4, 4)),
            A2=jnp.zeros((4, 4)),
            d=jnp.zeros(4),
            B=jnp.eye(4),
            sigma2=jnp.ones(()),
            m0=jnp.zeros(8),
            S0=jnp.eye(8),
        )
    with pytest.raises(ValueError, match="stack_textons"):
        stack_textons([to_texton(p), to_texton(random_texton_np(np.random.default_rng(2), 6, 3))])
    with pytest.raises(ValueError, match="empty"):
        stack_textons([])


# --------------------------------------------------------------------------------------------
# Fitting: numpy re-derivation, segments, batching, summable statistics
# --------------------------------------------------------------------------------------------

SEG_IDS = np.array(
    [0] * 10 + [1] * 7 + [-1] * 3 + [2] * 3 + [3] * 2 + [4] * 1 + [0] * 8 + [5] * 12 + [-1] * 2
)


def test_multi_segment_fit_matches_numpy_rederivation():
    rng = np.random.default_rng(3)
    T, D, k = len(SEG_IDS), 8, 3
    Y = anisotropic_data(rng, T, D)
    q_floor, s2_floor, kappa = 1e-7, 1e-9, 2.5
    tex = fit_texton(
        Y,
        SEG_IDS,
        state_dim=k,
        ridge=0.0,
        q_floor=q_floor,
        sigma2_floor=s2_floor,
        init_prior_weight=kappa,
    )
    ref = numpy_fit(Y, SEG_IDS, k, q_floor, s2_floor, kappa)
    for name in ("mu", "C", "A1", "A2", "d", "Q", "sigma2", "m0", "S0"):
        np.testing.assert_allclose(
            np.asarray(getattr(tex, name)), ref[name], rtol=1e-10, atol=1e-10, err_msg=name
        )
    np.testing.assert_allclose(np.asarray(tex.B), np.linalg.cholesky(ref["Q"]), atol=1e-10)


def test_boundary_terms_are_dropped():
    """Adjacent segments with different ids must not share a dynamics term."""
    rng = np.random.default_rng(4)
    Y = anisotropic_data(rng, 40, 6)
    ids = np.array([0] * 20 + [1] * 20)
    sub = subspace_from_stats(frame_stats(Y, ids), state_dim=2)
    merged = dynamics_stats(Y, np.zeros(40, int), sub)
    split = dynamics_stats(Y, ids, sub)
    assert float(merged.n3) == 38 and float(split.n3) == 36
    assert float(merged.n_start) == 1 and float(split.n_start) == 2
    assert float(split.n2) == 38


def test_batched_sequences_equal_concatenation_with_boundary_mask():
    rng = np.random.default_rng(5)
    T, D, k = 50, 7, 3
    Y = np.stack([anisotropic_data(rng, T, D), anisotropic_data(rng, T, D)])
    m1 = np.where(np.arange(T) < 30, 0, 1)
    m2 = np.where(np.arange(T) % 17 == 5, -1, 0)
    mask = np.stack([m1, m2])
    batched = fit_texton(Y, mask, state_dim=k)
    concat = fit_texton(
        Y.reshape(2 * T, D), np.concatenate([m1, np.where(m2 >= 0, m2 + 10, -1)]), state_dim=k
    )
    for name in internal.TEXTON_FIELDS:
        np.testing.assert_allclose(
            getattr(batched, name), getattr(concat, name), rtol=1e-10, atol=1e-10, err_msg=name
        )
    # the same through summed two-pass statistics (what a multi-sequence M-step does)
    fs = frame_stats(Y[0], m1) + frame_stats(Y[1], m2)
    assert isinstance(fs, FrameStats)
    sub = subspace_from_stats(fs, state_dim=k)
    ds = sum([dynamics_stats(Y[0], m1, sub), dynamics_stats(Y[1], m2, sub)])
    assert isinstance(ds, DynamicsStats)
    two_pass = texton_from_stats(sub, ds)
    for name in internal.TEXTON_FIELDS:
        np.testing.assert_allclose(
            getattr(two_pass, name), getattr(batched, name), rtol=1e-10, atol=1e-10
        )


def test_mask_none_and_boolean_mask():
    rng = np.random.default_rng(6)
    Y = anisotropic_data(rng, 40, 6)
    a = fit_texton(Y, state_dim=2)
    b = fit_texton(Y, np.zeros(40, np.int64), state_dim=2)
    c = fit_texton(Y, np.ones(40, bool), state_dim=2)
    for name in internal.TEXTON_FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        np.testing.assert_array_equal(getattr(a, name), getattr(c, name))


# --------------------------------------------------------------------------------------------
# Recovery of known systems
# --------------------------------------------------------------------------------------------

# Tolerances at T = 5000: about 2-3x the largest error observed over these seeds; the errors
# are statistical (they shrink as 1/sqrt(T), see the next test).
RECOVERY_TOL = dict(eig=0.15, A=0.08, d=0.2, Q=0.1, subspace=0.003)


@pytest.mark.parametrize("k", [4, 8, 15])
def test_recovers_known_systems(k):
    D, T = 60, 5000
    for seed in range(3):
        rng = np.random.default_rng(1000 * k + seed)
        system = make_oscillator_system(rng, k, D)
        _, Y = simulate(rng, system, T)
        tex = fit_texton(Y[0], state_dim=k)
        err = recovery_errors(tex, system)
        for name, tol in RECOVERY_TOL.items():
            assert err[name] < tol, (k, seed, name, err)
        # observation noise is recovered too (sigma2 = 1e-6 in the generator)
        np.testing.assert_allclose(float(tex.sigma2), system["sigma2"], rtol=0.05)


@pytest.mark.parametrize("k", [4, 15])
def test_recovery_error_shrinks_like_inverse_sqrt_T(k):
    """RMS error over 4 independent runs at T = 5000 vs T = 20000: ratio ≈ √4 = 2."""
    D, reps = 60, 4
    rng = np.random.default_rng(77 + k)
    system = make_oscillator_system(rng, k, D)
    rms = {}
    for T in (5000, 20000):
        _, Y = simulate(rng, system, T, reps=reps)
        errs = [recovery_errors(fit_texton(Y[r], state_dim=k), system) for r in range(reps)]
        rms[T] = {n: np.sqrt(np.mean([e[n] ** 2 for e in errs])) for n in ("A", "Q", "d")}
    for name in ("A", "Q"):
        ratio = rms[5000][name] / rms[20000][name]
        assert 1.4 < ratio < 2.9, (name, rms)
    # all three parameters together
    total = sum(rms[5000].values()) / sum(rms[20000].values())
    assert 1.5 < total < 2.7, rms


# --------------------------------------------------------------------------------------------
# Stability projection
# --------------------------------------------------------------------------------------------


def test_rho_max_projection():
    rng = np.random.default_rng(8)
    # a random walk: the unconstrained fit has companion spectral radius ≈ 1
    Y = np.cumsum(rng.standard_normal((400, 6)), axis=0)
    free = fit_texton(Y, state_dim=3)
    rho_free = float(spectral_radius(free))
    assert rho_free > 0.95
    rho_max = 0.9
    proj = fit_texton(Y, state_dim=3, rho_max=rho_max)
    rho = float(spectral_radius(proj))
    assert rho <= rho_max + 1e-12
    np.testing.assert_allclose(rho, rho_max, rtol=1e-9)
    # radial scaling: every companion eigenvalue is multiplied by s = rho_max / rho_free
    s = rho_max / rho_free
    np.testing.assert_allclose(proj.A1, s * free.A1, rtol=1e-9)
    np.testing.assert_allclose(proj.A2, s * s * free.A2, rtol=1e-9)
    ev_f = np.sort_complex(np.linalg.eigvals(np_companion(*map(np.asarray, (free.A1, free.A2)))))
    ev_p = np.sort_complex(np.linalg.eigvals(np_companion(*map(np.asarray, (proj.A1, proj.A2)))))
    np.testing.assert_allclose(ev_p, s * ev_f, atol=1e-9)
    # d and Q are the least-squares offset / residual covariance for the projected A1, A2
    X = (Y - np.asarray(proj.mu)) @ np.asarray(proj.C)
    Z = np.hstack([X[1:-1], X[:-2]])
    r0 = X[2:] - Z @ np.hstack([np.asarray(proj.A1), np.asarray(proj.A2)]).T
    np.testing.assert_allclose(proj.d, r0.mean(axis=0), atol=1e-9)
    res = r0 - r0.mean(axis=0)
    np.testing.assert_allclose(proj.Q, res.T @ res / len(res) + 1e-6 * np.eye(3), rtol=1e-8)
    # a bound above the free radius changes nothing
    loose = fit_texton(Y, state_dim=3, rho_max=rho_free + 0.5)
    np.testing.assert_allclose(loose.A1, free.A1, rtol=1e-12)
    with pytest.raises(ValueError, match="rho_max"):
        fit_texton(Y, state_dim=3, rho_max=-1.0)


# --------------------------------------------------------------------------------------------
# Per-frame terms, segment scores and the direct segment likelihood
# --------------------------------------------------------------------------------------------


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


def test_segment_log_likelihood_matches_scipy():
    rng = np.random.default_rng(9)
    p = random_texton_np(rng, 7, 3)
    Yseg = rng.standard_normal((9, 7))
    np.testing.assert_allclose(
        float(segment_log_likelihood(to_texton(p), Yseg)), scipy_segment_ll(p, Yseg), rtol=1e-11
    )


def test_frame_and_init_terms_match_scipy():
    rng = np.random.default_rng(10)
    D, k, T = 8, 3, 12
    ps = [random_texton_np(rng, D, k) for _ in range(3)]
    st = stack_textons([to_texton(p) for p in ps])
    Y = rng.standard_normal((T, D)) + 2.0
    dyn, obs = frame_terms(st, Y)
    init = init_terms(st, Y)
    assert dyn.shape == obs.shape == init.shape == (3, T)
    for i, p in enumerate(ps):
        X = (Y - p["mu"]) @ p["C"]
        Q = p["B"] @ p["B"].T
        assert dyn[i, 0] == 0 and dyn[i, 1] == 0
        for t in range(2, T):
            mean = p["A1"] @ X[t - 1] + p["A2"] @ X[t - 2] + p["d"]
            ref = scipy.stats.multivariate_normal.logpdf(X[t], mean, Q)
            np.testing.assert_allclose(dyn[i, t], ref, rtol=1e-11)
        r = (Y - p["mu"]) - X @ p["C"].T
        ref_obs = -0.5 * ((D - k) * np.log(2 * np.pi * p["sigma2"]) + (r**2).sum(1) / p["sigma2"])
        np.testing.assert_allclose(obs[i], ref_obs, rtol=1e-11)
        for b in range(T - 1):
            ref = scipy.stats.multivariate_normal.logpdf(
                np.concatenate([X[b], X[b + 1]]), p["m0"], p["S0"]
            )
            np.testing.assert_allclose(init[i, b], ref, rtol=1e-11)
        assert init[i, T - 1] == -np.inf
    # a single (unstacked) texton gives (T,) arrays equal to the stacked rows
    d1, o1 = frame_terms(st[1], Y)
    np.testing.assert_allclose(d1, dyn[1], rtol=1e-13)
    np.testing.assert_allclose(o1, obs[1], rtol=1e-13)
    # the per-texton algorithm (chunk_size) and other time blocks give the same result
    for chunk in (2, 1):
        dc, oc = internal.frame_terms_per_texton(st, Y, chunk_size=chunk)
        np.testing.assert_allclose(dc, dyn, rtol=1e-12, err_msg=f"chunk {chunk}")
        np.testing.assert_allclose(oc, obs, rtol=1e-12, err_msg=f"chunk {chunk}")
    for kw in (dict(block_size=1), dict(block_size=5)):
        d3, o3 = frame_terms(st, Y, **kw)
        np.testing.assert_allclose(d3, dyn, rtol=1e-12, err_msg=str(kw))
        np.testing.assert_allclose(o3, obs, rtol=1e-12, err_msg=str(kw))


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


@pytest.mark.parametrize(
    ("T", "block_size"),
    [(1, None), (2, None), (3, None), (3, 1), (10, 3), (10, 4), (10, 10), (10, 64), (41, 8)],
)
def test_frame_terms_time_blocks_cover_every_frame(T, block_size):
    # blocks that do not divide T (the last block overlaps), blocks longer than T, T < 3
    rng = np.random.default_rng(13)
    D, k = 5, 2
    ps = [random_texton_np(rng, D, k) for _ in range(2)]
    st = stack_textons([to_texton(p) for p in ps])
    Y = rng.standard_normal((T, D)) + 1.0
    dyn, obs = frame_terms(st, Y, block_size=block_size)
    assert dyn.shape == obs.shape == (2, T)
    assert_terms_equal_reference(ps, Y, dyn, obs)


@pytest.mark.parametrize(("D", "k"), [(20, 20), (23, 18)])
def test_frame_terms_beyond_the_unrolled_state_dimension(D, k):
    """k > 16: the vectorised sums over the state index and the wider automatic time blocks,
    against the scipy reference and against short blocks."""
    rng = np.random.default_rng(21)
    ps = [random_texton_np(rng, D, k) for _ in range(3)]
    st = stack_textons([to_texton(p) for p in ps])
    Y = rng.standard_normal((700, D)) * 0.3 + 0.5
    dyn, obs = frame_terms(st, Y)
    assert_terms_equal_reference(ps, Y, dyn, obs)
    dyn7, obs7 = frame_terms(st, Y, block_size=7)
    np.testing.assert_allclose(np.asarray(dyn7), np.asarray(dyn), rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(np.asarray(obs7), np.asarray(obs), rtol=1e-10, atol=1e-9)


@pytest.mark.parametrize(
    ("T", "block_size"), [(2, None), (3, None), (3, 1), (10, 3), (10, 64), (41, 8), (300, None)]
)
def test_full_texton_kernel_blocks_and_init_terms_against_scipy(T, block_size):
    """k = D: the stacked-lag kernel (``_frame_terms_full``) on blocks that do and do not
    divide T, blocks longer than T and short T; dyn and the initial-state terms (through
    ``segment_scores``) against scipy densities of each texton."""
    rng = np.random.default_rng(T)
    D = 5
    ps = [random_texton_np(rng, D, D) for _ in range(3)]
    st = stack_textons([to_texton(p) for p in ps])
    Y = rng.standard_normal((T, D)) * 0.5 + 1.0
    dyn, obs = frame_terms(st, Y, block_size=block_size)
    assert_terms_equal_reference(ps, Y, dyn, obs)
    np.testing.assert_array_equal(obs, 0.0)
    init = np.asarray(segment_scores(st, Y, block_size=block_size).init)
    for i, p in enumerate(ps):
        X = (Y - p["mu"]) @ p["C"]
        for b in range(T - 1):
            pair = np.concatenate([X[b], X[b + 1]])
            ref = scipy.stats.multivariate_normal.logpdf(pair, p["m0"], p["S0"])
            np.testing.assert_allclose(init[i, b], ref, rtol=1e-10)
        assert init[i, T - 1] == -np.inf


def test_frame_terms_ill_conditioned_q_and_k_equal_d():
    # B with singular values from 1e-3 to 1 (the whitened coordinates rescale by 1/s); then
    # textons with k = D (no residual dimensions: obs = 0)
    rng = np.random.default_rng(14)
    D, k, T = 7, 4, 30
    p = random_texton_np(rng, D, k)
    q1 = np.linalg.qr(rng.standard_normal((k, k)))[0]
    p["B"] = np.linalg.cholesky(q1 @ np.diag([1.0, 0.1, 1e-2, 1e-3]) ** 2 @ q1.T)
    X = rng.standard_normal((T, k)) * 0.1
    Y = X @ p["C"].T + p["mu"] + 0.01 * rng.standard_normal((T, D))
    dyn, obs = frame_terms(to_texton(p), Y)
    ref_dyn, ref_obs = scipy_frame_terms(p, Y)
    np.testing.assert_allclose(dyn, ref_dyn, rtol=1e-9)
    np.testing.assert_allclose(obs, ref_obs, rtol=1e-11)
    pk = random_texton_np(rng, k, k)
    Yk = rng.standard_normal((T, k))
    dyn_k, obs_k = frame_terms(stack_textons([to_texton(pk)] * 2), Yk, block_size=7)
    np.testing.assert_array_equal(obs_k, 0.0)
    np.testing.assert_allclose(dyn_k[1], scipy_frame_terms(pk, Yk)[0], rtol=1e-11, atol=1e-12)


def test_frame_terms_block_and_chunk_arguments_are_validated():
    rng = np.random.default_rng(15)
    st = stack_textons([to_texton(random_texton_np(rng, 4, 2)) for _ in range(2)])
    Y = rng.standard_normal((12, 4))
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="block_size"):
            frame_terms(st, Y, block_size=bad)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="chunk_size"):
            internal.frame_terms_per_texton(st, Y, chunk_size=bad)  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        frame_terms(st, Y, chunk_size=1)  # type: ignore[call-arg]  # no longer a public knob


@pytest.mark.parametrize("workers", [2, 3, 7, 12])
def test_frame_terms_split_over_concurrent_executions(workers, monkeypatch):
    """Textons split into row blocks computed by executions from separate threads and
    assembled in place equal the scipy reference (7 textons: blocks of unequal size, more
    workers than textons), in a short block size so that each block's windows overlap; under
    jit the call is one computation with the same values."""
    import warnings

    rng = np.random.default_rng(16)
    D, k, T = 6, 3, 53
    ps = [random_texton_np(rng, D, k) for _ in range(7)]
    st = stack_textons([to_texton(p) for p in ps])
    Y = rng.standard_normal((T, D)) + 0.5
    parts = min(workers, 7)
    assert internal.frame_terms_parts(workers, st, jnp.asarray(Y)) == parts
    calls = []  # (thread, rows) of every kernel execution
    kernel = internal.frame_terms_jit

    def spy(textons, *args, **kwargs):
        calls.append((threading.get_ident(), textons.n_textons))
        return kernel(textons, *args, **kwargs)

    monkeypatch.setattr("mtex_jax.texture._frame_terms._frame_terms_jit", spy)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # e.g. a donated buffer that could not be reused
        dyn, obs = frame_terms(st, Y, workers=workers, block_size=8)
    monkeypatch.undo()
    # one execution per block, from more than one thread (a pool thread that is done may
    # take another block), blocks of 7 // parts rows or one more
    assert len(calls) == parts and len({t for t, _ in calls}) >= 2
    assert sorted(r for _, r in calls) == sorted(
        7 * (i + 1) // parts - 7 * i // parts for i in range(parts)
    )
    assert dyn.shape == obs.shape == (7, T)
    assert_terms_equal_reference(ps, Y, dyn, obs)
    jitted = jax.jit(lambda t, y: frame_terms(t, y, workers=workers, block_size=8))(st, Y)
    np.testing.assert_allclose(jitted[0], dyn, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(jitted[1], obs, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="NaN or inf"):
        frame_terms(st, np.where(np.arange(T)[:, None] == 40, np.nan, Y), workers=workers)


def test_frame_terms_split_keeps_the_callers_thread_local_settings():
    """The block executions run in other threads under the caller's settings: here x64 is
    off globally and on in the caller's thread only (``jax.enable_x64``), so a block run
    under the global setting would compute in float32."""
    rng = np.random.default_rng(18)
    ps = [random_texton_np(rng, 6, 3) for _ in range(4)]
    Y = rng.standard_normal((30, 6))
    jax.config.update("jax_enable_x64", False)
    try:
        with jax.enable_x64(True):
            st = stack_textons([to_texton(p) for p in ps])
            dyn, obs = frame_terms(st, Y, workers=3)
            one = frame_terms(st, Y, workers=1)
    finally:
        jax.config.update("jax_enable_x64", True)
    assert dyn.dtype == obs.dtype == jnp.float64
    np.testing.assert_allclose(dyn, one[0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(obs, one[1], rtol=1e-12, atol=1e-12)
    assert_terms_equal_reference(ps, Y, dyn, obs)


def test_frame_terms_workers_choice_and_validation():
    rng = np.random.default_rng(17)
    st = stack_textons([to_texton(random_texton_np(rng, 4, 2)) for _ in range(3)])
    small, large = jnp.zeros((10, 4)), jnp.zeros((2**20 // 3 + 1, 4))
    cores = internal.available_cores()
    assert internal.frame_terms_parts(None, st, small) == 1  # too little work: one execution
    assert internal.frame_terms_parts(None, st, large) == min(cores, 3)
    assert internal.frame_terms_parts(1, st, large) == 1
    traced = jax.jit(lambda y: jnp.asarray(internal.frame_terms_parts(2, st, y)))(small)
    assert int(traced) == 1  # under a trace: one computation
    Y = rng.standard_normal((12, 4))
    for bad in (0, -1, 2.5, True, "2"):
        with pytest.raises(ValueError, match="workers"):
            frame_terms(st, Y, workers=bad)  # type: ignore[arg-type]


def test_prefix_sum_scores_equal_direct_segment_likelihood():
    rng = np.random.default_rng(11)
    T, D, k, n_t = 150, 10, 4, 4
    Y = anisotropic_data(rng, T, D)
    # textons fitted on different parts of the data (realistic magnitudes), one random
    textons = [fit_texton(Y[j * 30 : j * 30 + 45], state_dim=k) for j in range(n_t - 1)]
    textons.append(to_texton(random_texton_np(rng, D, k)))
    st = stack_textons(textons)
    scorer = segment_scores(st, Y)
    assert isinstance(scorer, SegmentScorer)
    assert scorer.cum_dyn.shape == (n_t, T + 1) and scorer.init.shape == (n_t, T)
    triples = []
    for L in (2, 5, 40):  # few distinct lengths: the reference compiles once per length
        for _ in range(10):
            b = int(rng.integers(0, T - L + 1))
            triples.append((b, b + L - 1, int(rng.integers(0, n_t))))
    triples += [(0, 39, 0), (T - 2, T - 1, 3), (0, 1, 2), (T - 40, T - 1, 1)]
    b, e, i = (np.array(v) for v in zip(*triples, strict=True))
    fast = np.asarray(scorer.score(b, e, i))
    ref = np.array(
        [float(segment_log_likelihood(textons[ii], Y[bb : ee + 1])) for bb, ee, ii in triples]
    )
    np.testing.assert_allclose(fast, ref, rtol=1e-9, atol=1e-9)
    # the kernel's time blocks (window edges at other frames, a last window overlapping the
    # previous one) change nothing; a bad block size is rejected
    for block_size in (1, 7, 200):
        other = segment_scores(st, Y, block_size=block_size)
        np.testing.assert_allclose(np.asarray(other.score(b, e, i)), fast, rtol=1e-12, atol=1e-9)
        np.testing.assert_array_equal(np.isinf(other.init), np.isinf(scorer.init))
    with pytest.raises(ValueError, match="block_size"):
        segment_scores(st, Y, block_size=0)
    # broadcasting over all textons, and invalid segments give -inf
    all_i = np.asarray(scorer.score(b[None, :], e[None, :], np.arange(n_t)[:, None]))
    assert all_i.shape == (n_t, len(triples))
    np.testing.assert_allclose(all_i[i, np.arange(len(triples))], fast, rtol=1e-12)
    bad = scorer.score(
        np.array([5, 5, -1, 3, 3]), np.array([5, 4, 3, T, 6]), np.array([0] * 4 + [9])
    )
    assert np.all(np.asarray(bad) == -np.inf)
    # scores_ending_at = score with b = e − L + 1
    se = np.asarray(scorer.scores_ending_at(40, np.array([2, 3, 10, 41, 42])))
    for j, L in enumerate([2, 3, 10, 41]):
        np.testing.assert_allclose(se[:, j], scorer.score(40 - L + 1, 40, np.arange(n_t)))
    assert np.all(se[:, 4] == -np.inf)
    # jit/vmap friendly
    jitted = jax.jit(lambda s, b, e, i: s.score(b, e, i))(scorer, b, e, i)
    np.testing.assert_allclose(jitted, fast, rtol=1e-13)


def test_frame_terms_do_not_retrace_for_new_data():
    rng = np.random.default_rng(12)
    st = stack_textons([to_texton(random_texton_np(rng, 6, 2)) for _ in range(3)])
    frame_terms(st, rng.standard_normal((40, 6)))
    internal.frame_terms_per_texton(st, rng.standard_normal((40, 6)), chunk_size=1)
    n0 = eqx.debug.get_num_traces(internal.frame_terms_traced)
    n0_chunk = eqx.debug.get_num_traces(internal.all_terms_traced)
    for _ in range(3):
        st2 = jax.tree.map(lambda a: a * 1.01, st)
        frame_terms(st2, rng.standard_normal((40, 6)))
        internal.frame_terms_per_texton(st2, rng.standard_normal((40, 6)), chunk_size=1)
    assert eqx.debug.get_num_traces(internal.frame_terms_traced) == n0
    assert eqx.debug.get_num_traces(internal.all_terms_traced) == n0_chunk
    fit_texton(rng.standard_normal((40, 6)), state_dim=2)
    n1 = eqx.debug.get_num_traces(internal.fit_texton_traced)
    for _ in range(3):
        fit_texton(rng.standard_normal((40, 6)), rng.integers(-1, 3, 40), state_dim=2)
    assert eqx.debug.get_num_traces(internal.fit_texton_traced) == n1


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
    p: dict[str, Any] = {n: np.asarray(getattr(tex, n)) for n in internal.TEXTON_FIELDS}
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
    for name in internal.TEXTON_FIELDS:
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
