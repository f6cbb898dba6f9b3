"""Bookkeeping of segment labels in EM (numpy, host side): padded stack sizes, transition
counts, pruning of under-used textons and relabelling."""

from __future__ import annotations

import jax
import numpy as np

from .._texton.texton import Texton
from .init import Segs


def capacity_for(n: int) -> int:
    return 1 << max(0, (n - 1).bit_length())


def padded_logs(M: np.ndarray, pi: np.ndarray, cap: int) -> tuple[np.ndarray, np.ndarray]:
    """log M and log π padded to ``cap`` textons with −inf (padding slots are never used)."""
    n = M.shape[0]
    with np.errstate(divide="ignore"):
        log_M = np.full((cap, cap), -np.inf)
        log_M[:n, :n] = np.log(M)
        log_pi = np.full(cap, -np.inf)
        log_pi[:n] = np.log(pi)
    return log_M, log_pi


def transition_counts(segs: Segs, n_textons: int, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    counts = np.zeros((n_textons, n_textons))
    first = np.zeros(n_textons)
    prev_seq = -1
    prev_label = -1
    for s, _, _, i in segs:
        if s != prev_seq:
            first[i] += 1
        else:
            counts[prev_label, i] += 1
        prev_seq, prev_label = s, i
    M = (counts + alpha) / (counts + alpha).sum(axis=1, keepdims=True)
    pi = (first + alpha) / (first + alpha).sum()
    return M, pi


def underused(segs: Segs, min_segments: int) -> np.ndarray:
    """Labels with fewer than ``min_segments`` segments (never all of them: the texton with
    the most segments is kept)."""
    labels, counts = np.unique(segs[:, 3], return_counts=True)
    few = counts < min_segments
    if few.all():
        few[np.argmax(counts)] = False
    return labels[few]


def keep_textons(
    tex: Texton, M: np.ndarray, pi: np.ndarray, keep: np.ndarray
) -> tuple[Texton, np.ndarray, np.ndarray]:
    """The model restricted to textons ``keep`` (``M`` rows and ``π`` renormalised)."""
    M = M[np.ix_(keep, keep)]
    return (
        take(tex, keep),
        M / M.sum(axis=1, keepdims=True),
        pi[keep] / pi[keep].sum(),
    )


def relabel(segs: Segs) -> tuple[Segs, np.ndarray]:
    """Drop unused labels: returns new segments and the old label of each new label."""
    used = np.unique(segs[:, 3])
    remap = {int(o): n for n, o in enumerate(used)}
    out = segs.copy()
    out[:, 3] = [remap[int(i)] for i in segs[:, 3]]
    return out, used


def take(tex: Texton, idx: np.ndarray) -> Texton:
    """``tex`` indexed by ``idx`` along the stack, on the host: an eager JAX gather compiles
    once per pair of stack sizes, and EM visits many."""
    return jax.tree.map(lambda a: jax.device_put(np.asarray(a)[idx]), tex)
