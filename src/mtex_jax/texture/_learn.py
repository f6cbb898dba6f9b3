"""Learning a motion texture (MT §4, SPEC §4): greedy initialisation, hard EM, model files.

``learn(data, LearnConfig(...))`` turns clips into a :class:`MotionTexture`:

1. observation vectors ``Y`` (a :class:`FeatureMap` fitted on the clips, or arrays as given);
2. greedy initialisation (MT §4): grow segments while a texton's one-step prediction error
   stays below a threshold, reusing an existing texton when it explains the next ``tmin`` frames;
3. hard EM: M-step = closed-form texton fits on all segments of each texton (sufficient
   statistics summed over sequences and devices), transition matrix and initial distribution
   with a Dirichlet pseudo-count; E-step = globally optimal segmentation by the semi-Markov
   Viterbi (:func:`segment`), batched over padded sequences and sharded across devices.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..internal import load_arrays_json, save_arrays_json
from ..motion import FeatureMap, Motion
from ._segment import Segmentation, _check_lengths, _segment_batch, segment
from ._texton import (
    Texton,
    _dynamics_stats_impl,
    _frame_stats_impl,
    _segment_scores_impl,
    _SolveOptions,
    _subspace_impl,
    _texton_from_stats_impl,
    fit_texton,
    stack_textons,
)

__all__ = [
    "LearnConfig",
    "MotionTexture",
    "bic_select",
    "greedy_init",
    "learn",
    "load_texture",
    "threshold_for_textons",
]

FORMAT_VERSION = 1
_KIND = "mtex_jax.MotionTexture"


@dataclasses.dataclass(frozen=True)
class LearnConfig:
    """Settings of :func:`learn` (lengths in frames).

    Attributes:
        tmin: shortest segment (frames, ``>= 3``); the paper uses about 1 s.
        tmax: longest segment (frames); ``None`` = unbounded (paper-exact, ``O(T²)``).
        state_dim: texton state dimension ``k`` (the paper: 12–15).
        threshold: greedy-initialisation error threshold (squared one-step prediction error
            per observation dimension, in the units of ``Y``: z-units for motions). ``None``:
            from ``n_textons``, else by BIC over ``bic_thresholds``, else 0.3.
        n_textons: target number of textons for the threshold search (used when
            ``threshold`` is ``None``).
        max_iter: most EM iterations.
        tol: stop when the objective gains less than ``tol`` per frame.
        pseudo_count: Dirichlet pseudo-count added to transition and initial counts.
        fps: resample motions to this frame rate first (``None``: keep; all clips must agree).
        ridge, q_floor, sigma2_floor, rho_max, init_prior_weight: texton fit regularisation
            (see :func:`fit_texton`).
        shard: split sequences across all JAX devices when there is more than one.
        bic_thresholds: thresholds to choose from by BIC (see :func:`bic_select`).
        min_segments: prune textons that the segmentation gives fewer training segments: after
            each E-step they are removed (``M``, ``π`` renormalised) and the clips segmented
            again by the remaining textons, which EM then refits (a texton fitted on one
            60-frame segment has unreliable dynamics). ``1`` = no pruning (the paper).
    """

    tmin: int = 60
    tmax: int | None = 180
    state_dim: int = 12
    threshold: float | None = None
    n_textons: int | None = None
    max_iter: int = 20
    tol: float = 1e-4
    pseudo_count: float = 0.1
    fps: float | None = None
    ridge: float = 1e-6
    q_floor: float = 1e-6
    sigma2_floor: float = 1e-6
    rho_max: float | None = None
    init_prior_weight: float = 4.0
    shard: bool = True
    bic_thresholds: tuple[float, ...] | None = None
    min_segments: int = 1

    def __post_init__(self) -> None:
        if isinstance(self.min_segments, bool) or not isinstance(self.min_segments, int):
            raise ValueError(
                f"LearnConfig.min_segments must be a positive integer, got {self.min_segments!r}"
            )
        if self.min_segments < 1:
            raise ValueError(f"LearnConfig.min_segments must be >= 1, got {self.min_segments}")
        if not isinstance(self.tmin, int) or self.tmin < 3:
            raise ValueError(f"LearnConfig.tmin must be an integer >= 3, got {self.tmin!r}")
        if self.tmax is not None and (not isinstance(self.tmax, int) or self.tmax < self.tmin):
            raise ValueError(
                f"LearnConfig.tmax must be None or an integer >= tmin = {self.tmin}, "
                f"got {self.tmax!r}"
            )
        if not isinstance(self.state_dim, int) or self.state_dim < 1:
            raise ValueError(
                f"LearnConfig.state_dim must be a positive integer, got {self.state_dim!r}"
            )
        if self.threshold is not None and not self.threshold > 0:
            raise ValueError(f"LearnConfig.threshold must be positive, got {self.threshold!r}")
        if self.n_textons is not None and (
            not isinstance(self.n_textons, int) or self.n_textons < 1
        ):
            raise ValueError(
                f"LearnConfig.n_textons must be a positive integer, got {self.n_textons!r}"
            )
        if not isinstance(self.max_iter, int) or self.max_iter < 0:
            raise ValueError(f"LearnConfig.max_iter must be >= 0, got {self.max_iter!r}")
        if not self.pseudo_count > 0:
            raise ValueError(
                f"LearnConfig.pseudo_count must be positive, got {self.pseudo_count!r}"
            )
        if self.fps is not None and not self.fps > 0:
            raise ValueError(f"LearnConfig.fps must be positive, got {self.fps!r}")

    def to_json_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        if d["bic_thresholds"] is not None:
            d["bic_thresholds"] = list(d["bic_thresholds"])
        return d


# ---------------------------------------------------------------------------------------------
# Segment lists: numpy arrays (seq, start, length, label), one row per segment, in time order
# ---------------------------------------------------------------------------------------------
Segs = np.ndarray  # (n, 4) int64


def _feasible(n: int, tmin: int, tmax: int) -> bool:
    """Whether ``n`` frames split into pieces of lengths in ``[tmin, tmax]`` (0 is fine)."""
    if n == 0:
        return True
    k = -(-n // tmax)  # fewest pieces
    return k * tmin <= n


def _check_data(
    data: Sequence[Motion] | Sequence[Any] | Motion, config: LearnConfig
) -> tuple[list[np.ndarray], FeatureMap | None, list[Motion] | None]:
    if isinstance(data, Motion) or (hasattr(data, "ndim") and getattr(data, "ndim", 0) == 2):
        data = [data]  # type: ignore[list-item]
    data = list(data)
    if not data:
        raise ValueError("learn: the data list is empty")
    fm = None
    motions = None
    if all(isinstance(d, Motion) for d in data):
        motions = [m if config.fps is None else m.resample(config.fps) for m in data]
        fm = FeatureMap.fit(motions)
        ys = [np.asarray(fm.encode(m)) for m in motions]
    elif any(isinstance(d, Motion) for d in data):
        raise TypeError("learn: data must be all Motions or all (T, D) arrays, not a mixture")
    else:
        ys = []
        for i, d in enumerate(data):
            a = np.asarray(d)
            if a.ndim != 2:
                raise ValueError(f"learn: sequence {i} must have shape (T, D), got {a.shape}")
            if a.dtype.kind not in "fiu":
                raise TypeError(f"learn: sequence {i} has dtype {a.dtype}, expected numbers")
            ys.append(a.astype(np.result_type(a.dtype, np.float32)))
    dim = ys[0].shape[1]
    tmax = config.tmax
    for i, y in enumerate(ys):
        if y.shape[1] != dim:
            raise ValueError(
                f"learn: sequence {i} has D = {y.shape[1]} but sequence 0 has D = {dim}"
            )
        bad = ~np.all(np.isfinite(y), axis=1)
        if bad.any():
            raise ValueError(
                f"learn: sequence {i} has NaN/inf in frame {int(np.nonzero(bad)[0][0])}"
            )
        if y.shape[0] < config.tmin:
            raise ValueError(
                f"learn: sequence {i} has {y.shape[0]} frames, shorter than tmin = {config.tmin}"
            )
        if tmax is not None and not _feasible(y.shape[0], config.tmin, tmax):
            raise ValueError(
                f"learn: sequence {i} has {y.shape[0]} frames, which cannot be cut into "
                f"segments of {config.tmin}..{tmax} frames"
            )
    if config.state_dim > dim:
        raise ValueError(
            f"learn: state_dim = {config.state_dim} exceeds the observation dimension {dim}"
        )
    return ys, fm, motions


# ---------------------------------------------------------------------------------------------
# Greedy initialisation
# ---------------------------------------------------------------------------------------------
@eqx.filter_jit
def _prediction_errors(tex: Texton, Y: Float[Array, "L D"]) -> Float[Array, "n L"]:
    """Per-frame one-step prediction error ``‖y_t − μ − C(A1 x_{t−1} + A2 x_{t−2} + d)‖² / D``.

    ``tex`` may be stacked (leading axis ``n``); frames 0 and 1 get 0.
    """

    def one(t: Texton) -> Array:
        X = (Y - t.mu) @ t.C
        pred = X[1:-1] @ t.A1.T + X[:-2] @ t.A2.T + t.d
        yhat = t.mu + pred @ t.C.T
        e = jnp.sum((Y[2:] - yhat) ** 2, axis=1) / Y.shape[1]
        return jnp.concatenate([jnp.zeros((2,), Y.dtype), e])

    if tex.mu.ndim == 1:
        return one(tex)[None]
    return jax.vmap(one)(tex)


class _Bank:
    """Textons found so far, stacked with a doubling capacity (few recompilations)."""

    def __init__(self) -> None:
        self.items: list[Texton] = []
        self._stack: Texton | None = None
        self._cap = 0

    def add(self, t: Texton) -> int:
        self.items.append(t)
        self._stack = None
        return len(self.items) - 1

    def stacked(self) -> Texton:
        if self._stack is None:
            n = len(self.items)
            self._cap = max(self._cap, 1)
            while self._cap < n:
                self._cap *= 2
            padded = self.items + [self.items[-1]] * (self._cap - n)
            self._stack = stack_textons(padded)
        return self._stack


def greedy_init(
    ys: Sequence[np.ndarray], config: LearnConfig, threshold: float, *, smooth: int = 3
) -> tuple[Segs, int]:
    """Greedy segmentation of MT §4.

    For each sequence, from frame ``b``: test every texton found so far on the next ``tmin``
    frames and take the one with the lowest mean prediction error if that is at most
    ``threshold``; otherwise fit a new texton on those frames. Then extend the segment frame by
    frame while that texton's prediction error (averaged over the last ``smooth`` frames) stays
    at most ``threshold`` (never beyond ``tmax``, and never leaving a remainder that cannot be
    segmented). The error of frame ``t`` is ``‖y_t − μ − C(A1 x_{t−1} + A2 x_{t−2} + d)‖² / D``.

    Returns:
        ``(segments, n_textons)``; segments as rows ``(seq, start, length, label)``.
    """
    tmin = config.tmin
    rows: list[tuple[int, int, int, int]] = []
    bank = _Bank()
    for s, y in enumerate(ys):
        T = y.shape[0]
        tmax = T if config.tmax is None else config.tmax
        yj = jnp.asarray(y)
        b = 0
        while b < T:
            win = yj[b : b + tmin]
            label = -1
            if bank.items:
                err = np.asarray(_prediction_errors(bank.stacked(), win))[: len(bank.items)]
                mean_err = err[:, 2:].mean(axis=1)
                best = int(np.argmin(mean_err))
                if mean_err[best] <= threshold:
                    label = best
            if label < 0:
                label = bank.add(
                    fit_texton(
                        win,
                        state_dim=config.state_dim,
                        ridge=config.ridge,
                        q_floor=config.q_floor,
                        sigma2_floor=config.sigma2_floor,
                        rho_max=config.rho_max,
                        init_prior_weight=config.init_prior_weight,
                    )
                )
            # extend while the running mean error stays below the threshold
            hi = min(b + tmax, T)
            span = np.zeros((tmax, y.shape[1]), y.dtype)
            span[: hi - b] = y[b:hi]
            e_t = np.asarray(_prediction_errors(bank.items[label], jnp.asarray(span)))[0]
            e_t = e_t[: hi - b]
            # local error: mean over the last `smooth` frames (robust to a single noisy frame,
            # but sharp at a change of dynamics, unlike a running mean over the whole segment)
            loc = np.convolve(e_t, np.ones(smooth) / smooth, mode="full")[: hi - b]
            length = tmin
            while length < hi - b and loc[length] <= threshold:
                length += 1
            # keep the rest segmentable
            if not _feasible(T - b - length, tmin, tmax):
                cands = [L for L in range(tmin, hi - b + 1) if _feasible(T - b - L, tmin, tmax)]
                length = min(cands, key=lambda L: (abs(L - length), L))
            rows.append((s, b, length, label))
            b += length
    return np.asarray(rows, dtype=np.int64).reshape(-1, 4), len(bank.items)


def threshold_for_textons(
    ys: Sequence[np.ndarray], config: LearnConfig, n_textons: int, *, iters: int = 18
) -> tuple[float, Segs, int]:
    """Bisection on the (log) threshold for a greedy initialisation with ``n_textons`` textons.

    Returns the threshold, its segmentation and the number of textons it gives (the closest
    to the request that the search found; ties prefer more textons).
    """
    lo, hi = math.log(1e-5), math.log(1e3)
    best: tuple[int, float, Segs, int] | None = None
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        segs, n = greedy_init(ys, config, math.exp(mid))
        score = abs(n - n_textons)
        if best is None or score < best[0] or (score == best[0] and n > best[3]):
            best = (score, math.exp(mid), segs, n)
        if n == n_textons:
            break
        if n > n_textons:
            lo = mid
        else:
            hi = mid
    assert best is not None
    return best[1], best[2], best[3]


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


# ---------------------------------------------------------------------------------------------
# The model
# ---------------------------------------------------------------------------------------------
class MotionTexture(eqx.Module):
    """A learned motion texture: textons, their transition matrix and statistics.

    Attributes:
        textons: stacked :class:`Texton` (leading axis ``N_t``).
        M: ``(N_t, N_t)`` transition matrix, rows sum to 1 (``M[l, i] = P(i | l)``).
        pi: ``(N_t,)`` initial texton distribution.
        key_poses: ``(n_seg, 2, D)`` first two frames of every training segment.
        key_pose_labels: ``(n_seg,)`` texton of each key pose pair.
        segment_lengths: ``(n_seg,)`` length of every training segment.
        segments: ``(n_seg, 4)`` training segmentation rows ``(seq, start, length, label)``.
        history: ``(n_iter, 2)`` per EM iteration: objective after the M-step and after the
            E-step (log-likelihood of the segmentation).
        feature_map: the :class:`FeatureMap` of the training clips (``None`` for raw arrays).
        config: the :class:`LearnConfig` (static).
        threshold: the greedy-initialisation threshold used (static).
    """

    textons: Texton
    M: Float[Array, "n n"]
    pi: Float[Array, " n"]
    key_poses: Float[Array, "s 2 D"]
    key_pose_labels: Int[Array, " s"]
    segment_lengths: Int[Array, " s"]
    segments: Int[Array, "s 4"]
    history: Float[Array, "it 2"]
    feature_map: FeatureMap | None
    config: LearnConfig = eqx.field(static=True)
    threshold: float = eqx.field(static=True)

    def __check_init__(self) -> None:
        n = self.textons.n_textons if self.textons.is_stacked else 1
        if np.shape(self.M) != (n, n):
            raise ValueError(f"MotionTexture.M must have shape ({n}, {n}), got {np.shape(self.M)}")
        if np.shape(self.pi) != (n,):
            raise ValueError(f"MotionTexture.pi must have shape ({n},), got {np.shape(self.pi)}")
        s = np.shape(self.key_pose_labels)[0]
        if np.shape(self.key_poses)[:2] != (s, 2):
            raise ValueError("MotionTexture.key_poses must have shape (n_seg, 2, D)")
        if np.shape(self.segments) != (s, 4) or np.shape(self.segment_lengths) != (s,):
            raise ValueError("MotionTexture.segments / segment_lengths disagree with key poses")

    @property
    def n_textons(self) -> int:
        return int(np.shape(self.M)[0])

    @property
    def obs_dim(self) -> int:
        return int(np.shape(self.textons.mu)[-1])

    def length_stats(self) -> np.ndarray:
        """Per texton: ``(count, mean, std, min, max)`` of its training segment lengths."""
        out = np.zeros((self.n_textons, 5))
        lab = np.asarray(self.key_pose_labels)
        ln = np.asarray(self.segment_lengths)
        for i in range(self.n_textons):
            li = ln[lab == i]
            if li.size:
                out[i] = (li.size, li.mean(), li.std(), li.min(), li.max())
        return out

    def segment(self, Y: Float[Any, "T D"]) -> Segmentation:
        """Optimal segmentation of observations ``Y (T, D)`` (or a :class:`Motion`)."""
        if isinstance(Y, Motion):
            if self.feature_map is None:
                raise ValueError("this texture was learned from arrays; pass observations Y")
            Y = self.feature_map.encode(Y)
        y = jnp.asarray(Y)
        if y.ndim != 2 or y.shape[1] != self.obs_dim:
            raise ValueError(f"Y must have shape (T, {self.obs_dim}), got {tuple(y.shape)}")
        return segment(
            self.textons,
            jnp.log(jnp.asarray(self.M)),
            jnp.log(jnp.asarray(self.pi)),
            y,
            self.config.tmin,
            self.config.tmax,
        )

    # ------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write to a ``.npz`` (arrays) with JSON metadata; no pickle."""
        arrays: dict[str, Any] = {
            f"texton.{f.name}": np.asarray(getattr(self.textons, f.name))
            for f in dataclasses.fields(self.textons)
        }
        arrays.update(
            M=np.asarray(self.M),
            pi=np.asarray(self.pi),
            key_poses=np.asarray(self.key_poses),
            key_pose_labels=np.asarray(self.key_pose_labels),
            segment_lengths=np.asarray(self.segment_lengths),
            segments=np.asarray(self.segments),
            history=np.asarray(self.history),
        )
        meta: dict[str, Any] = {
            "kind": _KIND,
            "format_version": FORMAT_VERSION,
            "config": self.config.to_json_dict(),
            "threshold": self.threshold,
            "texton_fields": [f.name for f in dataclasses.fields(self.textons)],
            "feature_map": None,
        }
        if self.feature_map is not None:
            fa, fmeta = self.feature_map.to_arrays_json()
            arrays.update({f"feature_map.{k}": v for k, v in fa.items()})
            meta["feature_map"] = fmeta
        save_arrays_json(path, arrays, meta)


_REQUIRED = ("M", "pi", "key_poses", "key_pose_labels", "segment_lengths", "segments", "history")


def load_texture(path: str | os.PathLike[str]) -> MotionTexture:
    """Read a :class:`MotionTexture` written by :meth:`MotionTexture.save`.

    Raises:
        ValueError: naming the file and the problem (corrupt or truncated archive, another kind
            of file, unsupported format version, missing or inconsistent arrays).
    """
    arrays, meta = load_arrays_json(path, kind=_KIND, required=_REQUIRED)
    if meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(
            f"{path}: format version {meta.get('format_version')!r} is not supported "
            f"(this mtex_jax reads version {FORMAT_VERSION})"
        )
    try:
        fields = meta["texton_fields"]
        missing = [f for f in fields if f"texton.{f}" not in arrays]
        if missing:
            raise ValueError(f"missing arrays {['texton.' + f for f in missing]}")
        textons = Texton(**{f: jnp.asarray(arrays[f"texton.{f}"]) for f in fields})
        fm = None
        if meta.get("feature_map") is not None:
            fa = {k.split(".", 1)[1]: v for k, v in arrays.items() if k.startswith("feature_map.")}
            fm = FeatureMap.from_arrays_json(fa, meta["feature_map"])
        cfg_d = dict(meta["config"])
        if cfg_d.get("bic_thresholds") is not None:
            cfg_d["bic_thresholds"] = tuple(cfg_d["bic_thresholds"])
        cfg = LearnConfig(**cfg_d)
        return MotionTexture(
            textons=textons,
            M=jnp.asarray(arrays["M"]),
            pi=jnp.asarray(arrays["pi"]),
            key_poses=jnp.asarray(arrays["key_poses"]),
            key_pose_labels=jnp.asarray(arrays["key_pose_labels"]),
            segment_lengths=jnp.asarray(arrays["segment_lengths"]),
            segments=jnp.asarray(arrays["segments"]),
            history=jnp.asarray(arrays["history"]),
            feature_map=fm,
            config=cfg,
            threshold=float(meta["threshold"]),
        )
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: invalid motion texture file: {e}") from None


# ---------------------------------------------------------------------------------------------
# EM
# ---------------------------------------------------------------------------------------------
class _Runner:
    """Padded, optionally sharded data and the jitted M- and E-steps."""

    def __init__(self, ys: list[np.ndarray], config: LearnConfig) -> None:
        self.ys = ys
        self.config = config
        self.n_real = len(ys)
        devices = jax.devices()
        n_dev = len(devices) if config.shard else 1
        n_seq = -(-self.n_real // n_dev) * n_dev
        ypad, nf = _pad(ys, n_seq)
        self.T = ypad.shape[1]
        self.n_seq = n_seq
        self.sharding = None
        if n_dev > 1:
            mesh = jax.sharding.Mesh(np.asarray(devices), ("seq",))
            self.sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("seq"))
        self.Y = self._put(ypad)
        self.nf = self._put(nf)
        self.opts = _SolveOptions.make(
            config.ridge, config.q_floor, config.rho_max, config.init_prior_weight
        )
        self.tmax = self.T if config.tmax is None else config.tmax

    def _put(self, a: np.ndarray) -> Array:
        if self.sharding is None:
            return jnp.asarray(a)
        return jax.device_put(a, self.sharding)

    def m_step(self, segs: Segs, n_textons: int) -> tuple[Texton, np.ndarray, np.ndarray]:
        """Fit all textons; the stack is padded to a power of two (slots past ``n_textons``
        are unused) so that a changing number of textons recompiles rarely."""
        n = len(segs)
        cap = _capacity(n)
        rows = np.zeros((cap, 4), dtype=np.int64)
        rows[:n] = segs
        valid = np.arange(cap) < n
        tex = _fit_all(
            self.Y,
            jnp.asarray(rows),
            jnp.asarray(valid),
            _capacity(n_textons),
            self.tmax,
            self.config.state_dim,
            float(self.config.sigma2_floor),
            self.opts,
        )
        M, pi = _transitions(segs, n_textons, self.config.pseudo_count)
        return tex, M, pi

    def e_step(self, tex: Texton, M: np.ndarray, pi: np.ndarray) -> tuple[Segs, float]:
        # only the real textons: the capacity padding of the M-step would double the work
        # (N_t changes rarely, so the extra compilations are few)
        tex = jax.tree.map(lambda a: a[: M.shape[0]], tex)
        log_M, log_pi = _padded_logs(M, pi, tex.n_textons)
        seg = _segment_batch(
            tex,
            jnp.asarray(log_M, self.Y.dtype),
            jnp.asarray(log_pi, self.Y.dtype),
            self.Y,
            self.nf,
            self.config.tmin,
            self.tmax,
        )
        starts = np.asarray(seg.starts)
        lengths = np.asarray(seg.lengths)
        labels = np.asarray(seg.labels)
        nseg = np.asarray(seg.n_segments)
        scores = np.asarray(seg.score)
        rows = []
        for s in range(self.n_real):
            for k in range(int(nseg[s])):
                rows.append((s, int(starts[s, k]), int(lengths[s, k]), int(labels[s, k])))
        return np.asarray(rows, dtype=np.int64).reshape(-1, 4), float(scores[: self.n_real].sum())

    def objective(self, tex: Texton, M: np.ndarray, pi: np.ndarray, segs: Segs) -> float:
        """log P(Y, segmentation | model): segment scores plus initial/transition terms."""
        n = len(segs)
        cap = _capacity(n)
        rows = np.zeros((cap, 4), dtype=np.int64)
        rows[:, 2] = 2  # padding rows: a valid 2-frame segment, weight 0
        rows[:n] = segs
        w = np.zeros(cap)
        w[:n] = 1.0
        tex = jax.tree.map(lambda a: a[: M.shape[0]], tex)
        seg_ll = float(_rows_score(tex, self.Y, jnp.asarray(rows), jnp.asarray(w, self.Y.dtype)))
        log_M, log_pi = np.log(M), np.log(pi)
        total = seg_ll
        for s in range(self.n_real):
            lab = segs[segs[:, 0] == s, 3]
            total += float(log_pi[lab[0]] + log_M[lab[:-1], lab[1:]].sum())
        return total


def _n_params(n_t: int, D: int, k: int) -> int:
    per = D + (D * k - k * (k + 1) // 2) + 2 * k * k + k + k * (k + 1) // 2 + 1 + 2 * k
    per += k * (2 * k + 1)
    return n_t * per + n_t * (n_t - 1) + n_t - 1


def learn(
    data: Sequence[Motion] | Sequence[Any] | Motion,
    config: LearnConfig | None = None,
    *,
    verbose: bool = False,
    callback: Callable[[dict[str, Any]], None] | None = None,
) -> MotionTexture:
    """Learn a motion texture from clips (MT §4): greedy initialisation and hard EM.

    The greedy threshold comes from ``config.threshold``; else from a search for
    ``config.n_textons`` textons; else, if ``config.bic_thresholds`` is set, every threshold
    there is tried (initialisation + EM) and the model with the lowest BIC is returned
    (see :func:`bic_select`); else 0.3.

    Args:
        data: a list of :class:`Motion` (one skeleton; a :class:`FeatureMap` is fitted and
            stored) or of ``(T_s, D)`` observation arrays.
        config: :class:`LearnConfig` (lengths in frames).
        verbose: print progress: the initialisation and one line per EM iteration.
        callback: called after every EM iteration with a dict (``iteration``, ``n_textons``,
            ``objective_m``, ``objective_e``, ``changed`` (frames whose texton changed),
            ``seconds``).

    Returns:
        the :class:`MotionTexture` of the EM iteration with the best objective
        ``max_H log P(Y, H | Θ, M)``; its ``segments`` are that model's optimal segmentation.

    Raises:
        ValueError: empty data, sequences shorter than ``tmin`` (or not segmentable into
            ``[tmin, tmax]``), inconsistent ``D``, NaN frames, ``tmin < 3``, ``tmax < tmin``.
    """
    config = LearnConfig() if config is None else config
    if not isinstance(config, LearnConfig):
        raise TypeError(f"config must be a LearnConfig, got {type(config).__name__}")
    ys, fm, _ = _check_data(data, config)
    _check_lengths(config.tmin, config.tmax, max(y.shape[0] for y in ys))
    run = _Runner(ys, config)
    if config.threshold is None and config.n_textons is None and config.bic_thresholds:
        _, table, models = _bic(run, fm, config, config.bic_thresholds, verbose, callback)
        best = int(np.argmin([r["bic"] for r in table]))
        return models[best]
    t0 = time.perf_counter()
    if config.threshold is not None:
        threshold = float(config.threshold)
        segs, _ = greedy_init(ys, config, threshold)
    elif config.n_textons is not None:
        threshold, segs, _ = threshold_for_textons(ys, config, config.n_textons)
    else:
        threshold = 0.3
        segs, _ = greedy_init(ys, config, threshold)
    if verbose:
        print(
            f"[mtex learn] greedy init: {int(segs[:, 3].max()) + 1} textons, {len(segs)} "
            f"segments, threshold {threshold:.4g}, {time.perf_counter() - t0:.1f} s",
            flush=True,
        )
    return _em(run, fm, config, threshold, segs, verbose, callback, t0)


def _em(
    run: _Runner,
    fm: FeatureMap | None,
    config: LearnConfig,
    threshold: float,
    segs: Segs,
    verbose: bool,
    callback: Callable[[dict[str, Any]], None] | None,
    t0: float,
) -> MotionTexture:
    ys = run.ys
    n_frames = sum(y.shape[0] for y in ys)
    segs, _ = _relabel(segs)
    history: list[tuple[float, float]] = []
    best: tuple[float, Texton, np.ndarray, np.ndarray, Segs] | None = None
    for it in range(config.max_iter + 1):
        n_t = int(segs[:, 3].max()) + 1
        tex, M, pi = run.m_step(segs, n_t)
        obj_m = run.objective(tex, M, pi, segs)
        new_segs, obj_e = run.e_step(tex, M, pi)
        # pruning: textons with fewer than min_segments segments are removed from the model
        # (M, π renormalised) and every clip is segmented again by the others, until none is
        # left; the model and segmentation stay complete and consistent
        n_pruned = 0
        while (prune := _underused(new_segs, config.min_segments)).size:
            tex, M, pi = _keep_textons(tex, M, pi, np.setdiff1d(np.arange(M.shape[0]), prune))
            new_segs, obj_e = run.e_step(tex, M, pi)
            n_pruned += prune.size
        lab_old, _ = _masks(segs, run.n_real, run.T)
        lab_new, _ = _masks(new_segs, run.n_real, run.T)
        changed = int(np.sum(lab_old != lab_new))  # frames whose texton changed
        history.append((obj_m, obj_e))
        if best is None or obj_e > best[0]:
            best = (obj_e, tex, M, pi, new_segs)
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
        converged = changed == 0 or gain < config.tol * n_frames
        # after a pruning the remaining textons are refitted to their new segments first
        if it == config.max_iter or (converged and n_pruned == 0):
            break
        segs, _ = _relabel(new_segs)

    assert best is not None
    _, tex, M, pi, final_segs = best
    tex = jax.tree.map(lambda a: a[: M.shape[0]], tex)  # drop the capacity padding
    used = np.unique(final_segs[:, 3])
    if len(used) < M.shape[0]:  # a texton that lost all its segments: remove it
        tex, M, pi = _keep_textons(tex, M, pi, used)
        final_segs, _ = _relabel(final_segs)
    key = np.stack([np.stack([ys[s][b], ys[s][b + 1]]) for s, b, _, _ in final_segs])
    return MotionTexture(
        textons=tex,
        M=jnp.asarray(M),
        pi=jnp.asarray(pi),
        key_poses=jnp.asarray(key),
        key_pose_labels=jnp.asarray(final_segs[:, 3]),
        segment_lengths=jnp.asarray(final_segs[:, 2]),
        segments=jnp.asarray(final_segs),
        history=jnp.asarray(np.asarray(history)),
        feature_map=fm,
        config=config,
        threshold=threshold,
    )


def _bic(
    run: _Runner,
    fm: FeatureMap | None,
    config: LearnConfig,
    thresholds: Sequence[float],
    verbose: bool,
    callback: Callable[[dict[str, Any]], None] | None,
) -> tuple[float, list[dict[str, float]], list[MotionTexture]]:
    n = sum(y.shape[0] for y in run.ys)
    D = run.ys[0].shape[1]
    table: list[dict[str, float]] = []
    models: list[MotionTexture] = []
    for th in thresholds:
        t0 = time.perf_counter()
        segs, _ = greedy_init(run.ys, config, float(th))
        model = _em(run, fm, config, float(th), segs, False, callback, t0)
        ll = float(np.asarray(model.history)[:, 1].max())
        p = _n_params(model.n_textons, D, config.state_dim)
        row = {
            "threshold": float(th),
            "n_textons": model.n_textons,
            "loglik": ll,
            "params": p,
            "bic": -2 * ll + p * math.log(n),
        }
        if verbose:
            print(
                f"[mtex learn] BIC: threshold {th:.4g}  textons {model.n_textons:3d}  "
                f"loglik {ll:.1f}  BIC {row['bic']:.1f}  {time.perf_counter() - t0:.1f} s",
                flush=True,
            )
        table.append(row)
        models.append(model)
    best = min(table, key=lambda r: r["bic"])
    return best["threshold"], table, models


def bic_select(
    data: Sequence[Motion] | Sequence[Any],
    config: LearnConfig,
    thresholds: Sequence[float],
    *,
    verbose: bool = False,
) -> tuple[float, list[dict[str, float]]]:
    """Choose the greedy threshold by BIC: initialisation and EM for every threshold.

    ``BIC = −2 max_H log P(Y, H | Θ, M) + p log n`` with ``n`` frames and ``p`` free
    parameters (per texton: ``μ`` D, ``C`` Dk − k(k+1)/2, ``A1, A2`` 2k², ``d`` k, ``Q``
    k(k+1)/2, ``σ²`` 1, ``m0`` 2k, ``S0`` k(2k+1); plus ``N_t(N_t − 1)`` transition and
    ``N_t − 1`` initial probabilities).

    Returns:
        ``(best_threshold, table)``, one dict per threshold (``threshold``, ``n_textons``,
        ``loglik``, ``params``, ``bic``).
    """
    ys, fm, _ = _check_data(data, config)
    run = _Runner(ys, config)
    th, table, _ = _bic(run, fm, config, thresholds, verbose, None)
    return th, table


def texture_summary(tex: MotionTexture) -> str:
    """A short human-readable description (used by the CLI)."""
    st = tex.length_stats()
    hist = np.asarray(tex.history)
    lines = [
        f"textons: {tex.n_textons}   segments: {len(np.asarray(tex.segments))}   "
        f"state dim: {tex.config.state_dim}   D: {tex.obs_dim}   threshold: {tex.threshold:.4g}",
        f"segment lengths (frames): min {int(st[:, 3][st[:, 0] > 0].min())}  "
        f"mean {np.asarray(tex.segment_lengths).mean():.1f}  max {int(st[:, 4].max())}  "
        f"(tmin {tex.config.tmin}, tmax {tex.config.tmax})",
        "objective per EM iteration (after M-step / after E-step):",
    ]
    lines += [f"  {i:2d}: {a:14.2f} / {b:14.2f}" for i, (a, b) in enumerate(hist)]
    return "\n".join(lines)
