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

Proposals (:attr:`ParticleFilter.proposal`, design §12.4). ``"bootstrap"`` (the default, the
paper's) samples the prior and weights by the likelihood; its small innovations cannot follow
the root's depth, which the observations pin only through the body's apparent size, and a
cloud that has drifted in depth does not come back. ``"gauss_newton"`` lets the data move the
body. Its model adds a *root diffusion* to the prior: after the prior's step the root moves by
``u ~ N(0, σ_r² I₃)`` and the heading turns by ``v ~ N(0, σ_h²)`` (``root_noise``,
``heading_noise``; the ground-plane part and the turn accumulate, the height stays the pose
vector's, the window the prior reads keeps the prior's pose vectors), a rigid move (every joint
translated by ``u``, turned by ``v`` about the vertical through the root). The proposal of
``θ = (u, v)`` is the Laplace approximation of ``p(o_t | θ) N(θ; 0, Σ)``: ``gn_steps``
Gauss–Newton (IRLS) steps from ``θ = 0`` on the confidence-weighted reprojection error, then a
draw from ``N(θ*, H⁻¹)`` (``H``: the Gauss–Newton Hessian at ``θ*``). The weight
``p(o_t | θ) N(θ; 0, Σ) / N(θ; θ*, H⁻¹)`` is the exact importance weight of the draw for the
diffused model (the pose comes from the prior, whose density cancels): the filter stays
consistent for that model, and the weight estimates the predictive likelihood
``∫ p(o_t | θ) N(θ; 0, Σ) dθ`` of the particle's prior step (exactly, were the projection
linear in ``θ`` and the likelihood Gaussian). ``"bootstrap"`` with ``root_noise > 0`` samples
the same diffused model blind.

Likelihoods (:attr:`ParticleFilter.likelihood`): ``"gaussian"`` (above) or ``"student_t"``,
``−(ν + 2)/2 · Σ_k c_k log(1 + ‖r_k‖² / ν)`` with ``r_k = (π(x_k) − o_k) / s``, ``ν = dof``
(robust to detections far off; IRLS weights ``c_k (ν + 2) / (ν + ‖r_k‖²)``). A joint of
confidence 0 counts nowhere, whatever its pixels.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

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
    check_memory,
    pad_frames,
    program_bytes,
)
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

__all__ = [
    "Dynamics",
    "ParticleFilter",
    "decode_frame",
    "gauss_newton_root",
    "rigid_move",
    "robust_loglik",
    "run_particle_filter",
    "systematic",
]

Dynamics = Literal["implicit", "constant_velocity"]
_OPTIONS = ("likelihood", "likelihood_sigma", "root_noise", "heading_noise")
_DEFAULTS = {  # the options left at None take their proposal's value (design §12.4)
    "bootstrap": dict(zip(_OPTIONS, ("gaussian", 20.0, 0.0, 0.0), strict=True)),
    "gauss_newton": dict(zip(_OPTIONS, ("student_t", 10.0, 0.03, 0.03), strict=True)),
}


class ParticleFilter(Tracker):
    """A particle filter with the implicit model's prior (IP §3, §6): the options of
    :func:`~mtex_jax.tracking.track` for an :class:`~mtex_jax.implicit.ImplicitModel`.

    Options left at ``None`` take their proposal's default (bootstrap / Gauss–Newton, read by
    :meth:`setting`; the latter's chosen on training clips, design §12.4).

    Attributes:
        n_particles: particles ``N``.
        dynamics: ``"implicit"`` (tree search, IP Eq. 7–8) or ``"constant_velocity"``.
        beta: sampling temperature of the implicit prior.
        noise: innovation of the implicit prior, in database standard deviations ``γ``.
        cv_noise: innovation of the constant-velocity prior, in database standard deviations
            of each parameter's second difference.
        likelihood_sigma: pixel scale ``s`` of the likelihood (default 20 / 10), wider than
            the true pixel noise (2 px by default) on purpose: with ``2K`` observed
            coordinates a likelihood at the true noise leaves one particle with all the weight.
        leaf: leaf rule of the tree search (``"uniform"`` or ``"weighted"``).
        candidates: tree walks per particle and frame (see :meth:`ImplicitModel.sample`;
            1 = the paper's sampler).
        proposal: ``"bootstrap"`` (the paper's: sample the prior, weight by the likelihood)
            or ``"gauss_newton"`` (the root moved towards the observations; its weights are
            exact importance weights of the root-diffused model and estimate the predictive
            likelihood of the particle's prior step, module notes).
        likelihood: ``"gaussian"`` or ``"student_t"`` (robust; default Gaussian / Student-t).
        dof: degrees of freedom ``ν`` of the Student-t likelihood.
        gn_steps: Gauss–Newton steps per particle and frame.
        root_noise: ``σ_r``, metres per frame, of the root diffusion (module notes;
            default: 0, the paper's model / 0.03; Gauss–Newton needs it > 0).
        heading_noise: ``σ_h``, radians per frame, of the heading diffusion (default:
            0 / 0.03; 0 for Gauss–Newton: the root's position only).
    """

    n_particles: int = eqx.field(static=True, default=300)
    dynamics: str = eqx.field(static=True, default="implicit")
    beta: float = eqx.field(static=True, default=0.1)
    noise: float = eqx.field(static=True, default=0.1)
    cv_noise: float = eqx.field(static=True, default=0.1)
    likelihood_sigma: float | None = eqx.field(static=True, default=None)
    leaf: str = eqx.field(static=True, default="uniform")
    candidates: int = eqx.field(static=True, default=1)
    proposal: str = eqx.field(static=True, default="bootstrap")
    likelihood: str | None = eqx.field(static=True, default=None)
    dof: float = eqx.field(static=True, default=4.0)
    gn_steps: int = eqx.field(static=True, default=2)
    root_noise: float | None = eqx.field(static=True, default=None)
    heading_noise: float | None = eqx.field(static=True, default=None)

    def __check_init__(self) -> None:
        for name, allowed in (
            ("dynamics", ("implicit", "constant_velocity")),
            ("leaf", ("uniform", "weighted")),
            ("proposal", tuple(_DEFAULTS)),
            ("likelihood", (None, "gaussian", "student_t")),
        ):
            if getattr(self, name) not in allowed:
                raise ValueError(
                    f"ParticleFilter: {name} must be one of {allowed}, got {getattr(self, name)!r}"
                )
        for name in ("n_particles", "candidates", "gn_steps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer):
                raise ValueError(f"ParticleFilter: {name} must be an integer, got {v!r}")
            if v < 1:
                raise ValueError(f"ParticleFilter: {name} must be ≥ 1, got {v}")
        check_count(self.n_particles, "ParticleFilter: n_particles", MAX_PARTICLES)
        gn = self.proposal == "gauss_newton"
        for name, positive in (
            *(("beta", True), ("noise", False), ("cv_noise", False), ("dof", True)),
            *(("likelihood_sigma", True), ("root_noise", gn), ("heading_noise", False)),
        ):
            v = self.setting(name)
            if isinstance(v, bool) or not (np.isfinite(v) and (v > 0 if positive else v >= 0)):
                bound = "positive" if positive else "≥ 0"
                why = " for gauss_newton" if name == "root_noise" else ""
                raise ValueError(
                    f"ParticleFilter: {name} must be finite and {bound}{why}, got {v!r}"
                )

    def setting(self, name: str) -> Any:
        """The option ``name``, the proposal's default if it is ``None``."""
        v = getattr(self, name)
        return _DEFAULTS[self.proposal].get(name) if v is None else v

    def run(self, key: PRNGKeyArray, prior: Any, problem: TrackingProblem) -> TrackResult:
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


def rigid_move(
    x: Float[Array, "K 3"], root: Float[Array, " 3"], theta: Float[Array, " q"], up: Array
) -> Float[Array, "K 3"]:
    """Joints ``x`` with the root moved by ``θ[:3]`` and, if ``θ`` has a fourth entry, the
    heading turned by ``θ[3]`` about the vertical ``up`` through ``root`` (module notes)."""
    if theta.shape[0] > 3:
        x = root + quat_rotate(yaw_quat(theta[3], up), x - root)
    return x + theta[:3]


def robust_loglik(
    r: Float[Array, "K 2"], conf: Float[Array, " K"], likelihood: str, dof: Array | float
) -> tuple[Array, Array]:
    """Log-likelihood (up to a constant) of the normalised residuals ``r`` and the IRLS weight
    of each joint (module notes); joints with confidence 0 count for nothing."""
    on = conf > 0
    r = jnp.where(on[:, None], r, 0.0)
    r2 = jnp.where(on, r[:, 0] ** 2 + r[:, 1] ** 2, 0.0)  # not a sum: slow under vmap
    if likelihood == "gaussian":
        return -0.5 * jnp.sum(conf * r2), conf
    return -0.5 * (dof + 2) * jnp.sum(conf * jnp.log1p(r2 / dof)), conf * (dof + 2) / (dof + r2)


def gauss_newton_root(
    camera: Camera,
    obs: Float[Array, "K 2"],
    conf: Float[Array, " K"],
    x: Float[Array, "K 3"],
    root: Float[Array, " 3"],
    precision: Float[Array, " q"],
    sigma: Array,
    up: Array,
    steps: int,
    likelihood: str = "gaussian",
    dof: Array | float = 4.0,
) -> tuple[Array, Array]:
    """Gauss–Newton (IRLS) steps from ``θ = 0`` on the rigid root move ``θ`` (:func:`rigid_move`)
    of one particle: minimise ``−log p(o | θ) + ½ θᵀ diag(precision) θ`` (design §12.4).

    Args:
        camera, obs, conf: the camera, ``(K, 2)`` observed pixels and ``(K,)`` confidences
            (0: missing, whatever the pixel).
        x, root: ``(K, 3)`` the particle's joints after the prior's step, ``(3,)`` its root.
        precision: ``(q,)`` prior precision of ``θ`` (``q = 3``: position; ``4``: and heading).
        sigma, up, steps: pixel scale ``s``, ``(3,)`` the vertical, Gauss–Newton steps.
        likelihood, dof: ``"gaussian"`` or ``"student_t"`` and the latter's ``ν``.

    Returns:
        ``θ*`` ``(q,)`` and the Gauss–Newton Hessian ``H = Jᵀ W J + diag(precision)`` at it
        (``W``: the IRLS weights there), the proposal's precision.
    """
    on = (conf > 0)[:, None]
    obs = jnp.where(on, obs, 0.0)
    dof = jnp.asarray(dof, obs.dtype)
    rot = camera.rotation.astype(x.dtype)
    q = precision.shape[0]

    def to_camera(v):  # R v as elementwise products: tiny dots and sums are slow under vmap
        return jnp.stack([sum(rot[i, j] * v[..., j] for j in range(3)) for i in range(3)], -1)

    def normal_eqs(th):
        """``H`` and the gradient ``g``, the residuals' Jacobian in closed form."""
        arm = rigid_move(x, root, th.at[:3].set(0.0), up) - root  # (K, 3), turned
        xc = to_camera(root + arm + th[:3]) + camera.translation
        z = xc[:, 2:]
        r = jnp.where(on, (camera.focal * xc[:, :2] / z + camera.center - obs) / sigma, 0.0)
        w = robust_loglik(r, conf, likelihood, dof)[1][:, None] * on / sigma**2
        dxc = [jnp.broadcast_to(rot[:, i], xc.shape) for i in range(3)]
        dxc = [*dxc, to_camera(jnp.cross(up, arm))][:q]  # ∂x_c / ∂θ_i, (K, 3) each
        jac = [camera.focal / z * (d[:, :2] - xc[:, :2] / z * d[:, 2:]) for d in dxc]
        terms = [w * a * b for a in jac for b in jac] + [w * a * r * sigma for a in jac]
        sums = jnp.sum(jnp.stack(terms), axis=(1, 2))  # one reduction over the joints
        h = sums[: q * q].reshape(q, q) + jnp.diag(precision)
        return h, sums[q * q :] + precision * th

    theta = jnp.zeros_like(precision)
    for _ in range(steps):  # unrolled: a few steps, fused into the caller's loop body
        h, g = normal_eqs(theta)
        theta = theta - jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(h), True), g)
    return theta, normal_eqs(theta)[0]


class _Settings(eqx.Module):
    """What the filter's program reads of a :class:`ParticleFilter`: the sizes and choices
    (static: a new one compiles a new program) and the scales (arrays, in the data's dtype)."""

    n_particles: int = eqx.field(static=True)
    prior: str = eqx.field(static=True)
    leaf: str = eqx.field(static=True)
    candidates: int = eqx.field(static=True)
    proposal: str = eqx.field(static=True)
    likelihood: str = eqx.field(static=True)
    gn_steps: int = eqx.field(static=True)
    diffusion: tuple[float, float] = eqx.field(static=True)
    beta: Array
    noise: Array
    cv_noise: Array
    likelihood_sigma: Array
    dof: Array


def _track_impl(
    db: MotionDatabase, fm: FeatureMap, problem: _Inputs, key: PRNGKeyArray, settings: _Settings
) -> tuple[Array, Array, Array, Array]:
    st = settings
    n_particles, prior, leaf, candidates = st.n_particles, st.prior, st.leaf, st.candidates
    proposal, likelihood, gn_steps = st.proposal, st.likelihood, st.gn_steps
    diffusion, beta, noise, cv_noise = st.diffusion, st.beta, st.noise, st.cv_noise
    likelihood_sigma, dof = st.likelihood_sigma, st.dof
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
    up = jnp.zeros(3, dt).at[fm.skeleton.up_axis].set(1.0)
    # the rigid root move θ: its standard deviation (the heading's only if it diffuses)
    q = 4 if (proposal == "bootstrap" or diffusion[1] > 0) else 3
    theta_std = jnp.asarray([diffusion[0]] * 3 + [diffusion[1]], dt)[:q]
    dof = jnp.asarray(dof, dt)

    def gn_move(e, obs, conf, x, root):
        """One particle's proposal (``e``: its normal draw): moved joints, θ, log weight."""
        prec = 1.0 / theta_std**2
        m, h = gauss_newton_root(
            problem.camera, obs, conf, x, root, prec, likelihood_sigma, up, gn_steps,
            likelihood, dof,
        )  # fmt: skip
        chol = jnp.linalg.cholesky(h)
        th = m + jax.scipy.linalg.solve_triangular(chol.T, e, lower=False)  # ~ N(m, H⁻¹)
        log_q = -0.5 * jnp.sum(e * e) + jnp.sum(jnp.log(jnp.diag(chol)))
        xs = rigid_move(x, root, th, up)
        r = (problem.camera.project(xs) - obs) / likelihood_sigma
        ll = robust_loglik(r, conf, likelihood, dof)[0]
        return xs, th, ll - 0.5 * jnp.sum(prec * th * th) - log_q

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
        if problem.bone_scale is not None:  # the person's bones, given
            b = problem.bone_scale.astype(dt)[None, :, None]
            if lp is None:
                off = jnp.asarray(fm.skeleton.offsets_array, dt)
                lp = jnp.broadcast_to(off, (n, *off.shape))
            lp = lp * b
        x = forward_kinematics_arrays(fm.skeleton, pos, rot, lp)[:, jidx]  # (N, K, 3)
        e_move = jax.random.normal(jax.random.fold_in(k_noise, 1), (n, q), dt)
        th = None  # the root's rigid move (module notes)
        if proposal == "gauss_newton":
            x, th, loglik = jax.vmap(gn_move, (0, None, None, 0, 0))(e_move, obs, conf, x, pos)
        else:
            if max(diffusion) > 0:  # the diffused model, sampled blind
                th = theta_std * e_move
                x = jax.vmap(rigid_move, (0, 0, 0, None))(x, pos, th, up)
            r = (problem.camera.project(x) - obs) / likelihood_sigma
            if likelihood == "gaussian":
                loglik = -0.5 * jnp.sum(conf[None, :, None] * r * r, axis=(1, 2))
            else:
                loglik = jax.vmap(lambda r: robust_loglik(r, conf, likelihood, dof)[0])(r)
        if th is not None:  # the paper's filter (no diffusion) is left exactly as it was
            pos, head = pos + th[:, :3], (head + th[:, 3] if q > 3 else head)
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
#: From this many particles the filter's memory is estimated before it runs, and a filter that
#: needs more than the process can allocate is refused (core.check_memory).
MEASURED_PARTICLES = 100_000
_PROBE_PARTICLES = (1024, 2048)


def _memory_estimate(args: tuple[Any, ...], n: int) -> int:
    """The bytes the filter of ``n`` particles holds: XLA's memory analysis of the same program
    at two small particle counts (arguments, outputs, temporaries), extrapolated linearly, as
    every per-particle array is. Compiling the large program itself only to refuse it would
    take minutes."""
    *rest, settings = args
    sizes = []
    for m in _PROBE_PARTICLES:
        probe = dataclasses.replace(settings, n_particles=m)
        sizes.append(program_bytes(_track_jit.lower(*rest, probe).compile().compiled))
    lo, hi = _PROBE_PARTICLES
    per = max(0.0, (sizes[1] - sizes[0]) / (hi - lo))
    return int(sizes[1] + per * (n - hi))


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
    bone_scale: Float[Array, " J"] | None = None


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
    if problem.init_window.shape != (model.database.window, model.database.pose_dim):
        raise ValueError("track: the problem was made for a different model (window shape)")
    dt = model.database.windows.dtype
    # the filter is causal: run on the observations padded to a shape bucket (design §11),
    # the first T frames kept (cut on the host: eager slices compile once per length)
    T = problem.n_frames
    n_pad = bucket_length(T)
    conf = np.asarray(problem.confidence)  # a missing pixel may hold anything: 0 (0 · r² = 0)
    obs = np.where(conf[..., None] > 0, np.asarray(problem.observations), 0.0)
    inputs = _Inputs(
        joints=problem.joints,
        camera=problem.camera,
        init_window=problem.init_window,
        init_position=problem.init_position,
        init_heading=jnp.asarray(problem.init_heading),
        observations=pad_frames(obs, n_pad, axis=0),
        confidence=pad_frames(conf, n_pad, axis=0),
        bone_scale=problem.bone_scale,
    )
    settings = _Settings(
        n_particles=int(pf.n_particles),
        prior=pf.dynamics,
        leaf=pf.leaf,
        candidates=int(pf.candidates),
        proposal=pf.proposal,
        likelihood=pf.setting("likelihood"),
        gn_steps=int(pf.gn_steps),
        diffusion=(float(pf.setting("root_noise")), float(pf.setting("heading_noise"))),
        beta=jnp.asarray(pf.beta, dt),
        noise=jnp.asarray(pf.noise, dt),
        cv_noise=jnp.asarray(pf.cv_noise, dt),
        likelihood_sigma=jnp.asarray(pf.setting("likelihood_sigma"), dt),
        dof=jnp.asarray(pf.dof, dt),
    )
    args = (model.database, model.feature_map, inputs, key, settings)
    if pf.n_particles >= MEASURED_PARTICLES:  # measured before it runs: refused, not killed
        need = _memory_estimate(args, pf.n_particles)
        check_memory(need, f"track: {pf.n_particles:,} particles over {T:,} frames")
    out = _track_jit(*args)
    mean_x, mean_psi, mean_root, ess = (np.asarray(a)[:T] for a in out)
    errs: tuple[np.ndarray | None, ...] = (None, None, None)
    if problem.truth is not None:
        errs = joint_errors(mean_x, np.asarray(problem.truth))
    put = lambda a: None if a is None else jax.device_put(a)
    return TrackResult(
        prior=pf.dynamics,
        n_particles=int(pf.n_particles),
        mean_joints=jax.device_put(mean_x),
        mean_pose=jax.device_put(mean_psi),
        mean_root=jax.device_put(mean_root),
        ess=put(ess),
        error=put(errs[0]),
        error_root_relative=put(errs[1]),
        error_aligned=put(errs[2]),
    )
