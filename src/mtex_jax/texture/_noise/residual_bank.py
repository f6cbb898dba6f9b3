"""Synthesis innovations drawn from the training residuals themselves (a block bootstrap).

The :class:`~mtex_jax.texture.InnovationProcess` keeps two statistics of the textons'
whitened innovations, their autocorrelation and the persistence of their scale. Real
residuals hold more than that: each channel has its own spectrum, channels move together over
several frames, calm stretches and bursts have their own shapes. A :class:`ResidualBank`
keeps the residuals themselves, and synthesis replays them in blocks:

.. code-block:: text

    u_t = B_i⁻¹ (x_t − A1_i x_{t−1} − A2_i x_{t−2} − d_i),   x = C_iᵀ (y − μ_i)

for the frames ``a + 2 … a + n − 1`` of every training segment ``(clip, a, n, i)``, in order.
A texton on a synthesis path draws one of its own segments uniformly and replays its
residuals from the first, cyclically when it needs more rows than the segment has.

Capture glitches are residuals the texton's own law calls impossible (a hand channel off by
0.3 rad for one frame is hundreds of standard deviations): a segment with a frame whose
``q = ‖u‖² / k`` lies beyond the ``1 − tail`` quantile of its law under the model
(``F(k, ν)`` for Student-t textons, ``χ²_k / k`` for Gaussian ones; ``tail = 1e-6``: about one
frame in a million) is left out of the bank, unless all of its texton's segments would be (then
the one with the smallest largest ``q`` stays). Replayed, such a glitch is no longer cancelled
by the frames around it and throws the motion off for the rest of the texton.

This is the residual (block) bootstrap of time-series statistics: nothing is estimated, and
the draws keep every property of real innovations except their alignment with the state they
were measured in. On the quality split (``benchmarks/results/quality.md``) it brings the
acceleration and, most of all, jerk distances of constrained synthesis closer to real motion
than the fitted process; the table there also lists its costs (more frame-to-frame jumps, a
larger speed distance).
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float, Int
from scipy import stats

from .._texton.texton import Texton
from .innovation_process import segment_innovations

__all__ = [
    "PLAUSIBLE_TAIL",
    "ResidualBank",
    "draw_residuals",
    "plausible_limit",
    "residual_bank",
]

#: Tail probability beyond which a frame's residual is a capture glitch (module docstring).
PLAUSIBLE_TAIL = 1e-6


class ResidualBank(eqx.Module):
    """The whitened residuals of a texture's training segments, segment after segment.

    Attributes:
        rows: ``(R, k)`` the residuals of the kept segments, stacked.
        starts: ``(s,)`` the first row of each kept segment.
        lengths: ``(s,)`` its number of rows (``≥ 1``).
        labels: ``(s,)`` its texton.
    """

    rows: Float[Array, "R k"]
    starts: Int[Array, " s"]
    lengths: Int[Array, " s"]
    labels: Int[Array, " s"]

    def __check_init__(self) -> None:
        r = np.shape(self.rows)
        s, n, lab = (np.shape(a) for a in (self.starts, self.lengths, self.labels))
        if len(r) != 2 or r[0] < 1 or r[1] < 1:
            raise ValueError(f"ResidualBank.rows must have shape (R >= 1, k >= 1), got {r}")
        if len(s) != 1 or s[0] < 1 or lab != s or n != s:
            raise ValueError(
                "ResidualBank.starts, .lengths and .labels must have one shape (s >= 1,), "
                f"got {s}, {n}, {lab}"
            )
        if not any(isinstance(a, Tracer) for a in (self.starts, self.lengths, self.labels)):
            st, ln = np.asarray(self.starts), np.asarray(self.lengths)
            if ln.min() < 1 or st.min() < 0 or (st + ln).max() > r[0]:
                raise ValueError(
                    f"ResidualBank.starts and .lengths must give row ranges within [0, {r[0]}]"
                )
            if np.asarray(self.labels).min() < 0:
                raise ValueError("ResidualBank.labels must be non-negative")


def plausible_limit(k: int, dof: float | None, tail: float = PLAUSIBLE_TAIL) -> float:
    """The ``1 − tail`` quantile of ``‖u‖² / k`` under the textons' law: ``F(k, ν)``, or
    ``χ²_k / k`` for Gaussian textons (``dof=None``)."""
    if dof is None:
        return float(stats.chi2.isf(tail, k) / k)
    return float(stats.f.isf(tail, k, dof))


def residual_bank(
    textons: Texton,
    ys: Sequence[ArrayLike],
    segments: Int[ArrayLike, "s 4"],
    tail: float = PLAUSIBLE_TAIL,
) -> ResidualBank:
    """The :class:`ResidualBank` of a segmentation (numpy; float64 rows).

    Args:
        textons: stacked textons (``N_t``, ``D``, ``k``; ``textons.dof`` their law).
        ys: the training clips' observation vectors, ``(T_c, D)`` each.
        segments: ``(s, 4)`` rows ``(clip, start, length, label)`` (as
            :attr:`MotionTexture.segments`); segments shorter than 3 frames have no residual.
        tail: segments with a frame beyond the ``1 − tail`` quantile of the law are left out
            (module docstring); ``0`` keeps every segment.

    Returns:
        The bank.

    Raises:
        ValueError: no segment of 3 frames or more, labels outside the textons, clips
            outside ``ys``, a segment outside its clip, a clip not ``(T, D)``, or ``tail``
            outside ``[0, 1)``.
    """
    segs = np.asarray(segments, dtype=np.int64)
    if segs.ndim != 2 or segs.shape[1] != 4 or len(segs) == 0:
        raise ValueError(f"residual_bank: segments must have shape (s >= 1, 4), got {segs.shape}")
    if not 0.0 <= float(tail) < 1.0:
        raise ValueError(f"residual_bank: tail must lie in [0, 1), got {tail!r}")
    n_t, D = np.shape(textons.mu)
    if segs[:, 3].min() < 0 or segs[:, 3].max() >= n_t:
        raise ValueError(f"residual_bank: segment labels outside [0, {n_t})")
    if segs[:, 0].min() < 0 or segs[:, 0].max() >= len(ys):
        raise ValueError(f"residual_bank: segments name clips outside [0, {len(ys)})")
    clips = [np.asarray(y, dtype=np.float64) for y in ys]
    for c, y in enumerate(clips):
        if y.ndim != 2 or y.shape[1] != D:
            raise ValueError(f"residual_bank: clip {c} must have shape (T, {D}), got {y.shape}")
    for c, a, n, _ in segs:
        if a < 0 or a + n > len(clips[c]):
            raise ValueError(
                f"residual_bank: segment ({c}, {a}, {n}) lies outside clip {c} "
                f"({len(clips[c])} frames)"
            )
    segs = segs[segs[:, 2] >= 3]  # shorter segments have no residual
    return plausible_bank(segment_innovations(textons, clips, segs), segs[:, 3], textons.dof, tail)


def plausible_bank(
    residuals: Sequence[np.ndarray], labels: np.ndarray, dof: float | None, tail: float
) -> ResidualBank:
    """The bank of the segments' whitened residuals ``(n_s − 2, k)`` (empty for segments
    shorter than 3 frames) and their texton ``labels``: the plausibility rule of the module
    docstring, then the kept segments stacked."""
    full = [i for i, r in enumerate(residuals) if len(r) > 0]
    if not full:
        raise ValueError("residual_bank: no segment of 3 frames or more")
    res = [np.asarray(residuals[i], dtype=np.float64) for i in full]
    labels = np.asarray(labels, dtype=np.int64)[full]
    k = res[0].shape[1]
    worst = np.asarray([np.max(np.sum(r**2, axis=1)) / k for r in res])
    keep = worst <= (np.inf if tail == 0 else plausible_limit(k, dof, tail))
    for i in np.unique(labels):  # every texton keeps at least its most plausible segment
        own = labels == i
        if not keep[own].any():
            keep[np.flatnonzero(own)[np.argmin(worst[own])]] = True
    kept = [r for r, ok in zip(res, keep, strict=True) if ok]
    lengths = np.asarray([len(r) for r in kept])
    return ResidualBank(
        rows=jnp.asarray(np.concatenate(kept)),
        starts=jnp.asarray(np.cumsum(lengths) - lengths),
        lengths=jnp.asarray(lengths),
        labels=jnp.asarray(labels[keep]),
    )


def _draw_impl(key: Array, bank: ResidualBank, labels: Array, length: int) -> Array:
    match = bank.labels[None, :] == labels[:, None]  # (n, s)
    # a texton without a segment of its own (not made by learn) draws from every segment
    allowed = match | ~match.any(axis=1, keepdims=True)
    logits = jnp.where(allowed, 0.0, -jnp.inf)
    choice = jax.random.categorical(key, logits, axis=-1)
    offset = jnp.arange(length)[None, :] % bank.lengths[choice][:, None]
    return bank.rows[bank.starts[choice][:, None] + offset]


_draw = eqx.filter_jit(_draw_impl)


def draw_residuals(
    key: Array, bank: ResidualBank, labels: Int[ArrayLike, " n"], length: int, dtype=None
) -> Float[Array, "n length k"]:
    """One block of ``length`` rows for each texton of ``labels``.

    Block ``m`` replays the residuals of a training segment of texton ``labels[m]``, drawn
    uniformly and independently for each ``m``, from its first row, cyclically (module
    docstring). Jit-compiled; calls with the same shapes do not recompile.

    Args:
        key: JAX PRNG key.
        bank: the :class:`ResidualBank`.
        labels: ``(n,)`` texton labels.
        length: rows per block (static).
        dtype: of the result (default the bank's).

    Returns:
        ``(n, length, k)`` innovations.

    Raises:
        TypeError: ``bank`` is not a :class:`ResidualBank`.
        ValueError: ``labels`` not a non-empty 1-D integer array, or ``length < 1``.
    """
    if not isinstance(bank, ResidualBank):
        raise TypeError(f"draw_residuals: bank must be a ResidualBank, got {type(bank).__name__}")
    lab = jnp.asarray(labels)
    if lab.ndim != 1 or lab.shape[0] < 1 or not jnp.issubdtype(lab.dtype, jnp.integer):
        raise ValueError(
            f"draw_residuals: labels must be a non-empty 1-D integer array, got {lab.shape} "
            f"{lab.dtype}"
        )
    if isinstance(length, bool) or not isinstance(length, int | np.integer) or length < 1:
        raise ValueError(f"draw_residuals: length must be a positive integer, got {length!r}")
    out = _draw(key, bank, lab, int(length))
    return out if dtype is None else out.astype(dtype)
