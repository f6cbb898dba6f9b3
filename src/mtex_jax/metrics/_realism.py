"""Realism of a set of clips against another: distances between joint speed distributions.

For every joint ``j`` and each of the three magnitudes ``|v|``, ``|a|``, ``|j|`` (design §10.4),
the samples of all frames of all clips of a set are pooled into one empirical distribution, and
two sets are compared by the 1-Wasserstein distance

    W₁(P, Q) = ∫ |F_P(x) − F_Q(x)| dx = ∫₀¹ |F_P⁻¹(u) − F_Q⁻¹(u)| du,

in the unit of the magnitude (m/s, m/s², m/s³), then averaged over the moving joints
(:func:`~mtex_jax.metrics.moving_joints` of the reference set, so both sets, and the real-vs-real
floor, use the same joints). Divided by the floor (the same distance between two real sets,
e.g. training vs held-out clips), 1 means "as far from the reference as real data is".
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike

from ..motion import Motion
from ._kinematics import as_motion_list, joint_positions, joint_speeds, moving_joints

__all__ = ["RealismResult", "realism", "speed_samples", "wasserstein_1d"]

QUANTITIES = ("speed", "acceleration", "jerk")


def wasserstein_1d(u: ArrayLike | Sequence[float], v: ArrayLike | Sequence[float]) -> float:
    """1-Wasserstein distance between two 1-D empirical distributions (equal sample weights).

    With the pooled sorted samples ``z_0 ≤ … ≤ z_{n+m−1}`` and the empirical CDFs ``F_u``,
    ``F_v`` (step functions, constant between consecutive ``z``),

        W₁ = Σ_k |F_u(z_k) − F_v(z_k)| (z_{k+1} − z_k),

    which is exact for any sample sizes ``n``, ``m`` (the area between the two CDFs). Cost
    ``O((n + m) log(n + m))``.

    Args:
        u: ``(n,)`` samples, ``n ≥ 1``, finite.
        v: ``(m,)`` samples, ``m ≥ 1``, finite.

    Returns:
        ``W₁ ≥ 0`` in the unit of the samples.
    """
    a = np.sort(np.asarray(u, dtype=np.float64).ravel())
    b = np.sort(np.asarray(v, dtype=np.float64).ravel())
    if a.size == 0 or b.size == 0:
        raise ValueError("wasserstein_1d: both sample sets must be non-empty")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError("wasserstein_1d: samples must be finite (found NaN or inf)")
    z = np.sort(np.concatenate([a, b]))
    dz = np.diff(z)
    fa = np.searchsorted(a, z[:-1], side="right") / a.size
    fb = np.searchsorted(b, z[:-1], side="right") / b.size
    return float(np.sum(np.abs(fa - fb) * dz))


def speed_samples(
    motions: Motion | Sequence[Motion], fps: float | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pooled ``|v|``, ``|a|``, ``|j|`` samples of a set of clips, per joint.

    Args:
        motions: clips of one skeleton, each at least 4 frames long at ``fps``.
        fps: common frame rate (``None``: the first clip's).

    Returns:
        ``(N_v, J)``, ``(N_a, J)``, ``(N_j, J)``: the magnitudes of all clips stacked along the
        first axis (``N_v = Σ (T_i − 1)``, etc.).
    """
    ps = joint_positions(motions, fps, min_frames=4, where="speed_samples")
    f = as_motion_list(motions, "speed_samples")[0].fps if fps is None else float(fps)
    per_clip = [joint_speeds(p, f) for p in ps]
    return tuple(np.concatenate([c[k] for c in per_clip]) for k in range(3))  # type: ignore[return-value]


@dataclasses.dataclass(frozen=True)
class RealismResult:
    """Distances between the joint speed, acceleration and jerk distributions of two sets.

    Attributes:
        speed: mean over joints of ``W₁(|v|)`` in m/s.
        acceleration: mean over joints of ``W₁(|a|)`` in m/s².
        jerk: mean over joints of ``W₁(|j|)`` in m/s³.
        per_joint: ``(3, K)`` the distances of each joint (rows: speed, acceleration, jerk).
        joints: names of the ``K`` joints compared (the moving joints of the reference).
        fps: the common frame rate.
        speed_ratio: ``speed / floor.speed`` when a floor was given, else ``None``.
        acceleration_ratio: likewise.
        jerk_ratio: likewise.
    """

    speed: float
    acceleration: float
    jerk: float
    per_joint: np.ndarray
    joints: tuple[str, ...]
    fps: float
    speed_ratio: float | None = None
    acceleration_ratio: float | None = None
    jerk_ratio: float | None = None

    @property
    def distances(self) -> tuple[float, float, float]:
        """``(speed, acceleration, jerk)``."""
        return (self.speed, self.acceleration, self.jerk)

    @property
    def ratios(self) -> tuple[float, float, float] | None:
        """``(speed_ratio, acceleration_ratio, jerk_ratio)``, or ``None`` without a floor."""
        if self.speed_ratio is None or self.acceleration_ratio is None or self.jerk_ratio is None:
            return None
        return (self.speed_ratio, self.acceleration_ratio, self.jerk_ratio)

    def to_dict(self) -> dict[str, float | list[str] | None]:
        """Plain JSON-ready summary (no per-joint array)."""
        return {
            "speed": self.speed,
            "acceleration": self.acceleration,
            "jerk": self.jerk,
            "speed_ratio": self.speed_ratio,
            "acceleration_ratio": self.acceleration_ratio,
            "jerk_ratio": self.jerk_ratio,
            "fps": self.fps,
            "joints": list(self.joints),
        }


def _floor_values(
    floor: RealismResult | Sequence[float], joints: tuple[str, ...], fps: float
) -> tuple[float, float, float]:
    if isinstance(floor, RealismResult):
        if floor.joints != joints:
            raise ValueError(
                "realism: the floor was computed on other joints "
                f"({len(floor.joints)} vs {len(joints)}); compute both against the same reference"
            )
        if floor.fps != fps:
            raise ValueError(f"realism: the floor is at {floor.fps:g} fps, this at {fps:g} fps")
        vals = floor.distances
    else:
        vals = tuple(float(x) for x in floor)
        if len(vals) != 3:
            raise ValueError(f"realism: floor must hold 3 distances, got {len(vals)}")
    if not all(np.isfinite(x) and x > 0 for x in vals):
        raise ValueError(f"realism: floor distances must be positive and finite, got {vals}")
    return vals[0], vals[1], vals[2]


def realism(
    generated: Motion | Sequence[Motion],
    reference: Motion | Sequence[Motion],
    *,
    fps: float | None = None,
    floor: RealismResult | Sequence[float] | None = None,
    joints: Sequence[str] | None = None,
) -> RealismResult:
    """Per-joint 1-Wasserstein distances of ``|v|``, ``|a|``, ``|j|``, averaged over joints.

    ``D_q = (1/K) Σ_{j ∈ joints} W₁(P_q^gen(j), P_q^ref(j))`` for ``q ∈ {|v|, |a|, |j|}``,
    each distribution pooled over all frames of all clips of its set, both sets resampled to
    one frame rate. With ``floor`` (the same figure between two *real* sets, e.g.
    ``realism(held_out, training)``), the ratios ``D_q / floor_q`` are filled in as well.

    Args:
        generated: the clips judged (one skeleton structure, the reference's).
        reference: the real clips (e.g. the training set).
        fps: common frame rate; ``None`` uses the first reference clip's rate. Distances at
            different rates are not comparable (finite-difference jerk grows with ``f``).
        floor: a :class:`RealismResult` on the same joints and rate, or three distances
            ``(speed, acceleration, jerk)``.
        joints: names of the joints to compare; default the moving joints of ``reference``
            (:func:`~mtex_jax.metrics.moving_joints`).

    Returns:
        A :class:`RealismResult`.

    Raises:
        ValueError: on empty sets, mismatched skeletons, clips shorter than 4 frames at
            ``fps``, NaN values, unknown joint names, or a floor on other joints or rate.
    """
    ref = as_motion_list(reference, "realism (reference)")
    gen = as_motion_list(generated, "realism (generated)")
    if not gen[0].skeleton.same_structure(ref[0].skeleton):
        raise ValueError("realism: generated and reference clips have different skeletons")
    f = ref[0].fps if fps is None else float(fps)
    sk = ref[0].skeleton
    if joints is None:
        idx = moving_joints(ref)
    else:
        idx = np.asarray([sk.index(n) for n in joints], dtype=np.int64)
        if idx.size == 0:
            raise ValueError("realism: joints must not be empty")
    names = tuple(sk.names[i] for i in idx)
    s_gen = speed_samples(gen, f)
    s_ref = speed_samples(ref, f)
    per_joint = np.array(
        [[wasserstein_1d(g[:, j], r[:, j]) for j in idx] for g, r in zip(s_gen, s_ref, strict=True)]
    )
    d = per_joint.mean(axis=1)
    ratios: tuple[float | None, ...] = (None, None, None)
    if floor is not None:
        fl = _floor_values(floor, names, f)
        ratios = tuple(float(d[k] / fl[k]) for k in range(3))
    return RealismResult(
        speed=float(d[0]),
        acceleration=float(d[1]),
        jerk=float(d[2]),
        per_joint=per_joint,
        joints=names,
        fps=f,
        speed_ratio=ratios[0],
        acceleration_ratio=ratios[1],
        jerk_ratio=ratios[2],
    )
