"""Monocular 3-D tracking with a particle filter (Sidenbladh, Black & Sigal, IP §3 and §6).

Observation model (design §7): the 3-D positions of ``K`` joints of a motion the database has not
seen are projected through a pin-hole camera (:class:`Camera`) and perturbed with Gaussian pixel
noise; depth is not observed. :func:`make_problem` builds such a problem, with its ground truth.

State of a particle: a window of ``d`` pose vectors ``ψ = [y, Δy]`` (the model's coordinates,
FeatureMap units) plus the root's world position and heading, which the per-frame displacement
and yaw change in ``y`` are integrated into (exactly as :meth:`FeatureMap.decode` does).

Temporal priors ``p(ψ_t | Ψ_{t−1})``:

* ``"implicit"`` (IP §3): sample a database example for the particle's window with the tree
  search (IP Eq. 7–8) and take its successor pose ``y_{i+1}`` plus Gaussian noise
  ``noise · γ``;
* ``"constant_velocity"``: ``y_t = y_{t−1} + (y_{t−1} − y_{t−2}) + cv_noise · a ⊙ ε`` with
  independent noise per parameter, ``a`` the database standard deviation of the second
  difference of each parameter (:attr:`ImplicitModel.acceleration_std`). The root's
  displacement and yaw-change channels already are velocities: for them constant velocity
  means ``y_t = y_{t−1} + cv_noise · a ⊙ ε``.

In both, the velocity half of the new pose vector is ``y_t − y_{t−1}``.

Filter (bootstrap / SIR, IP Eq. 1): per frame, propagate every particle with the prior, weight
it by ``p(o_t | ψ_t) ∝ exp(−Σ_k ‖π(x_k) − o_{t,k}‖² / (2 s²))`` (``x_k`` from forward kinematics
of the particle's pose, batched over particles; ``s`` = ``likelihood_sigma``), record the
posterior means, and resample systematically. One ``lax.scan`` over frames, ``vmap`` over
particles; all randomness comes from explicit keys.

Error (what :class:`TrackResult` reports): for each frame the mean over the ``K`` observed
joints of the Euclidean distance between the posterior-mean 3-D joint position (weighted mean of
the particles' forward-kinematics positions) and the true joint position, in world coordinates
(``error``), and after subtracting each skeleton's first observed joint — the root by default —
(``error_root_relative``); both in
the skeleton's length unit (metres for the CMU salsa and DeepMimic data: × 1000 for mm).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float, Int, PRNGKeyArray

from ..core import (
    MAX_GENERATED_FRAMES,
    MAX_PARTICLES,
    bucket_length,
    check_count,
    check_key,
    pad_frames,
)
from ..motion import (
    FeatureMap,
    Motion,
    forward_kinematics,
    forward_kinematics_arrays,
    ground_axes,
    quat_twist,
)
from ._camera import Camera, decode_frame, default_joints
from ._database import MotionDatabase
from ._model import ImplicitModel
from ._tree import tree_sample_indices
from ._windows import velocity_channels

Prior = Literal["implicit", "constant_velocity"]


# --------------------------------------------------------------------------- problem
class TrackingProblem(eqx.Module):
    """Observations and ground truth of one tracking run (shared by the priors compared).

    Attributes:
        joints: indices of the ``K`` observed joints (static; the root first).
        frames: clip frame numbers of the tracked frames (static).
        camera: the pin-hole camera.
        pixel_noise: standard deviation of the pixel noise added to the observations.
        init_window: ``(d, P)`` true pose vectors of the ``d`` frames before the first tracked
            one (the known initial state, as in IP §6).
        init_position: ``(3,)`` true root position of the frame before the first tracked one.
        init_heading: its root yaw.
        observations: ``(T, K, 2)`` noisy pixel positions.
        truth: ``(T, K, 3)`` true world joint positions.
    """

    joints: tuple[int, ...] = eqx.field(static=True)
    frames: tuple[int, ...] = eqx.field(static=True)
    camera: Camera
    pixel_noise: Float[Array, ""]
    init_window: Float[Array, "d P"]
    init_position: Float[Array, " 3"]
    init_heading: Float[Array, ""]
    observations: Float[Array, "T K 2"]
    truth: Float[Array, "T K 3"]

    @property
    def n_frames(self) -> int:
        return len(self.frames)


def _default_camera(truth_root: np.ndarray, up_axis: int, distance: float) -> Camera:
    u, _, h1 = ground_axes(up_axis)
    target = truth_root.mean(axis=0)
    eye = target.copy()
    eye[h1] += distance
    up = np.zeros(3)
    up[u] = 1.0
    return Camera.look_at(eye, target, up)


def make_problem(
    key: PRNGKeyArray,
    model: ImplicitModel,
    motion: Motion,
    *,
    n_frames: int | None = None,
    start: int = 0,
    camera: Camera | None = None,
    camera_distance: float = 4.0,
    pixel_noise: float = 2.0,
    joints: Sequence[int | str] | None = None,
) -> TrackingProblem:
    """Synthetic monocular observations of a (held-out) clip.

    The first ``d + 1`` frames from ``start`` give the known initial state; frames
    ``start + d + 1 …`` are tracked.

    Args:
        key: PRNG key of the pixel noise.
        model: the implicit model (its feature map defines the pose vectors).
        motion: the clip to track, at the model's frame rate.
        n_frames: frames to track (default: all the clip has).
        start: first frame of the initial window.
        camera: default: 1000 px focal length, looking horizontally at the mean root position
            from ``camera_distance`` along the second horizontal axis (``+z`` for a y-up
            skeleton).
        camera_distance: distance of the default camera.
        pixel_noise: standard deviation (pixels) of the Gaussian noise on each coordinate.
        joints: observed joints (indices or names); default :func:`default_joints`.

    Raises:
        ValueError: clip too short, bad arguments, non-finite values.
    """
    check_key(key, "make_problem")
    fm = model.feature_map
    fm._check_motion(motion)
    d = model.window
    if not (np.isfinite(pixel_noise) and pixel_noise >= 0):
        raise ValueError(f"make_problem: pixel_noise must be finite and ≥ 0, got {pixel_noise}")
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
    psi = model.pose_vectors(clip)  # rows = clip frames 1 … d+n
    world = np.asarray(forward_kinematics(clip))
    truth = world[d + 1 :, list(jidx)]
    root = np.asarray(clip.root_positions)
    q_root = np.asarray(clip.rotations)[:, 0]
    up = np.zeros(3)
    up[sk.up_axis] = 1.0
    heading = np.asarray(quat_twist(jnp.asarray(q_root[d]), jnp.asarray(up)))
    cam = camera or _default_camera(root[d + 1 :], sk.up_axis, camera_distance)
    obs = cam.project(jnp.asarray(truth))
    obs = obs + pixel_noise * jax.random.normal(key, obs.shape, obs.dtype)
    frames = tuple(range(start + d + 1, start + d + 1 + n))
    dt = model.windows.dtype
    return TrackingProblem(
        joints=jidx,
        frames=frames,
        camera=cam,
        pixel_noise=jnp.asarray(pixel_noise, dt),
        init_window=jnp.asarray(psi[:d], dt),
        init_position=jnp.asarray(root[d], dt),
        init_heading=jnp.asarray(heading, dt),
        observations=jnp.asarray(obs, dt),
        truth=jnp.asarray(truth, dt),
    )


# --------------------------------------------------------------------------- filter
class TrackResult(eqx.Module):
    """Output of :func:`track` (per tracked frame ``t``).

    Attributes:
        prior: which temporal prior (static).
        n_particles: number of particles (static).
        mean_joints: ``(T, K, 3)`` posterior-mean world joint positions.
        mean_pose: ``(T, P)`` posterior-mean pose vector.
        mean_root: ``(T, 3)`` posterior-mean root position.
        ess: ``(T,)`` effective sample size ``1 / Σ w²`` before resampling.
        error: ``(T,)`` mean per-joint 3-D distance to the truth (world coordinates).
        error_root_relative: ``(T,)`` the same after subtracting each skeleton's first observed
            joint (the root with the default joints).
    """

    prior: str = eqx.field(static=True)
    n_particles: int = eqx.field(static=True)
    mean_joints: Float[Array, "T K 3"]
    mean_pose: Float[Array, "T P"]
    mean_root: Float[Array, "T 3"]
    ess: Float[Array, " T"]
    error: Float[Array, " T"]
    error_root_relative: Float[Array, " T"]

    @property
    def mean_error(self) -> float:
        """Mean of :attr:`error` over frames."""
        return float(jnp.mean(self.error))


def _systematic(key: PRNGKeyArray, w: Float[Array, " N"]) -> Int[Array, " N"]:
    n = w.shape[0]
    u = (jax.random.uniform(key, (), w.dtype) + jnp.arange(n, dtype=w.dtype)) / n
    cdf = jnp.cumsum(w)
    cdf = cdf / cdf[-1]
    return jnp.minimum(jnp.searchsorted(cdf, u, side="left"), n - 1).astype(jnp.int32)


def _track_impl(
    db: MotionDatabase,
    fm: FeatureMap,
    problem: _Inputs,
    key: PRNGKeyArray,
    n_particles: int,
    prior: str,
    beta: Array,
    noise: Array,
    cv_noise: Array,
    likelihood_sigma: Array,
    leaf: str,
    candidates: int,
) -> tuple[Array, Array, Array, Array]:
    dim = fm.dim
    dt = db.windows.dtype
    jidx = np.asarray(problem.joints)
    g = db.pose_std.astype(dt)[:dim]
    acc = db.acceleration_std.astype(dt)
    n = n_particles
    # root displacement / yaw change already are velocities: constant velocity keeps them
    vel_mask = jnp.ones(dim, dt).at[np.asarray(velocity_channels(fm), dtype=np.int64)].set(0.0)

    win = jnp.broadcast_to(problem.init_window, (n, *problem.init_window.shape))
    pos = jnp.broadcast_to(problem.init_position, (n, 3))
    head = jnp.broadcast_to(problem.init_heading, (n,))
    dec = jax.vmap(lambda y, p, h: decode_frame(fm, y, p, h))

    def step(carry, inp):
        win, pos, head, k = carry
        obs = inp
        k, k_prior, k_noise, k_res = jax.random.split(k, 4)
        last = win[:, -1, :dim]
        eps = jax.random.normal(k_noise, (n, dim), dt)
        if prior == "implicit":
            probes = db.scale_windows(win)
            idx = tree_sample_indices(db, k_prior, probes, beta, leaf, candidates)
            pose = db.successors[idx, :dim].astype(dt) + noise * g * eps
        else:
            pose = last + vel_mask * win[:, -1, dim:] + cv_noise * acc * eps
        psi = jnp.concatenate([pose, pose - last], axis=-1)
        win = jnp.concatenate([win[:, 1:], psi[:, None]], axis=1)
        pos, head, rot, lp = dec(pose, pos, head)
        x = forward_kinematics_arrays(fm.skeleton, pos, rot, lp)[:, jidx]  # (N, K, 3)
        r = (problem.camera.project(x) - obs) / likelihood_sigma
        loglik = -0.5 * jnp.sum(r * r, axis=(1, 2))
        w = jax.nn.softmax(loglik)
        mean_x = jnp.einsum("n,nkc->kc", w, x)
        mean_psi = w @ psi
        mean_root = w @ pos
        ess = 1.0 / jnp.sum(w * w)
        sel = _systematic(k_res, w)
        return (win[sel], pos[sel], head[sel], k), (mean_x, mean_psi, mean_root, ess)

    _, out = lax.scan(step, (win, pos, head, key), problem.observations)
    return out


_track_jit = eqx.filter_jit(_track_impl)


class _Inputs(eqx.Module):
    """What the filter reads of a :class:`TrackingProblem`: its arrays and the observed
    joints, without the static frame numbers (which differ from problem to problem), the
    observations padded to a shape bucket (design §11)."""

    joints: tuple[int, ...] = eqx.field(static=True)
    camera: Camera
    init_window: Float[Array, "d P"]
    init_position: Float[Array, " 3"]
    init_heading: Float[Array, ""]
    observations: Float[Array, "T K 2"]


def track(
    key: PRNGKeyArray,
    model: ImplicitModel,
    problem: TrackingProblem,
    *,
    prior: Prior = "implicit",
    n_particles: int = 300,
    beta: float = 0.1,
    noise: float = 0.1,
    cv_noise: float = 0.1,
    likelihood_sigma: float = 20.0,
    leaf: Literal["uniform", "weighted"] = "uniform",
    candidates: int = 1,
) -> TrackResult:
    """Bootstrap particle filter on a :class:`TrackingProblem` (IP §3, §6).

    Args:
        key: PRNG key of the filter (prior sampling and resampling).
        model: the implicit model (database; also provides γ and the acceleration scale).
        problem: observations, ground truth and initial state (:func:`make_problem`).
        prior: ``"implicit"`` (tree search, IP Eq. 7–8) or ``"constant_velocity"``.
        n_particles: particles ``N``.
        beta: sampling temperature of the implicit prior.
        noise: innovation of the implicit prior, in database standard deviations ``γ``.
        cv_noise: innovation of the constant-velocity prior, in database standard deviations
            of each parameter's second difference.
        likelihood_sigma: pixel standard deviation assumed by the likelihood. Wider than the
            true pixel noise (2 px by default) on purpose: with ``2K`` observed coordinates a
            likelihood at the true noise leaves one particle with all the weight.
        leaf: leaf rule of the tree search.
        candidates: tree walks per particle and frame (see :meth:`ImplicitModel.sample`;
            1 = the paper's sampler).

    Returns:
        a :class:`TrackResult` (errors in the skeleton's length unit).
    """
    if prior not in ("implicit", "constant_velocity"):
        raise ValueError(f"track: prior must be 'implicit' or 'constant_velocity', got {prior!r}")
    if leaf not in ("uniform", "weighted"):
        raise ValueError(f"track: leaf must be 'uniform' or 'weighted', got {leaf!r}")
    if isinstance(n_particles, bool) or not isinstance(n_particles, int | np.integer):
        raise ValueError(f"track: n_particles must be an integer, got {n_particles!r}")
    if n_particles < 1:
        raise ValueError(f"track: n_particles must be ≥ 1, got {n_particles}")
    check_key(key, "track")
    check_count(n_particles, "track: n_particles", MAX_PARTICLES)
    check_count(problem.n_frames, "track: frames to track", MAX_GENERATED_FRAMES)
    if not (np.isfinite(beta) and beta > 0):
        raise ValueError(f"track: beta must be positive and finite, got {beta}")
    for name, v in (("noise", noise), ("cv_noise", cv_noise)):
        if not (np.isfinite(v) and v >= 0):
            raise ValueError(f"track: {name} must be finite and ≥ 0, got {v}")
    if isinstance(candidates, bool) or not isinstance(candidates, int | np.integer):
        raise ValueError(f"track: candidates must be an integer, got {candidates!r}")
    if candidates < 1:
        raise ValueError(f"track: candidates must be ≥ 1, got {candidates}")
    if problem.init_window.shape != (model.window, model.pose_dim):
        raise ValueError("track: the problem was made for a different model (window shape)")
    if not (np.isfinite(likelihood_sigma) and likelihood_sigma > 0):
        raise ValueError(f"track: likelihood_sigma must be positive, got {likelihood_sigma}")
    dt = model.windows.dtype
    # the filter is causal: run on the observations padded to a shape bucket (design §11),
    # the first T frames kept (cut on the host: eager slices compile once per length)
    T = problem.n_frames
    inputs = _Inputs(
        joints=problem.joints,
        camera=problem.camera,
        init_window=problem.init_window,
        init_position=problem.init_position,
        init_heading=problem.init_heading,
        observations=pad_frames(np.asarray(problem.observations), bucket_length(T), axis=0),
    )
    out = _track_jit(
        model.database,
        model.feature_map,
        inputs,
        key,
        int(n_particles),
        prior,
        jnp.asarray(beta, dt),
        jnp.asarray(noise, dt),
        jnp.asarray(cv_noise, dt),
        jnp.asarray(likelihood_sigma, dt),
        leaf,
        int(candidates),
    )
    mean_x, mean_psi, mean_root, ess = (np.asarray(a)[:T] for a in out)
    truth = np.asarray(problem.truth)
    err = np.mean(np.linalg.norm(mean_x - truth, axis=-1), axis=-1)
    rel = (mean_x - mean_x[:, :1]) - (truth - truth[:, :1])
    err_rel = np.mean(np.linalg.norm(rel, axis=-1), axis=-1)
    put = jax.device_put
    return TrackResult(
        prior=prior,
        n_particles=int(n_particles),
        mean_joints=put(mean_x),
        mean_pose=put(mean_psi),
        mean_root=put(mean_root),
        ess=put(ess),
        error=put(err),
        error_root_relative=put(err_rel),
    )
