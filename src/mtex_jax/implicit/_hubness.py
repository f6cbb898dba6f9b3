"""Hubness of the database windows: each example's mean squared distance to its nearest
neighbours, for the cross-domain similarity local scaling (CSLS) of the synthesis kernel.

In model coordinates a window has ``W = d·P`` numbers (about a thousand), and in so many
dimensions the nearest database window of a probe is barely nearer than a random one. The
examples near the database mean — slow, near-neutral motion — are then the nearest neighbours of
far more probes than their share (*hubs*; Radovanović et al., JMLR 2010): a kernel sampler that
picks near neighbours picks slow motion too often, and the synthesised figure moves more slowly
than the real one. CSLS (Conneau et al., ICLR 2018) removes the hubs' advantage by scoring an
example by its distance minus half its own neighbourhood radius,

    s(Φ, Ψ_i) = ‖Ψ_i − Φ‖² − ½ r_i,    r_i = (1/k) Σ_{j ∈ kNN(i)} ‖Ψ_i − Ψ_j‖²

(with unit-norm vectors this is the published ``2 cos − r``), so an example in a dense region
(small ``r_i``) must be correspondingly nearer to be chosen. The neighbours ``kNN(i)`` exclude
the windows of the same clip within ``d`` frames (overlapping windows of one take).

The synthesis uses ``s = ‖Ψ_i − Φ‖² − h r_i`` with a weight ``h``
(``SynthesisConfig.hubness``). ``r_i`` is heavy-tailed (isolated, unusual windows have radii
many times the median), so the full CSLS weight ``h = ½`` also favours poor matches and the
transitions get rough; the default ``h = 0.2`` was chosen on validation folds of the
training clips (design §7.5; the folds' figures are on the documentation's results page).
"""

from __future__ import annotations

import numpy as np

__all__ = ["neighbour_radius"]

_BLOCK = 512  # rows per distance block: 512 × n distances in memory at once


def neighbour_radius(
    windows: np.ndarray,
    clip_index: np.ndarray,
    frame_index: np.ndarray,
    window: int,
    k: int = 10,
) -> np.ndarray:
    """Mean squared distance ``r_i`` from each window to its ``k`` nearest database windows.

    Windows of the same clip whose newest frames are at most ``window`` frames apart are not
    neighbours (they overlap). Exact, ``O(n² W)`` in blocks of rows (BLAS), once at learning.

    Args:
        windows: ``(n, W)`` windows in model coordinates.
        clip_index: ``(n,)`` clip of each window.
        frame_index: ``(n,)`` newest frame of each window in its clip.
        window: ``d``, the exclusion radius in frames.
        k: neighbours averaged (fewer if fewer are admissible; ``0`` where none is).

    Returns:
        ``(n,)`` float64 ``r_i ≥ 0``.
    """
    x = np.asarray(windows, dtype=np.float32)  # d² ~ W: float32 rounding is negligible
    n = x.shape[0]
    clip = np.asarray(clip_index, dtype=np.int64)
    frame = np.asarray(frame_index, dtype=np.int64)
    sq = np.einsum("ij,ij->i", x, x)
    out = np.zeros(n)
    for s in range(0, n, _BLOCK):
        e = min(s + _BLOCK, n)
        d2 = (sq[s:e, None] + sq[None, :] - 2.0 * (x[s:e] @ x.T)).astype(np.float64)
        near = (clip[s:e, None] == clip[None, :]) & (
            np.abs(frame[s:e, None] - frame[None, :]) <= window
        )
        d2[near] = np.inf
        kk = min(k, n - 1)
        if kk < 1:
            continue
        part = np.partition(d2, kk - 1, axis=1)[:, :kk]
        fin = np.isfinite(part)
        cnt = fin.sum(axis=1)
        tot = np.where(fin, np.maximum(part, 0.0), 0.0).sum(axis=1)
        out[s:e] = np.where(cnt > 0, tot / np.maximum(cnt, 1), 0.0)
    return out
