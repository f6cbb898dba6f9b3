"""Seam smoothing of implicit-model synthesis: the frames around each transition are low-passed.

A transition (:mod:`._synthesis`, step 2) keeps the pose continuous but not its velocity: the
new example moves as it did in its own clip, so the acceleration has a step and the jerk a
spike at every seam. With a search every ``continuation`` frames these spikes are most of the
excess jerk of the synthesised motion (a validation fold, 60_01–03 judged: the median jerk of
the hands over the four frames around a seam is 2.6× that of the training clips, and 1.0×
two to four frames after it). The generated poses near a seam are therefore replaced by a
blend with their ``[1, 2, 1] / 4`` average:

    ŷ'_t = ŷ_t + m_t ((ŷ_{t−1} + 2 ŷ_t + ŷ_{t+1}) / 4 − ŷ_t),
    m_t = max(0, 1 − |t − s(t)| / S),

where ``s(t)`` is the seam frame (the first frame played from a newly searched example)
nearest to ``t`` and ``S = SynthesisConfig.seam_smoothing ≥ 1`` (``1``: the seam frames
only; ``2``: also their neighbours, at half weight). Frames ``S`` or more from every seam are
untouched, so the examples' own motion between seams is replayed as it was.
The seed frames are never changed (``m = 0`` there; the last generated frame uses itself as
its missing successor). The root-velocity channels (:func:`._windows.velocity_channels`) are
left alone: they already are velocities, and the foot lock sets them so that planted feet
hold. Only the output is smoothed: the history that the generator searches with is the
unsmoothed motion.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float

__all__ = ["seam_weights", "smooth_seams"]


def seam_weights(seam: Bool[Array, " n"], width: int) -> Float[Array, " n"]:
    """``m_t = max(0, 1 − |t − s(t)| / S)`` for generated frames with seams ``seam``.

    Args:
        seam: ``(n,)`` True where a generated frame is the first of a newly chosen example.
        width: ``S ≥ 1``.

    Returns:
        ``(n,)`` weights in ``[0, 1]``, 1 at the seams (float64 if enabled, else float32).
    """
    n = seam.shape[0]
    t = jnp.arange(n)
    big = n + width  # farther than any frame: weight 0
    last = lax.cummax(jnp.where(seam, t, -big), axis=0)
    nxt = lax.cummin(jnp.where(seam, t, n + big), axis=0, reverse=True)
    dist = jnp.minimum(t - last, nxt - t)
    return jnp.clip(1.0 - dist / float(width), 0.0, 1.0)


def smooth_seams(
    poses: Float[Array, "n D"],
    before: Float[Array, " D"],
    seam: Bool[Array, " n"],
    width: int,
    channels: np.ndarray,
    n_valid: Array | None = None,
) -> Float[Array, "n D"]:
    """The generated poses with the frames around each seam low-passed (module docstring).

    Args:
        poses: ``(n, D)`` generated poses ``ŷ_1 … ŷ_n``.
        before: ``(D,)`` the last seed pose ``ŷ_0`` (the predecessor of the first frame).
        seam: ``(n,)`` True at the first frame of each newly chosen example.
        width: ``S = SynthesisConfig.seam_smoothing ≥ 1``.
        channels: ``(D,)`` bool, the channels that are smoothed.
        n_valid: the frames ``0 … n_valid − 1`` are the motion, the rest padding (a shape
            bucket): frame ``n_valid − 1`` is the last one and seams after it do not count.

    Returns:
        ``(n, D)`` smoothed poses, same dtype.
    """
    n = poses.shape[0]
    prev = jnp.concatenate([before[None], poses[:-1]], axis=0)
    nxt = jnp.concatenate([poses[1:], poses[-1:]], axis=0)
    if n_valid is not None:
        t = jnp.arange(n)
        nxt = jnp.where((t + 1 < n_valid)[:, None], nxt, poses)
        seam = seam & (t < n_valid)
    avg = 0.25 * (prev + 2.0 * poses + nxt)
    m = seam_weights(seam, width).astype(poses.dtype)[:, None]
    m = m * jnp.asarray(channels, poses.dtype)[None, :]
    return poses + m * (avg - poses)
