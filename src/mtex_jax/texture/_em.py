"""The M-step building blocks of learning (MT §4.1): fitting every texton from its segments,
transition counts, and pruning of under-used textons."""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ._fit import _texton_from_stats_impl
from ._init import Segs
from ._scores import _segment_scores_impl
from ._stats import _dynamics_stats_impl, _frame_stats_impl, _subspace_impl
from ._texton import Texton


# ---------------------------------------------------------------------------------------------
# M-step
# ---------------------------------------------------------------------------------------------
def _pad(ys: Sequence[np.ndarray], n_seq: int) -> tuple[np.ndarray, np.ndarray]:
    T = max(y.shape[0] for y in ys)
    D = ys[0].shape[1]
    out = np.zeros((n_seq, T, D), dtype=ys[0].dtype)
    nf = np.zeros(n_seq, dtype=np.int64)
    for i, y in enumerate(ys):
        out[i, : y.shape[0]] = y
        nf[i] = y.shape[0]
    for i in range(len(ys), n_seq):  # dummy sequences (device padding): copies of the first
        out[i] = out[0]
        nf[i] = nf[0]
    return out, nf


def _masks(segs: Segs, n_seq: int, T: int) -> tuple[np.ndarray, np.ndarray]:
    lab = np.full((n_seq, T), -1, dtype=np.int32)
    sid = np.full((n_seq, T), -1, dtype=np.int32)
    for k, (s, b, length, i) in enumerate(segs):
        lab[s, b : b + length] = i
        sid[s, b : b + length] = k
    return lab, sid


def _fit_all_impl(
    Y: Array, rows: Array, valid: Array, n_tex: int, width: int, k: int, floor: float, opts
) -> Texton:
    """M-step: fit every texton on all of its segments (SPEC §2), from per-segment statistics.

    Each segment (row ``(seq, start, length, label)``) is gathered into a ``(width, D)`` slab;
    pass-1 statistics are computed per segment and summed per texton (``segment_sum``), the
    subspaces solved, pass-2 statistics computed per segment in its texton's subspace and
    summed again. The work is ``O(total frames)``, not ``O(N_t × frames)``.
    """
    T = Y.shape[1]
    n = rows.shape[0]
    seq, start, length, lab = rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3]
    off = jnp.arange(width)
    inside = (off[None, :] < length[:, None]) & valid[:, None]
    G = Y[seq[:, None], jnp.clip(start[:, None] + off[None, :], 0, T - 1)]  # (n, W, D)
    ids = jnp.where(inside, jnp.arange(n)[:, None], -1)
    bucket = jnp.where(valid, lab, n_tex)  # invalid rows go to a discarded bucket

    def per_texton(x: Array) -> Array:
        return jax.ops.segment_sum(x, bucket, num_segments=n_tex + 1)[:n_tex]

    fs = jax.tree.map(per_texton, jax.vmap(_frame_stats_impl)(G, ids))
    # The eigen-decompositions and Cholesky factorisations run one texton at a time
    # (lax.map): batched LAPACK calls in jaxlib's CPU runtime split their batch over the
    # intra-op thread pool and two of them running concurrently can deadlock a 2-core pool.
    sub = jax.lax.map(lambda f: _subspace_impl(f, k, floor), fs)
    sub_seg = jax.tree.map(lambda a: a[jnp.clip(lab, 0, n_tex - 1)], sub)
    ds = jax.vmap(_dynamics_stats_impl)(G, ids, sub_seg)
    ds = jax.tree.map(per_texton, ds)
    return jax.lax.map(lambda a: _texton_from_stats_impl(a[0], a[1], opts), (sub, ds))


_fit_all = eqx.filter_jit(_fit_all_impl)


@eqx.filter_jit
def _rows_score(tex: Texton, Y: Array, rows: Array, w: Array) -> Array:
    """Σ_r w_r score_{label_r}(start_r, end_r) over segment rows (seq, start, length, label)."""
    sc = jax.vmap(lambda y: _segment_scores_impl(tex, y))(Y)  # arrays (S, N, T[+1])
    T = Y.shape[1]
    s, i = rows[:, 0], rows[:, 3]
    b = rows[:, 1]
    e = rows[:, 1] + rows[:, 2] - 1
    dyn = (
        sc.cum_dyn[s, i, e + 1]
        - sc.cum_dyn[s, i, jnp.minimum(b + 2, T)]
        + (e - b - 1).astype(Y.dtype) * sc.dyn_offset[s, i]
    )
    obs = (
        sc.cum_obs[s, i, e + 1]
        - sc.cum_obs[s, i, b]
        + (e - b + 1).astype(Y.dtype) * sc.obs_offset[s, i]
    )
    vals = sc.init[s, i, b] + dyn + obs
    return jnp.sum(jnp.where(w > 0, vals, 0.0) * w)


def _capacity(n: int) -> int:
    return 1 << max(0, (n - 1).bit_length())


def _padded_logs(M: np.ndarray, pi: np.ndarray, cap: int) -> tuple[np.ndarray, np.ndarray]:
    """log M and log π padded to ``cap`` textons with −inf (padding slots are never used)."""
    n = M.shape[0]
    with np.errstate(divide="ignore"):
        log_M = np.full((cap, cap), -np.inf)
        log_M[:n, :n] = np.log(M)
        log_pi = np.full(cap, -np.inf)
        log_pi[:n] = np.log(pi)
    return log_M, log_pi


def _transitions(segs: Segs, n_textons: int, alpha: float) -> tuple[np.ndarray, np.ndarray]:
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


def _underused(segs: Segs, min_segments: int) -> np.ndarray:
    """Labels with fewer than ``min_segments`` segments (never all of them: the texton with
    the most segments is kept)."""
    labels, counts = np.unique(segs[:, 3], return_counts=True)
    few = counts < min_segments
    if few.all():
        few[np.argmax(counts)] = False
    return labels[few]


def _keep_textons(
    tex: Texton, M: np.ndarray, pi: np.ndarray, keep: np.ndarray
) -> tuple[Texton, np.ndarray, np.ndarray]:
    """The model restricted to textons ``keep`` (``M`` rows and ``π`` renormalised)."""
    M = M[np.ix_(keep, keep)]
    return (
        jax.tree.map(lambda a: a[keep], tex),
        M / M.sum(axis=1, keepdims=True),
        pi[keep] / pi[keep].sum(),
    )


def _relabel(segs: Segs) -> tuple[Segs, np.ndarray]:
    """Drop unused labels: returns new segments and the old label of each new label."""
    used = np.unique(segs[:, 3])
    remap = {int(o): n for n, o in enumerate(used)}
    out = segs.copy()
    out[:, 3] = [remap[int(i)] for i in segs[:, 3]]
    return out, used
