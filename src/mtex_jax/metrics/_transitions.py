"""Transitions: frame-to-frame joint jumps, at segment boundaries, against real motion.

At a frame rate ``f`` the jump of step ``t → t+1`` is the largest joint displacement

    J_t = max_j ‖p_{t+1}(j) − p_t(j)‖    (metres per step at ``f``; ``J_t f`` is a speed).

The real distribution of ``J_t`` (all steps of the reference clips, pooled) gives a 99th
percentile ``J_99``; a seam between two synthesised segments (a texton boundary) is judged by the
jump into its first frame, ``J_{b−1}``, against ``J_99``. Jumps depend on the rate (about
``1/f`` for smooth motion), so the reference and the judged clips are measured at one ``f``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike

from ..motion import Motion
from ._kinematics import as_motion_list, joint_positions

__all__ = ["TransitionResult", "boundary_jumps", "joint_jumps", "jump_p99", "transitions"]


def joint_jumps(motions: Motion | Sequence[Motion], fps: float | None = None) -> list[np.ndarray]:
    """Per-step maximum joint jump ``J_t = max_j ‖p_{t+1}(j) − p_t(j)‖`` of each clip.

    Args:
        motions: clips of one skeleton, at least 2 frames each at ``fps``.
        fps: frame rate the jumps are measured at (``None``: the first clip's).

    Returns:
        One ``(T_i − 1,)`` array per clip, in metres.
    """
    ps = joint_positions(motions, fps, min_frames=2, where="joint_jumps")
    return [np.linalg.norm(np.diff(p, axis=0), axis=-1).max(axis=1) for p in ps]


def jump_p99(reference: Motion | Sequence[Motion], fps: float | None = None) -> float:
    """The 99th percentile of the real per-step jump ``J_t`` over all steps of ``reference``."""
    return float(np.quantile(np.concatenate(joint_jumps(reference, fps)), 0.99))


@dataclasses.dataclass(frozen=True)
class TransitionResult:
    """Jumps at boundaries, and over all steps, against a real threshold.

    Attributes:
        threshold: the real 99th-percentile jump ``J_99`` (metres per step at ``fps``).
        fps: frame rate of the measurement.
        boundary_jumps: ``(B,)`` jump into each boundary frame, metres.
        boundary_share_above: share of boundaries whose jump exceeds ``J_99`` (NaN if none).
        boundary_max: largest boundary jump (NaN if none).
        boundary_median: median boundary jump (NaN if none).
        share_above: share of *all* steps of the clips whose jump exceeds ``J_99`` (a real clip
            gives about 0.01).
    """

    threshold: float
    fps: float
    boundary_jumps: np.ndarray
    boundary_share_above: float
    boundary_max: float
    boundary_median: float
    share_above: float


def _boundary_steps(b: ArrayLike, m: Motion, fps: float, n_steps: int, i: int) -> np.ndarray:
    """Step indices ``b' − 1`` at ``fps`` of the boundary frames ``b`` of clip ``m``."""
    arr = np.asarray(b).ravel()
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"boundary_jumps: boundaries of clip {i} must be integer frame indices")
    arr = arr.astype(np.int64)
    if arr.size and (arr.min() < 1 or arr.max() > m.n_frames - 1):
        raise ValueError(
            f"boundary_jumps: boundary frames of clip {i} must lie in 1..{m.n_frames - 1} "
            f"(T − 1 of the clip), got {arr.min()}..{arr.max()}"
        )
    steps = np.rint(arr * (fps / m.fps)).astype(np.int64) - 1
    return np.clip(steps, 0, n_steps - 1)


def boundary_jumps(
    motions: Motion | Sequence[Motion],
    boundaries: ArrayLike | Sequence[ArrayLike],
    threshold: float,
    *,
    fps: float | None = None,
) -> TransitionResult:
    """Jumps into boundary frames, against a real threshold.

    Boundary frame ``b`` (the first frame of a new segment, e.g. a texton boundary) of a clip is
    given in the clip's *own* frame rate; at ``fps`` it is frame ``b' = round(b · fps / f_clip)``
    and its jump is ``J_{b'−1}``.

    Args:
        motions: the clips (one skeleton).
        boundaries: per clip, an integer array of boundary frames in ``1 .. T − 1`` (for a
            single clip, one array).
        threshold: the real ``J_99`` (:func:`jump_p99`) at the same ``fps``.
        fps: frame rate of the measurement (``None``: the first clip's).

    Returns:
        A :class:`TransitionResult`.
    """
    ms = as_motion_list(motions, "boundary_jumps")
    f = ms[0].fps if fps is None else float(fps)
    if not (np.isfinite(threshold) and threshold > 0):
        raise ValueError(f"boundary_jumps: threshold must be positive, got {threshold!r}")
    if isinstance(motions, Motion):
        per_clip: list[ArrayLike] = [boundaries]  # type: ignore[list-item]
    else:
        per_clip = list(boundaries)  # type: ignore[arg-type]
    if len(per_clip) != len(ms):
        raise ValueError(f"boundary_jumps: {len(per_clip)} boundary arrays for {len(ms)} clips")
    jumps = joint_jumps(ms, f)
    at = [
        jmp[_boundary_steps(b, m, f, jmp.size, i)]
        for i, (m, b, jmp) in enumerate(zip(ms, per_clip, jumps, strict=True))
    ]
    bj = np.concatenate(at) if at else np.zeros(0)
    alls = np.concatenate(jumps)
    has = bj.size > 0
    return TransitionResult(
        threshold=float(threshold),
        fps=f,
        boundary_jumps=bj,
        boundary_share_above=float(np.mean(bj > threshold)) if has else float("nan"),
        boundary_max=float(bj.max()) if has else float("nan"),
        boundary_median=float(np.median(bj)) if has else float("nan"),
        share_above=float(np.mean(alls > threshold)),
    )


def transitions(
    generated: Motion | Sequence[Motion],
    boundaries: ArrayLike | Sequence[ArrayLike],
    reference: Motion | Sequence[Motion],
    *,
    fps: float | None = None,
) -> TransitionResult:
    """:func:`boundary_jumps` against the ``J_99`` of ``reference`` at one frame rate.

    Args:
        generated: the judged clips.
        boundaries: their boundary frames (see :func:`boundary_jumps`).
        reference: real clips giving ``J_99``.
        fps: common frame rate (``None``: the first reference clip's).
    """
    ref = as_motion_list(reference, "transitions (reference)")
    gen = as_motion_list(generated, "transitions (generated)")
    if not gen[0].skeleton.same_structure(ref[0].skeleton):
        raise ValueError("transitions: generated and reference clips have different skeletons")
    f = ref[0].fps if fps is None else float(fps)
    return boundary_jumps(generated, boundaries, jump_p99(ref, f), fps=f)
