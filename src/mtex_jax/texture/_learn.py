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

import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..motion import FeatureMap, Motion
from ._config import LearnConfig
from ._em import (
    _capacity,
    _fit_all,
    _keep_textons,
    _masks,
    _pad,
    _padded_logs,
    _relabel,
    _rows_score,
    _transitions,
    _underused,
)
from ._fit import _SolveOptions
from ._init import Segs, _feasible, greedy_init, threshold_for_textons
from ._model import MotionTexture
from ._segment import _check_lengths, _segment_batch
from ._texton import Texton


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
    if dim == 0 and fm is not None:
        raise ValueError(
            "learn: the clip does not move (every observation channel is constant in every "
            "clip); there is no motion to learn"
        )
    if config.state_dim > dim:
        raise ValueError(
            f"learn: state_dim = {config.state_dim} exceeds the observation dimension {dim}"
        )
    return ys, fm, motions


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
