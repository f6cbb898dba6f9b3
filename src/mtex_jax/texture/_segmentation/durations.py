"""Explicit segment-length distributions of textons (an extension of MT §3: the paper's
durations are flat on ``[tmin, tmax]``).

Texton ``i`` has a distribution ``p_i(ℓ)`` over the lengths ``ℓ = tmin … tmax``, stored as
``log_durations (N_t, tmax − tmin + 1)``. The default is a discretised log-normal mixed with a
little of the flat distribution, fitted in the M-step from the texton's training segments:

.. code-block:: text

    m_i = Σ_s log ℓ_s / n_i
    v_i = (Σ_s (log ℓ_s − m_i)² + κ v̄_w) / (n_i + κ),   v_i ≥ v_min
    p_i(ℓ) = (1 − ε) q_i(ℓ) / Σ_ℓ' q_i(ℓ') + ε / (tmax − tmin + 1),
    q_i(ℓ) = exp(−(log ℓ − m_i)² / (2 v_i)) / ℓ

with ``v̄_w`` the pooled within-texton variance as the shrinkage target of the spread
(``κ = 2`` pseudo-segments, so that a texton with one segment gets the typical spread around
its own length; a texton with no segment gets the mean and variance of all segments' log
lengths),
``v_min = 0.05²`` and ``ε = 0.01`` (a held-out segment of an unusual length costs at most
``log(1/ε)`` nats more than under flat durations).
"""

from __future__ import annotations

import numpy as np

__all__ = ["fit_durations", "flat_durations"]

_KAPPA = 2.0
_V_MIN = 0.05**2
_EPS = 0.01


def flat_durations(n_textons: int, tmin: int, tmax: int) -> np.ndarray:
    """The paper's flat durations: ``−log(tmax − tmin + 1)`` everywhere, ``(N_t, L)``."""
    L = tmax - tmin + 1
    return np.full((n_textons, L), -np.log(L))


def fit_durations(
    lengths: np.ndarray, labels: np.ndarray, n_textons: int, tmin: int, tmax: int
) -> np.ndarray:
    """Fit the discretised log-normal durations of every texton (see the module doc).

    Args:
        lengths: ``(n_seg,)`` segment lengths, each in ``[tmin, tmax]``.
        labels: ``(n_seg,)`` texton of each segment, in ``[0, n_textons)``.
        n_textons: ``N_t``.
        tmin: the shortest segment length.
        tmax: the longest segment length.

    Returns:
        ``log_durations (N_t, tmax − tmin + 1)``, each row a normalised log-distribution.
    """
    lengths = np.asarray(lengths, dtype=np.float64)
    labels = np.asarray(labels, dtype=np.int64)
    if lengths.shape != labels.shape or lengths.ndim != 1:
        raise ValueError(
            f"lengths and labels must be 1-D of one shape, got {lengths.shape}, {labels.shape}"
        )
    if lengths.size and (lengths.min() < tmin or lengths.max() > tmax):
        raise ValueError(f"segment lengths must lie in [{tmin}, {tmax}]")
    ell = np.arange(tmin, tmax + 1, dtype=np.float64)
    if lengths.size == 0:
        return flat_durations(n_textons, tmin, tmax)
    logs = np.log(lengths)
    m_all = float(logs.mean())
    v_all = max(float(logs.var()), _V_MIN)
    within = sum(
        float(np.sum((logs[labels == i] - logs[labels == i].mean()) ** 2))
        for i in np.unique(labels)
    )
    v_w = max(within / logs.size, _V_MIN)
    out = np.empty((n_textons, ell.size))
    for i in range(n_textons):
        li = logs[labels == i]
        n = li.size
        if n == 0:
            m, v = m_all, v_all
        else:
            m = li.mean()
            v = max((np.sum((li - m) ** 2) + _KAPPA * v_w) / (n + _KAPPA), _V_MIN)
        lq = -((np.log(ell) - m) ** 2) / (2 * v) - np.log(ell)
        q = np.exp(lq - lq.max())
        p = (1 - _EPS) * q / q.sum() + _EPS / ell.size
        out[i] = np.log(p)
    return out
