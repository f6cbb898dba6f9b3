"""Editing as optimisation: the residual form and its solution with optimistix.

Variables: the displacement ``Z (T, D)`` of the observation vectors, ``Y = Y₀ + Z`` (frames
held by a pose constraint take the given pose instead, exactly). The objective is

.. code-block:: text

    ½ ‖w_prior (r(Y) − r(Y₀))‖² + ½ ‖w_anchor (P(Y) − P(Y₀))‖² + ½ Σ_c ‖w_c c(P(Y))‖²

with ``r`` the texture prior's whitened residuals (:func:`prior_residuals`: texton dynamics,
initial pairs, the part outside each texton's subspace), ``P(Y)`` the world joint positions
(decode + forward kinematics, both differentiable) and ``c`` the constraint residuals
(:mod:`._constraints`). Because the prior is affine in ``Y``,
``½‖r(Y)‖² = ½‖r(Y₀) + J_r Z‖²``: subtracting ``r(Y₀)`` (``relative=True``, the default) keeps
the prior's curvature (how unlikely a *change* is under the textons' dynamics) but makes an
unconstrained motion a fixed point, so an edit changes the motion near the edit only and never
"smooths" the rest towards the textons' mean dynamics; ``relative=False`` is the plain negative
log-likelihood of ``Y`` (its minimiser moves every frame towards the textons' most likely
motion).

The solver is Levenberg–Marquardt on the residual form (optimistix), matrix-free: the damped
normal equations ``(JᵀJ + λI) δ = −Jᵀr`` are solved by conjugate gradients with
Jacobian-vector products, so nothing of size ``(T·D)²`` is formed. Position targets are met by
a few rounds of the method of multipliers (the penalty's target is shifted by the remaining
error between rounds). If Levenberg–Marquardt does not converge, BFGS is run on ``½‖res‖²`` from
where it stopped. Convergence is reported, never assumed.
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ..motion import FeatureMap, Skeleton, ground_axes, quat_rotate, sub_skeleton
from ._constraints import Constraints, EditWeights
from ._fk import fk_positions
from ._prior import (
    FrameSegments,
    WhitenedTextons,
    prior_hessian,
    prior_residuals,
    smoothness_hessian,
)
from ._whiten import Whitening, band_quad, whitening_each

__all__ = ["EditResult", "bfgs_polish", "problem", "solve_edit"]

TOLERANCE = 1e-3  # metres: a position target or a plant/floor within this is met


class EditResult(eqx.Module):
    """What an edit did, measured.

    Attributes:
        Y: ``(T, D)`` edited observation vectors (the original ones if the solve produced
            non-finite values; then ``finite`` is false).
        converged: whether the solver's own termination test succeeded (Levenberg–Marquardt,
            or BFGS after it).
        steps: solver steps taken in all rounds.
        cost: final ``½‖residuals‖²``.
        prior_cost: ``½‖w_prior (r(Y) − r(Y₀))‖²`` (``½‖r(Y)‖²`` when not relative).
        position_error: ``(P,)`` distance of each position target's joint from the target,
            metres (0 for padding slots).
        velocity_error: ``(V,)`` norm of each velocity target's error, m/s.
        plant_slide: largest horizontal speed (m/s) of a planted foot over its planted steps.
        plant_height_error: largest ``|h − plant height|`` over planted steps, metres.
        floor_depth: largest depth of any joint below the floor, metres (0 without a floor).
        u: ``(T, D)`` the solver's variables at the solution (Levenberg–Marquardt: whitened;
            Gauss–Newton: the displacement of ``Y``, with the root offset when it moved).
        start_position: ``(3,)`` root position of frame 0 for decoding ``Y`` (changed only
            when the solve moved the root trajectory).
        finite: whether the solution was finite.
        used_bfgs: whether the BFGS fallback ran.
    """

    Y: Float[Array, "T D"]
    u: Float[Array, "T D"]
    start_position: Float[Array, " 3"]
    converged: Bool[Array, ""]
    steps: Int[Array, ""]
    cost: Float[Array, ""]
    prior_cost: Float[Array, ""]
    position_error: Float[Array, " P"]
    velocity_error: Float[Array, " V"]
    plant_slide: Float[Array, ""]
    plant_height_error: Float[Array, ""]
    floor_depth: Float[Array, ""]
    finite: Bool[Array, ""]
    used_bfgs: Bool[Array, ""]

    def __check_init__(self) -> None:
        if np.ndim(self.Y) < 2:
            raise ValueError("EditResult.Y must have shape (T, D)")

    @property
    def miss(self) -> float:
        """The largest miss, metres: of a position target, a planted foot's height or the
        floor (infinite if the solution was not finite)."""
        if not bool(self.finite):
            return math.inf
        errs = [float(np.max(np.asarray(self.position_error), initial=0.0))]
        errs += [float(self.plant_height_error), float(self.floor_depth)]
        return max(errs)

    def met_within(self, tolerance: float = TOLERANCE) -> bool:
        """Whether every position target, plant and the floor hold to ``tolerance`` metres."""
        return self.miss <= tolerance

    @property
    def met(self) -> bool:
        """Whether every position target, plant and the floor hold to 1 mm (one motion)."""
        return self.met_within(TOLERANCE)

    def report(self, tolerance: float = TOLERANCE) -> str:
        """One paragraph for people: converged or not, every constraint's error, and one
        verdict: met or not within ``tolerance`` metres (default 1 mm)."""
        pe = np.asarray(self.position_error)
        lines = [
            f"solver {'converged' if bool(self.converged) else 'did NOT converge'} in "
            f"{int(self.steps)} steps{' (after the BFGS fallback)' if bool(self.used_bfgs) else ''}"
            f"; final cost {float(self.cost):.4g}, prior cost {float(self.prior_cost):.4g}",
        ]
        if not bool(self.finite):
            lines.append("the solution was not finite: the original motion is returned")
        if pe.size:
            lines.append(
                "position targets: error " + ", ".join(f"{1e3 * e:.2f} mm" for e in pe.tolist())
            )
        lines.append(
            f"plants: slide {float(self.plant_slide):.3g} m/s, height error "
            f"{1e3 * float(self.plant_height_error):.2f} mm; floor depth "
            f"{1e3 * float(self.floor_depth):.2f} mm"
        )
        miss = "not finite" if not bool(self.finite) else _mm(self.miss)
        verdict = f"largest miss {miss} (tolerance {_mm(tolerance)})"
        lines.append(
            f"all constraints met: {verdict}"
            if self.met_within(tolerance)
            else f"NOT all constraints met: {verdict}; the request may be infeasible"
        )
        return "\n".join(lines)


def _mm(metres: float) -> str:
    """A distance in millimetres, two decimals, or two significant digits below 0.01 mm."""
    mm = 1e3 * float(metres)
    return f"{mm:.2f} mm" if mm == 0 or abs(mm) >= 0.01 else f"{mm:.2g} mm"


def run_means(values: Array, plant: Array) -> Array:
    """Per column, the mean of ``values`` over each run of consecutive ``plant`` rows."""

    def one(v: Array, p: Array) -> Array:
        first = p & ~jnp.concatenate([jnp.zeros((1,), bool), p[:-1]])
        rid = jnp.cumsum(first) * p
        n = p.shape[0] + 1
        s = jax.ops.segment_sum(jnp.where(p, v, 0.0), rid, n)
        c = jax.ops.segment_sum(p.astype(v.dtype), rid, n)
        return (s / jnp.maximum(c, 1.0))[rid]

    return jax.vmap(one, in_axes=(1, 1), out_axes=1)(values, plant)


class _Problem(eqx.Module):
    fm: FeatureMap
    tx: WhitenedTextons
    seg: FrameSegments
    wh: Whitening | None  # None for the banded Gauss–Newton solver, which does not whiten
    Y0: Array
    r0: tuple[Array, Array, Array] | None  # None: the prior cost is measured on bands
    sp: Array
    sh: Array
    cons: Constraints
    plant_h: Array
    root0: Array
    w: EditWeights
    n_valid: Array  # the motion's own frames (the rest pad it to a shape bucket)
    sub: Skeleton = eqx.field(static=True)
    keep: tuple[int, ...] = eqx.field(static=True)

    def edited(self, u: Array) -> Array:
        if self.wh is None:
            raise ValueError("this edit problem was built without its whitening")
        Y = self.Y0 + self.wh.displacement(u)
        return jnp.where(self.cons.pose_mask[:, None], self.cons.poses, Y)  # held: exact

    def positions(self, Y: Array) -> Array:
        """World positions ``(T, J, 3)`` of every skeleton joint; joints outside ``keep`` (those
        no constraint or floor can see, e.g. fingers) are not computed and read as the root."""
        return self.kinematics(Y)[0]

    def kinematics(self, Y: Array) -> tuple[Array, Array]:
        """Joint positions ``(T, J, 3)`` and the root frame ``(T, 2, 3)`` (its position and a
        point 1 m along its first horizontal axis)."""
        m = self.fm.decode(Y, self.sp, self.sh)
        k = list(self.keep)
        lp = None if m.local_positions is None else m.local_positions[:, k]
        P = fk_positions(self.sub, m.root_positions, m.rotations[:, k], lp)
        idx = np.zeros(self.fm.skeleton.n_joints, np.int64)
        idx[k] = np.arange(len(k))
        _, h0, _ = ground_axes(self.fm.skeleton.up_axis)
        e = jnp.zeros((3,), Y.dtype).at[h0].set(1.0)
        ahead = quat_rotate(m.rotations[:, 0], jnp.broadcast_to(e, m.root_positions.shape))
        return P[:, idx], jnp.stack([m.root_positions, m.root_positions + ahead], axis=1)

    def residuals(self, u: Array, shift: Array) -> tuple[Array, ...]:
        c, w = self.cons, self.w
        P = self.positions(self.edited(u))
        up, h0, h1 = ground_axes(self.fm.skeleton.up_axis)
        pos = P[c.frames, c.joints] - c.targets - shift
        pos = w.position * jnp.where(c.active[:, None], pos, 0.0)
        vel = (P[c.vel_frames + 1, c.vel_joints] - P[c.vel_frames, c.vel_joints]) * self.fm.fps
        vel = w.velocity * jnp.where(c.vel_active[:, None], vel - c.vel_targets, 0.0)
        F = P[:, list(c.feet)]  # (T, F, 3)
        step = (F[1:] - F[:-1])[..., jnp.array([h0, h1])]
        slide = w.plant * jnp.where(c.plant[..., None], step, 0.0)
        hgt = jnp.stack([F[:-1, :, up] - self.plant_h, F[1:, :, up] - self.plant_h], axis=-1)
        hgt = w.plant * jnp.where(c.plant[..., None], hgt, 0.0)
        depth = jnp.maximum(c.floor - P[:, list(self.keep), up], 0.0)
        depth = w.floor * jnp.where(c.floor_on, depth, 0.0)
        lift = w.floor * jnp.maximum(c.lift - F[..., up], 0.0)  # −inf where free: 0
        # u is the whitened prior + anchor residual: ½‖u‖² is their cost up to a constant
        return (u, pos, vel, slide, hgt, depth, lift)


def _sq(tree: Any) -> Array:
    return 0.5 * jnp.sum(jnp.stack([jnp.sum(a * a) for a in jax.tree.leaves(tree)]))


def _measure(prob: _Problem, Y: Array, prior_cost: Array | None = None) -> dict[str, Array]:
    c = prob.cons
    P = prob.positions(Y)
    up, h0, h1 = ground_axes(prob.fm.skeleton.up_axis)
    pe = jnp.linalg.norm(P[c.frames, c.joints] - c.targets, axis=-1)
    ve = (P[c.vel_frames + 1, c.vel_joints] - P[c.vel_frames, c.vel_joints]) * prob.fm.fps
    ve = jnp.linalg.norm(ve - c.vel_targets, axis=-1)
    F = P[:, list(c.feet)]
    speed = jnp.linalg.norm((F[1:] - F[:-1])[..., jnp.array([h0, h1])], axis=-1) * prob.fm.fps
    herr = jnp.maximum(jnp.abs(F[:-1, :, up] - prob.plant_h), jnp.abs(F[1:, :, up] - prob.plant_h))
    own = (jnp.arange(P.shape[0]) < prob.n_valid)[:, None]
    depth = jnp.max(jnp.where(own, jnp.maximum(c.floor - P[:, list(prob.keep), up], 0.0), 0.0))
    depth = jnp.where(c.floor_on, depth, 0.0)
    if prior_cost is None:
        if prob.r0 is None:
            raise ValueError("this edit problem was built without its prior residuals")
        pri = prior_residuals(prob.tx, prob.seg, Y, prob.n_valid)
        d = tuple(prob.w.prior * (a - b) for a, b in zip(pri, prob.r0, strict=True))
        prior_cost = _sq(d)
    return dict(
        position_error=jnp.where(c.active, pe, 0.0),
        velocity_error=jnp.where(c.vel_active, ve, 0.0),
        plant_slide=jnp.max(jnp.where(c.plant, speed, 0.0), initial=0.0),
        plant_height_error=jnp.max(jnp.where(c.plant, herr, 0.0), initial=0.0),
        floor_depth=depth,
        prior_cost=prior_cost,
    )


def problem(
    fm,
    tx,
    seg,
    Y0,
    sp,
    sh,
    cons,
    w,
    relative: bool,
    keep,
    n_valid: Any = None,
    whiten: bool = True,
    residuals: bool = True,
) -> _Problem:
    """The residual form of one edit (whitening factored, plant heights resolved).

    ``n_valid``: the motion's own frames when ``Y0`` is padded to a shape bucket (the padding
    frames must be held by ``cons.pose_mask``; their prior and floor terms are left out).
    ``whiten=False``: no whitening (the banded Gauss–Newton solver has its own normal
    equations; leaving it out keeps a block Cholesky out of its program).
    ``residuals=False`` (relative problems only): the prior's residuals at ``Y0`` are not
    computed; the caller measures the prior cost on the prior's bands
    (:func:`finish_banded`), which needs no per-frame gather of the textons' matrices.
    """
    dtype = Y0.dtype
    T, D = Y0.shape
    n_valid = jnp.asarray(T if n_valid is None else n_valid, jnp.int32)
    sub, keep = sub_skeleton(fm.skeleton, keep)
    w = jax.tree.map(lambda a: jnp.asarray(a, dtype), w)
    if not residuals:
        if not relative:
            raise ValueError("an absolute edit problem needs the prior residuals")
        r0, linear = None, jnp.zeros_like(Y0)
    elif relative:
        r0 = prior_residuals(tx, seg, Y0, n_valid)
        linear = jnp.zeros_like(Y0)
    else:
        r0, pull = jax.vjp(lambda y: prior_residuals(tx, seg, y, n_valid), Y0)
        (linear,) = pull(r0)
        linear = (w.prior**2) * linear
        r0 = (jnp.zeros_like(r0[0]), jnp.zeros_like(r0[1]), jnp.zeros_like(r0[2]))
    wh = None
    if whiten:
        bands = tuple(
            (w.prior**2) * a + (w.smooth**2) * b
            for a, b in zip(
                prior_hessian(tx, seg, dtype, n_valid),
                smoothness_hessian(T, D, dtype, n_valid),
                strict=True,
            )
        )
        held = cons.pose_mask
        delta = jnp.where(held[:, None], cons.poses.astype(dtype) - Y0, 0.0)
        is_root = np.array([n.startswith("root.d") for n in fm.active_names])  # dh0, dh1, dyaw
        anchor = jnp.where(jnp.asarray(is_root), jnp.hypot(w.anchor, w.root), w.anchor)
        wh = whitening_each(bands, anchor, held, delta, linear)
    zero = jnp.zeros((), dtype)
    prob = _Problem(fm, tx, seg, wh, Y0, r0, sp, sh, cons, zero, zero, w, n_valid, sub, keep)
    P0, root0 = prob.kinematics(Y0)
    h_orig = P0[:-1, list(cons.feet), fm.skeleton.up_axis]
    mean_h = run_means(h_orig, cons.plant)
    plant_h = jnp.where(jnp.isnan(cons.plant_height), mean_h, cons.plant_height).astype(dtype)
    return eqx.tree_at(lambda p: (p.plant_h, p.root0), prob, (plant_h, root0))


def _lm(rtol: float, atol: float, cg_steps: int, cg_rtol: float, dtype) -> Any:
    cg = lx.Normal(lx.CG(rtol=cg_rtol, atol=1e-9, max_steps=cg_steps))
    if jnp.dtype(dtype) != jnp.dtype(jnp.result_type(float)):
        # optimistix 0.1.0 keeps Levenberg–Marquardt's damping in the default float dtype, so
        # float32 variables with x64 enabled fail its structure check; Gauss–Newton (no
        # damping; in the whitened variables JᵀJ ⪰ I, so its steps are well posed) instead
        return optx.GaussNewton(rtol=rtol, atol=atol, linear_solver=cg)
    return optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=cg)


def solve_edit(
    fm: FeatureMap,
    tx: WhitenedTextons,
    seg: FrameSegments,
    Y0: Float[Array, "T D"],
    start_position: Float[Array, " 3"],
    start_heading: Float[Array, ""],
    cons: Constraints,
    weights: EditWeights,
    *,
    keep: tuple[int, ...] = (),
    relative: bool = True,
    rounds: int = 3,
    max_steps: int = 60,
    cg_steps: int = 100,
    cg_rtol: float = 1e-6,
    rtol: float = 1e-6,
    atol: float = 1e-6,
) -> EditResult:
    """The jit-compatible core of :func:`~mtex_jax.edit.edit` (one motion; ``vmap`` it for a
    batch). No BFGS fallback here (see :func:`~mtex_jax.edit.edit`).

    Args:
        fm: the texture's feature map.
        tx: whitened textons.
        seg: per-frame segmentation of ``Y0``.
        Y0: ``(T, D)`` the motion to edit.
        start_position: ``(3,)`` root position of frame 0; start_heading: its yaw.
        cons: the constraints; weights: the objective's weights.
        keep: joints whose world positions are computed (their ancestors too); the floor
            applies to them. Constraint joints and feet must be among them.
        relative: the prior on the change (default) or the plain negative log-likelihood.
        rounds: multiplier rounds for the position targets (``≥ 1``).
        max_steps: Levenberg–Marquardt steps per round.
        cg_steps: conjugate-gradient steps per linear solve (a solve that needs more fails
            the step: Levenberg–Marquardt then reports no convergence).
        cg_rtol: relative tolerance of the conjugate-gradient solves.
        rtol: Levenberg–Marquardt termination tolerance on the step.
        atol: Levenberg–Marquardt termination tolerance on the cost.

    Returns:
        :class:`EditResult` (``converged`` refers to the last round).
    """
    prob = problem(fm, tx, seg, Y0, start_position, start_heading, cons, weights, relative, keep)
    solver = _lm(rtol, atol, cg_steps, cg_rtol, Y0.dtype)

    def fn(z: Array, shift: Array) -> tuple[Array, ...]:
        return prob.residuals(z, shift)

    def one_round(carry, _):
        z, shift, _ok, steps = carry
        sol = optx.least_squares(fn, solver, z, args=shift, max_steps=max_steps, throw=False)
        z_new = sol.value
        P = prob.positions(prob.edited(z_new))
        err = P[cons.frames, cons.joints] - cons.targets
        shift = shift - jnp.where(cons.active[:, None], err, 0.0)
        ok = sol.result == optx.RESULTS.successful
        return (z_new, shift, ok, steps + sol.stats["num_steps"]), None

    z0 = jnp.zeros_like(Y0)
    shift0 = jnp.zeros_like(cons.targets)
    init = (z0, shift0, jnp.asarray(False), jnp.asarray(0, jnp.int32))
    (z, shift, ok, steps), _ = jax.lax.scan(one_round, init, None, length=rounds)
    return finish(prob, z, shift, ok, steps, jnp.asarray(False))


def finish(prob: _Problem, z, shift, ok, steps, used_bfgs) -> EditResult:
    """Undo the last multiplier update (it belongs to a round not run) and measure."""
    c = prob.cons
    P = prob.positions(prob.edited(z))
    err = P[c.frames, c.joints] - c.targets
    shift = shift + jnp.where(c.active[:, None], err, 0.0)
    finite = jnp.all(jnp.isfinite(z))
    z = jnp.where(finite, z, 0.0)
    cost = _sq(prob.residuals(z, shift))
    m = _measure(prob, prob.edited(z))
    return EditResult(
        start_position=prob.sp,
        Y=jnp.where(finite, prob.edited(z), prob.Y0),
        u=z,
        converged=jnp.asarray(ok) & finite,
        steps=jnp.asarray(steps, jnp.int32),
        cost=cost,
        used_bfgs=used_bfgs,
        finite=finite,
        **m,
    )


def finish_banded(
    prob: _Problem,
    Y: Array,
    z: Array,
    ok: Array,
    steps: Array,
    cost: Array,
    prior_bands: tuple[Array, Array, Array] | None = None,
) -> EditResult:
    """Measure a banded Gauss–Newton solution ``Y`` (``z``: the solver's variables; the start
    position is ``prob.sp``).

    ``prior_bands``: the prior's Hessian bands (:func:`prior_hessian`); the prior residuals
    are affine in ``Y``, so the prior cost ``½‖w (r(Y) − r(Y₀))‖²`` is the quadratic form
    ``½ w² uᵀ (RᵀR) u`` of the change ``u = Y − Y₀``. ``None``: from the residuals."""
    finite = jnp.all(jnp.isfinite(Y)) & jnp.all(jnp.isfinite(z))
    Y = jnp.where(finite, Y, prob.Y0)
    prior_cost = None
    if prior_bands is not None:
        prior_cost = 0.5 * prob.w.prior**2 * band_quad(prior_bands, Y - prob.Y0)
    return EditResult(
        start_position=jnp.where(finite, prob.sp, jnp.zeros_like(prob.sp)),
        Y=Y,
        u=jnp.where(finite, z, 0.0),
        converged=jnp.asarray(ok) & finite,
        steps=jnp.asarray(steps, jnp.int32),
        cost=jnp.where(finite, cost, jnp.inf),
        used_bfgs=jnp.asarray(False),
        finite=finite,
        **_measure(prob, Y, prior_cost),
    )


def bfgs_polish(
    fm: FeatureMap,
    tx: WhitenedTextons,
    seg: FrameSegments,
    Y0: Array,
    start_position: Array,
    start_heading: Array,
    cons: Constraints,
    weights: EditWeights,
    previous: EditResult,
    *,
    keep: tuple[int, ...] = (),
    relative: bool = True,
    max_steps: int = 500,
    rtol: float = 1e-6,
    atol: float = 1e-6,
) -> EditResult:
    """The BFGS fallback: minimise ``½‖res‖²`` from an unconverged result (plain targets).

    Limited-memory BFGS (optimistix ``LBFGS``): a dense BFGS inverse Hessian of ``T·D``
    variables would take ``(T·D)²`` numbers (8 GB for 10 s at 60 Hz).
    """
    prob = problem(fm, tx, seg, Y0, start_position, start_heading, cons, weights, relative, keep)
    z0 = previous.u
    shift = jnp.zeros_like(cons.targets)

    def f(z: Array, _args: Any) -> Array:
        return _sq(prob.residuals(z, shift))

    solver = optx.LBFGS(rtol=rtol, atol=atol)
    sol = optx.minimise(f, solver, z0, max_steps=max_steps, throw=False)
    ok = sol.result == optx.RESULTS.successful
    steps = previous.steps + sol.stats["num_steps"]
    return finish(prob, sol.value, shift, ok, steps, jnp.asarray(True))
