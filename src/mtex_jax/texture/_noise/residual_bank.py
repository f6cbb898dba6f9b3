"""Synthesis innovations drawn from the training residuals themselves (a block bootstrap).

The :class:`~mtex_jax.texture.InnovationProcess` keeps two statistics of the textons'
whitened innovations, their autocorrelation and the persistence of their scale. Real
residuals hold more than that: each channel has its own spectrum, channels move together over
several frames, calm stretches and bursts have their own shapes. A :class:`ResidualBank`
keeps the residuals themselves, and synthesis replays them in blocks:

.. code-block:: text

    u_t = B_i⁻¹ (x_t − A1_i x_{t−1} − A2_i x_{t−2} − d_i),   x = C_iᵀ (y − μ_i)

for the frames ``a + 2 … a + n − 1`` of every training segment ``(clip, a, n, i)``, in order.
A texton on a synthesis path replays the residuals of one of its own segments from the
first, cyclically when it needs more rows than the segment has: by default (*aligned*) those
of the training segment whose key poses it starts from, so that the innovations meet the
state they were measured in (past that segment's end, draws of the innovation process: see
below); otherwise (*shuffled*, and where that segment is not in the bank) a segment of the
texton drawn uniformly.

Why aligned. Replayed from another segment's start, a block keeps its law and colour but not
its alignment with the state, and real residuals are not independent of the state (the
linear dynamics leave part of the dance's state feedback in them, design §10.8). The texton
then follows the source segment plus the free response of the dynamics to the difference of
the two starts, and with a spectral radius near 1 a velocity difference persists over the
whole texton: the shuffled replay of the training clips through their own segmentation is
4.3 times the real-vs-real floor in joint speed (the documentation's results page), although
its innovations are real ones. Root translation and legs drift apart, so feet skate.
On three folds of the training clips of the quality split (learn on 7, judge against the
other 3; the default texture and synthesis, 8 syntheses of 20 s) the aligned replay brings
the foot-skating median from 0.76 to 0.48 m/s (real: about 0.2) and the joint-speed distance
from 2.8 to 2.1 times the real-vs-real floor, acceleration and jerk unchanged (1.29 → 1.19,
1.05 → 1.09); its cost is more copying (share of verbatim steps 0.33 → 0.56, longest run
1.1 → 1.9 s): a texton replays its source segment's innovations, bent to its end poses by
the constraint.

Past the segment's end. A texton is often longer than the segment it replays (its length
is drawn from its duration distribution, and the two dynamics equations of its end frames
come after the segment's last residual). Replaying the segment's residuals again from its
first row there puts the innovations of the segment's start (often a burst: segments begin at
abrupt events) where the state is elsewhere, out of alignment once more. The aligned replay of
synthesis therefore draws those rows from the texture's fitted
:class:`~mtex_jax.texture.InnovationProcess` instead (``draw_residuals(..., beyond=…)``): the
same law and colour, no alignment claimed. On the three folds of the training clips (the
default texture and synthesis, 8 syntheses of 20 s, 5 seeds) this brings the joint-speed
distance from 1.93 to 1.69 times the real-vs-real floor, acceleration unchanged
(1.16 → 1.15), jerk 1.05 → 1.09, foot skating 0.48 → 0.47 m/s, copying 0.54 → 0.56 (on
the first fold the synthesised joints moved 6.8 % faster than the training segments the
textons replay, 2.8 % after; in the rows past a segment's end 4–12 % faster, then 3–6 %
slower). What remains of the speed excess is the bend towards the end poses: there, a
texton drawn shorter than its segment (its block cut) moved 31 % faster than the segment
over the frames they share, and one held at key poses other than those that followed its
segment in training (with the segment's own length) 24 % faster.

Capture glitches are residuals the texton's own law calls impossible (a hand channel off by
0.3 rad for one frame is hundreds of standard deviations): a segment with a frame whose
``q = ‖u‖² / k`` lies beyond the ``1 − tail`` quantile of its law under the model
(``F(k, ν)`` for Student-t textons, ``χ²_k / k`` for Gaussian ones; ``tail = 1e-6``: about one
frame in a million) is left out of the bank, unless all of its texton's segments would be (then
the one with the smallest largest ``q`` stays). Replayed, such a glitch is no longer cancelled
by the frames around it and throws the motion off for the rest of the texton.

This is the residual (block) bootstrap of time-series statistics: nothing is estimated, and the
shuffled draws keep every property of real innovations except their alignment with the state
they were measured in (design §10.8), which the aligned replay keeps as well. On the quality
split it brings the acceleration and, most of all, jerk distances of constrained synthesis
closer to real motion than the fitted process, at the cost of more frame-to-frame jumps and a
larger speed distance (the documentation's results page).
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
        segments: ``(s,)`` the row of the segmentation (:attr:`MotionTexture.segments`) it
            was measured on, or ``None`` when unknown (then only shuffled replay is possible).
    """

    rows: Float[Array, "R k"]
    starts: Int[Array, " s"]
    lengths: Int[Array, " s"]
    labels: Int[Array, " s"]
    segments: Int[Array, " s"] | None = None

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
        if self.segments is not None and np.shape(self.segments) != s:
            raise ValueError(
                f"ResidualBank.segments must have the shape of .starts {s}, "
                f"got {np.shape(self.segments)}"
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
    # segments shorter than 3 frames have no residual (an empty block keeps the numbering)
    full = segs[:, 2] >= 3
    res = [np.zeros((0, int(np.shape(textons.C)[-1])))] * len(segs)
    for j, r in zip(
        np.flatnonzero(full), segment_innovations(textons, clips, segs[full]), strict=True
    ):
        res[int(j)] = r
    return plausible_bank(res, segs[:, 3], textons.dof, tail)


def plausible_bank(
    residuals: Sequence[np.ndarray], labels: np.ndarray, dof: float | None, tail: float
) -> ResidualBank:
    """The bank of the segments' whitened residuals ``(n_s − 2, k)`` (empty for segments
    shorter than 3 frames) and their texton ``labels``: the plausibility rule of the module
    docstring, then the kept segments stacked. ``residuals[j]`` is segment ``j`` of the
    segmentation (:attr:`ResidualBank.segments` records it)."""
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
        segments=jnp.asarray(np.asarray(full, dtype=np.int64)[keep]),
    )


def _draw_impl(
    key: Array,
    bank: ResidualBank,
    labels: Array,
    length: int,
    instances: Array | None = None,
    beyond: Array | None = None,
) -> Array:
    match = bank.labels[None, :] == labels[:, None]  # (n, s)
    # a texton without a segment of its own (not made by learn) draws from every segment
    allowed = match | ~match.any(axis=1, keepdims=True)
    logits = jnp.where(allowed, 0.0, -jnp.inf)
    choice = jax.random.categorical(key, logits, axis=-1)
    aligned = None
    if instances is not None and bank.segments is not None:
        # aligned: the bank segment measured on the block's own training segment, if kept
        own = (bank.segments[None, :] == instances[:, None]) & match & (instances[:, None] >= 0)
        aligned = own.any(axis=1)
        choice = jnp.where(aligned, jnp.argmax(own, axis=1), choice)
    rows = jnp.arange(length)[None, :]
    n_own = bank.lengths[choice][:, None]
    out = bank.rows[bank.starts[choice][:, None] + rows % n_own]
    if beyond is not None and aligned is not None:
        # past an aligned block's own rows: ``beyond`` (module docstring), not the block again
        past = (rows >= n_own) & aligned[:, None]
        out = jnp.where(past[..., None], beyond.astype(out.dtype), out)
    return out


_draw = eqx.filter_jit(_draw_impl)


def draw_residuals(
    key: Array,
    bank: ResidualBank,
    labels: Int[ArrayLike, " n"],
    length: int,
    dtype=None,
    instances: Int[ArrayLike, " n"] | None = None,
    beyond: Float[ArrayLike, "n length k"] | None = None,
) -> Float[Array, "n length k"]:
    """One block of ``length`` rows for each texton of ``labels``.

    Block ``m`` replays the residuals of a training segment of texton ``labels[m]`` from its
    first row, cyclically (module docstring): with ``instances`` (aligned replay), those of
    segment ``instances[m]`` of the segmentation (the one whose key poses block ``m``
    starts from) when the bank keeps it and it is a segment of ``labels[m]``; otherwise, and
    without ``instances`` or for a bank without :attr:`ResidualBank.segments`, a segment
    drawn uniformly and independently for each ``m``. With ``beyond``, the rows of an aligned
    block past its segment's own residuals are ``beyond``'s instead of the segment's again
    from its first row (module docstring: *past the segment's end*). Jit-compiled; calls
    with the same shapes do not recompile.

    Args:
        key: JAX PRNG key.
        bank: the :class:`ResidualBank`.
        labels: ``(n,)`` texton labels.
        length: rows per block (static).
        dtype: of the result (default the bank's).
        instances: ``(n,)`` rows of :attr:`MotionTexture.segments` (``-1``: none), or
            ``None`` (shuffled replay).
        beyond: ``(n, length, k)`` innovations for the rows of aligned blocks past their
            segment's residuals (``None``: the segment's rows again, cyclically).

    Returns:
        ``(n, length, k)`` innovations.

    Raises:
        TypeError: ``bank`` is not a :class:`ResidualBank`.
        ValueError: ``labels`` not a non-empty 1-D integer array, ``length < 1``, or
            ``beyond`` of another shape.
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
    inst = None
    if instances is not None:
        inst = jnp.asarray(instances)
        if inst.shape != lab.shape or not jnp.issubdtype(inst.dtype, jnp.integer):
            raise ValueError(
                f"draw_residuals: instances must be {lab.shape[0]} integers, got {inst.shape} "
                f"{inst.dtype}"
            )
    far = None
    if beyond is not None:
        far = jnp.asarray(beyond)
        k = int(np.shape(bank.rows)[1])
        if far.shape != (lab.shape[0], int(length), k):
            raise ValueError(
                f"draw_residuals: beyond must have shape {(lab.shape[0], int(length), k)}, "
                f"got {far.shape}"
            )
    out = _draw(key, bank, lab, int(length), inst, far)
    return out if dtype is None else out.astype(dtype)
