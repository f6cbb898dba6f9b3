"""The EM objective's segment scores: every training segment scored by its own texton only
(``rows_score``), the rows grouped into per-texton chunks (``row_chunks``)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._texton.texton import Texton
from .frame_terms import block_frames, frame_terms_impl


@eqx.filter_jit
def rows_score(
    tex: Texton, Y: Array, rows: Array, w: Array, chunks: tuple[Array, Array], width: int
) -> Array:
    """``Σ_r w_r score_{label_r}(start_r, end_r)`` over segment rows ``(seq, start, length,
    label)`` of ``Y (S, T, D)``, each segment scored by its own texton only.

    ``chunks = (labels (n,), groups (n, G))``: chunk ``c`` holds up to ``G`` rows of texton
    ``labels[c]`` (row indices, ``-1``: none; see :func:`row_chunks`). Every row is a slab of
    ``min(width, T)`` frames holding its segment (``width`` >= the longest segment, static);
    a chunk's slabs are laid end to end and their frame terms come from the E-step's blocked
    kernel (:func:`frame_terms_impl`, one texton). A segment's score is the initial term at
    its first frame plus the dynamics terms from its third frame and the observation terms
    over all its frames, as in :meth:`SegmentScorer.score`; terms that reach across two slabs
    are never used. The chunks run one after the other (``lax.map``): the work is about
    ``rows × width`` frames of one texton (plus one texton's set-up per chunk), where scoring
    every frame by every texton (the E-step's ``O(S·T·N_t)``) made the objective cost more
    than the E-step itself."""
    _, T, D = Y.shape
    W = min(int(width), T)
    labels, groups = chunks
    G = groups.shape[1]
    t = jnp.arange(W)

    def per_texton(args: tuple[Array, Array]) -> Array:
        i, g = args
        r = rows[jnp.maximum(g, 0)]
        wr = jnp.where(g >= 0, w[jnp.maximum(g, 0)], 0.0)
        s, b, n = r[:, 0], r[:, 1], r[:, 2]
        b0 = jnp.clip(b, 0, T - W)  # a slab starts at its segment unless that overruns T
        slabs = Y[s[:, None], b0[:, None] + t[None, :]].reshape(G * W, D)
        one = jax.tree.map(lambda a: jax.lax.dynamic_index_in_dim(a, i), tex)
        block = min(block_frames(None, one, slabs), G * W)
        dyn, obs, init = frame_terms_impl(one, slabs, block, with_init=True, check=False)
        dyn, obs, init = (x.reshape(G, W) for x in (dyn, obs, init))
        o = b - b0
        e = o + n - 1
        obs_sum = jnp.sum(jnp.where((t >= o[:, None]) & (t <= e[:, None]), obs, 0.0), axis=1)
        dyn_in = (t >= o[:, None] + 2) & (t <= e[:, None])
        dyn_sum = jnp.sum(jnp.where(dyn_in, dyn, 0.0), axis=1)
        vals = jnp.take_along_axis(init, o[:, None], axis=1)[:, 0] + dyn_sum + obs_sum
        return jnp.sum(jnp.where(wr > 0, vals * wr, 0.0))

    per = jax.lax.map(per_texton, (labels, groups))
    return jnp.sum(per)


CHUNK_ROWS = 8


def row_chunks(labels: np.ndarray, n_chunks: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rows grouped by label into chunks of at most ``CHUNK_ROWS``: ``(chunk labels (n,),
    row indices (n, CHUNK_ROWS))`` with ``-1`` padding, padded to ``n_chunks`` chunks (empty
    chunks of label 0). The number of chunks is ``Σ_i ⌈count_i / CHUNK_ROWS⌉``."""
    lab_out: list[int] = []
    grp_out: list[np.ndarray] = []
    for i in np.unique(labels):
        idx = np.flatnonzero(labels == i)
        for c in range(0, len(idx), CHUNK_ROWS):
            g = np.full(CHUNK_ROWS, -1, dtype=np.int64)
            part = idx[c : c + CHUNK_ROWS]
            g[: len(part)] = part
            lab_out.append(int(i))
            grp_out.append(g)
    n = len(lab_out) if n_chunks is None else n_chunks
    lab = np.zeros(n, dtype=np.int64)
    grp = np.full((n, CHUNK_ROWS), -1, dtype=np.int64)
    lab[: len(lab_out)] = lab_out
    if grp_out:
        grp[: len(grp_out)] = np.stack(grp_out)
    return lab, grp
