"""Clips packed end to end for the learner's E-step: the frame terms of a batch of clips on
their real frames only, not on the padding that brings every clip to the longest one.

The learner holds its clips zero-padded to ``(S, T, D)``. On the 51 salsa clips of the scale
benchmark (49,708 frames, the longest 1,284) the padded layout has 65,484 frames: 32 % of the
frame terms' work was spent on padding. :func:`pack_clips` groups the clips into batches of
``c`` clips with nearly equal frame totals (longest first, each into the lightest batch with a
free slot) and lays each batch's real frames end to end in ``P`` frames (the largest total,
rounded up to a multiple of 16); :func:`packed_scores_impl` computes the frame terms of one
batch on those ``P`` frames and gathers them back to the per-clip ``(c, N_t, T)`` layout of the
segment scores.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int

from .._texton.texton import Texton
from .frame_terms import block_frames, frame_terms_impl, has_residual
from .scores import SegmentScorer, scorer_from_terms


class Packing(eqx.Module):
    """Where the real frames of ``S`` padded clips ``(S, T, D)`` go in ``n_b`` batches of ``c``
    packed clips (from :func:`pack_clips`).

    Attributes:
        frames: ``(n_b, P)`` index into the flattened frames ``Y.reshape(S·T, D)`` of each
            packed frame (past a batch's total: a copy of its first frame).
        where: ``(n_b, c, T)`` packed position of frame ``t`` of each slot's clip (0 past its
            end).
        n: ``(n_b, c)`` frames of each slot's clip (an empty slot holds a stand-in of
            ``min(P, T)`` packed frames, whose segmentation is dropped).
        clip: ``(n_b, c)`` clip of each slot (``−1``: empty).
        order: ``(S,)`` slot ``b·c + j`` of each clip.
    """

    frames: Int[Array, "nb P"]
    where: Int[Array, "nb c T"]
    n: Int[Array, "nb c"]
    clip: Int[Array, "nb c"]
    order: Int[Array, " S"]


def pack_clips(n_frames: np.ndarray, T: int, clip_batch: int) -> Packing:
    """The packing of clips of ``n_frames`` real frames (each ``<= T``) in batches of
    ``clip_batch`` clips; see the module notes."""
    nf = np.asarray(n_frames, dtype=np.int64)
    S, c = nf.size, int(clip_batch)
    if S == 0 or c < 1 or np.any(nf < 1) or np.any(nf > T):
        raise ValueError(f"pack_clips: need 1 <= n_frames <= T = {T} and clip_batch >= 1")
    n_b = -(-S // c)
    members: list[list[int]] = [[] for _ in range(n_b)]
    totals = np.zeros(n_b, dtype=np.int64)
    for s in np.argsort(-nf, kind="stable"):  # longest first, into the lightest open batch
        open_ = [b for b in range(n_b) if len(members[b]) < c]
        b = min(open_, key=lambda i: (totals[i], i))
        members[b].append(int(s))
        totals[b] += nf[s]
    P = int(-(-totals.max() // 16) * 16)
    frames = np.zeros((n_b, P), dtype=np.int64)
    where = np.zeros((n_b, c, T), dtype=np.int64)
    n = np.zeros((n_b, c), dtype=np.int64)
    clip = np.full((n_b, c), -1, dtype=np.int64)
    order = np.zeros(S, dtype=np.int64)
    t = np.arange(T)
    for b, clips in enumerate(members):
        pos = 0
        for j, s in enumerate(sorted(clips)):
            L = int(nf[s])
            frames[b, pos : pos + L] = s * T + np.arange(L)
            where[b, j] = np.where(t < L, pos + t, 0)
            n[b, j] = L
            clip[b, j] = s
            order[s] = b * c + j
            pos += L
        frames[b, pos:] = frames[b, 0]
        for j in range(len(clips), c):  # an empty slot: the batch's first frames
            L = min(P, T)
            where[b, j] = np.where(t < L, t, 0)
            n[b, j] = L
    return Packing(
        frames=jnp.asarray(frames, dtype=jnp.int32),
        where=jnp.asarray(where, dtype=jnp.int32),
        n=jnp.asarray(n, dtype=jnp.int32),
        clip=jnp.asarray(clip, dtype=jnp.int32),
        order=jnp.asarray(order, dtype=jnp.int32),
    )


def packed_scores_impl(
    textons: Texton,
    Yflat: Array,
    frames: Array,
    where: Array,
    n: Array,
    coefs: tuple[Array, dict[str, Array], dict[str, Array] | None] | None = None,
    n_active: Array | None = None,
    check: bool = True,
) -> SegmentScorer:
    """The :class:`SegmentScorer` of each clip of one packed batch (leading axis ``c``), equal
    to the per-clip :func:`segment_scores` to rounding on every segment of the clip.

    Terms that reach across two clips of the batch (``dyn`` at a clip's frames 0 and 1,
    ``init`` at its last frame) are never part of a segment score; they are set to the values
    the per-clip kernel gives them (0 and ``−inf``), and the terms past a clip's end to 0
    (``init``: ``−inf``). ``coefs``: the textons' :func:`frame_coefs` (``with_init=True``),
    computed once for all batches (default: from this batch's frames). ``n_active``: only
    the first ``n_active`` textons' scores are needed (the others' are not computed for
    full-dimensional textons: see :func:`frame_terms_impl`). ``check=False``: no in-program
    NaN/inf check of ``Yflat`` (see :func:`~.scores.batch_scores_impl`).
    """
    Yb = Yflat[frames]  # (P, D): the batch's real frames end to end
    P = Yb.shape[0]
    block = block_frames(None, textons, Yb)
    dyn, obs, init = frame_terms_impl(
        textons, Yb, min(block, P), with_init=True, coefs=coefs, n_active=n_active, check=check
    )
    T = where.shape[-1]
    t = jnp.arange(T)

    def per_clip(a: Array, fill: float, last: Array) -> Array:  # (N, P) -> (c, N, T)
        g = jnp.moveaxis(a[:, where], 1, 0)
        return jnp.where(last[:, None, :], fill, g)

    past = t[None, :] >= n[:, None]  # (c, T)
    dyn = per_clip(dyn, 0.0, past | (t[None, :] < 2))
    obs = per_clip(obs, 0.0, past) if has_residual(textons, Yb) else None
    init = per_clip(init, -jnp.inf, t[None, :] >= n[:, None] - 1)
    return jax.vmap(scorer_from_terms)(dyn, obs, init)
