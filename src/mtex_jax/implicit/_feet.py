"""Foot lock of implicit-model synthesis: planted feet do not skate through a transition.

After a transition the generator plays the new example plus a pose offset that fades out
(:mod:`._synthesis`). The example's joint motion fits its own root motion, so while the offset
fades, a foot that the example keeps planted slides. The foot lock corrects the root's
horizontal displacement of every generated frame so that each planted foot moves as the
example's foot moves:

* **Contact weight** ``c_{i,k} ∈ [0, 1]`` of foot ``k`` in the successor frame of example
  ``i`` (:func:`foot_contact`, computed once from the training clips): with ``s`` the foot's
  world speed, smoothed by a centred moving average of 5 frames, and ``m_k`` the foot's median
  speed over the training frames, ``c = 1 − min(s / m_k, 1)``: 1 for a still foot, 0 for a
  foot at least as fast as usual.
* **Slide.** For the generated step ``ŷ_t → ŷ_{t+1}`` and the example's own step
  ``y(e) → y(e + 1)``, both decoded from their first frame's heading frame, ``Δ_k`` is the
  foot's displacement in the generated step minus its displacement in the example's step
  (the example's own foot motion, e.g. a rolling ankle, is kept).
* **Correction.** ``δ = Σ_k c_k Δ_k / max(Σ_k c_k, 1)``, smoothed over frames,
  ``δ̄_t = λ δ̄_{t−1} + (1 − λ) δ`` (``λ = SynthesisConfig.lock_smoothing``: a correction that
  switches with the contact weights would shake the whole body), scaled by
  ``SynthesisConfig.foot_lock`` and subtracted from the root's horizontal displacement of
  frame ``t + 1`` (the two ``root.d…`` channels).

With ``λ = 0``, strength 1 and one fully planted foot the generated foot moves exactly as the
example's (``tests/test_implicit_feet.py``).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..motion import FeatureMap, Motion, forward_kinematics, ground_axes

__all__ = ["SMOOTH_FRAMES", "foot_contact", "lock_root", "root_channels"]

SMOOTH_FRAMES = 5  # moving average of the foot speed before the contact weight


def _smooth(v: np.ndarray, k: int) -> np.ndarray:
    """Centred moving average of ``k`` frames along axis 0 (edges padded with their value)."""
    if k <= 1 or v.shape[0] == 0:
        return v
    pad = np.pad(v, ((k // 2, k - 1 - k // 2), (0, 0)), mode="edge")
    c = np.cumsum(np.concatenate([np.zeros((1, v.shape[1])), pad]), axis=0)
    return (c[k:] - c[:-k]) / k


def foot_contact(
    motions: Sequence[Motion], feet: Sequence[int], window: int
) -> Float[np.ndarray, "n F"]:
    """Contact weight ``c = 1 − min(s / m, 1)`` of every foot in every example's successor
    frame (module docstring), ``(n, F)`` in example order.

    Args:
        motions: the training clips of the database, at its frame rate.
        feet: foot joint indices (:func:`mtex_jax.motion.foot_joints`).
        window: ``d``; clip ``c`` of ``T`` frames gives examples whose successors are frames
            ``d + 1 … T − 1``.
    """
    feet = list(feet)
    if not feet:
        n = sum(m.n_frames - 1 - window for m in motions)
        return np.zeros((n, 0))
    speeds = []
    for m in motions:
        p = np.asarray(forward_kinematics(m), dtype=np.float64)[:, feet]
        s = np.linalg.norm(np.diff(p, axis=0), axis=-1) * m.fps  # row f − 1: frame f
        speeds.append(_smooth(s, SMOOTH_FRAMES))
    med = np.maximum(np.median(np.concatenate(speeds), axis=0), 1e-12)
    out = [1.0 - np.minimum(s[window:] / med, 1.0) for s in speeds]
    return np.concatenate(out, axis=0)


def root_channels(fm: FeatureMap) -> tuple[int, int] | None:
    """Positions in ``y`` of the root's two horizontal displacement channels, or ``None`` when
    either is not an active channel (then there is nothing to correct)."""
    act = list(fm.active)
    if 0 in act and 1 in act:
        return act.index(0), act.index(1)
    return None


def lock_root(
    fm: FeatureMap,
    feet: tuple[int, ...],
    chans: tuple[int, int],
    last: Float[Array, " D"],
    pose: Float[Array, " D"],
    ex_last: Float[Array, " D"],
    ex_pose: Float[Array, " D"],
    contact: Float[Array, " F"],
    prev: Float[Array, " 3"],
    strength: float,
    smoothing: float,
) -> tuple[Float[Array, " D"], Float[Array, " 3"]]:
    """One generated frame with its root displacement corrected (module docstring).

    Args:
        fm: the model's feature map.
        feet: foot joint indices.
        chans: :func:`root_channels`.
        last, pose: the previous and the new generated pose ``ŷ_t``, ``ŷ_{t+1}``.
        ex_last, ex_pose: the example's ``y(e)`` and ``y(e + 1)``.
        contact: ``(F,)`` contact weights of the example's successor frame.
        prev: the smoothed correction of the previous frame ``δ̄_{t−1}`` (metres).
        strength: ``SynthesisConfig.foot_lock``.
        smoothing: ``λ``.

    Returns:
        The corrected pose and ``δ̄_t``.
    """
    f = np.asarray(feet)
    gen = fm.joint_positions(jnp.stack([last, pose]))[:, f]
    ex = fm.joint_positions(jnp.stack([ex_last, ex_pose]))[:, f]
    slide = (gen[1] - gen[0]) - (ex[1] - ex[0])  # (F, 3)
    c = contact.astype(pose.dtype)
    delta = jnp.sum(c[:, None] * slide, axis=0) / jnp.maximum(jnp.sum(c), 1.0)
    delta = smoothing * prev + (1.0 - smoothing) * delta
    _, h0, h1 = ground_axes(fm.skeleton.up_axis)
    scale = jnp.asarray(fm.scale, pose.dtype)
    i0, i1 = chans
    pose = pose.at[i0].add(-strength * delta[h0] / scale[0])
    pose = pose.at[i1].add(-strength * delta[h1] / scale[1])
    return pose, delta
