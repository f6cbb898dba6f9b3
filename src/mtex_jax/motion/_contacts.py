"""Foot contacts, foot skating and floor penetration, with thresholds fitted on training clips.

The contact model lives with the motions (not with the metrics that use it) so that a motion
texture can fit and carry the contacts of its training clips (``MotionTexture.contacts``);
:mod:`mtex_jax.metrics` re-exports it.

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

**Feet** come from the joint names when they say so (:func:`foot_joints`), else from the
skeleton's structure: the lowest leaf joint of each leg, lowest by the joints' median height
over the training frames, so that a skeleton of any exporter gets its feet.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from ..core import MAX_ABS_VALUE, check_real
from ._feet import foot_joints
from ._kinematics import as_motion_list, joint_positions
from ._motion import Motion
from ._skeleton import Skeleton, ground_axes

__all__ = ["ContactModel", "PenetrationResult", "SkatingResult", "fit_contacts"]

_MIN_SPEED = 1e-4  # m/s: speeds are clipped here before taking log₁₀ (a still foot)
_MAX_FPS = 10_000.0  # the largest frame rate of a LearnConfig and of a motion file


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

    Construction checks every value (a fitted model, one read from a file and one built by
    hand pass the same checks): at least one foot, distinct joint indices of the skeleton;
    ``(F,)`` finite thresholds, heights at or above the floor, speeds positive; a finite floor;
    a frame rate in ``(0, 10000]``. Arrays are stored as float64.

    Attributes:
        skeleton: the figure the model applies to.
        feet: ``(F,)`` joint indices of the feet.
        height_threshold: ``(F,)`` height ``H`` below which a foot is low (world up coordinate,
            metres).
        speed_threshold: ``(F,)`` horizontal speed ``S`` (m/s) below which a low foot is in
            contact.
        floor: the training floor ``h_floor`` (metres).
        fps: the frame rate the speeds are measured at.
        stance: the height the feet stand at: the median over the training frames of the
            lowest foot's height (metres; a tracker's floor term, design §12.2). ``None`` in a
            model read from a file written before it was fitted: then ``floor``.

    Raises:
        ValueError: a value out of range or of the wrong shape (``TypeError`` for a wrong type),
            naming the field.
    """

    skeleton: Skeleton
    feet: tuple[int, ...]
    height_threshold: np.ndarray
    speed_threshold: np.ndarray
    floor: float
    fps: float
    stance: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.skeleton, Skeleton):
            raise TypeError(f"ContactModel.skeleton must be a Skeleton, got {self.skeleton!r}")
        feet = _check_feet(self.feet, self.skeleton.n_joints)
        floor = check_real(self.floor, "ContactModel.floor", low=-MAX_ABS_VALUE, high=MAX_ABS_VALUE)
        ht = _check_vector(self.height_threshold, len(feet), "height_threshold")
        st = _check_vector(self.speed_threshold, len(feet), "speed_threshold")
        if (ht < floor).any():
            k = int(np.argmax(ht < floor))
            raise ValueError(
                f"ContactModel.height_threshold[{k}] = {ht[k]:.6g} is below the floor "
                f"{floor:.6g} (a foot's height threshold lies at or above the lowest foot height)"
            )
        if (st <= 0).any():
            raise ValueError("ContactModel.speed_threshold must be positive (m/s)")
        fps = check_real(self.fps, "ContactModel.fps", low=0.0, open_low=True, high=_MAX_FPS)
        stance = self.stance
        if stance is not None:
            stance = check_real(stance, "ContactModel.stance", low=floor, high=MAX_ABS_VALUE)
        for name, value in (
            ("stance", stance),
            ("feet", feet),
            ("height_threshold", ht),
            ("speed_threshold", st),
            ("floor", floor),
            ("fps", fps),
        ):
            object.__setattr__(self, name, value)

    @property
    def stance_height(self) -> float:
        """The height the feet stand at (``stance``; ``floor`` where it is not known)."""
        return float(self.floor if self.stance is None else self.stance)

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


def _check_feet(feet: object, n_joints: int) -> tuple[int, ...]:
    """``feet`` as a tuple of distinct joint indices in ``[0, n_joints)`` (at least one)."""
    try:
        items = list(feet)  # type: ignore[call-overload]
    except TypeError:
        raise TypeError(
            f"ContactModel.feet must be a sequence of joint indices, got {feet!r}"
        ) from None
    bad = [f for f in items if isinstance(f, bool) or not isinstance(f, int | np.integer)]
    if bad:
        raise TypeError(f"ContactModel.feet must hold integer joint indices, got {bad[0]!r}")
    out = tuple(int(f) for f in items)
    if not out:
        raise ValueError("ContactModel.feet must name at least one joint")
    if len(set(out)) != len(out) or min(out) < 0 or max(out) >= n_joints:
        raise ValueError(
            f"ContactModel.feet must be distinct joint indices in [0, {n_joints}), got {out}"
        )
    return out


def _check_vector(a: object, n: int, name: str) -> np.ndarray:
    """``a`` as a finite float64 vector of shape ``(n,)`` within ``±MAX_ABS_VALUE``."""
    x = np.asarray(a)
    if x.dtype.kind not in "fiu":
        raise TypeError(f"ContactModel.{name} must hold real numbers, got dtype {x.dtype}")
    x = x.astype(np.float64)
    if x.shape != (n,):
        raise ValueError(
            f"ContactModel.{name} must have shape ({n},) (one per foot), got {x.shape}"
        )
    if not np.isfinite(x).all() or (np.abs(x) > MAX_ABS_VALUE).any():
        raise ValueError(
            f"ContactModel.{name} must hold finite numbers of magnitude at most {MAX_ABS_VALUE:g}"
        )
    return x


def _heights_speeds(
    ms: list[Motion], feet: tuple[int, ...], fps: float, where: str
) -> list[tuple[np.ndarray, np.ndarray]]:
    return [
        _of_positions(p, feet, ms[0].skeleton.up_axis, fps)
        for p in joint_positions(ms, fps, min_frames=2, where=where)
    ]


def _of_positions(
    p: np.ndarray, feet: tuple[int, ...], up_axis: int, fps: float
) -> tuple[np.ndarray, np.ndarray]:
    """Foot heights ``(T, F)`` and horizontal step speeds ``(T − 1, F)`` of positions
    ``(T, J, 3)``."""
    up, h0, h1 = ground_axes(up_axis)
    pf = p[:, list(feet)]
    step = np.diff(pf[..., [h0, h1]], axis=0)
    return pf[..., up], np.linalg.norm(step, axis=-1) * fps


def fit_contacts(
    training: Motion | Sequence[Motion],
    *,
    fps: float | None = None,
    feet: Sequence[str] | None = None,
) -> ContactModel:
    """Fit the per-foot height and speed thresholds and the floor on training clips.

    ``H_f = median_t h_t(f)``, ``S_f = 10^{otsu(log₁₀ max(s_t(f), 10⁻⁴))}`` over all training
    frames, ``h_floor = min_{t, f} h_t(f)`` (see the module notes for why these rules), and the
    stance height ``median_t min_f h_t(f)``.

    The feet are :func:`foot_joints` of the skeleton: by name, else the lowest leaf joint of
    each leg by the joints' median height over the training frames.

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
    ps = joint_positions(ms, f, min_frames=2, where="fit_contacts")
    heights = np.median(np.concatenate([p[..., sk.up_axis] for p in ps]), axis=0)
    idx = foot_joints(sk, feet, heights=heights)
    hs = [_of_positions(p, idx, sk.up_axis, f) for p in ps]
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
        stance=float(np.median(h.min(axis=1))),
    )
