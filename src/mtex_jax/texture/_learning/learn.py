"""Learning a motion texture (MT §4, design §4): greedy initialisation, hard EM, selection.

``learn(data, LearnConfig(...))`` turns clips into a :class:`MotionTexture`:

1. observation vectors ``Y`` (a :class:`FeatureMap` fitted on the clips, or arrays as given)
   and the state dimension (by BIC unless given; design §4.7);
2. greedy initialisation (design §4.4): grow segments while a texton's one-step prediction
   error stays below a threshold, reusing an existing texton when it explains the next
   ``tmin`` frames;
3. hard EM (design §4.1–4.6; the loop is :func:`~.loop.run_em`): M-step = closed-form texton
   fits on all segments of each texton, transition matrix and initial distribution with a
   Dirichlet pseudo-count; E-step = globally optimal segmentation by the semi-Markov Viterbi,
   batched over clips (:class:`~.em.Runner`);
4. the BIC selection of the textons or of the threshold (design §4.7), and the innovations
   of synthesis (design §10.8).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ...motion import FeatureMap, Motion
from .._config import LearnConfig
from .._model import MotionTexture
from .._noise.innovation_process import (
    innovation_statistics,
    process_from_statistics,
    segment_innovations,
)
from .._noise.residual_bank import PLAUSIBLE_TAIL, plausible_bank
from .._observation import OBSERVATION_MODELS, FullObservation
from .._segmentation.segment import check_lengths
from .._texton.select import choose_state_dim, n_params
from .checkpoint import Checkpoint, SelectionState, learn_digest
from .contacts import with_contacts
from .em import PAD_E_STEP, Capacity, Runner
from .init import (
    Segs,
    chunk_init,
    feasible,
    greedy_init,
    initial_textons,
    threshold_for_textons,
)
from .labels import capacity_for, keep_textons
from .loop import EM, EMSettings, run_em


def check_data(
    data: Sequence[Motion] | Sequence[Any] | Motion, config: LearnConfig
) -> tuple[list[np.ndarray], FeatureMap | None, list[Motion] | None]:
    """The observation arrays of ``data``, checked against ``config`` (design §1, §4.8).

    Returns:
        ``(ys, feature_map, motions)``: the ``(T_s, D)`` arrays; for motions (resampled to
        ``config.fps``) the fitted :class:`FeatureMap` and the motions, else ``None``.

    Raises:
        TypeError, ValueError: as :func:`learn` documents.
    """
    if isinstance(data, Motion) or (hasattr(data, "ndim") and getattr(data, "ndim", 0) == 2):
        data = [data]  # type: ignore[list-item]
    data = list(data)
    if not data:
        raise ValueError("learn: the data list is empty")
    fm = None
    motions = None
    if all(isinstance(d, Motion) for d in data):
        motions = [m if config.fps is None else m.resample(config.fps) for m in data]
        fm, ys = FeatureMap.fit_encode(motions)
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
        if tmax is not None and not feasible(y.shape[0], config.tmin, tmax):
            raise ValueError(
                f"learn: sequence {i} has {y.shape[0]} frames, which cannot be cut into "
                f"segments of {config.tmin}..{tmax} frames"
            )
    if dim == 0 and fm is not None:
        raise ValueError(
            "learn: the clip does not move (every observation channel is constant in every "
            "clip); there is no motion to learn"
        )
    if config.state_dim is not None and config.state_dim > dim:
        raise ValueError(
            f"learn: state_dim = {config.state_dim} exceeds the observation dimension {dim}"
        )
    fixed = config.observation_model.fixed_state_dim(dim)
    if fixed is not None and config.state_dim not in (None, fixed):
        free = [n for n, m in OBSERVATION_MODELS.items() if m.fixed_state_dim(dim) is None]
        raise ValueError(
            f"learn: observation={config.observation!r} has state_dim = D = {dim}, "
            f"got {config.state_dim}; leave state_dim unset, or choose an observation model "
            f"whose state dimension is free: {', '.join(free)}"
        )
    return ys, fm, motions


def resolve_state_dim(ys: list[np.ndarray], config: LearnConfig, verbose: bool) -> LearnConfig:
    """The config with a concrete ``state_dim`` (``D`` for ``"full"``, else by BIC if unset)
    and ``dof=None`` unless the textons are full-dimensional (``LearnConfig.dof``)."""
    cfg = _resolve_k(ys, config, verbose)
    if cfg.dof != cfg.texton_dof:
        cfg = dataclasses.replace(cfg, dof=cfg.texton_dof)
    if verbose:
        inn = "Gaussian" if cfg.dof is None else f"Student-t, {cfg.dof:g} degrees of freedom"
        print(f"[mtex learn] dynamics innovations: {inn}", flush=True)
    return cfg


def _resolve_k(ys: list[np.ndarray], config: LearnConfig, verbose: bool) -> LearnConfig:
    D = ys[0].shape[1]
    fixed = config.observation_model.fixed_state_dim(D)
    if fixed is not None:
        return dataclasses.replace(config, state_dim=fixed)
    if config.state_dim is not None:
        return config
    if D == 1:
        return dataclasses.replace(config, state_dim=1)
    k, table = choose_state_dim(ys, config.observation_model, ridge=config.ridge)
    if verbose:
        bics = ", ".join(f"{int(r['k'])}: {r['bic']:.4g}" for r in table)
        print(f"[mtex learn] state dimension by BIC: k = {k}  ({bics})", flush=True)
    # k = D leaves no residual: the texton is the "full" one
    return dataclasses.replace(
        config, state_dim=k, observation=FullObservation.name if k == D else config.observation
    )


def learn(
    data: Sequence[Motion] | Sequence[Any] | Motion,
    config: LearnConfig | None = None,
    *,
    verbose: bool = False,
    callback: Callable[[dict[str, Any]], None] | None = None,
    checkpoint: str | os.PathLike[str] | None = None,
    resume: bool = False,
) -> MotionTexture:
    """Learn a motion texture from clips (MT §4, design §4): greedy initialisation and hard EM.

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
        checkpoint: a file (``.npz``) where the progress is written, atomically, after every
            EM iteration (design §4.9); it must not exist unless ``resume``.
        resume: continue from ``checkpoint`` if it exists (else start afresh). The model is
            bit for bit the one an uninterrupted learn gives. A checkpoint of other clips or
            another configuration is refused.

    Returns:
        the :class:`MotionTexture` of the EM iteration with the best objective
        ``max_H log P(Y, H | Θ, M)``; its ``segments`` are that model's optimal segmentation.
        Learned from clips, it carries their contact model (``contacts``, design §6.6).

    Raises:
        ValueError: empty data, sequences shorter than ``tmin`` (or not segmentable into
            ``[tmin, tmax]``), inconsistent ``D``, NaN frames, ``tmin < 3``, ``tmax < tmin``;
            a checkpoint that exists without ``resume``, or is of another learn.
    """
    config = LearnConfig() if config is None else config
    if not isinstance(config, LearnConfig):
        raise TypeError(f"config must be a LearnConfig, got {type(config).__name__}")
    ys, fm, clips = check_data(data, config)
    check_lengths(config.tmin, config.tmax, max(y.shape[0] for y in ys))
    search = (
        config.bic_thresholds if config.threshold is None and config.n_textons is None else None
    )
    if checkpoint is not None and search:
        raise ValueError(
            "checkpoint: a learn that tries every threshold of bic_thresholds is not "
            "checkpointed; give threshold or n_textons"
        )
    given = config  # a checkpoint's digest is of the configuration as given
    config = resolve_state_dim(ys, config, verbose)
    run = Runner(ys, config)
    ck = None
    if checkpoint is not None:
        ck = Checkpoint(checkpoint, learn_digest(ys, given), resume, run)
    if ck is not None and ck.resumed and verbose:
        print(f"[mtex learn] resuming from {checkpoint} ({ck.saved_stage()})", flush=True)
    if search:
        settings = EMSettings(fm, verbose, callback)
        greedy = lambda th: greedy_init(ys, config, th)[0]
        _, table, models = threshold_bic(run, config, search, greedy, settings)
        best = int(np.argmin([r["bic"] for r in table]))
        return with_contacts(with_innovations(models[best], ys), clips, verbose)
    t0 = time.perf_counter()
    threshold, segs = greedy_segments(ys, config, verbose, t0)
    settings = EMSettings(fm, verbose, callback, t0)
    model = em_and_selection(run, config, threshold, segs, settings, ck)
    return with_contacts(with_innovations(model, ys), clips, verbose)


def with_innovations(
    model: MotionTexture,
    ys: Sequence[np.ndarray],
    offset: int = 0,
    reduce: Callable[[np.ndarray], np.ndarray] | None = None,
    gather: Callable[[dict[str, np.ndarray]], list[dict[str, np.ndarray]]] | None = None,
) -> MotionTexture:
    """``model`` with its :class:`InnovationProcess` fitted on the training residuals of its
    segmentation (``config.innovations`` ``"fitted"`` or ``"residuals"``; the latter also
    keeps the residuals themselves, a :class:`ResidualBank`); with ``"white"`` unchanged.

    ``ys`` are the clips numbered from ``offset`` in ``model.segments`` (a process's share
    of a distributed learn); ``reduce`` sums the statistics over processes and ``gather``
    collects every process's arrays, in process order (both collectives).
    """
    if model.config.innovations == "white":
        return model
    segs = np.asarray(model.segments, dtype=np.int64)
    mine = (segs[:, 0] >= offset) & (segs[:, 0] < offset + len(ys))
    rows = segs[mine]
    rows[:, 0] -= offset
    res = segment_innovations(model.textons, ys, rows)
    stats = innovation_statistics(res)
    if reduce is not None:
        stats = reduce(stats)
    process = process_from_statistics(stats)
    if model.config.innovations != "residuals":
        return dataclasses.replace(model, innovations=process)
    if gather is not None:  # every process's residuals, in the order of model.segments
        k = int(np.shape(model.textons.C)[-1])
        local = {
            "u": np.concatenate(res) if res else np.zeros((0, k)),
            "n": np.asarray([len(r) for r in res], np.int64),
            "idx": np.flatnonzero(mine),
        }
        res = [np.zeros((0, k))] * len(segs)
        for part in gather(local):
            cuts = np.cumsum(part["n"])[:-1]
            for i, r in zip(part["idx"], np.split(part["u"], cuts), strict=True):
                res[int(i)] = r
    elif offset or reduce is not None:
        raise ValueError("LearnConfig.innovations='residuals' needs gather with offset/reduce")
    bank = plausible_bank(res, segs[:, 3], model.textons.dof, PLAUSIBLE_TAIL)
    return dataclasses.replace(model, innovations=process, residuals=bank)


def _refit_config(config: LearnConfig) -> LearnConfig:
    """``config`` with at most 5 EM iterations: the EM runs of the BIC selection."""
    return dataclasses.replace(config, max_iter=min(config.max_iter, 5))


def _em(
    em: EM,
    segs: Segs,
    threshold: float,
    settings: EMSettings,
    ck: Checkpoint | None,
    stage: str | None = None,
    **kw: Any,
) -> MotionTexture:
    """:func:`run_em` of the checkpoint's current stage (``stage``: it begins here; a
    selection round begins before its E-step): continued from its saved state if it was made
    there, and saved after every iteration."""
    if ck is None:
        return run_em(em, segs, threshold, settings, **kw)
    if stage is not None:
        ck.begin(stage)
    return run_em(em, segs, threshold, settings, start=ck.enter(), on_state=ck.save, **kw)


def em_and_selection(
    run: Runner,
    config: LearnConfig,
    threshold: float,
    segs: Segs,
    settings: EMSettings,
    ck: Checkpoint | None = None,
) -> MotionTexture:
    """EM from the greedy segments, then (``config.selection`` ``"aic"`` or ``"bic"``) the
    selection of the textons (design §4.7).

    With selection, the first EM runs at most 5 iterations: its many textons are only a
    starting point, and each selection round refits for 5 more. EM then runs to convergence
    (``config.max_iter``) on the selected textons, where an iteration is cheap.

    Args:
        run: the clips and the E- and M-steps.
        config: the configuration (``state_dim`` resolved).
        threshold: the greedy threshold of ``segs``.
        segs: the greedy segment rows ``(clip, start, length, label)``.
        settings: reporting and the feature map of every EM run.
        ck: the learn's checkpoint (design §4.9): the stages done are skipped, the one it
            was made in continues from its state.

    Returns:
        The model of the last EM run.
    """
    saved = None if ck is None else ck.saved_stage()
    if config.selection == "none":
        return _em(EM(run, config), segs, threshold, settings, ck, "em", prune_initial=True)
    sel = None if ck is None else ck.saved_selection()
    if saved == "final":
        assert sel is not None
        model, capacity = sel.best, Capacity(*sel.capacity)
    else:
        if sel is None:
            short = EM(run, _refit_config(config))
            model = _em(short, segs, threshold, settings, ck, "em", prune_initial=True)
        else:
            model = sel.best
        model, capacity = _backward_bic(run, config, model, settings, ck, sel)
    if settings.verbose:
        print("[mtex learn] EM on the selected textons", flush=True)
    # with the selection's padded sizes, so that no program is compiled again
    final = EM(run, config, capacity)
    segs = np.asarray(model.segments)
    return _em(final, segs, threshold, settings, ck, "final", prev=model.textons)


def greedy_segments(
    ys: list[np.ndarray], config: LearnConfig, verbose: bool, t0: float
) -> tuple[float, np.ndarray]:
    """The greedy initialisation's threshold and segments (``config.threshold``, or the one
    that gives ``config.n_textons``, or 0.3)."""
    if config.init == "chunks":
        threshold = 0.0 if config.threshold is None else float(config.threshold)
        n_init = config.n_textons
        if n_init is None:
            n_init = initial_textons(ys, config.chunk_length)
        segs = chunk_init(ys, config, n_init, config.chunk_length)
    elif config.threshold is not None:
        threshold = float(config.threshold)
        segs, _ = greedy_init(ys, config, threshold)
    elif config.n_textons is not None:
        threshold, segs, _ = threshold_for_textons(ys, config, config.n_textons)
    else:
        threshold = 0.3
        segs, _ = greedy_init(ys, config, threshold)
    if verbose:
        print(
            f"[mtex learn] {config.init} init: {int(segs[:, 3].max()) + 1} textons, {len(segs)} "
            f"segments, threshold {threshold:.4g}, {time.perf_counter() - t0:.1f} s",
            flush=True,
        )
    return threshold, segs


def bic_parts(model: MotionTexture, n_frames: int) -> tuple[float, float, float]:
    """``(log P(Y, H), p, BIC)`` of a learned model: its best EM objective, its number of free
    parameters and ``−2 log P(Y, H) + p log n``."""
    cfg = model.config
    assert cfg.state_dim is not None
    ll = float(np.asarray(model.history)[:, 1].max())
    p = n_params(
        model.n_textons,
        model.obs_dim,
        cfg.state_dim,
        cfg.observation_model,
        cfg.durations,
        np.asarray(model.segments),
    )
    return ll, p, -2 * ll + p * math.log(n_frames)


def penalty_weight(config: LearnConfig, n_frames: int) -> float:
    """The price of one free parameter in ``−2 log P(Y, H) + w p`` (design §4.7): ``log n``
    for ``selection="bic"``, 2 for ``"aic"``."""
    return math.log(n_frames) if config.selection == "bic" else 2.0


def _model_criterion(model: MotionTexture, n_frames: int, w: float) -> float:
    ll, p, _ = bic_parts(model, n_frames)
    return -2 * ll + w * p


def _backward_bic(
    run: Runner,
    config: LearnConfig,
    model: MotionTexture,
    settings: EMSettings,
    ck: Checkpoint | None = None,
    start: SelectionState | None = None,
) -> tuple[MotionTexture, Capacity]:
    """Backward elimination by BIC, ``BIC = −2 log P(Y, H) + p log n`` (design §4.7).

    Each round drops the ``m`` textons with the fewest segments (ties: fewest frames) and
    segments the clips again by the others. If the BIC of that segmentation under the
    remaining textons (an upper bound of the BIC after refitting) is lower, EM is rerun from
    it (at most 5 iterations); if the refitted model's BIC is lower too, it is accepted and
    the next round drops ``m`` again (at most half the textons). Otherwise ``m`` is halved; the
    selection stops when dropping a single texton does not lower the BIC. ``m`` starts at half
    the textons, so ``N_t`` textons are reduced to a few in ``O(log N_t)`` refits instead of
    ``N_t``, with the same one-at-a-time stopping rule at the end.

    Every E-step and refit pads its texton stacks (:class:`Capacity`): the M-step's to the
    first model's size (its cost is in the rows, not the textons, and each smaller stack
    would compile it again), the E-step's (up to ``PAD_E_STEP`` textons) to the current
    model's, so that a rejected drop compiles nothing.

    Args:
        run: the clips and the E- and M-steps.
        config: the configuration, stored in the refitted models.
        model: the model to reduce (from EM on the greedy segments).
        settings: the refits' callback and feature map (they print nothing).
        ck: the learn's checkpoint: each round's state is saved with its refit's iterations.
        start: the state to continue from (a resumed learn; ``model`` is then its best).

    Returns:
        The selected model, and the capacity of the last round: the final EM on the
        selected textons (:func:`em_and_selection`) uses it, so that it compiles nothing
        again.
    """
    n = run.n_frames
    w = penalty_weight(config, n)
    name = config.selection.upper()
    if start is None:
        best, best_bic = model, _model_criterion(model, n, w)
        m_cap = capacity_for(best.n_textons)
        m = max(1, best.n_textons // 2)
        rounds = 0
    else:
        best, best_bic, m, rounds, m_cap = (
            start.best,
            start.best_value,
            start.m,
            start.round,
            start.m_cap,
        )
    capacity = Capacity(m_step=m_cap)
    short = _refit_config(config)
    while best.n_textons > 1:
        t0 = time.perf_counter()
        if ck is not None:
            ck.set_selection(SelectionState(best, best_bic, m, rounds, m_cap))
            ck.begin("selection", rounds)
        rounds += 1
        cap = capacity_for(best.n_textons)
        capacity = Capacity(cap if cap <= PAD_E_STEP else 1, m_cap)
        m = min(m, max(1, best.n_textons // 2))
        segs = np.asarray(best.segments)
        counts = np.bincount(segs[:, 3], minlength=best.n_textons)
        frames = np.bincount(segs[:, 3], weights=segs[:, 2], minlength=best.n_textons)
        drop = np.lexsort((frames, counts))[:m]
        keep = np.setdiff1d(np.arange(best.n_textons), drop)
        tex, M, pi = keep_textons(best.textons, np.asarray(best.M), np.asarray(best.pi), keep)
        log_d = None if best.log_durations is None else np.asarray(best.log_durations)[keep]
        segs, score = run.e_step(tex, M, pi, log_d, capacity)
        cfg = best.config
        assert cfg.state_dim is not None
        p = n_params(
            len(keep), best.obs_dim, cfg.state_dim, cfg.observation_model, cfg.durations, segs
        )
        bound = -2 * score + p * w
        b, cand = bound, None
        if bound < best_bic:  # refit only when it can pay
            quiet = dataclasses.replace(settings, verbose=False, t0=t0)
            refit = EM(run, short, capacity)
            cand = _em(refit, segs, best.threshold, quiet, ck, prev=tex)
            cand = dataclasses.replace(cand, config=config) if cand.config != config else cand
            b = _model_criterion(cand, n, w)
        if settings.verbose:
            what = "before refitting" if bound >= best_bic else "refitted"
            print(
                f"[mtex learn] {name} selection: {best.n_textons} textons {best_bic:.6g}; "
                f"without {m} ({what}) {b:.6g}  {time.perf_counter() - t0:.1f} s",
                flush=True,
            )
        if cand is not None and b < best_bic:
            best, best_bic = cand, b
        elif m == 1:
            break
        else:
            m //= 2
    if settings.verbose:
        print(f"[mtex learn] {name} selection: keep {best.n_textons} textons", flush=True)
    if ck is not None:  # what the final EM starts from, in its checkpoints
        ck.set_selection(
            SelectionState(best, best_bic, m, rounds, m_cap, (capacity.textons, capacity.m_step))
        )
    return best, capacity


def threshold_bic(
    run: Runner,
    config: LearnConfig,
    thresholds: Sequence[float],
    greedy: Callable[[float], Segs],
    settings: EMSettings,
) -> tuple[float, list[dict[str, float]], list[MotionTexture]]:
    """Greedy initialisation and EM for every threshold, and each model's BIC (design §4.7).

    Args:
        run: the clips and the E- and M-steps.
        config: the configuration (``state_dim`` resolved).
        thresholds: the greedy thresholds to try.
        greedy: the initial segment rows of a threshold.
        settings: the feature map and callback of the EM runs (which print nothing);
            ``settings.verbose`` prints one line per threshold.

    Returns:
        ``(best_threshold, table, models)``: one dict per threshold (``threshold``,
        ``n_textons``, ``loglik``, ``params``, ``bic``) and its model.
    """
    n = run.n_frames
    table: list[dict[str, float]] = []
    models: list[MotionTexture] = []
    for th in thresholds:
        t0 = time.perf_counter()
        segs = greedy(float(th))
        quiet = dataclasses.replace(settings, verbose=False, t0=t0)
        model = run_em(EM(run, config), segs, float(th), quiet, prune_initial=True)
        ll, p, bic = bic_parts(model, n)
        row = {
            "threshold": float(th),
            "n_textons": model.n_textons,
            "loglik": ll,
            "params": p,
            "bic": bic,
        }
        if settings.verbose:
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
    ys, fm, _ = check_data(data, config)
    config = resolve_state_dim(ys, config, verbose)
    run = Runner(ys, config)
    greedy = lambda th: greedy_init(ys, config, th)[0]
    th, table, _ = threshold_bic(run, config, thresholds, greedy, EMSettings(fm, verbose))
    return th, table
