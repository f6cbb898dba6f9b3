"""Building the implicit model (IP §4, design §7): the database of motion windows, their PCA and
the sign tree, from training clips.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import jax.numpy as jnp
import numpy as np

from ..core import check_count, check_size
from ..motion import FeatureMap, Motion, foot_joints
from ._database import MotionDatabase
from ._feet import foot_contact
from ._hubness import neighbour_radius
from ._model import ImplicitModel
from ._tree import codes_np, right_svd
from ._windows import (
    MAX_BITS,
    channel_importance,
    check_motion_values,
    pose_vectors,
    time_weights,
    velocity_channels,
    window_view,
)

Weighting = Literal["body", "channel"]


def learn(
    motions: Motion | Sequence[Motion],
    window: int,
    *,
    fps: float | None = None,
    n_components: int | None = None,
    max_components: int | None = None,
    feature_map: FeatureMap | None = None,
    min_std: float = 1e-8,
    weighting: Weighting = "body",
    min_explained: float | None = None,
    recent_weight: float = 32.0,
) -> ImplicitModel:
    """Build the database and its sign tree from training clips (IP §4, design §7).

    Args:
        motions: one clip or a list (same skeleton); windows never straddle two clips.
        window: ``d``, pose vectors per window (the paper: ``d = 10`` at 30 Hz ≈ 1/3 s).
        fps: resample every clip to this rate first (default: keep; clips must agree).
        n_components: ``b``; default ``⌊log₂ n⌋``. Always capped by the window dimension
            and the numerical rank of the windows.
        max_components: optional further cap on ``b`` (at most 30: codes are int32).
        feature_map: observation map to use (default ``FeatureMap.fit(motions)``).
        min_std: floor on each parameter's ``γ`` (relative to the largest ``γ``).
        weighting: how pose-vector channels are scaled into model coordinates ``ψ_c / γ_c``.
            ``"channel"`` (the paper, IP Eq. 2): ``γ_c`` is each channel's database standard
            deviation, so every channel weighs the same. ``"body"`` (default): each channel is
            first expressed as the distance it moves the body, ``ψ_c · m_c`` with ``m_c`` from
            :func:`channel_importance` (joint reach × channel scale), and then the pose half
            and the velocity half are each whitened as a group,
            ``γ_c = g_group / m_c`` with ``g_group² = mean_{c ∈ group} Var(ψ_c m_c)``, so the
            PCA follows the limbs and trunk rather than small joints.
        min_explained: if given (in ``(0, 1]``), choose ``b`` as the fewest components whose
            explained variance reaches this fraction (still capped as above) instead of
            ``⌊log₂ n⌋``. Exclusive with ``n_components``.
        recent_weight: ``w ≥ 0``: the newest pose vector of every window (the current pose
            and velocity) is scaled by ``√(1 + w)`` in model coordinates, so every distance
            (tree, kernels, hubness radii) weighs it ``1 + w`` times:
            ``‖Ψ_i − Φ‖² + w ‖ψ_i − φ‖²``. ``0`` is the paper's window distance. A
            transition then starts from a closer pose and velocity, so its fading offset
            adds less motion (design §7.5). The default 32 was chosen, together with the
            synthesis foot lock, on validation folds of the training clips. For tracking
            (:func:`~mtex_jax.tracking.track`) use ``0``: the paper's window distance tracks
            better (the documentation's results page has both).

    Returns:
        the model (``summary()`` reports ``b``, the explained variance and leaf sizes).

    Raises:
        ValueError: empty database, a clip shorter than ``window + 2`` frames, non-finite
            poses, ``window < 1``, bad component counts, mismatched frame rates.
    """
    if isinstance(motions, Motion):
        motions = [motions]
    motions = list(motions)
    if not motions:
        raise ValueError("ImplicitModel.build: empty database (no motions given)")
    for i, m in enumerate(motions):
        if not isinstance(m, Motion):
            raise TypeError(f"ImplicitModel.build: item {i} is {type(m).__name__}, not Motion")
    if isinstance(window, bool) or not isinstance(window, int | np.integer) or window < 1:
        raise ValueError(f"ImplicitModel.build: window must be an integer ≥ 1, got {window!r}")
    d = int(window)
    for i, m in enumerate(motions):
        check_motion_values(m, f"ImplicitModel.build: motion {i}")
    if fps is not None:
        motions = [m if m.fps == fps else m.resample(fps) for m in motions]
    for i, m in enumerate(motions):
        if m.n_frames < d + 2:
            raise ValueError(
                f"ImplicitModel.build: window ({d} pose vectors) is longer than motion {i} "
                f"allows: it has {m.n_frames} frames, a window plus its successor needs "
                f"at least {d + 2}"
            )
    if feature_map is None:
        fm = FeatureMap.fit(motions)
    else:
        fm = feature_map
        for m in motions:
            fm._check_motion(m)
    for arg, name in ((n_components, "n_components"), (max_components, "max_components")):
        if arg is not None and (
            isinstance(arg, bool) or not isinstance(arg, int | np.integer) or arg < 1
        ):
            raise ValueError(f"ImplicitModel.build: {name} must be a positive integer")
        if arg is not None:
            check_count(arg, f"ImplicitModel.build: {name}", "MAX_COMPONENTS")
    if weighting not in ("body", "channel"):
        raise ValueError(
            f"ImplicitModel.build: weighting must be 'body' or 'channel', got {weighting!r}"
        )
    if (
        isinstance(recent_weight, bool)
        or not isinstance(recent_weight, int | float | np.integer | np.floating)
        or not 0 <= recent_weight < np.inf
    ):
        raise ValueError(
            f"ImplicitModel.build: recent_weight must be a finite number ≥ 0, got {recent_weight!r}"
        )
    if min_explained is not None:
        if isinstance(min_explained, bool) or not (
            isinstance(min_explained, float | int) and 0 < min_explained <= 1
        ):
            raise ValueError(
                f"ImplicitModel.build: min_explained must be in (0, 1], got {min_explained!r}"
            )
        if n_components is not None:
            raise ValueError("ImplicitModel.build: give n_components or min_explained, not both")

    psis = [pose_vectors(fm, m) for m in motions]
    n_windows = sum(max(len(psi) - d, 0) for psi in psis)
    width = d * (psis[0].shape[1] if psis else 0)
    check_size(
        8 * n_windows * width,
        "ImplicitModel.build: bytes of the window database",
        "MAX_MODEL_BYTES",
    )
    allpsi = np.concatenate(psis, axis=0)
    if not np.all(np.isfinite(allpsi)):
        raise ValueError("ImplicitModel.build: non-finite pose vectors")
    pose_std = allpsi.std(axis=0)
    pose_std = np.maximum(pose_std, min_std * max(float(pose_std.max()), 1e-300))
    p = allpsi.shape[1]
    if weighting == "channel":
        gamma = pose_std
    else:
        imp = np.tile(channel_importance(fm), 2)
        spread = allpsi.std(axis=0) * imp
        g = np.empty(p)
        for half in (slice(0, p // 2), slice(p // 2, p)):
            g[half] = max(float(np.sqrt(np.mean(spread[half] ** 2))), 1e-300)
        gamma = g / imp
    vel_ch = np.asarray(velocity_channels(fm), dtype=np.int64)
    tw = time_weights(d, float(recent_weight))[None, :, None]

    wins, succ, clip_idx, frame_idx, sizes, accs = [], [], [], [], [], []
    for c, psi in enumerate(psis):
        # rows k of psi = frame k+1; window ending at row k needs k+1 < len(psi)
        v = window_view(psi / gamma, d)[:-1] * tw  # drop the window without a successor
        wins.append(v.reshape(v.shape[0], -1))
        succ.append(psi[d:])
        clip_idx.append(np.full(v.shape[0], c))
        frame_idx.append(np.arange(v.shape[0]) + d)  # newest row d-1+j = frame d+j
        sizes.append(int(v.shape[0]))
        y = psi[:, : p // 2]
        if y.shape[0] >= 3:
            dd = y[2:] - 2 * y[1:-1] + y[:-2]
            dd[:, vel_ch] = (y[2:] - y[1:-1])[:, vel_ch]
            accs.append(dd)
    windows = np.concatenate(wins, axis=0)
    n, w = windows.shape
    if n < 2:
        raise ValueError(f"ImplicitModel.build: database too small ({n} window), need ≥ 2")
    acc = np.concatenate(accs, axis=0) if accs else np.zeros((1, p // 2))
    acc_std = np.maximum(acc.std(axis=0), 1e-12)

    mean = windows.mean(axis=0)
    x = windows - mean
    s, vt = right_svd(x)
    rank = int(np.sum(s > s[0] * 1e-10)) if s[0] > 0 else 0
    if rank == 0:
        raise ValueError("ImplicitModel.build: all windows are identical")
    frac = np.cumsum(s**2) / np.sum(s**2)
    if min_explained is not None:
        b = int(np.searchsorted(frac, float(min_explained) - 1e-12) + 1)
    else:
        b = math.floor(math.log2(n)) if n_components is None else int(n_components)
    b = min(b, w, rank, MAX_BITS)
    if max_components is not None:
        b = min(b, int(max_components))
    b = max(b, 1)
    basis = vt[:b].T.copy()
    # fix the SVD's sign ambiguity: largest-magnitude loading of each direction positive
    flip = np.sign(basis[np.argmax(np.abs(basis), axis=0), np.arange(b)])
    basis = basis * np.where(flip == 0, 1.0, flip)
    coeffs = x @ basis
    sigma = coeffs.std(axis=0)
    explained = float(np.sum(s[:b] ** 2) / np.sum(s**2))
    codes = codes_np(coeffs)
    order = np.argsort(codes, kind="stable").astype(np.int32)
    # the largest leaf from the sorted codes (np.bincount would hold 2**n_components counts)
    leaf_max = int(np.unique(codes[order], return_counts=True)[1].max())

    dtype = np.result_type(*[np.asarray(m.rotations).dtype for m in motions], np.float32)
    f = lambda a: jnp.asarray(np.asarray(a, dtype=dtype))
    i32 = lambda a: jnp.asarray(np.asarray(a, dtype=np.int32))
    clip_index, frame_index = np.concatenate(clip_idx), np.concatenate(frame_idx)
    try:
        feet = tuple(int(j) for j in foot_joints(fm.skeleton))
    except ValueError:  # no leaf joint below the root: no feet to lock
        feet = ()
    contact = foot_contact(motions, feet, d)
    database = MotionDatabase(
        window=d,
        n_components=b,
        leaf_max=leaf_max,
        clip_sizes=tuple(sizes),
        recent_weight=float(recent_weight),
        feet=feet,
        gamma=f(gamma),
        pose_std=f(pose_std),
        mean=f(mean),
        basis=f(basis),
        sigma=f(sigma),
        windows=f(windows),
        successors=f(np.concatenate(succ, axis=0)),
        codes=i32(codes),
        order=i32(order),
        sorted_codes=i32(codes[order]),
        sorted_coeffs=f(coeffs[order]),
        clip_index=i32(clip_index),
        frame_index=i32(frame_index),
        acceleration_std=f(acc_std),
        neighbour_radius=f(neighbour_radius(windows, clip_index, frame_index, d)),
        foot_contact=f(contact),
    )
    return ImplicitModel(
        feature_map=fm, database=database, explained_variance=explained, weighting=weighting
    )
