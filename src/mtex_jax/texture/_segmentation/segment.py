"""Segmentation E-step: the semi-Markov Viterbi of design §4 as one ``lax.scan`` over frames.

With segment scores ``score_i(b, e)`` (design §3, O(1) from prefix sums), lengths
``tmin ≤ e − b + 1 ≤ tmax``, transition log-probabilities ``log M[l, i]`` and initial
log-probabilities ``log π[i]``:

.. code-block:: text

    V(e, i) = max_b [ score_i(b, e) + (b = 0 ? log π_i : H(b − 1, i)) ]
    H(t, i) = max_l V(t, l) + log M[l, i]
    answer  = max_i V(T − 1, i)

The segment score splits into a part that depends on the end only and a part that depends on
the start only, ``score_i(b, e) = A_i(e) + B⁰_i(b)`` (the prefix-sum differences), so with
``B_i(b) = B⁰_i(b) + (b = 0 ? log π_i : H(b − 1, i))`` the recursion is a sliding-window
maximum:

.. code-block:: text

    V(e, i) = A_i(e) + max_{e − tmax + 1 ≤ b ≤ e − tmin + 1} B_i(b)

``V(e)`` needs ``B(b)`` only for ``b ≤ e − tmin + 1``, and ``B(b)`` needs ``V(b − 1)``, so ``tmin``
consecutive ends are independent of each other: the ``lax.scan`` (``recursion.py``, shared with
the forward algorithm over another semiring) runs over blocks of ``tmin`` frames, each block one
windowed maximum (``lax.reduce_window``) over the buffer of the last
``tmax`` values of ``B`` and one max-plus product with ``log M``. Cost
``O(T·(tmax − tmin + 1)·N_t + T·N_t²)``; no back-pointer tables are stored: the arg-maxima along
the optimal path are recomputed from ``V (T, N_t)`` while back-tracking. ``tmax=None`` uses a
window as long as the sequence: the paper's exact, unbounded ``O(N_t T²)`` dynamic program.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float, Int

from ...core import as_array, bucket_length, cut_frames, pad_frames
from .._scoring.frame_terms import frame_coefs
from .._scoring.packing import packed_scores_impl
from .._scoring.scores import SegmentScorer, batch_scores_impl, segment_scores
from .._texton.checks import check_obs
from .._texton.texton import Texton
from .recursion import MaxPlus, semi_markov_values

__all__ = ["Segmentation", "segment", "segment_scorer", "viterbi_segments"]


class Segmentation(eqx.Module):
    """A segmentation of one sequence (or a batch of them, with a leading axis).

    Segments are stored in time order and padded to a fixed number of slots, so the shapes are
    static; slots beyond ``n_segments`` hold ``-1``.

    Attributes:
        starts: ``(K,)`` first frame of each segment.
        lengths: ``(K,)`` number of frames of each segment.
        labels: ``(K,)`` texton index of each segment.
        n_segments: number of valid slots.
        score: total log-likelihood ``max_i V(T − 1, i)`` (``−inf`` if no segmentation fits).
    """

    starts: Int[Array, "*batch K"]
    lengths: Int[Array, "*batch K"]
    labels: Int[Array, "*batch K"]
    n_segments: Int[Array, "*batch"]
    score: Float[Array, "*batch"]

    def __check_init__(self) -> None:
        s = np.shape(self.starts)
        for name in ("lengths", "labels"):
            if np.shape(getattr(self, name)) != s:
                raise ValueError(
                    f"Segmentation.{name} has shape {np.shape(getattr(self, name))}, expected {s}"
                )

    def to_list(self) -> list[tuple[int, int, int]]:
        """``[(start, length, label), ...]`` of one (unbatched) segmentation."""
        if np.ndim(self.starts) != 1:
            raise ValueError("to_list() needs an unbatched Segmentation; index the batch first")
        n = int(self.n_segments)
        st, ln, lb = (np.asarray(a)[:n] for a in (self.starts, self.lengths, self.labels))
        return [(int(a), int(b), int(c)) for a, b, c in zip(st, ln, lb, strict=True)]

    def frame_labels(self, n_frames: int) -> np.ndarray:
        """Per-frame texton label ``(n_frames,)`` (``-1`` where no segment covers a frame)."""
        out = np.full(n_frames, -1, dtype=np.int64)
        for b, length, i in self.to_list():
            out[b : b + length] = i
        return out

    def __getitem__(self, k: int) -> Segmentation:
        """The ``k``-th segmentation of a batch."""
        return jax.tree.map(lambda a: a[k], self)


def segment_scorer(textons: Texton, Y: ArrayLike) -> SegmentScorer:
    """Prefix sums of all textons' per-frame terms on ``Y`` (see :func:`segment_scores`)."""
    return segment_scores(textons, Y)


def check_lengths(tmin: int, tmax: int | None, T: int) -> tuple[int, int]:
    if not isinstance(tmin, int | np.integer) or tmin < 3:
        raise ValueError(
            f"tmin must be an integer >= 3 (a texton needs two initial frames), got {tmin!r}"
        )
    if tmax is None:
        tmax = T
    if not isinstance(tmax, int | np.integer) or tmax < tmin:
        raise ValueError(f"tmax must be an integer >= tmin = {tmin}, got {tmax!r}")
    return int(tmin), int(tmax)


def check_dp_inputs(
    textons: Texton, log_M: ArrayLike, log_pi: ArrayLike, T: int, tmin: int, tmax: int | None
) -> tuple[int, int, Array, Array]:
    """The checks shared by the Viterbi and forward entry points: lengths, and the shapes of
    ``log_M (N_t, N_t)`` and ``log_pi (N_t,)``."""
    tmin, tmax = check_lengths(tmin, tmax, T)
    n_t = textons.n_textons if textons.is_stacked else 1
    log_M = jnp.asarray(log_M)
    log_pi = jnp.asarray(log_pi)
    if log_M.shape != (n_t, n_t):
        raise ValueError(f"log_M must have shape ({n_t}, {n_t}), got {log_M.shape}")
    if log_pi.shape != (n_t,):
        raise ValueError(f"log_pi must have shape ({n_t},), got {log_pi.shape}")
    return tmin, tmax, log_M, log_pi


@eqx.filter_jit
def viterbi_segments(
    scorer: SegmentScorer,
    log_M: Float[Array, "n n"],
    log_pi: Float[Array, " n"],
    n_valid: Int[Array, ""],
    tmin: int,
    tmax: int,
    log_durations: Float[Array, "n L"] | None = None,
) -> Segmentation:
    """Globally optimal segmentation of the first ``n_valid`` frames (design §4).

    With duration log-probabilities the segment score becomes
    ``score_i(b, e) + log p_i(e − b + 1)``; the windowed maximum is then a max-plus product
    of the buffer window with the reversed duration row (``O(P·(tmax − tmin + 1)·N_t)`` per
    block, as before).

    Args:
        scorer: prefix sums of the textons' per-frame terms over ``T`` (padded) frames.
        log_M: ``(N_t, N_t)`` log transition matrix, ``log_M[l, i] = log P(i | l)``.
        log_pi: ``(N_t,)`` log initial distribution.
        n_valid: number of real frames ``T_s ≤ T`` (the rest is padding and ignored).
        tmin: shortest segment length (static), ``3 ≤ tmin ≤ tmax``.
        tmax: longest segment length (static).
        log_durations: ``(N_t, tmax − tmin + 1)`` log-probabilities of the lengths
            ``tmin … tmax`` per texton, or ``None`` (flat: the paper).

    Returns:
        the :class:`Segmentation` with ``K = T // tmin + 1`` slots.
    """
    n_t, T = scorer.init.shape
    dtype = scorer.cum_dyn.dtype
    neg = jnp.asarray(-jnp.inf, dtype)
    n_valid = jnp.asarray(n_valid)
    log_M = jnp.asarray(log_M, dtype)
    log_pi = jnp.asarray(log_pi, dtype)
    Wn = tmax - tmin + 1  # candidate starts per end
    sr = MaxPlus(log_M, log_durations, tmin, tmax, n_t, dtype)
    bbuf, V = semi_markov_values(scorer, log_pi, sr)
    last = n_valid - 1
    v_last = V[last]
    i_last = jnp.argmax(v_last).astype(jnp.int32)
    score = v_last[i_last]
    K = T // tmin + 1
    r = jnp.arange(tmax)
    if sr.dur_rev is not None:  # (tmax, N): row r = length tmax − r (−inf past tmin)
        dur_col = jnp.concatenate([sr.dur_rev, jnp.full((tmax - Wn, n_t), neg, dtype)], axis=0)

    def back(carry, _):
        # recompute the arg-maxima along the optimal path only (no back-pointer tables)
        e, i, done = carry
        col = jax.lax.dynamic_slice(bbuf[:, i], (e + 1,), (tmax,))  # b = e − tmax + 1 + r
        if log_durations is not None:  # length tmax − r
            col = col + dur_col[:, i]
        col = jnp.where(r <= tmax - tmin, col, neg)
        rb = jnp.argmax(col)
        b = e - tmax + 1 + rb
        length = e - b + 1
        out = (jnp.where(done, -1, b), jnp.where(done, -1, length), jnp.where(done, -1, i))
        finished = done | (b <= 0)
        prev_i = jnp.argmax(V[jnp.maximum(b - 1, 0)] + log_M[:, i]).astype(jnp.int32)
        nxt = (jnp.where(finished, e, b - 1), jnp.where(finished, i, prev_i), finished)
        return nxt, out

    feasible = jnp.isfinite(score)
    _, (bs, ls, lbs) = jax.lax.scan(back, (last, i_last, ~feasible), None, length=K)
    n_seg = jnp.sum(bs >= 0).astype(jnp.int32)
    # reverse the filled prefix into time order
    idx = jnp.clip(n_seg - 1 - jnp.arange(K), 0, K - 1)
    keep = jnp.arange(K) < n_seg
    starts = jnp.where(keep, bs[idx], -1)
    lengths = jnp.where(keep, ls[idx], -1)
    labels = jnp.where(keep, lbs[idx], -1)
    return Segmentation(starts, lengths, labels, n_seg, score)


def segment(
    textons: Texton,
    log_M: Float[ArrayLike, "n n"],
    log_pi: Float[ArrayLike, " n"],
    Y: Float[ArrayLike, "*S T D"],
    tmin: int,
    tmax: int | None = None,
    *,
    n_frames: Int[ArrayLike, "*S"] | None = None,
    log_durations: Float[ArrayLike, "n L"] | None = None,
) -> Segmentation:
    """Optimal segmentation and labelling of ``Y`` by the textons (semi-Markov Viterbi).

    Args:
        textons: stacked textons (``N_t`` on the leading axis).
        log_M: ``(N_t, N_t)`` log transition matrix (rows: from, columns: to).
        log_pi: ``(N_t,)`` log initial distribution.
        Y: ``(T, D)`` one sequence, or ``(S, T, D)`` sequences padded to a common ``T``.
        tmin: shortest segment (frames, ``>= 3``).
        tmax: longest segment; ``None`` runs the unbounded (paper-exact) DP.
        n_frames: with batched ``Y``, the real length of each sequence ``(S,)``; default all
            ``T``.
        log_durations: ``(N_t, tmax − tmin + 1)`` per-texton log-probabilities of the segment
            lengths ``tmin … tmax`` (needs a finite ``tmax``); ``None``: flat (the paper).

    Returns:
        a :class:`Segmentation` (batched with a leading ``S`` for batched input).

    Raises:
        ValueError: bad shapes, ``tmin < 3``, ``tmax < tmin``, a sequence shorter than
            ``tmin``, non-finite ``Y``.
    """
    Y = as_array(Y)
    if Y.ndim not in (2, 3):
        raise ValueError(f"Y must have shape (T, D) or (S, T, D), got {Y.shape}")
    batched = Y.ndim == 3
    T = Y.shape[-2]
    tmax_given = tmax
    tmin, tmax, log_M, log_pi = check_dp_inputs(textons, log_M, log_pi, T, tmin, tmax)
    log_d = _check_durations(log_durations, textons, tmin, tmax_given)
    if not batched:
        if T < tmin:
            raise ValueError(f"sequence has {T} frames, shorter than tmin = {tmin}")
        # padded to a shape bucket (design §11): one program per bucket, not per length
        Tb = bucket_length(T)
        if tmax_given is None:
            tmax = Tb
        check_obs("Y", Y, textons.obs_dim, min_len=2)
        n_valid = jax.device_put(np.asarray(T))
        traced = isinstance(Y, Tracer)  # a concrete Y was checked: no callback
        Yp = pad_frames(Y, Tb)
        seg = _padded_segment(textons, log_M, log_pi, Yp, n_valid, tmin, tmax, log_d, traced)
        K = T // tmin + 1  # the slots of the unpadded sequence
        return Segmentation(
            starts=cut_frames(seg.starts, K),
            lengths=cut_frames(seg.lengths, K),
            labels=cut_frames(seg.labels, K),
            n_segments=seg.n_segments,
            score=seg.score,
        )
    S = Y.shape[0]
    nf = np.full(S, T) if n_frames is None else np.asarray(n_frames)
    if nf.shape != (S,):
        raise ValueError(f"n_frames must have shape ({S},), got {nf.shape}")
    if np.any(nf < tmin) or np.any(nf > T):
        k = int(np.nonzero((nf < tmin) | (nf > T))[0][0])
        raise ValueError(
            f"sequence {k} has {int(nf[k])} frames; need tmin = {tmin} <= n_frames <= T = {T}"
        )
    return segment_batch(textons, log_M, log_pi, Y, jnp.asarray(nf), tmin, tmax, log_d)[0]


@eqx.filter_jit
def _padded_segment(
    textons: Texton,
    log_M: Array,
    log_pi: Array,
    Y: Array,
    n_valid: Array,
    tmin: int,
    tmax: int,
    log_durations: Array | None,
    check: bool = False,
) -> Segmentation:
    # the frame terms and the Viterbi recursion as one program per shape bucket (no NaN/inf
    # check inside for a Y checked eagerly: a host callback keeps a program out of the cache)
    scorer = segment_scores(textons, Y, check=check)
    return viterbi_segments(scorer, log_M, log_pi, n_valid, tmin, tmax, log_durations)


def _check_durations(
    log_durations: ArrayLike | None, textons: Texton, tmin: int, tmax: int | None
) -> Array | None:
    """``log_durations`` as an array of shape ``(N_t, tmax − tmin + 1)``, or ``None``."""
    if log_durations is None:
        return None
    if tmax is None:
        raise ValueError("log_durations need a finite tmax (lengths tmin … tmax)")
    n_t = textons.n_textons if textons.is_stacked else 1
    a = jnp.asarray(log_durations)
    shape = (n_t, tmax - tmin + 1)
    if a.shape != shape:
        raise ValueError(
            f"log_durations must have shape {shape} (textons, lengths {tmin}..{tmax}), "
            f"got {a.shape}"
        )
    if bool(jnp.any(jnp.isnan(a))) or bool(jnp.any(a == jnp.inf)):
        raise ValueError("log_durations must not contain NaN or +inf")
    return a


@eqx.filter_jit
def segment_batch(
    textons,
    log_M,
    log_pi,
    Y,
    nf,
    tmin: int,
    tmax: int,
    log_durations=None,
    packing=None,
    old=None,
    n_active=None,
    check: bool = True,
) -> tuple[Segmentation, Array]:
    """Segmentations of the clips ``Y (S, T, D)`` of ``nf (S,)`` frames, and ``(S,)`` sums of
    the scores of the segments ``old`` from the same segment scores (0 without ``old``).

    ``old``: ``(starts, lengths, labels)``, each ``(S, K)`` (length 0: no segment), segments
    of the clips.

    ``packing`` (a :class:`~._packing.Packing` of ``nf``): the clips go in its batches of ``c``
    clips, in sequence (``lax.map``), each batch's frame terms computed on its real frames
    only (no padding), so that memory holds the ``(N_t, T)`` score arrays and the DP's
    per-block temporaries (``(tmin, N_t, N_t)`` for the transitions, ``(tmin, tmax − tmin + 1,
    N_t)`` for the durations) of ``c`` clips only. ``None``: all clips at once, laid end to end
    with their padding (data sharded over devices along the clips).

    ``n_active`` (with ``packing``; a traced count): the textons past the first ``n_active``
    are padding that the transitions never enter (``log π``, ``log M`` columns ``−inf``);
    their frame terms are skipped where the kernel allows (full-dimensional textons).

    ``check=False`` (static): no in-program NaN/inf check of ``Y`` (a host callback keeps a
    program out of the persistent compilation cache), for callers that checked ``Y``
    eagerly, as :func:`~mtex_jax.texture.learn` does with its clips."""
    if not textons.is_stacked:
        textons = jax.tree.map(lambda a: a[None], textons)

    def one(sc, n):
        return viterbi_segments(sc, log_M, log_pi, n, tmin, tmax, log_durations)

    def old_sum(sc: SegmentScorer, st: Array, ln: Array, lb: Array) -> Array:
        s = sc._score(st, st + ln - 1, lb)
        return jnp.sum(jnp.where(ln > 0, s, 0.0))

    if packing is None:
        sc = batch_scores_impl(textons, Y, check)
        seg = jax.vmap(one)(sc, nf)
        if old is None:
            return seg, jnp.zeros(nf.shape, Y.dtype)
        return seg, jax.vmap(old_sum)(sc, *old)
    S, T, D = Y.shape
    Yflat = Y.reshape(S * T, D)
    # the textons' constants once for all batches, for frames centred by the clips' mean
    ybar = jnp.sum(Yflat, axis=0) / jnp.maximum(jnp.sum(nf), 1).astype(Y.dtype)
    coefs = frame_coefs(textons, ybar, with_init=True)

    def batch(args: tuple[Array, ...]) -> tuple[Segmentation, Array]:
        frames, where, n, clip = args
        n = n.astype(nf.dtype)
        sc = packed_scores_impl(textons, Yflat, frames, where, n, coefs, n_active, check)
        seg = jax.vmap(one)(sc, n)
        if old is None:
            return seg, jnp.zeros(clip.shape, Y.dtype)
        st, ln, lb = (a[jnp.maximum(clip, 0)] for a in old)
        return seg, jax.vmap(old_sum)(sc, st, jnp.where(clip[:, None] >= 0, ln, 0), lb)

    out = jax.lax.map(batch, (packing.frames, packing.where, packing.n, packing.clip))
    return jax.tree.map(lambda a: a.reshape(-1, *a.shape[2:])[packing.order], out)
