"""What a tracker is given: 2-D joint observations through a camera (design §12.1).

A :class:`TrackingProblem` holds the pixel positions of ``K`` skeleton joints over ``T``
frames, a confidence per joint and frame (``0``: missing), the camera, and, where known, the
state before the first frame and the ground truth. :func:`make_problem` builds one from a clip
the prior has not seen, for either prior (a :class:`~mtex_jax.texture.MotionTexture` or an
:class:`~mtex_jax.implicit.ImplicitModel`); with ``missing``, ``outliers`` and ``bone_scale``
it makes the *hard* setting of the tracking benchmark: joints dropped,
detections thrown far off, and a body whose bones are not the model's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from ..core import check_key
from ..implicit import ImplicitModel
from ..motion import (
    FeatureMap,
    Motion,
    Skeleton,
    foot_joints,
    forward_kinematics,
    ground_axes,
    quat_twist,
)
from ..texture import MotionTexture
from ._camera import Camera

__all__ = ["TrackingProblem", "default_joints", "feature_map_of", "make_problem", "scaled_skeleton"]


class TrackingProblem(eqx.Module):
    """Observations (and, for a synthetic problem, the ground truth) of one tracking run.

    Attributes:
        joints: indices of the ``K`` observed skeleton joints (static; the root first by
            default).
        frames: frame numbers of the tracked frames in their clip (static).
        camera: the pin-hole camera.
        pixel_noise: standard deviation of the pixel noise (pixels; what the trackers assume).
        observations: ``(T, K, 2)`` pixel positions (any value where ``confidence`` is 0).
        confidence: ``(T, K)`` weight of each observation in ``[0, 1]``; ``0``: missing.
        init_window: ``(d, P)`` the prior's coordinates of the ``d`` frames before the first
            tracked one (the implicit model's pose vectors, the texture's observation
            vectors), or ``None`` when unknown (real keypoints).
        init_position: ``(3,)`` root position of the frame before the first tracked one, or
            ``None``.
        init_heading: its root yaw, or ``None``.
        truth: ``(T, K, 3)`` true world joint positions, or ``None`` (real keypoints).
        bone_scale: ``(J,)`` the tracked person's bones when they are known (a measured
            skeleton: each joint's offset from its parent is the model skeleton's times
            ``bone_scale[j]``, :func:`scaled_skeleton`), or ``None``: the trackers use the
            model's skeleton, and a :class:`MapSmoother` with ``bones=True`` estimates them,
            from a prior centred on these when given (design §12.2).
    """

    joints: tuple[int, ...] = eqx.field(static=True)
    frames: tuple[int, ...] = eqx.field(static=True)
    camera: Camera
    pixel_noise: Float[Array, ""]
    observations: Float[Array, "T K 2"]
    confidence: Float[Array, "T K"]
    init_window: Float[Array, "d P"] | None = None
    init_position: Float[Array, " 3"] | None = None
    init_heading: Float[Array, ""] | None = None
    truth: Float[Array, "T K 3"] | None = None
    bone_scale: Float[Array, " J"] | None = None

    def __check_init__(self) -> None:
        T, K = len(self.frames), len(self.joints)
        if np.shape(self.observations) != (T, K, 2):
            raise ValueError(
                f"TrackingProblem: observations must have shape ({T}, {K}, 2) for {T} frames "
                f"and {K} joints, got {np.shape(self.observations)}"
            )
        if np.shape(self.confidence) != (T, K):
            raise ValueError(
                f"TrackingProblem: confidence must have shape ({T}, {K}), "
                f"got {np.shape(self.confidence)}"
            )
        if self.truth is not None and np.shape(self.truth) != (T, K, 3):
            raise ValueError(f"TrackingProblem: truth must have shape ({T}, {K}, 3)")
        if self.bone_scale is not None:
            b = np.asarray(self.bone_scale)
            if b.ndim != 1 or not b.size:
                raise ValueError(
                    f"TrackingProblem: bone_scale must be one factor per skeleton joint (J,), "
                    f"got shape {b.shape}"
                )
            if not (np.all(np.isfinite(b)) and np.all(b > 0)):
                raise ValueError("TrackingProblem: bone_scale must be positive and finite")
        known = [x is not None for x in (self.init_window, self.init_position, self.init_heading)]
        if any(known) and not all(known):
            raise ValueError(
                "TrackingProblem: init_window, init_position and init_heading are given together"
            )

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def has_init(self) -> bool:
        """Whether the state before the first tracked frame is known."""
        return self.init_window is not None


def feature_map_of(prior: Any, caller: str = "track") -> FeatureMap:
    """The feature map of a tracking prior (a texture or an implicit model)."""
    if isinstance(prior, ImplicitModel):
        return prior.feature_map
    if isinstance(prior, MotionTexture):
        if prior.feature_map is None:
            raise ValueError(f"{caller}: the texture was learned from arrays (no feature map)")
        return prior.feature_map
    raise TypeError(
        f"{caller}: the prior must be a MotionTexture or an ImplicitModel, got "
        f"{type(prior).__name__}"
    )


def default_joints(fm: FeatureMap) -> tuple[int, ...]:
    """The root and every joint with a moving rotation channel (the observed joints)."""
    moving = {name.rsplit(".", 1)[0] for name in fm.active_names}
    sk = fm.skeleton
    return tuple(i for i in range(sk.n_joints) if i == 0 or sk.names[i] in moving)


def scaled_skeleton(skeleton: Skeleton, scale: Float[Any, " J"]) -> Skeleton:
    """The skeleton with each joint's offset from its parent (its bone) scaled by ``scale[j]``."""
    s = np.asarray(scale, dtype=np.float64).reshape(-1)
    if s.shape != (skeleton.n_joints,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(
            f"scaled_skeleton: scale must be {skeleton.n_joints} positive finite numbers"
        )
    off = np.asarray(skeleton.offsets, dtype=np.float64) * s[:, None]
    return dataclasses.replace(skeleton, offsets=tuple(tuple(float(v) for v in o) for o in off))


def _default_camera(truth_root: np.ndarray, up_axis: int, distance: float) -> Camera:
    u, _, h1 = ground_axes(up_axis)
    target = truth_root.mean(axis=0)
    eye = target.copy()
    eye[h1] += distance
    up = np.zeros(3)
    up[u] = 1.0
    return Camera.look_at(eye, target, up)


def _unit_fraction(value: float, name: str) -> float:
    if isinstance(value, bool) or not (np.isfinite(value) and 0.0 <= value < 1.0):
        raise ValueError(f"make_problem: {name} must be a fraction in [0, 1), got {value!r}")
    return float(value)


def make_problem(
    key: PRNGKeyArray,
    prior: MotionTexture | ImplicitModel,
    motion: Motion,
    *,
    n_frames: int | None = None,
    start: int = 0,
    camera: Camera | None = None,
    camera_distance: float = 4.0,
    pixel_noise: float = 2.0,
    joints: Sequence[int | str] | None = None,
    missing: float = 0.0,
    outliers: float = 0.0,
    outlier_pixels: tuple[float, float] = (50.0, 200.0),
    bone_scale: tuple[float, float] | Float[Any, " J"] | None = None,
    known_bones: bool = False,
) -> TrackingProblem:
    """Synthetic monocular observations of a (held-out) clip (design §12.1).

    The first ``d + 1`` frames from ``start`` give the known initial state (``d``: the
    implicit model's window, 2 for a texture); frames ``start + d + 1 …`` are tracked.

    Args:
        key: PRNG key of the pixel noise (and of the missing joints, outliers and bone scales).
        prior: the texture or implicit model whose coordinates the initial window is given in.
        motion: the clip to track, at the prior's frame rate.
        n_frames: frames to track (default: all the clip has).
        start: first frame of the initial window.
        camera: default: 1000 px focal length, looking horizontally at the mean root position
            from ``camera_distance`` along the second horizontal axis (``+z`` for a y-up
            skeleton).
        camera_distance: distance of the default camera (metres).
        pixel_noise: standard deviation (pixels) of the Gaussian noise on each coordinate.
        joints: observed joints (indices or names); default :func:`default_joints`.
        missing: fraction of joint observations dropped at random (confidence 0).
        outliers: fraction of joint observations moved by ``outlier_pixels`` in a random
            direction (still at full confidence: a detector's confident mistake).
        outlier_pixels: ``(low, high)`` range of an outlier's displacement.
        bone_scale: the tracked person's bones: ``(low, high)``, each bone scaled by a factor
            drawn uniformly from the range, or ``(J,)`` factors per joint; ``None``: the
            skeleton's own bones. The truth and the observations follow the scaled body, its
            root lifted so that its feet stand on the same floor; the initial window is the
            same clip's (rotations do not depend on bone lengths).
        known_bones: give the trackers the person's bones (the problem's ``bone_scale``: a
            skeleton measured beforehand); ``False``: they are unknown to the trackers.

    Raises:
        ValueError: clip too short, bad arguments, non-finite values.
    """
    check_key(key, "make_problem")
    fm = feature_map_of(prior, "make_problem")
    fm._check_motion(motion)
    d = prior.database.window if isinstance(prior, ImplicitModel) else 2
    if not (np.isfinite(pixel_noise) and pixel_noise >= 0):
        raise ValueError(f"make_problem: pixel_noise must be finite and ≥ 0, got {pixel_noise}")
    missing = _unit_fraction(missing, "missing")
    outliers = _unit_fraction(outliers, "outliers")
    lo_px, hi_px = (float(v) for v in outlier_pixels)
    if not (np.isfinite(lo_px) and np.isfinite(hi_px) and 0 <= lo_px <= hi_px):
        raise ValueError("make_problem: outlier_pixels must be 0 ≤ low ≤ high, finite")
    available = motion.n_frames - start - d - 1
    if start < 0 or available < 1:
        raise ValueError(
            f"make_problem: the clip has {motion.n_frames} frames; with start={start} and a "
            f"window of {d} it leaves no frame to track (need at least {start + d + 2})"
        )
    n = available if n_frames is None else int(n_frames)
    if not 1 <= n <= available:
        raise ValueError(f"make_problem: n_frames must be in 1..{available}, got {n_frames}")
    sk = fm.skeleton
    if joints is None:
        jidx = default_joints(fm)
    else:
        jidx = tuple(sk.index(j) if isinstance(j, str) else int(j) for j in joints)
        if not jidx or any(not 0 <= j < sk.n_joints for j in jidx):
            raise ValueError("make_problem: joints must be non-empty valid joint indices")
    clip = motion[start : start + d + 1 + n]
    if isinstance(prior, ImplicitModel):
        init = prior.pose_vectors(clip)[:d]  # rows = clip frames 1 … d+n
        dt = prior.database.windows.dtype
    else:
        init = np.asarray(fm.encode(clip))[1 : d + 1]
        dt = jnp.asarray(prior.textons.mu).dtype
    if not isinstance(known_bones, bool):
        raise TypeError(f"make_problem: known_bones must be a bool, got {known_bones!r}")
    k_bones, k_miss, k_out, k_dir, k_len = (jax.random.fold_in(key, i) for i in range(1, 6))
    body = clip
    given = None
    if bone_scale is not None:
        bs = np.asarray(bone_scale, dtype=np.float64)
        if bs.shape == (2,) and sk.n_joints != 2:
            lo, hi = float(bs[0]), float(bs[1])
            if not (0 < lo <= hi and np.isfinite(hi)):
                raise ValueError("make_problem: bone_scale range must be 0 < low ≤ high")
            bs = np.asarray(jax.random.uniform(k_bones, (sk.n_joints,), minval=lo, maxval=hi))
        body = dataclasses.replace(clip, skeleton=scaled_skeleton(sk, bs))
        given = bs if known_bones else None
        if clip.local_positions is not None:
            lp = np.asarray(clip.local_positions) * np.asarray(bs)[None, :, None]
            body = dataclasses.replace(body, local_positions=jnp.asarray(lp))
        # the person stands on the same floor: the root is lifted (or lowered) by the change
        # of the feet's typical lowest height
        feet = list(foot_joints(sk))
        if feet:
            low = lambda m: np.median(np.asarray(forward_kinematics(m))[:, feet, sk.up_axis].min(1))
            lift = low(clip) - low(body)
            rp = np.asarray(body.root_positions).copy()
            rp[:, sk.up_axis] += lift
            body = dataclasses.replace(body, root_positions=jnp.asarray(rp))
    world = np.asarray(forward_kinematics(body))
    truth = world[d + 1 :, list(jidx)]
    root = np.asarray(clip.root_positions)
    q_root = np.asarray(clip.rotations)[:, 0]
    up = np.zeros(3)
    up[sk.up_axis] = 1.0
    heading = np.asarray(quat_twist(jnp.asarray(q_root[d]), jnp.asarray(up)))
    cam = camera or _default_camera(root[d + 1 :], sk.up_axis, camera_distance)
    obs = cam.project(jnp.asarray(truth))
    obs = obs + pixel_noise * jax.random.normal(key, obs.shape, obs.dtype)
    K = len(jidx)
    conf = np.ones((n, K))
    if missing > 0:
        conf = np.where(np.asarray(jax.random.uniform(k_miss, (n, K))) < missing, 0.0, 1.0)
    if outliers > 0:
        hit = np.asarray(jax.random.uniform(k_out, (n, K))) < outliers
        ang = np.asarray(jax.random.uniform(k_dir, (n, K), maxval=2 * np.pi))
        length = np.asarray(jax.random.uniform(k_len, (n, K), minval=lo_px, maxval=hi_px))
        move = np.stack([np.cos(ang), np.sin(ang)], axis=-1) * length[..., None]
        obs = jnp.asarray(np.where(hit[..., None], np.asarray(obs) + move, np.asarray(obs)))
    frames = tuple(range(start + d + 1, start + d + 1 + n))
    return TrackingProblem(
        joints=jidx,
        frames=frames,
        camera=cam,
        pixel_noise=jnp.asarray(pixel_noise, dt),
        observations=jnp.asarray(obs, dt),
        confidence=jnp.asarray(conf, dt),
        init_window=jnp.asarray(init, dt),
        init_position=jnp.asarray(root[d], dt),
        init_heading=jnp.asarray(heading, dt),
        truth=jnp.asarray(truth, dt),
        bone_scale=None if given is None else jnp.asarray(given, dt),
    )
