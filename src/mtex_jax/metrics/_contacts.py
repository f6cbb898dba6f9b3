"""Foot contacts, foot skating and floor penetration, with thresholds fitted on training clips.

Heights are world coordinates along the skeleton's up axis and horizontal speeds are in the
plane of the two other axes (:func:`~mtex_jax.motion.ground_axes`), from the world joint
positions at one frame rate ``f``: for a foot joint with position ``p_t``,

    h_t = p_t[up],    s_t = ‖(p_{t+1} − p_t)[h0, h1]‖ f    (m/s, one value per step t → t+1).

**Thresholds** (per foot joint, from the training clips' own distributions, design §10.4):

- height ``H`` = the *median* of the foot's height over all training frames. The height
  distribution is a sharp support mode (the ankle a few centimetres above the floor) with a
  long swing tail, not two comparable clusters: a two-class split such as Otsu's lands in the
  tail (about 10 cm on the CMU salsa clips, calling 77 % of the frames "low", swings included),
  while the median sits just above the support mode (6–7 cm, about 1.5 cm above it) for a foot
  that supports the body about half of the time, as in walking and dancing.
- speed ``S`` = Otsu's threshold of ``log₁₀ s``: the log-speed distribution *is* bimodal
  (stance near 0.2 m/s, swing near 2 m/s on the salsa clips), and Otsu's rule (the split that
  maximises the between-class variance of a 256-bin histogram) picks the valley between the
  two modes without a tuning constant (about 0.5 m/s here).

A step is a **contact** when the foot is low at both ends (``h_t < H`` and ``h_{t+1} < H``) and
slow (``s_t < S``).

**Skating** is measured on the *low* steps (height criterion only): a speed criterion would
exclude exactly the sliding steps whose speed is being measured, so a motion whose planted feet
slide fast would look clean. Reported: the median and 95th percentile of ``s_t`` over the low
steps of all feet and clips.

**Penetration** is measured against the **training floor** ``h_floor``, the lowest height any
foot joint reaches in any training frame: per frame the depth ``max(0, h_floor − min_feet h_t)``;
reported are the largest depth (metres) and the share of frames with a foot below the floor.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from ..motion import Motion, Skeleton, foot_joints, ground_axes
from ._kinematics import as_motion_list, joint_positions

__all__ = [
    "ContactModel",
    "PenetrationResult",
    "SkatingResult",
    "fit_contacts",
    "foot_joints",
]

_MIN_SPEED = 1e-4  # m/s: speeds are clipped here before taking log₁₀ (a still foot)


def _otsu(x: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold: the histogram split maximising the between-class variance
    ``w₀ w₁ (μ₀ − μ₁)²``."""
    hist, edges = np.histogram(x, bins=bins)
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(hist)[:-1].astype(np.float64)
    w1 = hist.sum() - w0
    m0 = np.cumsum(hist * centres)[:-1]
    mu0 = m0 / np.maximum(w0, 1.0)
    mu1 = (np.sum(hist * centres) - m0) / np.maximum(w1, 1.0)
    between = w0 * w1 * (mu0 - mu1) ** 2
    return float(edges[1:-1][int(np.argmax(between))])


@dataclasses.dataclass(frozen=True)
class SkatingResult:
    """Horizontal foot speed over the steps where the foot is low (m/s).

    Attributes:
        median: median over the low steps of all feet and clips (NaN if there are none).
        p95: 95th percentile, likewise.
        per_foot_median: ``(F,)`` median of each foot.
        per_foot_p95: ``(F,)`` 95th percentile of each foot.
        low_share: share of (step, foot) pairs that are low.
        n_low: number of low (step, foot) pairs.
    """

    median: float
    p95: float
    per_foot_median: np.ndarray
    per_foot_p95: np.ndarray
    low_share: float
    n_low: int


@dataclasses.dataclass(frozen=True)
class PenetrationResult:
    """Depth of the feet below the training floor.

    Attributes:
        max_depth: largest ``max(0, h_floor − min_feet h_t)`` over all frames, metres.
        share: share of frames with at least one foot strictly below the floor.
        mean_depth: mean depth over the frames below the floor (0 if there are none).
    """

    max_depth: float
    share: float
    mean_depth: float


def _quantiles(x: np.ndarray) -> tuple[float, float]:
    if x.size == 0:
        return float("nan"), float("nan")
    med, p95 = np.quantile(x, [0.5, 0.95])
    return float(med), float(p95)


@dataclasses.dataclass(frozen=True, eq=False)
class ContactModel:
    """Per-foot contact thresholds and the floor, fitted on training clips by
    :func:`fit_contacts` (or built by hand to override them).

    Attributes:
        skeleton: the figure the model applies to.
        feet: ``(F,)`` joint indices of the feet.
        height_threshold: ``(F,)`` height ``H`` below which a foot is low (world up coordinate,
            metres).
        speed_threshold: ``(F,)`` horizontal speed ``S`` (m/s) below which a low foot is in
            contact.
        floor: the training floor ``h_floor`` (metres).
        fps: the frame rate the speeds are measured at.
    """

    skeleton: Skeleton
    feet: tuple[int, ...]
    height_threshold: np.ndarray
    speed_threshold: np.ndarray
    floor: float
    fps: float

    @property
    def foot_names(self) -> tuple[str, ...]:
        return tuple(self.skeleton.names[i] for i in self.feet)

    def heights_and_speeds(
        self, motions: Motion | Sequence[Motion], where: str = "ContactModel"
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per clip, foot heights ``(T, F)`` and horizontal step speeds ``(T − 1, F)``."""
        ms = as_motion_list(motions, where, min_frames=1)
        if not ms[0].skeleton.same_structure(self.skeleton):
            raise ValueError(f"{where}: the motions' skeleton is not the model's")
        return _heights_speeds(ms, self.feet, self.fps, where)

    def labels(self, motion: Motion) -> np.ndarray:
        """Contact labels ``(T − 1, F)`` bool: low at both ends of the step and slow."""
        ((h, s),) = self.heights_and_speeds(motion, "ContactModel.labels")
        low = (h[:-1] < self.height_threshold) & (h[1:] < self.height_threshold)
        return low & (s < self.speed_threshold)

    def skating(self, motions: Motion | Sequence[Motion]) -> SkatingResult:
        """Median and p95 of horizontal foot speed over the low steps (height criterion only)."""
        pooled: list[list[np.ndarray]] = [[] for _ in self.feet]
        n_steps = 0
        for h, s in self.heights_and_speeds(motions, "ContactModel.skating"):
            low = (h[:-1] < self.height_threshold) & (h[1:] < self.height_threshold)
            n_steps += low.size
            for k in range(len(self.feet)):
                pooled[k].append(s[low[:, k], k])
        per_foot = [np.concatenate(p) for p in pooled]
        allv = np.concatenate(per_foot)
        med, p95 = _quantiles(allv)
        pq = np.array([_quantiles(p) for p in per_foot]).reshape(-1, 2)
        return SkatingResult(
            median=med,
            p95=p95,
            per_foot_median=pq[:, 0],
            per_foot_p95=pq[:, 1],
            low_share=float(allv.size / max(n_steps, 1)),
            n_low=int(allv.size),
        )

    def penetration(self, motions: Motion | Sequence[Motion]) -> PenetrationResult:
        """Largest depth below the training floor and the share of frames with any."""
        lowest = np.concatenate(
            [h.min(axis=1) for h, _ in self.heights_and_speeds(motions, "ContactModel.penetration")]
        )
        depth = np.maximum(self.floor - lowest, 0.0)
        below = lowest < self.floor
        return PenetrationResult(
            max_depth=float(depth.max()),
            share=float(below.mean()),
            mean_depth=float(depth[below].mean()) if below.any() else 0.0,
        )


def _heights_speeds(
    ms: list[Motion], feet: tuple[int, ...], fps: float, where: str
) -> list[tuple[np.ndarray, np.ndarray]]:
    up, h0, h1 = ground_axes(ms[0].skeleton.up_axis)
    out = []
    for p in joint_positions(ms, fps, min_frames=2, where=where):
        pf = p[:, list(feet)]
        step = np.diff(pf[..., [h0, h1]], axis=0)
        out.append((pf[..., up], np.linalg.norm(step, axis=-1) * fps))
    return out


def fit_contacts(
    training: Motion | Sequence[Motion],
    *,
    fps: float | None = None,
    feet: Sequence[str] | None = None,
) -> ContactModel:
    """Fit the per-foot height and speed thresholds and the floor on training clips.

    ``H_f = median_t h_t(f)``, ``S_f = 10^{otsu(log₁₀ max(s_t(f), 10⁻⁴))}`` over all training
    frames, ``h_floor = min_{t, f} h_t(f)`` (see the module notes for why these rules).

    Args:
        training: the training clips (one skeleton structure).
        fps: the frame rate of all speed measurements (``None``: the first clip's).
        feet: foot joint names overriding :func:`foot_joints`.

    Returns:
        A :class:`ContactModel`.
    """
    ms = as_motion_list(training, "fit_contacts", min_frames=2)
    f = ms[0].fps if fps is None else float(fps)
    sk = ms[0].skeleton
    idx = foot_joints(sk, feet)
    hs = _heights_speeds(ms, idx, f, "fit_contacts")
    h = np.concatenate([a for a, _ in hs])
    s = np.concatenate([b for _, b in hs])
    log_s = np.log10(np.maximum(s, _MIN_SPEED))
    return ContactModel(
        skeleton=sk,
        feet=idx,
        height_threshold=np.median(h, axis=0),
        speed_threshold=np.array([10.0 ** _otsu(log_s[:, k]) for k in range(len(idx))]),
        floor=float(h.min()),
        fps=f,
    )
