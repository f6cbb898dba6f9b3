"""Choosing the texton state dimension ``k`` by BIC (:func:`choose_state_dim`).

One texton is fitted on all the clips for every candidate ``k`` (closed form, in numpy: one
eigendecomposition of the frame scatter, then a least-squares AR(2) per ``k``), and the ``k``
with the lowest ``BIC = −2 log L + p log n`` is returned. With the maximum-likelihood
(least-squares) plug-in the Gaussian terms have the closed forms

.. code-block:: text

    Σ_t log N(x_t; A1 x_{t−1} + A2 x_{t−2} + d, Q) = −½ N (k log 2π + log|Q| + k)
    Σ_t log N(r_t; 0, σ² I_{D−k})                   = −½ n (D − k)(log 2πσ² + 1)        (paper)
    Σ_t log N(e_t; 0, s_r² I_{D−k})                 = −½ N (D − k)(log 2π s_r² + 1)   (residual)

(``N`` dynamics terms, ``n`` frames), which is what :func:`choose_state_dim` sums (the
initial-state terms of the first two frames of each clip are left out: a few frames out of
thousands). ``p`` counts the texton's free parameters (see :func:`n_params`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .._observation import (
    ObservationModel,
    PaperObservation,
    ResidualObservation,
    check_observation,
)

__all__ = ["choose_state_dim", "n_params"]

LOG_2PI = math.log(2 * math.pi)


def n_params(
    n_t: int,
    D: int,
    k: int,
    observation: ObservationModel = PaperObservation(),
    durations: str = "flat",
    segments: np.ndarray | None = None,
) -> float:
    """Free parameters of a motion texture with ``n_t`` textons (for BIC, design §4.7).

    The textons' parameters are the observation model's count
    (:meth:`ObservationModel.n_params`: per texton ``μ`` D, ``C`` Dk − k(k+1)/2, ``A1, A2``
    2k², ``d`` k, ``Q`` k(k+1)/2, ``σ²`` 1, ``m0`` 2k, ``S0`` k(2k+1), the residual AR(2) 3
    more); log-normal durations 2 more per texton; plus ``n_t(n_t − 1)`` transition and
    ``n_t − 1`` initial probabilities.

    ``segments`` (rows ``(clip, start, length, label)`` of the segmentation) give each
    texton's dynamics terms and segments to a model whose estimates are shrunk (the tied
    model, design §10.10), which then counts its effective parameters.
    """
    frames = starts = None
    if segments is not None:
        seg = np.asarray(segments).reshape(-1, 4)
        lab = seg[:, 3].astype(np.int64)
        starts = np.bincount(lab, minlength=n_t)[:n_t].astype(np.float64)
        frames = np.bincount(lab, weights=np.maximum(seg[:, 2] - 2, 0), minlength=n_t)[:n_t]
    p = check_observation(observation).n_params(n_t, D, k, frames, starts)
    if durations == "lognormal":
        p += 2 * n_t
    return p + n_t * (n_t - 1) + n_t - 1


def _candidates(D: int) -> list[int]:
    grid = [2, 4, 6, 8, 10, 12, 16, 20, 24, 32, 40, 48, 64, 96, 128]
    return [k for k in grid if k < D] + [D]


def choose_state_dim(
    ys: Sequence[np.ndarray],
    observation: ObservationModel = ResidualObservation(),
    candidates: Sequence[int] | None = None,
    ridge: float = 1e-6,
) -> tuple[int, list[dict[str, float]]]:
    """The state dimension ``k`` with the lowest BIC of one texton fitted on all clips.

    Args:
        ys: observation sequences ``(T_s, D)`` (each at least 3 frames).
        observation: ``PaperObservation()`` or ``ResidualObservation()`` (the full and
            tied models have ``k = D``).
        candidates: the ``k`` to try (default: 2, 4, 6, 8, 10, 12, 16, 20, 24, 32, … below
            ``D``, and ``D`` itself: no residual, the full texton).
        ridge: relative ridge of the AR(2) regression, as in :func:`fit_texton`.

    Returns:
        ``(k, table)``: one dict per candidate (``k``, ``loglik``, ``params``, ``bic``).
    """
    model = check_observation(observation)
    ys = [np.asarray(y, dtype=np.float64) for y in ys]
    if not ys or any(y.ndim != 2 or y.shape[0] < 3 for y in ys):
        raise ValueError("ys must be non-empty (T, D) arrays with T >= 3")
    D = ys[0].shape[1]
    if model.fixed_state_dim(D) is not None:
        raise ValueError(f"observation={model.name!r} has a fixed state dimension (k = D)")
    cands = _candidates(D) if candidates is None else [int(k) for k in candidates]
    if any(k < 1 or k > D for k in cands):
        raise ValueError(f"candidate state dimensions must lie in [1, {D}], got {cands}")
    allf = np.concatenate(ys)
    n = allf.shape[0]
    mu = allf.mean(axis=0)
    w, V = np.linalg.eigh((allf - mu).T @ (allf - mu))
    V = V[:, ::-1]
    w = np.maximum(w[::-1], 0.0)
    us = [y - mu for y in ys]
    # lagged frames of all clips, u_t, u_{t−1}, u_{t−2}, and their cross-products: every
    # statistic below is a block of S (or of s1) seen through C = V[:, :k] or its complement
    lag = np.concatenate([np.concatenate([u[2:], u[1:-1], u[:-2]], axis=1) for u in us])  # (N, 3D)
    N = lag.shape[0]
    S = lag.T @ lag
    s1 = lag.sum(axis=0)
    table = []
    for k in cands:
        C = V[:, :k]
        Cb = np.kron(np.eye(3), C)  # (3D, 3k): x_t, x_{t−1}, x_{t−2} from the lags
        Sx, m = Cb.T @ S @ Cb, Cb.T @ s1
        # Xp = [x_{t−1}, x_{t−2}, 1]: XpᵀXp, Xpᵀx_t and the residual E = x_t − Xp coef
        G0 = np.block([[Sx[k:, k:], m[k:, None]], [m[None, k:], np.array([[float(N)]])]])
        rhs = np.concatenate([Sx[k:, :k], m[None, :k]], axis=0)
        G = G0.copy()
        lam = ridge * np.trace(G0[:-1, :-1]) / (2 * k)
        G[:-1, :-1] += lam * np.eye(2 * k)
        coef = np.linalg.solve(G, rhs)
        EtE = Sx[:k, :k] - coef.T @ rhs - rhs.T @ coef + coef.T @ G0 @ coef
        Q = 0.5 * (EtE + EtE.T) / N + 1e-9 * np.eye(k)
        ll = -0.5 * N * (k * LOG_2PI + np.linalg.slogdet(Q)[1] + k)
        if k < D:
            ll += model.residual_loglik(w, V, S, n, N, k)
        p = n_params(1, D, k, observation)
        table.append({"k": k, "loglik": ll, "params": p, "bic": -2 * ll + p * math.log(n)})
    best = min(table, key=lambda r: r["bic"])
    return int(best["k"]), table
