"""Hard EM of learning (MT §4.1): the M-step building blocks (fitting every texton from its
segments, transition counts, pruning of under-used textons), the padded and sharded data with
the jitted M- and E-steps (``_Runner``), and the EM loop (``_em``)."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..motion import FeatureMap
from ._config import LearnConfig
from ._durations import fit_durations
from ._fit import _SolveOptions
from ._init import Segs
from ._labels import (
    _capacity,
    _keep_textons,
    _padded_logs,
    _relabel,
    _take,
    _transitions,
    _underused,
)
from ._model import MotionTexture
from ._mstep import _fit_all
from ._packing import pack_clips
from ._rows import _CHUNK_ROWS, _row_chunks, _rows_score
from ._segment import _segment_batch
from ._texton import Texton


# ---------------------------------------------------------------------------------------------
# M-step
# ---------------------------------------------------------------------------------------------
def _pad(
    ys: Sequence[np.ndarray], n_seq: int, T: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The sequences zero-padded to ``T`` frames (default: the longest), ``(n_seq, T, D)``,
    and their lengths."""
    width = max(y.shape[0] for y in ys) if T is None else T
    D = ys[0].shape[1]
    out = np.zeros((n_seq, width, D), dtype=ys[0].dtype)
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


# ---------------------------------------------------------------------------------------------
# EM
# ---------------------------------------------------------------------------------------------
_PAD_E_STEP = 16
_CLIP_BATCH = 4  # clips per batch of the E-step (memory: see _segment_batch)


class _Runner:
    """Padded, optionally sharded data and the jitted M- and E-steps."""

    def __init__(
        self,
        ys: list[np.ndarray],
        config: LearnConfig,
        devices: Sequence[Any] | None = None,
        T: int | None = None,
    ) -> None:
        """``ys`` padded to ``T`` frames (default: the longest) and put on ``devices``
        (default: all of JAX's, sharded as ``config.shard`` says)."""
        self.ys = ys
        self.config = config
        self.n_real = len(ys)
        self.n_frames = sum(y.shape[0] for y in ys)  # frames of all clips (every process's)
        devices = jax.devices() if devices is None else devices
        shard = config.shard
        if shard is None:  # not over one process's CPU devices (LearnConfig.shard)
            shard = any(d.platform != "cpu" for d in devices)
        n_dev = len(devices) if shard else 1
        n_seq = -(-self.n_real // n_dev) * n_dev
        ypad, nf = _pad(ys, n_seq, T)
        self.T = ypad.shape[1]
        self.n_seq = n_seq
        self.sharding = None
        if n_dev > 1:
            mesh = jax.sharding.Mesh(np.asarray(devices), ("seq",))
            self.sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("seq"))
        self.Y = self._put(ypad)
        self.nf = self._put(nf)
        # the E-step's clip batches, packed (real frames only); sharded data: all clips at once
        self.packing = None
        if self.sharding is None:
            self.packing = pack_clips(np.asarray(nf)[: self.n_real], self.T, _CLIP_BATCH)
        self.opts = _SolveOptions.make(
            config.ridge,
            config.q_floor,
            config.rho_max,
            config.init_prior_weight,
            config.observation,
            config.sigma2_floor,
            dof=config.texton_dof,
        )
        self.tmax = self.T if config.tmax is None else config.tmax
        self.use_durations = config.durations == "lognormal" and config.tmax is not None
        # model selection visits every smaller texton count: stacks are padded to at least
        # this many textons there, so that each step reuses the compiled programs
        self.min_cap = 1
        self.m_min_cap = 1  # the same for the M-step's stack
        self._caps: dict[str, int] = {}

    def _cap(self, name: str, want: int, slack: int = 2) -> int:
        """A padded size ``>= want`` for the program ``name``: the previous one while it is at
        most ``slack`` times ``want``, so that a count that shrinks a little (segments, pruned
        textons) reuses the compiled program instead of compiling a smaller one."""
        last = self._caps.get(name, 0)
        cap = last if want <= last <= slack * want else want
        self._caps[name] = cap
        return cap

    def durations(self, segs: Segs, n_textons: int) -> np.ndarray | None:
        """Per-texton duration log-probabilities fitted to ``segs`` (``None``: flat)."""
        if not self.use_durations:
            return None
        return fit_durations(segs[:, 2], segs[:, 3], n_textons, self.config.tmin, self.tmax)

    def _put(self, a: np.ndarray) -> Array:
        if self.sharding is None:
            return jax.device_put(a)
        return jax.device_put(a, self.sharding)

    def m_step(
        self,
        segs: Segs,
        n_textons: int,
        rows_valid: np.ndarray | None = None,
        prev: Texton | None = None,
    ) -> tuple[Texton, np.ndarray, np.ndarray]:
        """Fit all textons; the stack is padded to a power of two (slots past ``n_textons``
        are unused) so that a changing number of textons recompiles rarely. ``rows_valid``
        (``(len(segs),)`` bools): only those rows are fitted (the others keep their place, so
        the padded row count, and with it the compiled program, stays). ``prev``: the
        textons whose E-step gave ``segs`` (indexed by its labels), the start of the
        Student-t reweighting (:func:`~._mstep._fit_all_impl`; unused for Gaussian ones)."""
        n = len(segs)
        cap = self._cap("rows", _capacity(n))
        rows = np.zeros((cap, 4), dtype=np.int64)
        rows[:n] = segs
        chunks = self._m_chunks(segs, rows_valid)
        assert self.config.state_dim is not None  # resolved by learn before EM
        n_cap = self._cap("textons", max(_capacity(n_textons), self.min_cap, self.m_min_cap))
        args = (
            self.Y,
            jax.device_put(rows),
            chunks,
            n_cap,
            self.tmax,
            self.config.state_dim,
            float(self.config.sigma2_floor),
            self.opts,
        )
        warm, cold = _warm_start(prev, n_cap, self.opts), None
        if self.opts.dof is not None:  # Student-t: the cold and warm M-steps share a program
            cold = jnp.asarray(warm is None)
            if warm is None:
                warm = jax.tree.map(
                    lambda s: jnp.zeros(s.shape, s.dtype), eqx.filter_eval_shape(_fit_all, *args)
                )
        tex = _fit_all(*args, warm, cold)
        M, pi = _transitions(segs, n_textons, self.config.pseudo_count)
        return tex, M, pi

    def _m_chunks(self, segs: Segs, rows_valid: np.ndarray | None) -> tuple[Array, Array]:
        """The rows of ``segs`` (those of ``rows_valid``) in per-texton chunks of
        ``_CHUNK_ROWS`` (:func:`_row_chunks`), padded to a bucketed number of chunks."""
        idx = np.arange(len(segs)) if rows_valid is None else np.flatnonzero(rows_valid)
        lab = segs[idx, 3]
        # sized by a bound of the chunk count that changes little as EM relabels and prunes
        # (all rows, every texton with a row: one partial chunk each), and kept while it is
        # at most 4 times that: a padding chunk is skipped, not computed
        bound = -(-len(segs) // _CHUNK_ROWS) + np.unique(lab).size
        labels, groups = _row_chunks(lab, self._cap("m_chunks", _capacity(max(bound, 1)), 4))
        groups = np.where(groups >= 0, idx[np.maximum(groups, 0)], -1)
        return jax.device_put(labels), jax.device_put(groups)

    def e_step(
        self, tex: Texton, M: np.ndarray, pi: np.ndarray, log_d: np.ndarray | None = None
    ) -> tuple[Segs, float]:
        """The optimal segmentation of every clip and its total score."""
        rows, scores, _ = self._segment_clips(tex, M, pi, log_d)
        return rows, float(scores.sum())

    def e_step_scored(
        self, tex: Texton, M: np.ndarray, pi: np.ndarray, log_d: np.ndarray | None, segs: Segs
    ) -> tuple[Segs, float, float]:
        """:meth:`e_step`, and ``Σ`` of the scores of the segments ``segs`` (each by its own
        texton), from the same frame terms: the M-step's objective without a pass of its own
        (:meth:`objective` is the independent computation)."""
        rows, scores, old = self._segment_clips(tex, M, pi, log_d, segs)
        assert old is not None
        return rows, float(scores.sum()), float(old.sum())

    def _old_rows(self, segs: Segs) -> tuple[Array, Array, Array]:
        """``segs`` (clips numbered from 0 in ``self.ys``) as ``(S, K)`` starts, lengths and
        labels per clip (length 0: an empty slot), ``K = T // tmin``."""
        K = max(self.T // self.config.tmin, 1)
        out = np.zeros((3, self.n_seq, K), dtype=np.int64)
        if len(segs):
            order = np.lexsort((segs[:, 1], segs[:, 0]))
            r = segs[order]
            slot = np.arange(len(r)) - np.searchsorted(r[:, 0], r[:, 0])
            out[0, r[:, 0], slot] = r[:, 1]
            out[1, r[:, 0], slot] = r[:, 2]
            out[2, r[:, 0], slot] = r[:, 3]
        return tuple(self._put(a) for a in out)  # type: ignore[return-value]

    def _segment_clips(
        self,
        tex: Texton,
        M: np.ndarray,
        pi: np.ndarray,
        log_d: np.ndarray | None,
        old: Segs | None = None,
    ) -> tuple[Segs, np.ndarray, np.ndarray | None]:
        """Segment rows of the clips ``self.ys`` (numbered from 0) and each clip's score;
        with ``old`` (rows of those clips), each clip's sum of the scores of its ``old``
        segments."""
        # only the real textons: the capacity padding of the M-step would double the work
        # (N_t changes rarely, so the extra compilations are few); up to _PAD_E_STEP textons
        # the stack is padded to a power of two (model selection visits every small N_t),
        # kept while at most 4 times the need (an E-step program compiles in about 2 s, while
        # 16 slots instead of 4 cost about 0.5 s more per E-step at 50k frames); beyond
        # _PAD_E_STEP to a multiple of 8
        n = M.shape[0]
        if n <= _PAD_E_STEP:
            cap = self._cap("e_step", max(_capacity(n), self.min_cap), 4)
        else:  # a multiple of 8: at most 7 slots of extra work, fewer programs
            cap = -(-n // 8) * 8
        tex = _take(tex, np.minimum(np.arange(cap), n - 1))
        log_M, log_pi = _padded_logs(M, pi, cap)
        if log_d is not None and cap > n:
            log_d = np.concatenate([log_d, np.zeros((cap - n, log_d.shape[1]))])
        seg = _segment_batch(
            tex,
            jnp.asarray(log_M, self.Y.dtype),
            jnp.asarray(log_pi, self.Y.dtype),
            self.Y,
            self.nf,
            self.config.tmin,
            self.tmax,
            None if log_d is None else jnp.asarray(log_d, self.Y.dtype),
            self.packing,
            self._old_rows(np.zeros((0, 4), np.int64) if old is None else old),
            jax.device_put(np.int32(n)),  # the padding slots' frame terms are skipped
        )
        seg, old_j = seg
        old_scores = None if old is None else np.asarray(old_j)[: len(self.ys)]
        starts = np.asarray(seg.starts)
        lengths = np.asarray(seg.lengths)
        labels = np.asarray(seg.labels)
        nseg = np.asarray(seg.n_segments)
        scores = np.asarray(seg.score)
        rows = []
        n_clips = len(self.ys)
        for s in range(n_clips):
            for k in range(int(nseg[s])):
                rows.append((s, int(starts[s, k]), int(lengths[s, k]), int(labels[s, k])))
        return np.asarray(rows, dtype=np.int64).reshape(-1, 4), scores[:n_clips], old_scores

    def key_poses(self, segs: Segs) -> np.ndarray:
        """The first two frames of every segment, ``(n_segments, 2, D)``."""
        return np.stack([np.stack([self.ys[s][b], self.ys[s][b + 1]]) for s, b, _, _ in segs])

    def objective(
        self,
        tex: Texton,
        M: np.ndarray,
        pi: np.ndarray,
        segs: Segs,
        log_d: np.ndarray | None = None,
    ) -> float:
        """log P(Y, segmentation | model): segment scores plus initial/transition (and
        duration) terms."""
        return self._segments_ll(tex, M, segs) + self.path_terms(M, pi, segs, log_d)

    def path_terms(
        self, M: np.ndarray, pi: np.ndarray, segs: Segs, log_d: np.ndarray | None
    ) -> float:
        """The initial, transition (and duration) log-probabilities of the segmentation."""
        total = 0.0
        log_M, log_pi = np.log(M), np.log(pi)
        if log_d is not None:
            total += float(log_d[segs[:, 3], segs[:, 2] - self.config.tmin].sum())
        for s in range(self.n_real):
            lab = segs[segs[:, 0] == s, 3]
            total += float(log_pi[lab[0]] + log_M[lab[:-1], lab[1:]].sum())
        return total

    def _segments_ll(self, tex: Texton, M: np.ndarray, segs: Segs) -> float:
        """``Σ`` of the segment scores of the rows ``segs`` (each by its own texton)."""
        n = len(segs)
        cap = self._cap("rows", _capacity(n))
        rows = np.zeros((cap, 4), dtype=np.int64)
        rows[:, 2] = 2  # padding rows: a valid 2-frame segment, weight 0
        rows[:n] = segs
        w = np.zeros(cap)
        w[:n] = 1.0
        counts = np.bincount(segs[:, 3]) if n else np.zeros(1, np.int64)
        n_chunks = int(np.sum(-(-counts // _CHUNK_ROWS)))
        chunks = _row_chunks(segs[:, 3], self._cap("chunks", _capacity(max(n_chunks, 1))))
        return float(
            _rows_score(
                tex,
                self.Y,
                jnp.asarray(rows),
                jnp.asarray(w, self.Y.dtype),
                (jnp.asarray(chunks[0]), jnp.asarray(chunks[1])),
                self.tmax,
            )
        )


def _warm_start(prev: Texton | None, cap: int, opts: _SolveOptions) -> Texton | None:
    """``prev`` padded to ``cap`` textons (copies of its last), for Student-t M-steps only."""
    if opts.dof is None or prev is None or prev.dof != opts.dof:
        return None
    return _take(prev, np.minimum(np.arange(cap), prev.n_textons - 1))


def _fit_kept(
    run: _Runner, segs: Segs, n_t: int, few: np.ndarray
) -> tuple[Texton, np.ndarray, np.ndarray, np.ndarray | None, float, Segs, float]:
    """The model of ``segs`` without the textons ``few``: the others fitted to their own
    segments (the same fits as with all textons), ``M``, ``π`` and durations restricted and
    renormalised; the objective of the kept textons' segments (scores and durations; a
    partial segmentation has no transition term); and the E-step of that model."""
    keep = np.setdiff1d(np.arange(n_t), few)
    new_id = np.full(n_t, -1)
    new_id[keep] = np.arange(keep.size)
    ids = new_id[segs[:, 3]]
    rows = segs.copy()
    rows[:, 3] = np.maximum(ids, 0)
    tex, _, _ = run.m_step(rows, keep.size, rows_valid=ids >= 0)
    M, pi = _transitions(segs, n_t, run.config.pseudo_count)
    M = M[np.ix_(keep, keep)]
    M = M / M.sum(axis=1, keepdims=True)
    pi = pi[keep] / pi[keep].sum()
    log_d = run.durations(segs, n_t)
    log_d = None if log_d is None else log_d[keep]
    kept = rows[ids >= 0]
    new_segs, obj_e, obj = run.e_step_scored(tex, M, pi, log_d, kept)
    if log_d is not None:
        obj += float(log_d[kept[:, 3], kept[:, 2] - run.config.tmin].sum())
    return tex, M, pi, log_d, obj, new_segs, obj_e


def _em(
    run: _Runner,
    fm: FeatureMap | None,
    config: LearnConfig,
    threshold: float,
    segs: Segs,
    verbose: bool,
    callback: Callable[[dict[str, Any]], None] | None,
    t0: float,
    *,
    prune_initial: bool = False,
    prev: Texton | None = None,
) -> MotionTexture:
    """Hard EM from ``segs`` to convergence or ``config.max_iter`` iterations.

    ``prev``: the textons whose E-step gave ``segs`` (indexed by its labels), if any: the
    first M-step of Student-t textons then starts from them (one reweighting) instead of
    from the Gaussian fit (``opts.irls_steps``); later M-steps always do.

    With ``prune_initial`` (EM from the greedy initialisation), textons that ``segs`` gives
    fewer than ``config.min_segments`` segments are dropped after the first M-step, before the
    first E-step: fitted at the full state dimension to one or two windows, they score every
    other window poorly. On the salsa clips (14 and 51 clips, 155 and 305 greedy textons) the
    textons that survive the first E-step's pruning are exactly those with at least
    ``min_segments`` greedy segments, so this gives the same model without the E-step over all
    greedy textons (the costliest of the learn: 305 textons against 51 at 49,708 frames).
    The dropped textons are not fitted either, so that iteration's M-step objective
    (``history[0, 0]``) covers the kept textons' segments only (:func:`_fit_kept`).
    """
    n_frames = run.n_frames
    segs, used = _relabel(segs)
    # the textons of the E-step that gave segs, as its labels index them
    prev = None if prev is None else _take(prev, used)
    history: list[tuple[float, float]] = []
    best: tuple[float, Texton, np.ndarray, np.ndarray, Segs, np.ndarray | None] | None = None
    for it in range(config.max_iter + 1):
        r = run
        n_t = int(segs[:, 3].max()) + 1
        n_pruned = 0
        if prune_initial and it == 0 and (few := _underused(segs, config.min_segments)).size:
            tex, M, pi, log_d, obj_m, new_segs, obj_e = _fit_kept(r, segs, n_t, few)
            n_pruned = few.size
        else:
            tex, M, pi = r.m_step(segs, n_t, prev=prev)
            log_d = r.durations(segs, n_t)
            new_segs, obj_e, obj_m = r.e_step_scored(tex, M, pi, log_d, segs)
            obj_m += r.path_terms(M, pi, segs, log_d)
        # pruning: textons with fewer than min_segments segments are removed from the model
        # (M, π renormalised) and every clip is segmented again by the others, until none is
        # left; the model and segmentation stay complete and consistent
        while (prune := _underused(new_segs, config.min_segments)).size:
            keep = np.setdiff1d(np.arange(M.shape[0]), prune)
            tex, M, pi = _keep_textons(tex, M, pi, keep)
            log_d = None if log_d is None else log_d[keep]
            new_segs, obj_e = r.e_step(tex, M, pi, log_d)
            n_pruned += prune.size
        lab_old, _ = _masks(segs, run.n_real, run.T)
        lab_new, _ = _masks(new_segs, run.n_real, run.T)
        changed = int(np.sum(lab_old != lab_new))  # frames whose texton changed
        history.append((obj_m, obj_e))
        if best is None or obj_e > best[0]:
            best = (obj_e, tex, M, pi, new_segs, log_d)
        info = {
            "iteration": it,
            "n_textons": n_t,
            "pruned": n_pruned,
            "objective_m": obj_m,
            "objective_e": obj_e,
            "changed": changed,
            "seconds": time.perf_counter() - t0,
        }
        if verbose:
            pruned = f"  pruned {n_pruned} texton(s)" if n_pruned else ""
            print(
                f"[mtex learn] iter {it:2d}  textons {n_t:3d}  objective/frame "
                f"{obj_m / n_frames:9.4f} (M) {obj_e / n_frames:9.4f} (E)  "
                f"frames relabelled {changed:6d}  {info['seconds']:6.1f} s{pruned}",
                flush=True,
            )
        if callback is not None:
            callback(info)
        gain = obj_e - history[-2][1] if len(history) > 1 else np.inf
        converged = changed <= config.relabel_tol * n_frames or gain < config.tol * n_frames
        # after a pruning the remaining textons are refitted to their new segments first
        if it == config.max_iter or (converged and n_pruned == 0):
            break
        segs, used = _relabel(new_segs)
        prev = _take(tex, used)

    assert best is not None
    _, tex, M, pi, final_segs, log_d = best
    tex = _take(tex, np.arange(M.shape[0]))  # drop the capacity padding
    used = np.unique(final_segs[:, 3])
    if len(used) < M.shape[0]:  # a texton that lost all its segments: remove it
        tex, M, pi = _keep_textons(tex, M, pi, used)
        log_d = None if log_d is None else log_d[used]
        final_segs, _ = _relabel(final_segs)
    key = run.key_poses(final_segs)
    return MotionTexture(
        textons=tex,
        M=jax.device_put(M),
        pi=jax.device_put(pi),
        key_poses=jax.device_put(key),
        key_pose_labels=jax.device_put(final_segs[:, 3]),
        segment_lengths=jax.device_put(final_segs[:, 2]),
        segments=jax.device_put(final_segs),
        history=jax.device_put(np.asarray(history)),
        feature_map=fm,
        config=config,
        threshold=threshold,
        log_durations=None if log_d is None else jax.device_put(log_d),
    )
