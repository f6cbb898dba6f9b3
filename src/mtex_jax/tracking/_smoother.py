"""The texture as a tracking prior: a MAP smoother, batch or fixed-lag (design §12.2–§12.3).

The estimate of the tracker's coordinates ``X`` (:mod:`._body`) minimises

.. code-block:: text

    Σ_{t,k} c_{tk} ρ(‖π(x_k(X_t, b)) − o_{tk}‖² / σ²)  +  prior(X)  +  bones(b)

with the robust reprojection term of :mod:`._reprojection`, a quadratic motion prior of
:mod:`._priors` (the texture's, along a segmentation), and, when the person's bones are
estimated, a Gaussian prior on their log-scales. The poses are found by the banded
Gauss–Newton solver of edits (:class:`~mtex_jax.edit.BandedGaussNewton`) with the reprojection
and the floor contact as its residual terms (:class:`~mtex_jax.edit.FrameResidual` members):
every frame's joints depend on that frame's row alone, so each step is one block-banded
factorisation, ``O(T·D³)``.

*Batch.* A per-frame rigid fit (:mod:`._start`) gives the first estimate, or the known initial
window is held before the first frame. A first round uses the second-difference prior alone;
then, each round, the texture's segmentation of the current estimate is found again
(semi-Markov Viterbi, :meth:`~mtex_jax.texture.MotionTexture.segment`; a clip shorter than
the texture's shortest segment takes the single texton that explains it best) and the
texture's prior along it is minimised. With ``bones``, each round ends with a dense
Gauss–Newton step on the bone scales and, without extrinsics, the floor.

*Fixed-lag.* Frame ``t`` is final once frame ``t + L`` is seen: each new frame is
extrapolated from the two before it, and the window of the last ``L + 1`` frames, with the two
final frames before it held, is solved again. The window's texton is the one whose dynamics
explain it best. A new frame costs one solve of ``L + 3`` frames: ``O(L)``, not ``O(T)``.
When the initial state is unknown, the first ``L + 2`` frames are first solved in one batch;
when the bones are estimated, the first ``bone_window`` seconds (at least ``L + 2`` frames),
after the known initial window, held. The rest keeps that batch's bones and floor.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, PRNGKeyArray

from ..core import MAX_GENERATED_FRAMES, as_array, bucket_length, check_count
from ..edit import (
    BandedGaussNewton,
    BandedProblem,
    FrameSegments,
    WhitenedTextons,
    channel_colouring,
    frame_segments,
    prior_residuals,
    solve_banded,
)
from ..motion import Motion, ground_axes, quat_rotate, yaw_quat
from ..texture import MotionTexture
from ._body import Body
from ._floor import FloorContact
from ._priors import MotionPrior, SmoothPrior, TexturePrior, root_weights
from ._problem import TrackingProblem
from ._reprojection import PixelLoss, Reprojection, StudentT
from ._result import TrackResult, joint_errors
from ._start import rigid_start
from ._tracker import Tracker

__all__ = ["TRACK_FRAMES", "MapSmoother"]

#: the shape-bucket step of a smoother's clip (design §11): a 150-frame clip is solved as 192
#: frames, not as the 1,024 of the package's default bucket (a step costs time in proportion)
TRACK_FRAMES = 64


class MapSmoother(Tracker):
    """MAP tracking with a texture's prior (module notes): the options of
    :func:`~mtex_jax.tracking.track` for a :class:`~mtex_jax.texture.MotionTexture`.

    Attributes:
        lag: ``None``: batch (the whole clip at once); ``L ≥ 1``: fixed-lag, each frame final
            ``L`` frames later.
        prior: the motion prior (:class:`TexturePrior`; :class:`SmoothPrior` for a baseline
            without the texture).
        pixel_loss: the robust loss of the reprojection (:class:`StudentT` by default).
        pixel_sigma: pixel standard deviation (``None``: the problem's ``pixel_noise``, at
            least 1 px).
        rounds: batch: rounds with the texture's prior, each after a new segmentation.
        max_steps: Gauss–Newton steps per round (batch).
        lag_steps: Gauss–Newton steps per new frame (fixed-lag).
        root_accel: standard deviation of the root's horizontal acceleration, m/s²
            (measured on the training clips of the salsa split: 6.1 and 6.3 at 30 Hz).
        turn_accel: the same of its heading, rad/s² (measured there: 66).
        bones: estimate the person's bone lengths (a global scale and one correction per
            bone, with Gaussian priors on their logarithms of standard deviations
            ``scale_sd`` and ``bone_sd``).
        scale_sd: prior standard deviation of the log of the global scale.
        bone_sd: prior standard deviation of the log of each bone's correction.
        floor: ``"known"``: the world's floor is the skeleton's (a camera with extrinsics);
            ``"estimate"``: a camera without extrinsics, the floor height is estimated.
        n_headings: headings tried per frame by the rigid start.
        floor_contact: price the lowest foot's distance from the floor (:mod:`._floor`; only
            where the texture has a contact model).
        anneal_from: batch: the first round's pixel scale (pixels); each round halves it down
            to ``pixel_sigma`` (a continuation that keeps Gauss–Newton out of the narrow
            valleys of a precise reprojection).
        bone_window: fixed-lag with ``bones``: the first ``bone_window`` seconds (at least
            ``lag + 2`` frames) are solved in one batch, whose bones and floor the rest of the
            pass keeps; those frames are final once the window is seen (chosen on folds of the
            training clips, hard setting, design §12.3).
    """

    lag: int | None = eqx.field(static=True, default=None)
    prior: MotionPrior = eqx.field(default_factory=TexturePrior)
    pixel_loss: PixelLoss = eqx.field(default_factory=StudentT)
    pixel_sigma: float | None = eqx.field(static=True, default=None)
    rounds: int = eqx.field(static=True, default=2)
    max_steps: int = eqx.field(static=True, default=12)
    root_accel: float = eqx.field(static=True, default=6.0)
    turn_accel: float = eqx.field(static=True, default=60.0)
    bones: bool = eqx.field(static=True, default=False)
    scale_sd: float = eqx.field(static=True, default=0.05)
    bone_sd: float = eqx.field(static=True, default=0.05)
    floor: str = eqx.field(static=True, default="known")
    n_headings: int = eqx.field(static=True, default=16)
    lag_steps: int = eqx.field(static=True, default=6)
    anneal_from: float = eqx.field(static=True, default=8.0)
    floor_contact: bool = eqx.field(static=True, default=True)
    bone_window: float = eqx.field(static=True, default=2.0)

    def __check_init__(self) -> None:
        for name in ("rounds", "max_steps", "lag_steps", "n_headings"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
                raise ValueError(f"MapSmoother: {name} must be an integer ≥ 1, got {v!r}")
        if self.lag is not None and (
            isinstance(self.lag, bool) or not isinstance(self.lag, int | np.integer) or self.lag < 1
        ):
            raise ValueError(f"MapSmoother: lag must be None or an integer ≥ 1, got {self.lag!r}")
        if isinstance(self.bone_window, bool) or not (
            np.isfinite(self.bone_window) and self.bone_window >= 0
        ):
            raise ValueError(
                f"MapSmoother: bone_window must be ≥ 0 seconds, got {self.bone_window!r}"
            )
        for name in ("root_accel", "turn_accel", "scale_sd", "bone_sd", "anneal_from"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (np.isfinite(v) and v > 0):
                raise ValueError(f"MapSmoother: {name} must be positive and finite, got {v!r}")
        if self.pixel_sigma is not None and not (
            np.isfinite(self.pixel_sigma) and self.pixel_sigma > 0
        ):
            raise ValueError(f"MapSmoother: pixel_sigma must be positive, got {self.pixel_sigma}")
        if self.floor not in ("known", "estimate"):
            raise ValueError(
                f"MapSmoother: floor must be 'known' or 'estimate', got {self.floor!r}"
            )
        if not isinstance(self.prior, MotionPrior):
            raise TypeError(f"MapSmoother: prior must be a MotionPrior, got {self.prior!r}")
        if not isinstance(self.pixel_loss, PixelLoss):
            raise TypeError(f"MapSmoother: pixel_loss must be a PixelLoss, got {self.pixel_loss!r}")

    def run(self, key: PRNGKeyArray, prior: Any, problem: TrackingProblem) -> TrackResult:
        """MAP-track ``problem`` with the texture ``prior`` (module notes)."""
        del key  # deterministic
        return _smooth(self, prior, problem)


# --------------------------------------------------------------------------- the solves
class _Frame(eqx.Module):
    """What one banded solve needs besides the estimate (one shape per bucket)."""

    body: Body
    tx: WhitenedTextons
    reproj: Reprojection
    root_w: Float[Array, " D"]
    bone_scale: Float[Array, " J"]
    floor: Float[Array, ""]
    contact: FloorContact | None
    fps: float = eqx.field(static=True)
    #: the log of the bones' prior centre (a given skeleton's scales; ``None``: the model's)
    bone_centre: Float[Array, " J"] | None = None

    def terms(self, valid: Array) -> tuple[Any, ...]:
        """The residual terms: the reprojection and, where the texture knows its floor, the
        feet on it (at frames where ``valid``)."""
        if self.contact is None:
            return (self.reproj,)
        height = self.contact.height + self.floor
        c = eqx.tree_at(lambda c: (c.height, c.valid), self.contact, (height, valid))
        return (self.reproj, c)


def _solve(
    fr: _Frame,
    prior: MotionPrior,
    seg: FrameSegments,
    X0: Array,
    held: Array,
    prev: tuple[Array, Array] | None,
    n_valid: Array,
    max_steps: int,
) -> tuple[Array, Array]:
    """One round: the prior's quadratic at ``X₀`` plus the reprojection, by banded GN."""
    body = fr.body
    T, D = X0.shape
    dt = X0.dtype
    Y0 = body.observations(X0, *(prev or (None, None)))
    bands, grad = prior.quadratic(fr.tx, seg, X0, Y0, fr.root_w, fr.fps, n_valid)
    problem = BandedProblem(
        positions=lambda X: body.positions(X, fr.bone_scale, fr.floor),
        Y0=X0,
        bands=bands,
        anchor=jnp.full((D,), 1e-4, dt),
        free_ch=jnp.ones((D,), dt),
        terms=fr.terms((~held & (jnp.arange(T) < n_valid)).astype(dt)),
        held=held,
        linear=grad,
        colouring=channel_colouring(body.feature_map, body.order),
    )
    sol = solve_banded(
        problem, BandedGaussNewton(rtol=1e-7, atol=1e-6, rounds=1, max_steps=max_steps)
    )
    return X0 + sol.z, sol.cost


_solve_jit = eqx.filter_jit(_solve)


def _best_texton(tx: WhitenedTextons, Y: Array, n_valid: Array) -> Array:
    """The texton whose dynamics (alone, no segment start) explain ``Y`` best."""
    T = Y.shape[0]
    N = tx.A1.shape[0]
    pos = jnp.arange(T, dtype=jnp.int32) + 2

    def nll(i: Array) -> Array:
        lab = jnp.full((T,), i, jnp.int32)
        e, g, o = prior_residuals(tx, FrameSegments(lab, lab, pos), Y, n_valid)
        return jnp.sum(e * e) + jnp.sum(g * g) + jnp.sum(o * o)

    return jnp.argmin(jax.vmap(nll)(jnp.arange(N, dtype=jnp.int32)))


_best_texton_jit = eqx.filter_jit(_best_texton)


def _single(i: int, T: int) -> FrameSegments:
    lab = jnp.full((T,), i, jnp.int32)
    return FrameSegments(lab, lab, jnp.arange(T, dtype=jnp.int32) + 2)


# --------------------------------------------------------------------------- bones
def _bone_step(
    fr: _Frame, X: Array, movable: Array, sd: Array, estimate_floor: bool
) -> tuple[_Frame, Array]:
    """Gauss–Newton (optimistix's Levenberg–Marquardt) on the bones' log-scales (and the floor)
    with the poses fixed, the residual terms reweighted at the current estimate.

    A change of the body's overall size moves every ``movable`` frame's root along its camera
    ray by the same factor (about the camera's centre), so the step follows the valley in
    which one camera cannot tell a bigger body from a farther one; the feet on the floor (the
    floor term, whose camera height turns a foot's height into depth) and the bones' priors
    decide where in it the body is. With ``estimate_floor`` the floor's height is a parameter
    too.
    Returns the frame inputs and the moved ``X``."""
    body = fr.body
    dt = X.dtype
    J = fr.bone_scale.shape[0]
    fm = body.feature_map
    up, h0, h1 = ground_axes(fm.skeleton.up_axis)
    c0, c1, _ = body.root_cols
    act = np.asarray(fm.active, dtype=np.int64)
    sc_h = jnp.asarray(fm.scale, dt)[act[2]]
    off_h = jnp.asarray(fm.offset, dt)[act[2]]
    cam = fr.reproj.camera
    centre = -cam.rotation.astype(dt).T @ cam.translation.astype(dt)
    used = np.asarray(body.order)
    log_b0 = jnp.log(fr.bone_scale)
    size0 = jnp.mean(log_b0[used])
    mv = movable.astype(dt)
    # the pixels leave the body's size traded against its depth; the feet on the floor, seen by
    # a camera of known height, settle it (design §12.2: on folds of the training clips, hard
    # setting, 128 → 40 and 127 → 65 mm mean global error)
    terms = fr.terms(mv)
    has_contact = fr.contact is not None
    P0 = body.positions(X, fr.bone_scale, fr.floor)
    sws = [jnp.sqrt(t.weights(t.residual(P0))) for t in terms]
    scale_sd, bone_sd = sd[0], sd[1]
    log_centre = 0.0 if fr.bone_centre is None else fr.bone_centre

    def moved(theta: Array) -> tuple[Array, Array, Array]:
        g, c, fl = theta[0], theta[1 : 1 + J], theta[1 + J]
        log_b = g + c
        f = fl if estimate_floor else fr.floor
        k = jnp.exp(jnp.mean(log_b[used]) - size0)
        k = 1.0 + (k - 1.0) * mv  # (T,): held frames stay
        u = X[:, 2] * sc_h + off_h + fr.floor
        Xm = X.at[:, c0].set(centre[h0] + k * (X[:, c0] - centre[h0]))
        Xm = Xm.at[:, c1].set(centre[h1] + k * (X[:, c1] - centre[h1]))
        u_new = centre[up] + k * (u - centre[up])
        Xm = Xm.at[:, 2].set((u_new - f - off_h) / sc_h)
        return Xm, jnp.exp(log_b), f

    def residuals(theta: Array, _args: Any) -> Array:
        Xm, b, f = moved(theta)
        P = body.positions(Xm, b, f)
        now = terms
        if has_contact:  # the feet's height moves with the floor
            floor_term = terms[1]
            height = floor_term.height - fr.floor + f
            now = (terms[0], eqx.tree_at(lambda c: c.height, floor_term, height))
        parts = [(t.residual(P) * w).reshape(-1) for t, w in zip(now, sws, strict=True)]
        g, c = theta[0], theta[1 : 1 + J]
        return jnp.concatenate([*parts, (g / scale_sd)[None], (c - log_centre) / bone_sd])

    theta0 = jnp.concatenate([jnp.zeros((1,), dt), log_b0, fr.floor[None]])
    sol = optx.least_squares(
        residuals,
        optx.LevenbergMarquardt(rtol=1e-6, atol=1e-8),
        theta0,
        max_steps=40,
        throw=False,
    )
    Xm, b, f = moved(sol.value)
    return eqx.tree_at(lambda q: (q.bone_scale, q.floor), fr, (b, f)), Xm


_bone_step_jit = eqx.filter_jit(_bone_step)


# --------------------------------------------------------------------------- driver
def _init_frames(body: Body, problem: TrackingProblem) -> tuple[np.ndarray, np.ndarray, float]:
    """The known initial window as two held frames of ``X`` (and the frame before them)."""
    fm = body.feature_map
    Yi = np.asarray(problem.init_window, dtype=np.float64)
    if Yi.shape != (2, fm.dim):
        raise ValueError(
            f"track: the problem's initial window has shape {Yi.shape}; a texture smoother "
            f"needs (2, {fm.dim}): make the problem with this texture"
        )
    up, h0, h1 = ground_axes(fm.skeleton.up_axis)
    act = np.asarray(fm.active)
    raw = Yi * np.asarray(fm.scale)[act] + np.asarray(fm.offset)[act]
    c0, c1, cy = body.root_cols
    p1 = np.asarray(problem.init_position, dtype=np.float64)
    psi1 = float(np.asarray(problem.init_heading))
    psi0 = psi1 - raw[1, cy]
    local = np.zeros(3)
    local[h0], local[h1] = raw[1, c0], raw[1, c1]
    e_up = np.zeros(3)
    e_up[up] = 1.0
    step = np.asarray(
        quat_rotate(yaw_quat(jnp.asarray(psi0), jnp.asarray(e_up)), jnp.asarray(local))
    )
    p0 = p1 - step
    X = np.asarray(body.coordinates(jnp.asarray(Yi), jnp.asarray(p0), jnp.asarray(psi0)))
    return X, p0, psi0


def _segmentation(
    texture: MotionTexture, tx: WhitenedTextons, Y: np.ndarray, T_pad: int, n: int
) -> FrameSegments:
    """The texture's segmentation of the first ``n`` frames, padded to ``T_pad`` frames (the
    padding continues the last segment); a clip the texture cannot segment takes its best
    single texton."""
    try:
        rows = texture.segment(np.asarray(Y[:n])).to_list()
    except ValueError:
        rows = []
    if not rows or sum(r[1] for r in rows) != n:
        i = int(_best_texton_jit(tx, as_array(Y), as_array(np.asarray(n, np.int32))))
        return _single(i, T_pad)
    lengths = [r[1] for r in rows]
    lengths[-1] += T_pad - n
    return frame_segments(np.array(lengths), np.array([r[2] for r in rows]))


def _smooth(opts: MapSmoother, texture: Any, problem: TrackingProblem) -> TrackResult:
    if not isinstance(texture, MotionTexture):
        raise TypeError(
            f"track: a MapSmoother takes a MotionTexture prior, got {type(texture).__name__}"
        )
    if texture.feature_map is None:
        raise ValueError("track: the texture was learned from arrays (no feature map)")
    fm = texture.feature_map
    T = problem.n_frames
    check_count(T, "track: frames to track", MAX_GENERATED_FRAMES)
    body = Body.of(fm, problem.joints)
    dt = jnp.asarray(texture.textons.mu).dtype
    fps = float(fm.fps)
    D = fm.dim
    tx = opts.prior.whitened(texture.textons, dt)
    sigma = float(opts.pixel_sigma or max(float(np.asarray(problem.pixel_noise)), 1.0))
    obs = np.asarray(problem.observations, dtype=np.float64)
    conf = np.asarray(problem.confidence, dtype=np.float64)
    known_floor = opts.floor == "known"
    # the rigid start on the clip padded to its bucket (confidence 0), so that a new length
    # in the same bucket compiles nothing (design §12.5)
    T_b = bucket_length(T, TRACK_FRAMES)
    X_start, floor = rigid_start(
        body,
        problem.camera,
        as_array(_pad_rows(obs, T_b).astype(dt)),
        as_array(np.concatenate([conf, np.zeros((T_b - T, conf.shape[1]))]).astype(dt)),
        sigma,
        opts.pixel_loss,
        fps=fps,
        n_headings=opts.n_headings,
        floor_known=known_floor,
        bone_scale=None if problem.bone_scale is None else jnp.asarray(problem.bone_scale, dt),
    )
    X_start = X_start[:T]
    n_init = 0
    prev = None
    if problem.has_init:
        X_init, p0, psi0 = _init_frames(body, problem)
        n_init = 2
        X_start = np.concatenate([X_init, X_start])
        prev = (jnp.asarray(p0, dt), jnp.asarray(psi0, dt))
    root_w = jnp.asarray(root_weights(D, body.root_cols, fps, opts.root_accel, opts.turn_accel), dt)
    run = _batch if opts.lag is None else _fixed_lag
    clip = _Clip(
        texture, body, tx, problem, X_start, n_init, prev, obs, conf, sigma, root_w, floor, dt
    )
    X, fr, labels = run(opts, clip)
    X = np.asarray(X)
    n_all = X.shape[0]
    Xb = as_array(_pad_rows(X, bucket_length(n_all, TRACK_FRAMES)).astype(dt))
    P, Y = (
        np.asarray(a)[n_init:n_all] for a in _outputs_jit(body, Xb, fr.bone_scale, fr.floor, prev)
    )
    up, h0, h1 = ground_axes(fm.skeleton.up_axis)
    c0, c1, cy = body.root_cols
    root = np.zeros((T, 3))
    root[:, h0], root[:, h1] = X[n_init:, c0], X[n_init:, c1]
    act = np.asarray(fm.active)
    root[:, up] = Y[:, 2] * np.asarray(fm.scale)[act[2]] + np.asarray(fm.offset)[act[2]]
    root[:, up] += float(fr.floor)
    motion = fm.decode(as_array(Y.astype(dt)), as_array(root[0].astype(dt)), float(X[n_init, cy]))
    motion = Motion(
        motion.skeleton,
        motion.fps,
        as_array(root.astype(dt)),
        motion.rotations,
        motion.local_positions,
    )
    errs: tuple[Any, ...] = (None, None, None)
    if problem.truth is not None:
        errs = joint_errors(P, np.asarray(problem.truth))
    bones = np.asarray(fr.bone_scale) if opts.bones or problem.bone_scale is not None else None
    put = lambda a: None if a is None else as_array(np.asarray(a).astype(dt))
    return TrackResult(
        prior="texture" if isinstance(opts.prior, TexturePrior) else "smooth",
        n_particles=0,
        mean_joints=as_array(P.astype(dt)),
        mean_pose=as_array(Y.astype(dt)),
        mean_root=as_array(root.astype(dt)),
        error=put(errs[0]),
        error_root_relative=put(errs[1]),
        error_aligned=put(errs[2]),
        labels=None if labels is None else as_array(np.asarray(labels, np.int32)),
        bone_scale=None if bones is None else put(bones),
        motion=motion,
    )


def _floor_term(texture: MotionTexture, body: Body, T_pad: int, dt) -> FloorContact | None:
    """The feet-on-the-floor term, where the texture has a contact model whose feet are in the
    solve's kept joints."""
    cm = texture.contacts
    if cm is None:
        return None
    feet = [body.order.index(f) for f in cm.feet if f in body.order]
    if not feet:
        return None
    return FloorContact(
        slots=tuple(feet),
        up=body.feature_map.skeleton.up_axis,
        height=jnp.asarray(cm.stance_height, dt),
        valid=jnp.zeros((T_pad,), dt),
    )


def _outputs(
    body: Body, X: Array, bone_scale: Array, floor: Array, prev: Any
) -> tuple[Array, Array]:
    """The observed joints and the observation vectors of an estimate (one bucket's shape)."""
    return body.observed(X, bone_scale, floor), body.observations(X, *(prev or (None, None)))


_outputs_jit = eqx.filter_jit(_outputs)


@dataclasses.dataclass(frozen=True)
class _Clip:
    """One clip's inputs of the batch and fixed-lag solves: the prior's texture and body, the
    problem, the rigid start ``X_start`` (the known initial frames first), the observations
    with their confidences, the pixel scale, root weights, floor and dtype."""

    texture: Any
    body: Body
    tx: Any
    problem: Any
    X_start: Any
    n_init: int
    prev: Any
    obs: Any
    conf: Any
    sigma: float
    root_w: Any
    floor: float
    dt: Any


def _frame_inputs(clip: _Clip, T_pad: int, fps: float, contact: Any = None) -> _Frame:
    """The solve's inputs of a clip padded to ``T_pad`` frames (confidence 0 in the padding and
    in the held initial frames)."""
    body, tx, problem, obs, conf = clip.body, clip.tx, clip.problem, clip.obs, clip.conf
    sigma, root_w, floor, dt, n_init = clip.sigma, clip.root_w, clip.floor, clip.dt, clip.n_init
    T = obs.shape[0]
    K = obs.shape[1]
    o = np.zeros((T_pad, K, 2))
    c = np.zeros((T_pad, K))
    o[n_init : n_init + T], c[n_init : n_init + T] = obs, conf
    J = body.feature_map.skeleton.n_joints
    given = (
        jnp.ones((J,), dt) if problem.bone_scale is None else jnp.asarray(problem.bone_scale, dt)
    )
    rep = Reprojection(
        camera=problem.camera,
        slots=body.slots,
        observations=jnp.asarray(o, dt),
        confidence=jnp.asarray(c, dt),
        sigma=jnp.asarray(sigma, dt),
    )
    return _Frame(
        body=body,
        tx=tx,
        reproj=rep,
        root_w=root_w,
        bone_scale=given,
        bone_centre=None if problem.bone_scale is None else jnp.log(given),
        floor=jnp.asarray(floor, dt),
        contact=contact,
        fps=fps,
    )


def _pad_rows(X: np.ndarray, T_pad: int) -> np.ndarray:
    return (
        np.concatenate([X, np.repeat(X[-1:], T_pad - X.shape[0], axis=0)]) if T_pad > len(X) else X
    )


def _batch(opts: Any, clip: _Clip) -> tuple[Any, _Frame, Any]:
    texture, body, tx, X_start, n_init = clip.texture, clip.body, clip.tx, clip.X_start, clip.n_init
    prev, sigma, dt = clip.prev, clip.sigma, clip.dt
    n = X_start.shape[0]
    T_pad = bucket_length(n, TRACK_FRAMES)
    fps = float(body.feature_map.fps)
    contact = _floor_term(texture, body, T_pad, dt) if opts.floor_contact else None
    fr = _frame_inputs(clip, T_pad, fps, contact)
    fr = eqx.tree_at(lambda f: f.reproj.pixel_loss, fr, opts.pixel_loss)
    X = as_array(_pad_rows(X_start, T_pad).astype(dt))
    held = as_array((np.arange(T_pad) < n_init) | (np.arange(T_pad) >= n))
    nv = as_array(np.asarray(n, np.int32))
    movable = ~held
    sd = jnp.asarray([opts.scale_sd, opts.bone_sd], dt)
    est_floor = opts.floor == "estimate"
    seg0 = _single(0, T_pad)
    textured = isinstance(opts.prior, TexturePrior) or opts.prior.segmented
    labels = None
    for r, s_r in enumerate(_sigmas(sigma, opts.anneal_from, 1 + opts.rounds)):
        fr = eqx.tree_at(lambda f: f.reproj.sigma, fr, jnp.asarray(s_r, dt))
        if r == 0 or not textured:
            # the first round: a smoothness prior (the texture's needs a segmentation)
            first = SmoothPrior() if isinstance(opts.prior, TexturePrior) else opts.prior
            X, _ = _solve_jit(fr, first, seg0, X, held, prev, nv, opts.max_steps)
        else:
            Y = np.asarray(_outputs_jit(body, X, fr.bone_scale, fr.floor, prev)[1])
            seg = _segmentation(texture, tx, Y, T_pad, n)
            X, _ = _solve_jit(fr, opts.prior, seg, X, held, prev, nv, opts.max_steps)
            labels = np.asarray(seg.labels)[n_init:n]
        if opts.bones:
            fr, X = _bone_step_jit(fr, X, movable, sd, est_floor)
        elif est_floor:
            fr, X = _floor_only(fr, X, movable)
    return np.asarray(X)[:n], fr, labels


def _sigmas(sigma: float, start: float, at_least: int) -> list[float]:
    """The pixel scales of the rounds: halved from ``max(start, σ)`` down to ``σ`` (a
    continuation: early rounds see a smoother cost), then ``σ`` until ``at_least`` rounds."""
    out = [max(float(start), sigma)]
    while out[-1] > sigma:
        out.append(max(out[-1] / 2.0, sigma))
    return out + [sigma] * max(0, at_least - len(out))


def _floor_only(fr: _Frame, X: Array, movable: Array) -> tuple[_Frame, Array]:
    """The floor alone re-estimated (bones fixed): the bone step with the bones' priors tight."""
    sd = jnp.asarray([1e-6, 1e-6], X.dtype)
    return _bone_step_jit(fr, X, movable, sd, True)


def _lag_run(
    fr: _Frame,
    X_all: Array,
    obs: Array,
    conf: Array,
    t0: int,
    n: Array,
    lag: int,
    max_steps: int,
    prior: MotionPrior,
) -> Array:
    """Frames ``t0 … n − 1`` one at a time (module notes): a ``fori_loop`` over new frames, each
    a banded solve of the window of ``lag + 3`` frames ending at the new one."""
    W = lag + 3
    dt = X_all.dtype
    body = fr.body
    c0, c1, cy = body.root_cols
    _up, h0, h1 = ground_axes(body.feature_map.skeleton.up_axis)
    held = jnp.arange(W) < 2
    root = jnp.zeros(X_all.shape[1], dt).at[jnp.array([c0, c1, cy])].set(1.0)

    def step(t: Array, X_all: Array) -> Array:
        s = t - lag - 2  # the window's first (held) row
        velocity = X_all[t - 1] - X_all[t - 2]
        new = X_all[t - 1] + velocity * (root + 0.5 * (1.0 - root))
        X_all = X_all.at[t].set(new)
        Xw = jax.lax.dynamic_slice_in_dim(X_all, s, W)
        ow = jax.lax.dynamic_slice_in_dim(obs, s, W)
        cw = jax.lax.dynamic_slice_in_dim(conf, s, W) * (~held)[:, None]
        before = X_all[jnp.maximum(s - 1, 0)]
        p_prev = jnp.zeros(3, dt).at[h0].set(before[c0]).at[h1].set(before[c1])
        prev = (p_prev, before[cy])
        rep = eqx.tree_at(lambda r: (r.observations, r.confidence), fr.reproj, (ow, cw))
        frw = eqx.tree_at(lambda f: f.reproj, fr, rep)
        nv = jnp.asarray(W)
        Y = body.observations(Xw, *prev)
        seg = _single(0, W)
        i = _best_texton(fr.tx, Y, nv)
        seg = FrameSegments(seg.labels * 0 + i, seg.dyn_labels * 0 + i, seg.position)
        Xs, _ = _solve(frw, prior, seg, Xw, held, prev, nv, max_steps)
        return jax.lax.dynamic_update_slice_in_dim(X_all, Xs, s, axis=0)

    return jax.lax.fori_loop(t0, n, step, X_all)


_lag_run_jit = eqx.filter_jit(_lag_run)


def _fixed_lag(opts: Any, clip: _Clip) -> tuple[Any, Any, None]:
    texture, body, X_start, n_init, dt = clip.texture, clip.body, clip.X_start, clip.n_init, clip.dt
    obs, conf = clip.obs, clip.conf
    L = int(opts.lag)
    n = X_start.shape[0]
    fps = float(body.feature_map.fps)
    X0 = np.asarray(X_start)
    t0 = n_init
    fr_first = None
    if n_init < 2 or opts.bones:
        # no known state, or the bones to estimate: the first frames (L + 2, or bone_window
        # seconds with bones) in one batch solve, after the known initial window, held
        t0 = min(n, n_init + max(L + 2, round(opts.bone_window * fps) if opts.bones else 0))
        first = dataclasses.replace(opts, lag=None)
        head = dataclasses.replace(
            clip, X_start=X0[:t0], obs=obs[: t0 - n_init], conf=conf[: t0 - n_init]
        )
        Xb, fr_first, _ = _batch(first, head)
        X0 = np.concatenate([np.asarray(Xb), X0[t0:]])
        clip = dataclasses.replace(clip, floor=float(fr_first.floor))
    if t0 >= n:
        return X0, fr_first, None
    T_pad = bucket_length(n, TRACK_FRAMES)
    W = L + 3
    contact = _floor_term(texture, body, W, dt) if opts.floor_contact else None
    fr = _frame_inputs(clip, T_pad, fps, contact)
    fr = eqx.tree_at(lambda f: f.reproj.pixel_loss, fr, opts.pixel_loss)
    if fr_first is not None:
        fr = eqx.tree_at(lambda f: f.bone_scale, fr, fr_first.bone_scale)
    # rows before the window's start are never read before they are written; pad the front so
    # that every window of lag + 3 frames fits
    front = max(0, L + 2 - t0)
    Xp = np.concatenate([np.repeat(X0[:1], front, axis=0), X0, np.repeat(X0[-1:], T_pad - n, 0)])
    op = np.concatenate(
        [np.zeros((front, *fr.reproj.observations.shape[1:])), np.asarray(fr.reproj.observations)]
    )
    cp = np.concatenate(
        [np.zeros((front, fr.reproj.confidence.shape[1])), np.asarray(fr.reproj.confidence)]
    )
    X = _lag_run_jit(
        fr,
        jnp.asarray(Xp, dt),
        jnp.asarray(op, dt),
        jnp.asarray(cp, dt),
        t0 + front,
        jnp.asarray(n + front),
        L,
        opts.lag_steps,
        opts.prior,
    )
    return np.asarray(X)[front : front + n], fr, None
