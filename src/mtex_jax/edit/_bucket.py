"""Edits in shape buckets: the banded Gauss–Newton solve compiled once per bucket of lengths.

An edit of ``T`` frames is solved on :func:`edit_length` ``(T)`` frames (design §11). The
padding frames repeat the last frame and are *held* (``pose_mask``: they are not variables),
and the solve leaves out their prior, smoothness and floor terms (``n_valid``), so the
motion's own frames see the same objective as without padding: the normal equations of the
first ``T`` frames are unchanged and the padding frames form independent identity blocks.
The result is cut back to ``T`` frames on the host.

The buckets are finer than those of the likelihood (:data:`~mtex_jax.core.BUCKET_FRAMES`):
an edit's solve costs about 5 ms per frame, so padding 1,201 frames to 2,048 would add
seconds to every call, while its compilation (about 10 s) is paid once per bucket.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import numpy as np

from ..core import as_array, cut_frames, pad_frames
from ..motion import FeatureMap
from ._banded.terms import PointTargets
from ._constraints import Constraints, EditWeights
from ._gn import solve_edit_gn_jit
from ._prior import FrameSegments, WhitenedTextons
from ._solve import EditResult

__all__ = ["edit_length", "solve_gn_bucketed"]

#: The smallest edit bucket (frames).
MIN_EDIT_FRAMES = 128


def edit_length(n: int) -> int:
    """The bucket of an edit of ``n`` frames: ``n`` rounded up to a multiple of a quarter of
    the largest power of two below it (at least :data:`MIN_EDIT_FRAMES`).

    Four buckets per doubling of the length: the padding is below 25 % of ``n`` (1,201 frames
    solve as 1,280), and lengths of 200 to 3,000 frames fall in 16 buckets.
    """
    n = int(n)
    if n < 1:
        raise ValueError(f"edit_length needs n >= 1, got {n}")
    if n <= MIN_EDIT_FRAMES:
        return MIN_EDIT_FRAMES
    step = (1 << ((n - 1).bit_length() - 1)) // 4
    return -(-n // step) * step


def _pad(a: Any, n: int, fill: Any = None) -> jax.Array:
    """``a`` padded on the host along axis 0 to ``n`` entries: the last entry repeated
    (:func:`~mtex_jax.core.pad_frames`), or ``fill``."""
    x = np.asarray(a)
    if fill is None:
        return as_array(pad_frames(x, n, axis=0))
    widths = [(0, n - x.shape[0])] + [(0, 0)] * (x.ndim - 1)
    return as_array(np.pad(x, widths, mode="constant", constant_values=fill))


def pad_inputs(
    n: int,
    Y: Any,
    seg: FrameSegments,
    cons: Constraints,
    extra: PointTargets | None,
) -> tuple[jax.Array, FrameSegments, Constraints, PointTargets | None]:
    """The observation vectors, segmentation, constraints and extra targets of an edit,
    padded to ``n`` frames (module notes: the padding frames held at the last frame)."""
    T = int(np.shape(Y)[0])
    Yp = _pad(Y, n)
    segp = FrameSegments(
        labels=_pad(seg.labels, n),
        dyn_labels=_pad(seg.dyn_labels, n),
        position=_pad(seg.position, n),
    )
    poses = np.asarray(cons.poses)
    poses = np.concatenate([poses, np.asarray(Yp)[T:].astype(poses.dtype)])
    consp = eqx.tree_at(
        lambda c: (c.pose_mask, c.poses, c.plant, c.plant_height, c.lift),
        cons,
        (
            _pad(cons.pose_mask, n, True),
            as_array(poses),
            _pad(cons.plant, n - 1, False),
            _pad(cons.plant_height, n - 1, np.nan),
            _pad(cons.lift, n, -np.inf),
        ),
    )
    if extra is None:
        return Yp, segp, consp, None
    return Yp, segp, consp, pad_points(extra, T, n)


def pad_points(points: PointTargets, T: int, n: int) -> PointTargets:
    """Point targets of a ``T``-frame edit padded to ``n`` frames: the sparse targets kept,
    the frame-major ones (:class:`~mtex_jax.edit._banded.terms.PointTargets`) given weightless
    targets at each padding frame (same joints), so they stay frame-major."""
    F, s = points.per_frame, points.sparse_count
    if not F:
        return points
    if int(np.shape(points.frame)[0]) - s != T * F:
        raise ValueError(f"pad_points: the frame-major targets do not cover {T} frames")
    slots = np.asarray(points.slot)[s : s + F]
    head = lambda x: np.asarray(x)[:s]

    def tail(x: Any, fill: Any) -> np.ndarray:
        x = np.asarray(x)
        return np.concatenate([x[s:], np.full(((n - T) * F, *x.shape[1:]), fill, x.dtype)])

    return PointTargets(
        slot=as_array(np.concatenate([head(points.slot), np.tile(slots, n)]).astype(np.int32)),
        frame=as_array(
            np.concatenate([head(points.frame), np.repeat(np.arange(n), F)]).astype(np.int32)
        ),
        target=as_array(np.concatenate([head(points.target), tail(points.target, 0.0)])),
        weight=as_array(np.concatenate([head(points.weight), tail(points.weight, 0.0)])),
        exact=as_array(np.concatenate([head(points.exact), tail(points.exact, False)])),
        n_sparse=s,
        per_frame=F,
    )


def solve_gn_bucketed(
    fm: FeatureMap,
    tx: WhitenedTextons,
    seg: FrameSegments,
    Y: Any,
    start_position: Any,
    start_heading: Any,
    cons: Constraints,
    weights: EditWeights,
    *,
    extra: PointTargets | None = None,
    **kw: Any,
) -> EditResult:
    """:func:`~mtex_jax.edit._gn.solve_edit_gn` (jit-compiled) on the motion padded to
    :func:`edit_length` frames, the result cut back to its ``T`` frames.

    Args:
        fm, tx, seg, Y, start_position, start_heading, cons, weights: as for
            :func:`~mtex_jax.edit._gn.solve_edit_gn`, for one motion of ``T`` frames.
        extra: further point targets; frame-major ones (one per frame and foot, as
            :func:`~mtex_jax.edit.clean` makes) are padded with weightless targets
            (:func:`pad_points`), sparse ones kept as they are.
        **kw: the keyword arguments of :func:`~mtex_jax.edit._gn.solve_edit_gn`.

    Returns:
        :class:`~mtex_jax.edit.EditResult` of ``T`` frames.
    """
    T = int(np.shape(Y)[0])
    n = edit_length(T)
    Yp, segp, consp, extrap = pad_inputs(n, Y, seg, cons, extra)
    res = solve_edit_gn_jit(
        fm,
        tx,
        segp,
        Yp,
        start_position,
        start_heading,
        consp,
        weights,
        extra=extrap,
        n_valid=as_array(np.int32(T)),
        **kw,
    )
    return eqx.tree_at(lambda r: (r.Y, r.u), res, (cut_frames(res.Y, T), cut_frames(res.u, T)))
