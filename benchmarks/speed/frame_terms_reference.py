"""Random textons and the three numpy implementations of the per-frame texton terms that
``bench_frame_terms.py`` times against ``frame_terms``.
"""

from __future__ import annotations

import numpy as np

# --------------------------------------------------------------------------------------------
# data
# --------------------------------------------------------------------------------------------


def random_textons(rng: np.random.Generator, n: int, D: int, k: int) -> dict[str, np.ndarray]:
    """``n`` random valid textons (stable dynamics, PD covariances) as stacked numpy arrays."""
    C = np.linalg.qr(rng.standard_normal((n, D, k)))[0]
    A1 = rng.standard_normal((n, k, k)) / np.sqrt(k)
    A2 = 0.5 * rng.standard_normal((n, k, k)) / np.sqrt(k)
    for i in range(n):  # scale to spectral radius 0.95
        F = np.block([[A1[i], A2[i]], [np.eye(k), np.zeros((k, k))]])
        s = 0.95 / np.max(np.abs(np.linalg.eigvals(F)))
        A1[i] *= s
        A2[i] *= s * s
    tril = np.tril(0.05 * rng.standard_normal((n, k, k)), -1)
    B = tril + np.eye(k) * rng.uniform(0.1, 0.4, (n, k, 1))
    L0 = np.tril(0.1 * rng.standard_normal((n, 2 * k, 2 * k)), -1) + np.eye(2 * k)
    return dict(
        mu=0.3 * rng.standard_normal((n, D)),
        C=C,
        A1=A1,
        A2=A2,
        d=0.05 * rng.standard_normal((n, k)),
        B=B,
        sigma2=rng.uniform(0.01, 0.1, n),
        m0=rng.standard_normal((n, 2 * k)),
        S0=L0 @ np.swapaxes(L0, -1, -2),
    )


# --------------------------------------------------------------------------------------------
# numpy implementations
# --------------------------------------------------------------------------------------------

LOG_2PI = np.log(2 * np.pi)


def whitened_coords(p: dict[str, np.ndarray], ybar: np.ndarray) -> dict[str, np.ndarray]:
    """Per-texton constants of the whitened-state formulation (numpy, all textons at once).

    ``B = U diag(s) Vᵀ``; ``z_t = Ctᵀ(y_t − μ)`` with ``Ct = C U diag(s)⁻¹``; the whitened
    residual is ``z_t + F1 z_{t−1} + F2 z_{t−2} − e`` with ``F_j = −diag(s)⁻¹ Uᵀ A_j U diag(s)``,
    ``e = diag(s)⁻¹ Uᵀ d``, and ``‖x_t‖² = ‖diag(s) z_t‖²``.
    """
    _, D, k = p["C"].shape
    U, s, _ = np.linalg.svd(p["B"])
    Ut = np.swapaxes(U, 1, 2)
    ratio = s[:, None, :] / s[:, :, None]
    mc = p["mu"] - ybar
    Ct = (p["C"] @ U) / s[:, None, :]
    return dict(
        Ct=Ct,
        mc=mc,
        off=np.einsum("nd,ndk->nk", mc, Ct),
        F1=-(Ut @ p["A1"] @ U) * ratio,
        F2=-(Ut @ p["A2"] @ U) * ratio,
        e=np.einsum("nmj,nm->nj", U, p["d"]) / s,
        s2=s * s,
        mcmc=np.einsum("nd,nd->n", mc, mc),
        dyn_const=k * LOG_2PI
        + 2 * np.sum(np.log(np.abs(np.diagonal(p["B"], axis1=1, axis2=2))), axis=1),
        obs_const=(D - k) * (LOG_2PI + np.log(p["sigma2"])),
    )


def numpy_same_algorithm(
    p: dict[str, np.ndarray], Y: np.ndarray, block: int = 254
) -> tuple[np.ndarray, np.ndarray]:
    """Transcription of the JAX kernel: time blocks, one GEMM per block for all textons."""
    n, D, k = p["C"].shape
    T = Y.shape[0]
    ybar = Y.mean(axis=0)
    Yc = Y - ybar
    yn = np.einsum("td,td->t", Yc, Yc)
    w = whitened_coords(p, ybar)
    # rows i(k+1) … i(k+1)+k: texton i's [z_t; (y_t − ȳ)·(μ_i − ȳ)] from [y_t − ȳ; 1]
    P = np.zeros((n, k + 1, D + 1))
    P[:, :k, :D] = np.swapaxes(w["Ct"], 1, 2)
    P[:, :k, D] = -w["off"]
    P[:, k, :D] = w["mc"]
    P = P.reshape(n * (k + 1), D + 1)
    F = np.concatenate([w["F1"], w["F2"]], axis=1)
    YaT = np.zeros((D + 1, T + 2))
    YaT[:D, 2:] = Yc.T
    YaT[D, 2:] = 1.0
    e = w["e"][:, :, None]
    sigma2 = p["sigma2"][:, None]
    dyn = np.empty((n, T))
    obs = np.empty((n, T))
    block = min(block, T)
    for b in range(-(-T // block)):
        s = min(b * block, T - block)  # the last block overlaps the previous one
        Z = (P @ YaT[:, s : s + block + 2]).reshape(n, k + 1, block + 2)
        FZ = np.einsum("njm,nmt->njt", F, Z[:, :k], optimize=True)  # faster than F @ Z
        W = FZ[:, :k, 1:-1] + FZ[:, k:, :-2]
        W += Z[:, :k, 2:]
        W -= e
        dyn[:, s : s + block] = -0.5 * (w["dyn_const"][:, None] + np.einsum("njt,njt->nt", W, W))
        Z0 = Z[:, :k, 2:]
        r2 = yn[s : s + block] - 2 * Z[:, k, 2:]
        r2 += w["mcmc"][:, None]
        r2 -= np.einsum("njt,njt,nj->nt", Z0, Z0, w["s2"])
        np.maximum(r2, 0.0, out=r2)
        obs[:, s : s + block] = -0.5 * (w["obs_const"][:, None] + r2 / sigma2)
    dyn[:, :2] = 0.0
    return dyn, obs


def numpy_per_texton(p: dict[str, np.ndarray], Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same whitened-coordinate formulas, looping over textons (vectorised over frames)."""
    n, _, k = p["C"].shape
    T = Y.shape[0]
    ybar = Y.mean(axis=0)
    Yc = Y - ybar
    yn = np.einsum("td,td->t", Yc, Yc)
    w = whitened_coords(p, ybar)
    dyn = np.zeros((n, T))
    obs = np.empty((n, T))
    for i in range(n):
        Pm = Yc @ np.concatenate([w["Ct"][i], w["mc"][i][:, None]], axis=1)
        Z = Pm[:, :k] - w["off"][i]
        W = Z[1:-1] @ w["F1"][i].T + Z[:-2] @ w["F2"][i].T
        W += Z[2:]
        W -= w["e"][i]
        dyn[i, 2:] = -0.5 * (w["dyn_const"][i] + np.einsum("tk,tk->t", W, W))
        r2 = yn - 2 * Pm[:, k] + w["mcmc"][i] - np.einsum("tk,tk,k->t", Z, Z, w["s2"][i])
        obs[i] = -0.5 * (w["obs_const"][i] + np.maximum(r2, 0.0) / p["sigma2"][i])
    return dyn, obs


def numpy_straightforward(p: dict[str, np.ndarray], Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Textbook formulation (vectorised over frames, loop over textons)."""
    n, D, k = p["C"].shape
    T = Y.shape[0]
    dyn = np.zeros((n, T))
    obs = np.empty((n, T))
    for i in range(n):
        Yc = Y - p["mu"][i]
        X = Yc @ p["C"][i]
        E = X[2:] - X[1:-1] @ p["A1"][i].T - X[:-2] @ p["A2"][i].T - p["d"][i]
        W = np.linalg.solve(p["B"][i], E.T)
        logdet = 2 * np.sum(np.log(np.diag(p["B"][i])))
        dyn[i, 2:] = -0.5 * (k * LOG_2PI + logdet + np.sum(W * W, axis=0))
        r2 = np.maximum(np.sum(Yc * Yc, axis=1) - np.sum(X * X, axis=1), 0.0)
        s2 = p["sigma2"][i]
        obs[i] = -0.5 * ((D - k) * (LOG_2PI + np.log(s2)) + r2 / s2)
    return dyn, obs
