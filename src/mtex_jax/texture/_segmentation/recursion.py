"""The semi-Markov recursion of the segmentation dynamic programs (design §4, §10.1): one
``lax.scan`` over blocks of ends for both, over a semiring.

With segment scores ``score_i(b, e) = A_i(e) + B⁰_i(b)`` (design §3: the prefix-sum
differences split into a part of the end and a part of the start), lengths
``tmin ≤ e − b + 1 ≤ tmax``, optional duration terms ``log p_i(L)``, transitions
``log M[l, i]`` and initial log-probabilities ``log π[i]``:

.. code-block:: text

    V(e, i) = A_i(e) + ⊕_{e − tmax + 1 ≤ b ≤ e − tmin + 1} [ B_i(b) + log p_i(e − b + 1) ]
    B_i(b)  = B⁰_i(b) + (b = 0 ? log π_i : ⊕_l V(b − 1, l) + log M[l, i])

with ``⊕`` the maximum (the max-plus semiring, :class:`MaxPlus`: the Viterbi of
``viterbi_segments``) or the log-sum-exp (the log semiring, :class:`LogSumExp`: the forward
algorithm of ``forward_log_likelihood``). ``V(e)`` needs ``B(b)`` only for
``b ≤ e − tmin + 1``, and ``B(b)`` needs ``V(b − 1)``, so ``tmin`` consecutive ends are
independent: the scan runs over blocks of ``tmin`` ends, each block one windowed reduction
over a ring buffer of the last ``tmax`` values of ``B`` (``window``) and one semiring product
with ``log M`` (``transition``). A semiring is the pair of those two reductions, each written
for its own algebra: a ``reduce_window`` or a gather for the maximum; a chunked, exact
log-sum-exp and one matrix product in linear space for the sum.
"""

from __future__ import annotations

from typing import Protocol

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array

from .._scoring.scores import SegmentScorer

__all__ = [
    "LogSumExp",
    "MaxPlus",
    "Semiring",
    "end_start_parts",
    "safe_logsumexp",
    "semi_markov_values",
]


def end_start_parts(scorer: SegmentScorer, Tp: int) -> tuple[Array, Array]:
    """The end part ``A(e)`` and start part ``B⁰(b)`` of every segment score, each
    ``(Tp + 1, N_t)`` (rows beyond ``T`` are ``−inf``): ``score_i(b, e) = A_i(e) + B⁰_i(b)``."""
    init, cd, co = scorer.init, scorer.cum_dyn, scorer.cum_obs
    n_t, T = init.shape
    dtype = cd.dtype
    c = scorer.dyn_offset + scorer.obs_offset  # (N,)
    e_idx = jnp.arange(T)
    a_all = (cd[:, 1:] + co[:, 1:]).T + e_idx[:, None].astype(dtype) * c
    b0_all = (
        init
        - cd[:, jnp.minimum(e_idx + 2, T)]
        - co[:, :T]
        - e_idx[None, :].astype(dtype) * c[:, None]
        - scorer.dyn_offset[:, None]
        + scorer.obs_offset[:, None]
    ).T
    pad = jnp.full((Tp + 1 - T, n_t), -jnp.inf, dtype)
    return jnp.concatenate([a_all, pad], axis=0), jnp.concatenate([b0_all, pad], axis=0)


class Semiring(Protocol):
    """The two reductions of the recursion for one block of ``P = tmin`` ends."""

    tmin: int
    tmax: int

    def window(self, win: Array) -> Array:
        """``(P, N_t)``: for end ``p`` of the block, ``⊕_w win[p + w] + log p(tmax − w)``
        over the ``tmax − tmin + 1`` starts of the window ``win (tmax, N_t)``."""
        ...

    def transition(self, v: Array) -> Array:
        """``(P, N_t)``: ``⊕_l v(e, l) + log M[l, i]`` for the block's ends ``v (P, N_t)``."""
        ...


def semi_markov_values(
    scorer: SegmentScorer, log_pi: Array, semiring: Semiring
) -> tuple[Array, Array]:
    """``(B, V)`` of the recursion (module doc): the buffer of start values ``B``, row
    ``tmax + b`` for start ``b`` (the first ``tmax`` rows ``−inf``), and the end values
    ``V (Tp, N_t)``, ``Tp`` the frames rounded up to a multiple of ``tmin`` (rows past the
    scorer's frames ``−inf``)."""
    n_t, T = scorer.init.shape
    dtype = scorer.cum_dyn.dtype
    neg = jnp.asarray(-jnp.inf, dtype)
    tmax = semiring.tmax
    P = semiring.tmin  # ends processed together: V(e) needs B(b) only for b <= e − tmin + 1
    nb = -(-T // P)  # blocks
    Tp = nb * P
    a_all, b0_all = end_start_parts(scorer, Tp)
    # B(b) lives at row tmax + b; the first tmax rows are −inf (starts before frame 0)
    bbuf = jnp.full((tmax + Tp + 1, n_t), neg, dtype).at[tmax].set(b0_all[0] + log_pi)

    def block(bbuf: Array, s: Array) -> tuple[Array, Array]:
        win = lax.dynamic_slice(bbuf, (s + 1, 0), (tmax, n_t))  # b in [s − tmax + 1, s]
        v = lax.dynamic_slice(a_all, (s, 0), (P, n_t)) + semiring.window(win)
        v = jnp.where((s + jnp.arange(P) < T)[:, None], v, neg)
        h = semiring.transition(v)  # H(e, i) = ⊕_l V(e, l) + log M[l, i]
        bnew = lax.dynamic_slice(b0_all, (s + 1, 0), (P, n_t)) + h
        bbuf = lax.dynamic_update_slice(bbuf, bnew, (tmax + s + 1, 0))
        return bbuf, v

    bbuf, V = lax.scan(block, bbuf, jnp.arange(nb) * P)
    return bbuf, V.reshape(Tp, n_t)


# The duration-aware windowed maximum of a block (see ``viterbi_segments``) gathers the
# ``(P, Wn, N_t)`` window when it is at most this many bytes (it then stays in cache), and is
# otherwise an unrolled chain of shifted slices, for at most _UNROLL_MAX_LENGTHS lengths
# (compile time grows with it), or the gather again. Measured on 2 cores at 50,068 frames
# (P = 60, Wn = 121): on the clips joined into one sequence the gather took 0.046 s for 6
# textons against the chain's 0.26 s (whose 121 small operations per block then dominate),
# and in the learner's E-step 0.27 / 0.34 / 0.61 / 0.90 s for 6 / 8 / 16 / 32 textons against
# 0.30 / 0.37 / 0.70 / 1.00 s; for 56 textons (3.3 MB) the chain was faster, 1.65 against
# 1.94 s.
_GATHER_MAX_BYTES = 2 * 2**20
_UNROLL_MAX_LENGTHS = 256


class _Algebra:
    """What both semirings keep: the lengths, the textons' count and dtype, ``log M``."""

    def __init__(
        self,
        log_M: Array,
        log_durations: Array | None,
        tmin: int,
        tmax: int,
        n_t: int,
        dtype: jnp.dtype,
    ) -> None:
        self.tmin, self.tmax, self.n_t, self.dtype = tmin, tmax, n_t, dtype
        self.log_M = log_M
        self.neg = jnp.asarray(-jnp.inf, dtype)
        self.Wn = tmax - tmin + 1  # candidate starts per end
        self.prepare(log_durations)

    def prepare(self, log_durations: Array | None) -> None:
        """The semiring's own constants (traced), from the durations."""


class MaxPlus(_Algebra):
    """The max-plus semiring of the Viterbi (design §4), for ``N_t`` textons in ``dtype``."""

    def prepare(self, log_durations: Array | None) -> None:
        self.dur_rev: Array | None = None
        if log_durations is not None:
            # row p + w of a window is the start of a segment of length tmax − w for end s + p
            self.dur_rev = jnp.asarray(log_durations, self.dtype).T[::-1]  # (Wn, N)
            self.gather = jnp.arange(self.tmin)[:, None] + jnp.arange(self.Wn)[None, :]

    def window(self, win: Array) -> Array:
        P, Wn, neg = self.tmin, self.Wn, self.neg
        if self.dur_rev is None:
            return jax.lax.reduce_window(win, neg, jax.lax.max, (Wn, 1), (1, 1), "VALID")
        dur_rev = self.dur_rev
        gathered = P * Wn * self.n_t * jnp.dtype(self.dtype).itemsize
        if gathered <= _GATHER_MAX_BYTES or Wn > _UNROLL_MAX_LENGTHS:
            return jnp.max(win[self.gather] + dur_rev[None], axis=1)  # (P, N)
        # max over w of win[p + w] + dur_rev[w]: an unrolled chain of shifted slices, which
        # XLA fuses into one pass (a large gathered (P, Wn, N) array is written and re-read;
        # 0.57 -> 0.38 s for 56 textons on the 51 clips of 49,708 frames)
        out = win[:P] + dur_rev[0]
        for w in range(1, Wn):
            out = jnp.maximum(out, win[w : w + P] + dur_rev[w])
        return out  # (P, N)

    def transition(self, v: Array) -> Array:
        return jnp.max(v[:, :, None] + self.log_M[None], axis=1)


_GATHER_BUDGET = 1 << 21  # elements of one gathered (ends, starts, textons) chunk
_FORCE_EXACT = False  # tests: always take the exact (slower) transition path


def safe_logsumexp(x: Array, axis: int) -> Array:
    """``log Σ exp x`` along ``axis``; ``−inf`` (with zero gradient) where every term is
    ``−inf``."""
    m = lax.stop_gradient(jnp.max(x, axis=axis, keepdims=True))
    m = jnp.where(jnp.isfinite(m), m, 0.0)
    s = jnp.sum(jnp.exp(x - m), axis=axis)
    pos = s > 0
    return jnp.where(pos, jnp.log(jnp.where(pos, s, 1.0)) + jnp.squeeze(m, axis), -jnp.inf)


class LogSumExp(_Algebra):
    """The log semiring of the forward algorithm (design §10.1), for ``N_t`` textons in
    ``dtype``: the window's log-sum-exp gathered in chunks of starts with a running maximum
    (bounded memory even for ``tmax = None``; exact, and with finite gradients where a window
    holds no feasible start), and the transition as one matrix product in linear space,
    ``exp(v − max) · exp(log M − column max)``, with the ``(P, N, N)`` log-sum-exp as the
    exact fallback if a column's terms all underflow."""

    def prepare(self, log_durations: Array | None) -> None:
        P, Wn, n_t, dtype, log_M = self.tmin, self.Wn, self.n_t, self.dtype, self.log_M
        # window offset w holds start b = e − tmax + 1 + w, i.e. length L = tmax − w
        if log_durations is None:
            dur_w = jnp.zeros((Wn, n_t), dtype)
        else:
            dur_w = jnp.asarray(log_durations, dtype)[:, ::-1].T
        Wc = int(min(Wn, max(1, _GATHER_BUDGET // max(1, P * n_t))))
        self.Wc, self.nc = Wc, -(-Wn // Wc)
        pad = jnp.full((self.nc * Wc - Wn, n_t), -jnp.inf, dtype)
        self.dur_w = jnp.concatenate([dur_w, pad], axis=0)
        self.rows = jnp.arange(P)[:, None] + jnp.arange(Wc)[None, :]  # (P, Wc)
        col = jnp.max(log_M, axis=0)  # per column shift, so tiny probabilities do not underflow
        self.col = jnp.where(jnp.isfinite(col), col, 0.0)
        self.M_lin = jnp.exp(log_M - self.col)
        self.M_pos = jnp.isfinite(log_M).astype(dtype)

    def window(self, win: Array) -> Array:
        P, n_t, dtype, neg = self.tmin, self.n_t, self.dtype, self.neg
        Wc, nc, rows, dur_w = self.Wc, self.nc, self.rows, self.dur_w
        win = jnp.concatenate([win, jnp.full((nc * Wc - self.Wn, n_t), neg, dtype)], axis=0)

        def chunk(carry: tuple[Array, Array], c: Array) -> tuple[tuple[Array, Array], None]:
            m, acc = carry
            vals = win[rows + c * Wc] + lax.dynamic_slice_in_dim(dur_w, c * Wc, Wc)[None]
            new_m = lax.stop_gradient(jnp.maximum(m, jnp.max(vals, axis=1)))
            safe = jnp.where(jnp.isfinite(new_m), new_m, 0.0)
            acc = acc * jnp.exp(m - safe) + jnp.sum(jnp.exp(vals - safe[:, None]), axis=1)
            return (new_m, acc), None

        init = (jnp.full((P, n_t), neg, dtype), jnp.zeros((P, n_t), dtype))
        (m, acc), _ = lax.scan(chunk, init, jnp.arange(nc))
        pos = acc > 0
        safe_m = jnp.where(jnp.isfinite(m), m, 0.0)
        return jnp.where(pos, jnp.log(jnp.where(pos, acc, 1.0)) + safe_m, neg)

    def transition(self, v: Array) -> Array:
        # logsumexp_l v(e, l) + log M[l, i] as one GEMM in linear space, shifted by the row's
        # maximum; exact unless a column's terms all underflow where one is finite (then the
        # (P, N, N) logsumexp)
        log_M = self.log_M
        top = lax.stop_gradient(jnp.max(v, axis=1, keepdims=True))
        top = jnp.where(jnp.isfinite(top), top, 0.0)
        total = jnp.exp(v - top) @ self.M_lin
        pos = total > 0
        fast = jnp.where(pos, jnp.log(jnp.where(pos, total, 1.0)) + top + self.col, self.neg)
        feasible = (jnp.isfinite(v).astype(self.dtype) @ self.M_pos) > 0
        exact = jnp.all(pos | ~feasible) & (not _FORCE_EXACT)
        return lax.cond(
            exact, lambda v: fast, lambda v: safe_logsumexp(v[:, :, None] + log_M[None], 1), v
        )
