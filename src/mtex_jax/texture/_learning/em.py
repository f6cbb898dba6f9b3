"""The E-step and M-step of hard EM over padded, optionally sharded clips (design §4.2–4.3).

:class:`Runner` holds the clips and runs the jitted steps; :class:`Capacity` is the least size
of their texton stacks, an explicit input of every step. The EM loop that drives them is
:mod:`.loop` (design §4.6).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._config import LearnConfig
from .._scoring.packing import pack_clips
from .._scoring.rows import CHUNK_ROWS, row_chunks
from .._segmentation.durations import fit_durations
from .._segmentation.segment import segment_batch
from .._texton.options import SolveOptions
from .._texton.texton import Texton
from .init import Segs
from .labels import capacity_for, padded_logs, take, transition_counts
from .mstep import fit_all

PAD_E_STEP = 16
"""Up to this many textons the E-step's stack is padded to a power of two (:class:`Capacity`)."""
_CLIP_BATCH = 4  # clips per batch of the E-step (memory: see segment_batch)


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


class Capacity(NamedTuple):
    """The least texton-stack sizes of the compiled steps (design §4.7).

    The BIC selection visits ever smaller texton counts; padding their stacks to these sizes
    lets every step reuse the programs compiled for the larger model instead of compiling
    a smaller one. The default (1, 1) pads nothing beyond the steps' own rounding.

    Attributes:
        textons: least stack of both steps: the E-step's while it has at most
            :data:`PAD_E_STEP` textons, and the M-step's.
        m_step: least stack of the M-step alone.
    """

    textons: int = 1
    m_step: int = 1


NO_PADDING = Capacity()
"""The default :class:`Capacity`: stacks sized by their own textons only."""


class Runner:
    """The clips, padded and optionally sharded, and the jitted E- and M-steps (design §4.8).

    The steps depend on the runner only through its data and configuration, and on explicit
    arguments (:class:`Capacity`); the runner's one piece of state is the padded size each
    program last used (:meth:`_cap`), a compile cache that never changes a result.
    """

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
        self.opts = SolveOptions.make(
            config.ridge,
            config.q_floor,
            config.rho_max,
            config.init_prior_weight,
            config.observation_model,
            config.sigma2_floor,
            dof=config.texton_dof,
        )
        self.tmax = self.T if config.tmax is None else config.tmax
        self.use_durations = config.durations == "lognormal" and config.tmax is not None
        # the padded size last used by each program (_cap): the runner's own compile cache
        self._caps: dict[str, int] = {}

    def caps(self) -> dict[str, int]:
        """The padded size each program last used (:meth:`_cap`), to save in a checkpoint."""
        return {k: int(v) for k, v in self._caps.items()}

    def set_caps(self, caps: dict[str, int]) -> None:
        """Restore the padded sizes of :meth:`caps` (a resumed learn pads as the
        uninterrupted one did)."""
        self._caps = {str(k): int(v) for k, v in caps.items()}

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

    def m_stack(self, n_textons: int, capacity: Capacity) -> int:
        """The M-step's padded texton stack for ``n_textons`` textons: a power of two, at least
        ``capacity``'s, kept while it shrinks a little (:meth:`_cap`)."""
        want = max(capacity_for(n_textons), capacity.textons, capacity.m_step)
        return self._cap("textons", want)

    def m_step(
        self,
        segs: Segs,
        n_textons: int,
        capacity: Capacity = NO_PADDING,
        rows_valid: np.ndarray | None = None,
        prev: Texton | None = None,
    ) -> tuple[Texton, np.ndarray, np.ndarray]:
        """The M-step (design §4.3): every texton fitted to its segments, ``M`` and ``π``.

        The stack is padded to a power of two (slots past ``n_textons`` are unused;
        :meth:`m_stack`) so that a changing number of textons recompiles rarely.

        Args:
            segs: segment rows ``(clip, start, length, label)``.
            n_textons: the number of textons (labels ``0 … n_textons − 1``).
            capacity: the least stack sizes (:class:`Capacity`).
            rows_valid: ``(len(segs),)`` bools: only those rows are fitted (the others keep
                their place, so the padded row count, and with it the compiled program,
                stays).
            prev: the textons whose E-step gave ``segs`` (indexed by its labels), the start
                of the Student-t reweighting (:func:`~.mstep.fit_all`; unused for Gaussian
                ones).

        Returns:
            The padded texton stack, ``M`` and ``π``.
        """
        n = len(segs)
        cap = self._cap("rows", capacity_for(n))
        rows = np.zeros((cap, 4), dtype=np.int64)
        rows[:n] = segs
        chunks = self._m_chunks(segs, rows_valid)
        assert self.config.state_dim is not None  # resolved by learn before EM
        n_cap = self.m_stack(n_textons, capacity)
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
        warm, cold = warm_start(prev, n_cap, self.opts), None
        if self.opts.dof is not None:  # Student-t: the cold and warm M-steps share a program
            cold = jnp.asarray(warm is None)
            if warm is None:
                warm = jax.tree.map(
                    lambda s: jnp.zeros(s.shape, s.dtype), eqx.filter_eval_shape(fit_all, *args)
                )
        tex = fit_all(*args, warm, cold)
        M, pi = transition_counts(segs, n_textons, self.config.pseudo_count)
        return tex, M, pi

    def _m_chunks(self, segs: Segs, rows_valid: np.ndarray | None) -> tuple[Array, Array]:
        """The rows of ``segs`` (those of ``rows_valid``) in per-texton chunks of
        ``CHUNK_ROWS`` (:func:`row_chunks`), padded to a bucketed number of chunks."""
        idx = np.arange(len(segs)) if rows_valid is None else np.flatnonzero(rows_valid)
        lab = segs[idx, 3]
        # sized by a bound of the chunk count that changes little as EM relabels and prunes
        # (all rows, every texton with a row: one partial chunk each), and kept while it is
        # at most 4 times that: a padding chunk is skipped, not computed
        bound = -(-len(segs) // CHUNK_ROWS) + np.unique(lab).size
        labels, groups = row_chunks(lab, self._cap("m_chunks", capacity_for(max(bound, 1)), 4))
        groups = np.where(groups >= 0, idx[np.maximum(groups, 0)], -1)
        return jax.device_put(labels), jax.device_put(groups)

    def e_step(
        self,
        tex: Texton,
        M: np.ndarray,
        pi: np.ndarray,
        log_d: np.ndarray | None = None,
        capacity: Capacity = NO_PADDING,
    ) -> tuple[Segs, float]:
        """The E-step (design §4.2): the optimal segmentation of every clip.

        Args:
            tex: the textons (a stack of at least ``len(M)``; the first ``len(M)`` are used).
            M: ``(N_t, N_t)`` transition matrix.
            pi: ``(N_t,)`` initial distribution.
            log_d: ``(N_t, tmax − tmin + 1)`` duration log-probabilities (``None``: flat).
            capacity: the least stack sizes (:class:`Capacity`).

        Returns:
            The segment rows ``(clip, start, length, label)`` and their total score.
        """
        rows, scores, _ = self._segment_clips(tex, M, pi, log_d, capacity)
        return rows, float(scores.sum())

    def e_step_scored(
        self,
        tex: Texton,
        M: np.ndarray,
        pi: np.ndarray,
        log_d: np.ndarray | None,
        segs: Segs,
        capacity: Capacity = NO_PADDING,
    ) -> tuple[Segs, float, float]:
        """:meth:`e_step`, and ``Σ`` of the scores of the segments ``segs`` (each by its own
        texton), from the same frame terms: the M-step's objective (design §4.3) without a
        pass of its own.

        Returns:
            The segment rows, their total score and the score of ``segs``.
        """
        rows, scores, old = self._segment_clips(tex, M, pi, log_d, capacity, segs)
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
        capacity: Capacity,
        old: Segs | None = None,
    ) -> tuple[Segs, np.ndarray, np.ndarray | None]:
        """Segment rows of the clips ``self.ys`` (numbered from 0) and each clip's score;
        with ``old`` (rows of those clips), each clip's sum of the scores of its ``old``
        segments."""
        # only the real textons: the capacity padding of the M-step would double the work
        # (N_t changes rarely, so the extra compilations are few); up to PAD_E_STEP textons
        # the stack is padded to a power of two (model selection visits every small N_t),
        # kept while at most 4 times the need (an E-step program compiles in about 2 s, while
        # 16 slots instead of 4 cost about 0.5 s more per E-step at 50k frames); beyond
        # PAD_E_STEP to a multiple of 8
        n = M.shape[0]
        if n <= PAD_E_STEP:
            cap = self._cap("e_step", max(capacity_for(n), capacity.textons), 4)
        else:  # a multiple of 8: at most 7 slots of extra work, fewer programs
            cap = -(-n // 8) * 8
        tex = take(tex, np.minimum(np.arange(cap), n - 1))
        log_M, log_pi = padded_logs(M, pi, cap)
        if log_d is not None and cap > n:
            log_d = np.concatenate([log_d, np.zeros((cap - n, log_d.shape[1]))])
        seg = segment_batch(
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
            check=False,  # the clips were checked when learning began: a cacheable program
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

    def path_terms(
        self, M: np.ndarray, pi: np.ndarray, segs: Segs, log_d: np.ndarray | None
    ) -> float:
        """The initial, transition (and duration) log-probabilities of the segmentation
        ``segs`` (design §4.1)."""
        total = 0.0
        log_M, log_pi = np.log(M), np.log(pi)
        if log_d is not None:
            total += float(log_d[segs[:, 3], segs[:, 2] - self.config.tmin].sum())
        for s in range(self.n_real):
            lab = segs[segs[:, 0] == s, 3]
            total += float(log_pi[lab[0]] + log_M[lab[:-1], lab[1:]].sum())
        return total


def warm_start(prev: Texton | None, cap: int, opts: SolveOptions) -> Texton | None:
    """``prev`` padded to ``cap`` textons (copies of its last), for Student-t M-steps only."""
    if opts.dof is None or prev is None or prev.dof != opts.dof:
        return None
    return take(prev, np.minimum(np.arange(cap), prev.n_textons - 1))
