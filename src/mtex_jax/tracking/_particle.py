"""Monocular 3-D tracking with a particle filter (Sidenbladh, Black & Sigal, IP §3 and §6).

State of a particle: a window of ``d`` pose vectors ``ψ = [y, Δy]`` (the implicit model's
coordinates, FeatureMap units) plus the root's world position and heading, which the per-frame
displacement and yaw change in ``y`` are integrated into (exactly as :meth:`FeatureMap.decode`
does).

Temporal priors ``p(ψ_t | Ψ_{t−1})`` (:attr:`ParticleFilter.dynamics`):

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
it by ``p(o_t | ψ_t) ∝ exp(−Σ_k c_{t,k} ‖π(x_k) − o_{t,k}‖² / (2 s²))`` (``x_k`` from forward
kinematics of the particle's pose, batched over particles; ``c`` the observation's confidence,
``0`` for a missing joint; ``s`` = ``likelihood_sigma``), record the posterior means, and
resample systematically. One ``lax.scan`` over frames, ``vmap`` over particles; all randomness
comes from explicit keys.
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float, Int, PRNGKeyArray

from ..core import MAX_GENERATED_FRAMES, MAX_PARTICLES, bucket_length, check_count, pad_frames
from ..implicit import ImplicitModel, MotionDatabase, tree_sample_indices, velocity_channels
from ..motion import (
    FeatureMap,
    expmap_to_quat,
    forward_kinematics_arrays,
    ground_axes,
    quat_mul,
    quat_rotate,
    yaw_quat,
)
from ._camera import Camera
from ._problem import TrackingProblem
from ._result import TrackResult, joint_errors
from ._tracker import Tracker

__all__ = ["Dynamics", "ParticleFilter", "decode_frame", "run_particle_filter", "systematic"]

Dynamics = Literal["implicit", "constant_velocity"]


class ParticleFilter(Tracker):
    """A particle filter with the implicit model's prior (IP §3, §6): the options of
    :func:`~mtex_jax.tracking.track` for an :class:`~mtex_jax.implicit.ImplicitModel`.

    Attributes:
        n_particles: particles ``N``.
        dynamics: ``"implicit"`` (tree search, IP Eq. 7–8) or ``"constant_velocity"``.
        beta: sampling temperature of the implicit prior.
        noise: innovation of the implicit prior, in database standard deviations ``γ``.
        cv_noise: innovation of the constant-velocity prior, in database standard deviations
            of each parameter's second difference.
        likelihood_sigma: pixel standard deviation assumed by the likelihood. Wider than the
            true pixel noise (2 px by default) on purpose: with ``2K`` observed coordinates a
            likelihood at the true noise leaves one particle with all the weight.
        leaf: leaf rule of the tree search (``"uniform"`` or ``"weighted"``).
        candidates: tree walks per particle and frame (see :meth:`ImplicitModel.sample`;
            1 = the paper's sampler).
    """

    n_particles: int = eqx.field(static=True, default=300)
    dynamics: str = eqx.field(static=True, default="implicit")
    beta: float = eqx.field(static=True, default=0.1)
    noise: float = eqx.field(static=True, default=0.1)
    cv_noise: float = eqx.field(static=True, default=0.1)
    likelihood_sigma: float = eqx.field(static=True, default=20.0)
    leaf: str = eqx.field(static=True, default="uniform")
    candidates: int = eqx.field(static=True, default=1)

    def __check_init__(self) -> None:
        if self.dynamics not in ("implicit", "constant_velocity"):
            raise ValueError(
                f"ParticleFilter: dynamics must be 'implicit' or 'constant_velocity', "
                f"got {self.dynamics!r}"
            )
        if self.leaf not in ("uniform", "weighted"):
            raise ValueError(
                f"ParticleFilter: leaf must be 'uniform' or 'weighted', got {self.leaf!r}"
            )
        for name in ("n_particles", "candidates"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer):
                raise ValueError(f"ParticleFilter: {name} must be an integer, got {v!r}")
            if v < 1:
                raise ValueError(f"ParticleFilter: {name} must be ≥ 1, got {v}")
        check_count(self.n_particles, "ParticleFilter: n_particles", MAX_PARTICLES)
        if not (np.isfinite(self.beta) and self.beta > 0):
            raise ValueError(f"ParticleFilter: beta must be positive and finite, got {self.beta}")
        for name in ("noise", "cv_noise"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"ParticleFilter: {name} must be finite and ≥ 0, got {v}")
        ls = self.likelihood_sigma
        if not (np.isfinite(ls) and ls > 0):
            raise ValueError(f"ParticleFilter: likelihood_sigma must be positive, got {ls}")

    def run(self, key: PRNGKeyArray, prior: ImplicitModel, problem: TrackingProblem) -> TrackResult:
        """The filter on ``problem`` (module notes)."""
        return run_particle_filter(key, prior, problem, self)


def decode_frame(
    fm: FeatureMap,
    y: Float[Array, " D"],
    position: Float[Array, " 3"],
    heading: Float[Array, ""],
) -> tuple[Array, Array, Array, Array | None]:
    """One step of :meth:`FeatureMap.decode`: frame ``t`` from ``y_t`` and frame ``t−1``'s root.

    The displacement of ``y_t`` (heading frame of ``t−1``) is rotated by ``heading`` and added
    to ``position``; the new heading is ``heading + Δyaw_t``; the height is absolute.

    Args:
        fm: the feature map.
        y: ``(D,)`` observation vector of frame ``t``.
        position: ``(3,)`` root position at ``t − 1``.
        heading: root yaw at ``t − 1`` (radians).

    Returns:
        root position ``(3,)``, heading ``()``, local rotations ``(J, 4)`` and local positions
        ``(J, 3)`` (``None`` unless the map has position channels) of frame ``t``.
    """
    dt = y.dtype
    act = np.asarray(fm.active, dtype=np.int64)
    off = jnp.asarray(fm.offset, dt)
    sc = jnp.asarray(fm.scale, dt)
    raw = off.at[act].set(y * sc[act] + off[act])
    sk = fm.skeleton
    j = sk.n_joints
    u, h0, h1 = ground_axes(sk.up_axis)
    up = jnp.zeros(3, dt).at[u].set(1.0)
    local = jnp.zeros(3, dt).at[h0].set(raw[0]).at[h1].set(raw[1])
    pos = position + quat_rotate(yaw_quat(heading, up), local)
    pos = pos.at[u].set(raw[2])
    new_heading = heading + raw[3]
    q = expmap_to_quat(raw[4 : 4 + 3 * j].reshape(j, 3))
    q = q.at[0].set(quat_mul(yaw_quat(new_heading, up), q[0]))
    lp = None
    if fm.has_local_positions:
        lp = jnp.concatenate([pos[None], raw[4 + 3 * j :].reshape(j - 1, 3)], axis=0)
    return pos, new_heading, q, lp


def systematic(key: PRNGKeyArray, w: Float[Array, " N"]) -> Int[Array, " N"]:
    """Systematic resampling: ``N`` indices drawn from the weights ``w`` with one uniform."""
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
        obs, conf = inp
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
        loglik = -0.5 * jnp.sum(conf[None, :, None] * r * r, axis=(1, 2))
        w = jax.nn.softmax(loglik)
        mean_x = jnp.einsum("n,nkc->kc", w, x)
        mean_psi = w @ psi
        mean_root = w @ pos
        ess = 1.0 / jnp.sum(w * w)
        sel = systematic(k_res, w)
        return (win[sel], pos[sel], head[sel], k), (mean_x, mean_psi, mean_root, ess)

    _, out = lax.scan(step, (win, pos, head, key), (problem.observations, problem.confidence))
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
    confidence: Float[Array, "T K"]


def run_particle_filter(
    key: PRNGKeyArray, model: ImplicitModel, problem: TrackingProblem, pf: ParticleFilter
) -> TrackResult:
    """The particle filter of :class:`ParticleFilter` on a problem (module notes)."""
    if not isinstance(model, ImplicitModel):
        raise TypeError(
            f"track: a ParticleFilter takes an ImplicitModel prior, got {type(model).__name__}"
        )
    if problem.init_window is None or problem.init_position is None:
        raise ValueError(
            "track: the particle filter starts from a known initial window; this problem has "
            "none (real keypoints): track it with a texture's MapSmoother"
        )
    check_count(problem.n_frames, "track: frames to track", MAX_GENERATED_FRAMES)
    if problem.init_window.shape != (model.window, model.pose_dim):
        raise ValueError("track: the problem was made for a different model (window shape)")
    dt = model.windows.dtype
    # the filter is causal: run on the observations padded to a shape bucket (design §11),
    # the first T frames kept (cut on the host: eager slices compile once per length)
    T = problem.n_frames
    n_pad = bucket_length(T)
    inputs = _Inputs(
        joints=problem.joints,
        camera=problem.camera,
        init_window=problem.init_window,
        init_position=problem.init_position,
        init_heading=jnp.asarray(problem.init_heading),
        observations=pad_frames(np.asarray(problem.observations), n_pad, axis=0),
        confidence=pad_frames(np.asarray(problem.confidence), n_pad, axis=0),
    )
    out = _track_jit(
        model.database,
        model.feature_map,
        inputs,
        key,
        int(pf.n_particles),
        pf.dynamics,
        jnp.asarray(pf.beta, dt),
        jnp.asarray(pf.noise, dt),
        jnp.asarray(pf.cv_noise, dt),
        jnp.asarray(pf.likelihood_sigma, dt),
        pf.leaf,
        int(pf.candidates),
    )
    mean_x, mean_psi, mean_root, ess = (np.asarray(a)[:T] for a in out)
    errs: tuple[np.ndarray | None, ...] = (None, None, None)
    if problem.truth is not None:
        errs = joint_errors(mean_x, np.asarray(problem.truth))
    put = lambda a: None if a is None else jax.device_put(a)
    return TrackResult(
        prior=pf.dynamics,
        n_particles=int(pf.n_particles),
        mean_joints=put(mean_x),
        mean_pose=put(mean_psi),
        mean_root=put(mean_root),
        ess=put(ess),
        error=put(errs[0]),
        error_root_relative=put(errs[1]),
        error_aligned=put(errs[2]),
    )
