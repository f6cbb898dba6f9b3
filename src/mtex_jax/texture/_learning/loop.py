"""The hard-EM loop of learning (design §4.1–4.6) over an explicit state.

:class:`EM` is the problem (a runner's E- and M-steps, the configuration, the stack
:class:`Capacity`); :class:`EMState` is everything an iteration changes. :meth:`EM.init`,
:meth:`EM.step` and :meth:`EM.terminate` are run by the one loop, :func:`run_em` (the pattern
of dynamax's ``fit_em`` and optimistix's ``iterative_solve``), which reports each iteration as
:class:`EMSettings` says and returns the best iteration's model (:meth:`EM.result`). The
single-process and the distributed learn share this loop: their runners differ only in the
E- and M-steps.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import numpy as np

from ...motion import FeatureMap
from .._config import LearnConfig
from .._model import MotionTexture
from .._texton.texton import Texton
from .em import NO_PADDING, Capacity, Runner
from .init import Segs
from .labels import keep_textons, relabel, take, transition_counts, underused


@dataclasses.dataclass(frozen=True)
class EMSettings:
    """How an EM run reports its iterations and what its model records besides the fit.

    Attributes:
        feature_map: the clips' :class:`FeatureMap`, stored in the model (``None``: arrays).
        verbose: print one line per iteration.
        callback: called after every iteration with its record (:func:`run_em`).
        t0: the ``time.perf_counter()`` that the records' ``seconds`` count from (default:
            when the settings are made).
    """

    feature_map: FeatureMap | None
    verbose: bool = False
    callback: Callable[[dict[str, Any]], None] | None = None
    t0: float = dataclasses.field(default_factory=time.perf_counter)


class Fit(NamedTuple):
    """A model of one EM iteration and the segmentation its E-step gave.

    Attributes:
        objective: ``log P(Y, H | Θ, M)`` of ``segs`` (design §4.1; the E-step objective).
        textons: the texton stack (possibly padded past ``len(M)``).
        M: ``(N_t, N_t)`` transition matrix.
        pi: ``(N_t,)`` initial distribution.
        log_d: duration log-probabilities, ``None`` if flat.
        segs: segment rows ``(clip, start, length, label)``, labels indexing ``M``.
    """

    objective: float
    textons: Texton
    M: np.ndarray
    pi: np.ndarray
    log_d: np.ndarray | None
    segs: Segs


class EMState(NamedTuple):
    """The state of EM between iterations (design §4.6).

    Attributes:
        segs: the segmentation the next M-step fits: the initial one, then the last E-step's
            (labels not yet renumbered).
        textons: the textons whose E-step gave ``segs``, indexed by its labels (``None``:
            initial segments without them; for Student-t textons the next M-step starts its
            reweighting from them).
        M: the last iteration's transition matrix (``None`` before the first).
        pi: the last iteration's initial distribution.
        log_d: the last iteration's duration log-probabilities (``None``: flat, or none yet).
        iteration: iterations done.
        history: ``(objective after the M-step, after the E-step)`` of every iteration.
        best: the iteration of the highest E-step objective so far.
        prune_initial: drop the textons with fewer than ``min_segments`` segments of ``segs``
            before the next E-step (the greedy initialisation's; design §4.5).
        converged: the last iteration passed the convergence test and pruned nothing.
    """

    segs: Segs
    textons: Texton | None
    M: np.ndarray | None
    pi: np.ndarray | None
    log_d: np.ndarray | None
    iteration: int
    history: tuple[tuple[float, float], ...]
    best: Fit | None
    prune_initial: bool
    converged: bool


def _labels(segs: Segs, n_seq: int, T: int) -> np.ndarray:
    """The texton of every frame, ``(n_seq, T)`` (``-1`` past a clip's end)."""
    lab = np.full((n_seq, T), -1, dtype=np.int32)
    for s, b, length, i in segs:
        lab[s, b : b + length] = i
    return lab


@dataclasses.dataclass(frozen=True)
class EM:
    """Hard EM (design §4.1): the runner's steps under ``config``, stacks padded to
    ``capacity``.

    Attributes:
        run: the clips and the E- and M-steps (a :class:`Runner`, or the distributed one).
        config: the EM settings (``max_iter``, ``tol``, ``relabel_tol``, ``min_segments``),
            stored in the model; the runner's own config sets the fits.
        capacity: the least texton-stack sizes of the steps (:class:`Capacity`).
    """

    run: Runner
    config: LearnConfig
    capacity: Capacity = NO_PADDING

    def init(self, segs: Segs, prev: Texton | None = None, prune_initial: bool = False) -> EMState:
        """The state before the first iteration.

        Args:
            segs: the initial segment rows ``(clip, start, length, label)``.
            prev: the textons whose E-step gave ``segs`` (indexed by its labels), if any: the
                first M-step of Student-t textons then starts from them (one reweighting)
                instead of from the Gaussian fit (``opts.irls_steps``); later M-steps always
                do.
            prune_initial: EM from the greedy initialisation: textons that ``segs`` gives
                fewer than ``config.min_segments`` segments are dropped after the first
                M-step, before the first E-step (design §4.5; see :meth:`step`).

        Returns:
            The initial :class:`EMState`.
        """
        return EMState(segs, prev, None, None, None, 0, (), None, prune_initial, False)

    def terminate(self, state: EMState) -> bool:
        """Whether EM stops: converged, or ``config.max_iter`` iterations after the first
        (design §4.6)."""
        return state.converged or state.iteration > self.config.max_iter

    def step(self, state: EMState) -> tuple[EMState, dict[str, Any]]:
        """One iteration: M-step, E-step, pruning and the convergence test (design §4.3–4.6).

        With ``state.prune_initial`` the textons of too few segments are not fitted and
        the first E-step runs without them. On the salsa clips (14 and 51 clips, 155 and 305
        greedy textons) the textons that survive the first E-step's pruning are exactly those
        with at least ``min_segments`` greedy segments, so this gives the same model without
        the E-step over all greedy textons (the costliest of the learn: 305 textons against 51
        at 49,708 frames). That iteration's M-step objective (``history[0, 0]``) then covers
        the kept textons' segments only (:meth:`_fit_kept`).

        Returns:
            The next state and the iteration's record: ``iteration``, ``n_textons`` (at the
            M-step), ``pruned``, ``objective_m``, ``objective_e``, ``changed`` (frames whose
            texton changed).
        """
        run, config, cap = self.run, self.config, self.capacity
        segs, used = relabel(state.segs)
        prev = None if state.textons is None else take(state.textons, used)
        n_t = int(segs[:, 3].max()) + 1
        n_pruned = 0
        if state.prune_initial and (few := underused(segs, config.min_segments)).size:
            tex, M, pi, log_d, obj_m, new_segs, obj_e = self._fit_kept(segs, n_t, few)
            n_pruned = few.size
        else:
            tex, M, pi = run.m_step(segs, n_t, cap, prev=prev)
            log_d = run.durations(segs, n_t)
            new_segs, obj_e, obj_m = run.e_step_scored(tex, M, pi, log_d, segs, cap)
            obj_m += run.path_terms(M, pi, segs, log_d)
        # pruning: textons with fewer than min_segments segments are removed from the model
        # (M, π renormalised) and every clip is segmented again by the others, until none is
        # left; the model and segmentation stay complete and consistent
        while (prune := underused(new_segs, config.min_segments)).size:
            keep = np.setdiff1d(np.arange(M.shape[0]), prune)
            tex, M, pi = keep_textons(tex, M, pi, keep)
            log_d = None if log_d is None else log_d[keep]
            new_segs, obj_e = run.e_step(tex, M, pi, log_d, cap)
            n_pruned += prune.size
        lab_old = _labels(segs, run.n_real, run.T)
        lab_new = _labels(new_segs, run.n_real, run.T)
        changed = int(np.sum(lab_old != lab_new))  # frames whose texton changed
        history = (*state.history, (obj_m, obj_e))
        best = state.best
        if best is None or obj_e > best.objective:
            best = Fit(obj_e, tex, M, pi, log_d, new_segs)
        n_frames = run.n_frames
        gain = obj_e - history[-2][1] if len(history) > 1 else np.inf
        converged = changed <= config.relabel_tol * n_frames or gain < config.tol * n_frames
        info = {
            "iteration": state.iteration,
            "n_textons": n_t,
            "pruned": n_pruned,
            "objective_m": obj_m,
            "objective_e": obj_e,
            "changed": changed,
        }
        # after a pruning the remaining textons are refitted to their new segments first
        new = EMState(
            new_segs,
            tex,
            M,
            pi,
            log_d,
            state.iteration + 1,
            history,
            best,
            False,
            converged and n_pruned == 0,
        )
        return new, info

    def _fit_kept(
        self, segs: Segs, n_t: int, few: np.ndarray
    ) -> tuple[Texton, np.ndarray, np.ndarray, np.ndarray | None, float, Segs, float]:
        """The model of ``segs`` without the textons ``few``: the others fitted to their own
        segments (the same fits as with all textons), ``M``, ``π`` and durations restricted
        and renormalised; the objective of the kept textons' segments (scores and durations;
        a partial segmentation has no transition term); and the E-step of that model."""
        run = self.run
        keep = np.setdiff1d(np.arange(n_t), few)
        new_id = np.full(n_t, -1)
        new_id[keep] = np.arange(keep.size)
        ids = new_id[segs[:, 3]]
        rows = segs.copy()
        rows[:, 3] = np.maximum(ids, 0)
        tex, _, _ = run.m_step(rows, keep.size, self.capacity, rows_valid=ids >= 0)
        M, pi = transition_counts(segs, n_t, run.config.pseudo_count)
        M = M[np.ix_(keep, keep)]
        M = M / M.sum(axis=1, keepdims=True)
        pi = pi[keep] / pi[keep].sum()
        log_d = run.durations(segs, n_t)
        log_d = None if log_d is None else log_d[keep]
        kept = rows[ids >= 0]
        new_segs, obj_e, obj = run.e_step_scored(tex, M, pi, log_d, kept, self.capacity)
        if log_d is not None:
            obj += float(log_d[kept[:, 3], kept[:, 2] - run.config.tmin].sum())
        return tex, M, pi, log_d, obj, new_segs, obj_e

    def result(self, state: EMState, threshold: float, fm: FeatureMap | None) -> MotionTexture:
        """The model of the best iteration (design §4.6), without the capacity padding and
        without textons that lost all their segments; its key poses (design §4.3) come from
        the runner (gathered from every process when distributed).

        Args:
            state: the final state.
            threshold: the greedy threshold of the initial segments, recorded in the model.
            fm: the feature map, recorded in the model.
        """
        assert state.best is not None
        _, tex, M, pi, log_d, final_segs = state.best
        tex = take(tex, np.arange(M.shape[0]))  # drop the capacity padding
        used = np.unique(final_segs[:, 3])
        if len(used) < M.shape[0]:  # a texton that lost all its segments: remove it
            tex, M, pi = keep_textons(tex, M, pi, used)
            log_d = None if log_d is None else log_d[used]
            final_segs, _ = relabel(final_segs)
        key = self.run.key_poses(final_segs)
        return MotionTexture(
            textons=tex,
            M=jax.device_put(M),
            pi=jax.device_put(pi),
            key_poses=jax.device_put(key),
            key_pose_labels=jax.device_put(final_segs[:, 3]),
            segment_lengths=jax.device_put(final_segs[:, 2]),
            segments=jax.device_put(final_segs),
            history=jax.device_put(np.asarray(state.history)),
            feature_map=fm,
            config=self.config,
            threshold=threshold,
            log_durations=None if log_d is None else jax.device_put(log_d),
        )


def _report(info: dict[str, Any], settings: EMSettings, n_frames: int) -> None:
    """Print (``settings.verbose``) and hand to ``settings.callback`` an iteration's record,
    with the ``seconds`` since ``settings.t0``."""
    info = {**info, "seconds": time.perf_counter() - settings.t0}
    if settings.verbose:
        n = info["pruned"]
        pruned = f"  pruned {n} texton(s)" if n else ""
        print(
            f"[mtex learn] iter {info['iteration']:2d}  textons {info['n_textons']:3d}  "
            f"objective/frame {info['objective_m'] / n_frames:9.4f} (M) "
            f"{info['objective_e'] / n_frames:9.4f} (E)  frames relabelled "
            f"{info['changed']:6d}  {info['seconds']:6.1f} s{pruned}",
            flush=True,
        )
    if settings.callback is not None:
        settings.callback(info)


def run_em(
    em: EM,
    segs: Segs,
    threshold: float,
    settings: EMSettings,
    *,
    prev: Texton | None = None,
    prune_initial: bool = False,
    start: EMState | None = None,
    on_state: Callable[[EMState], None] | None = None,
) -> MotionTexture:
    """Hard EM from ``segs`` to convergence or ``em.config.max_iter`` iterations (design §4.6):
    ``init``, then ``step`` until ``terminate``, then the best iteration's model.

    Args:
        em: the problem (:class:`EM`).
        segs: the initial segment rows ``(clip, start, length, label)``.
        threshold: the greedy threshold that gave them, recorded in the model.
        settings: reporting and the feature map (:class:`EMSettings`); after every iteration
            ``settings.callback`` gets its record (:meth:`EM.step`) with ``seconds``.
        prev: the textons whose E-step gave ``segs`` (:meth:`EM.init`).
        prune_initial: drop the greedy textons of too few segments first (:meth:`EM.init`).
        start: the state to continue from instead of :meth:`EM.init`'s (a resumed learn:
            the state of a checkpoint, design §4.9).
        on_state: called with the state after every iteration (a checkpoint's writer).

    Returns:
        The :class:`MotionTexture` of the iteration with the best E-step objective.
    """
    state = em.init(segs, prev, prune_initial) if start is None else start
    while not em.terminate(state):
        state, info = em.step(state)
        if on_state is not None:
            on_state(state)
        _report(info, settings, em.run.n_frames)
    return em.result(state, threshold, settings.feature_map)
