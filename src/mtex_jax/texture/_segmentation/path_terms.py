"""The per-frame terms of a texture's best path (``best_path_log_likelihood(per_frame=True)``,
design §3.1, §4.2): an exact decomposition of the segmentation's score by frame."""

from __future__ import annotations

from typing import Any

import numpy as np
from jaxtyping import Array

from .._scoring.frame_terms import frame_terms
from .._scoring.frame_terms_ref import init_terms
from .segment import Segmentation

__all__ = ["best_path_terms"]


def best_path_terms(tex: Any, y: Array, seg: Segmentation) -> np.ndarray:
    """The per-frame terms of the best path ``seg`` of ``y`` (see
    :meth:`MotionTexture.best_path_log_likelihood`): ``(T,)``, summing to ``seg.score``."""
    dyn, obs = (np.asarray(a, np.float64) for a in frame_terms(tex.textons, y))
    init = np.asarray(init_terms(tex.textons, y), np.float64)
    yn = np.asarray(y, np.float64)
    C, mu, m0, S0 = (
        np.asarray(getattr(tex.textons, f), np.float64) for f in ("C", "mu", "m0", "S0")
    )
    k = C.shape[-1]
    with np.errstate(divide="ignore"):  # a zero probability is log 0 = -inf
        log_pi = np.log(np.asarray(tex.pi, np.float64))
        log_M = np.log(np.asarray(tex.M, np.float64))
    log_d = None if tex.log_durations is None else np.asarray(tex.log_durations, np.float64)
    out = np.zeros(yn.shape[0])
    prev = -1
    for b, n, i in seg.to_list():
        t = np.arange(b, b + n)
        out[t] = obs[i, t] + np.where(t >= b + 2, dyn[i, t], 0.0)
        # log p(x_b): the marginal of the initial-state density N(m0, S0) of [x_b; x_{b+1}]
        L = np.linalg.cholesky(0.5 * (S0[i, :k, :k] + S0[i, :k, :k].T))
        z = np.linalg.solve(L, C[i].T @ (yn[b] - mu[i]) - m0[i, :k])
        first = -0.5 * (k * np.log(2 * np.pi) + 2 * np.log(np.diag(L)).sum() + z @ z)
        out[b] += first + (log_pi[i] if prev < 0 else log_M[prev, i])
        out[b + 1] += init[i, b] - first  # log p(x_{b+1} | x_b)
        if log_d is not None:
            out[b] += log_d[i, n - tex.config.tmin]
        prev = i
    return out
