"""Edits solved by banded Gauss–Newton (:mod:`._banded`): the default solver of
:func:`~mtex_jax.edit.edit`, :func:`~mtex_jax.edit.edit_many` and :func:`~mtex_jax.edit.clean`.

The objective is the one of :mod:`._solve` (relative texture prior, anchor, smoothness,
constraint penalties) with two changes that make every constraint residual local to a frame:

* the root's integrated channels (``root.d*``: heading-frame displacement and yaw change) are
  held exactly (the Levenberg–Marquardt solver prices them with ``EditWeights.root``, ``10⁴``
  by default, so they barely move there either);
* a planted foot is held at one horizontal position per contact run (the mean of the original
  positions over the run) and at the plant height, an absolute target per frame, instead of a
  zero horizontal step between frames.

Velocity targets couple two frames; edits with velocity targets use Levenberg–Marquardt.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..motion import FeatureMap, ground_axes, quat_conj, quat_rotate, yaw_quat
from ._banded.solve import BandedGaussNewton, BandedProblem, solve_banded
from ._banded.terms import HeightBounds, PointTargets, RootOffset
from ._constraints import Constraints, EditWeights
from ._jacobians import channel_colouring, kept_positions, root_free_channels
from ._prior import FrameSegments, WhitenedTextons, prior_hessian, smoothness_hessian
from ._solve import EditResult, finish_banded, problem, run_means

__all__ = ["join_points", "solve_edit_gn"]


def join_points(a: PointTargets, b: PointTargets) -> PointTargets:
    """Both sets of point targets as one: the sparse targets of both first, then the
    frame-major ones of both, merged frame by frame (both must cover the same frames)."""
    sa, sb = a.sparse_count, b.sparse_count
    fields = lambda p: (p.slot, p.frame, p.target, p.weight, p.exact)
    sparse = [jnp.concatenate([x[:sa], y[:sb]]) for x, y in zip(fields(a), fields(b), strict=True)]
    dense = [(p, p.per_frame) for p in (a, b) if p.per_frame]
    if not dense:
        slot, frame, target, weight, exact = sparse
        return PointTargets(slot=slot, frame=frame, target=target, weight=weight, exact=exact)
    T = {(int(jnp.shape(p.frame)[0]) - p.sparse_count) // F for p, F in dense}
    if len(T) != 1:
        raise ValueError("join_points: the frame-major targets cover different frames")
    (n,) = T
    per = lambda p, F, x: x[p.sparse_count :].reshape(n, F, *x.shape[1:])
    parts = [jnp.concatenate([per(p, F, fields(p)[i]) for p, F in dense], axis=1) for i in range(5)]
    parts = [x.reshape(-1, *x.shape[2:]) for x in parts]
    F = sum(F for _, F in dense)
    slot, frame, target, weight, exact = (
        jnp.concatenate([s_, d]) for s_, d in zip(sparse, parts, strict=True)
    )
    return PointTargets(
        slot=slot,
        frame=frame,
        target=target,
        weight=weight,
        exact=exact,
        n_sparse=int(sparse[0].shape[0]),
        per_frame=F,
    )


def _slots(J: int, keep: tuple[int, ...]) -> np.ndarray:
    s = np.zeros(J, np.int32)
    s[list(keep)] = np.arange(len(keep), dtype=np.int32)
    return s


def constraint_points(
    fm: FeatureMap, cons: Constraints, keep: tuple[int, ...], P0: Array, plant_h: Array, w
) -> tuple[PointTargets, Array]:
    """Point targets (position targets, planted feet) and the ``(T, K)`` lower heights (floor,
    lift) of the constraints; ``P0`` ``(T, K, 3)`` are the original kept positions."""
    dt = P0.dtype
    T, K = P0.shape[:2]
    up, h0, h1 = ground_axes(fm.skeleton.up_axis)
    slot_of = jnp.asarray(_slots(fm.skeleton.n_joints, keep))
    one = jnp.ones((cons.joints.shape[0], 3), dt)
    pos = PointTargets(
        slot=slot_of[cons.joints],
        frame=cons.frames,
        target=cons.targets,
        weight=w.position * one * cons.active[:, None],
        exact=cons.active,
    )
    feet = list(cons.feet)
    fslot = _slots(fm.skeleton.n_joints, keep)[feet] if feet else np.zeros(0, np.int32)
    F = len(feet)
    if F:
        pl = cons.plant
        on = jnp.concatenate([pl, jnp.zeros((1, F), bool)]) | jnp.concatenate(
            [jnp.zeros((1, F), bool), pl]
        )  # (T, F) frames touched by a planted step
        Pf = P0[:, fslot]  # (T, F, 3)
        anchor = jnp.stack([run_means(Pf[..., c], on) for c in range(3)], axis=-1)
        ph = jnp.concatenate([plant_h, plant_h[-1:]])
        ph = jnp.where(jnp.concatenate([pl, jnp.zeros((1, F), bool)]), ph, jnp.roll(ph, 1, 0))
        tgt = anchor.at[..., up].set(ph)
        wvec = jnp.zeros(3, dt).at[jnp.array([h0, h1, up])].set(1.0) * w.plant
        frames = jnp.repeat(jnp.arange(T, dtype=jnp.int32), F)
        plants = PointTargets(
            slot=jnp.tile(jnp.asarray(fslot, jnp.int32), T),
            frame=frames,
            target=tgt.reshape(T * F, 3),
            weight=(on[..., None] * wvec).reshape(T * F, 3),
            exact=on.reshape(T * F),
            n_sparse=0,
            per_frame=F,
        )
        pos = join_points(pos, plants)
    lower = jnp.where(cons.floor_on, cons.floor, -jnp.inf) * jnp.ones((T, K), dt)
    if F:
        lower = lower.at[:, fslot].max(cons.lift.astype(dt))
    return pos, lower


def solve_edit_gn(
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
    extra: PointTargets | None = None,
    n_valid: Any = None,
    move_root: bool = False,
    root_smooth: float = 10.0,
    rounds: int = 3,
    max_steps: int = 8,
    rtol: float = 1e-6,
    early_rtol: float | None = None,
    exact_lower: bool = False,
    exact_points: bool = True,
    lower_tol: float = 0.0,
    xtol: float = 1e-4,
    chord: bool = True,
) -> EditResult:
    """The jit-compatible banded Gauss–Newton core (one motion; ``vmap`` it for a batch).

    Args:
        fm, tx, seg, Y0, start_position, start_heading, cons, weights: as for
            :func:`~mtex_jax.edit.solve_edit` (velocity targets are not supported here).
        keep: joints whose world positions are computed (with their ancestors).
        extra: further point targets (their ``slot`` indexes the kept joints in order), e.g.
            the guidance of swing feet when cleaning.
        n_valid: the motion's own frames when it is padded to a shape bucket
            (:func:`~mtex_jax.edit._bucket.solve_gn_bucketed`: the padding frames are held by
            ``cons.pose_mask``, and have no prior, smoothness or floor terms); ``None``: all.
        move_root: let the root's horizontal trajectory change too, as a smooth world offset
            per frame (:class:`~mtex_jax.edit.RootOffset`); the root channels and the
            start position of the result are re-derived from it (``result.start_position``).
        root_smooth: per metre of the offset's second difference (with ``move_root``).
        rounds: multiplier rounds; max_steps: Gauss–Newton steps per round.
        rtol, early_rtol, xtol: stopping tests of :class:`~mtex_jax.edit.BandedGaussNewton`
            (``xtol`` is its ``atol``).
        exact_lower, exact_points, lower_tol: which constraints the multiplier rounds meet
            exactly (the floor and lift bounds; the exact point targets), and the tolerance of
            the floor that ends the rounds (:class:`~mtex_jax.edit.HeightBounds`,
            :class:`~mtex_jax.edit.PointTargets`).
        chord: reuse factorisations between steps
            (:class:`~mtex_jax.edit.BandedGaussNewton`).

    Returns:
        :class:`EditResult` (``u`` holds the displacement ``Y − Y₀``).
    """
    if np.shape(cons.vel_joints)[-1]:
        raise ValueError("the banded Gauss-Newton solver does not take velocity targets")
    prob = problem(
        fm,
        tx,
        seg,
        Y0,
        start_position,
        start_heading,
        cons,
        weights,
        True,
        keep,
        n_valid,
        whiten=False,
        residuals=False,
    )
    w, dt = prob.w, Y0.dtype
    T, D = Y0.shape
    pr = prior_hessian(tx, seg, dt, prob.n_valid)
    sm = smoothness_hessian(T, D, dt, prob.n_valid)
    bands = tuple((w.prior**2) * pr[i] + (w.smooth**2) * sm[i] for i in range(3))
    bands = (bands[0], bands[1], bands[2])
    free_ch = jnp.asarray(root_free_channels(fm), dt)
    anchor = w.anchor * jnp.ones((D,), dt)
    fn: Any = lambda Y: kept_positions(fm, prob.sub, prob.keep, Y, prob.sp, prob.sh)
    points, lower = constraint_points(fm, cons, prob.keep, fn(Y0), prob.plant_h, w)
    if extra is not None:
        points = join_points(points, extra)
    lower = jnp.where((jnp.arange(T) < prob.n_valid)[:, None], lower, -jnp.inf)
    floor_bounds = (lower == cons.floor.astype(lower.dtype)) & cons.floor_on  # not a lift
    roots = root_channels(fm) if move_root else None
    bounds = HeightBounds(
        lower=lower,
        weight=jnp.asarray(w.floor, dt),
        up=fm.skeleton.up_axis,
        exact=floor_bounds if exact_lower else None,
        tol=lower_tol,
    )
    points = dataclasses.replace(points, shifted=exact_points)
    root = None if roots is None else RootOffset(roots[0], roots[1], root_smooth, prob.n_valid)
    banded = BandedProblem(
        positions=fn,
        Y0=Y0,
        bands=bands,
        anchor=anchor,
        free_ch=free_ch,
        terms=(bounds, points),
        held=cons.pose_mask,
        poses=cons.poses.astype(dt),
        root=root,
        colouring=channel_colouring(fm, prob.keep),
    )
    solver = BandedGaussNewton(
        rtol=rtol,
        atol=xtol,
        rounds=rounds,
        max_steps=max_steps,
        early_rtol=early_rtol,
        chord=chord,
    )
    sol = solve_banded(banded, solver)
    z, sp = sol.z, prob.sp
    Y = jnp.where(cons.pose_mask[:, None], cons.poses.astype(dt), Y0 + z * free_ch)
    if roots is not None:
        Y, sp = apply_shift(fm, Y, sp, prob.sh, z[:, list(roots[0])])
    prob = eqx.tree_at(lambda p: p.sp, prob, sp)
    return finish_banded(prob, Y, z, sol.converged, sol.steps, sol.cost, pr)


def root_channels(fm: FeatureMap) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """``((c0, c1), (h0, h1))``: the columns of ``root.d*`` in ``Y`` and their world axes
    (``None`` if either channel or ``root.dyaw`` is constant, i.e. not in ``Y``)."""
    ax = "xyz"
    _, h0, h1 = ground_axes(fm.skeleton.up_axis)
    names = fm.active_names
    want = (f"root.d{ax[h0]}", f"root.d{ax[h1]}", "root.dyaw")
    if not all(n in names for n in want):
        return None
    return (names.index(want[0]), names.index(want[1])), (h0, h1)


def apply_shift(
    fm: FeatureMap, Y: Array, sp: Array, sh: Array, dx: Float[Array, "T 2"]
) -> tuple[Array, Array]:
    """Move the root by a world horizontal offset ``dx`` per frame: the new ``root.d*``
    channels (heading frame of the previous frame, z-scored) and start position."""
    up, h0, h1 = ground_axes(fm.skeleton.up_axis)
    names = fm.active_names
    (c0, c1), _ = root_channels(fm) or ((0, 0), (h0, h1))
    iy = names.index("root.dyaw")
    off, sc = jnp.asarray(fm.offset, Y.dtype), jnp.asarray(fm.scale, Y.dtype)
    act = np.asarray(fm.active)
    dyaw = Y[:, iy] * sc[act[iy]] + off[act[iy]]
    psi = sh + jnp.concatenate([jnp.zeros((1,), Y.dtype), jnp.cumsum(dyaw[1:])])
    step = jnp.zeros((Y.shape[0] - 1, 3), Y.dtype)
    step = step.at[:, h0].set(dx[1:, 0] - dx[:-1, 0]).at[:, h1].set(dx[1:, 1] - dx[:-1, 1])
    e_up = jnp.zeros((3,), Y.dtype).at[up].set(1.0)
    local = quat_rotate(quat_conj(yaw_quat(psi[:-1], e_up)), step)  # heading of frame t − 1
    d0 = local[:, h0] / sc[act[c0]]
    d1 = local[:, h1] / sc[act[c1]]
    d0 = jnp.concatenate([d0[:1], d0])  # frame 0 repeats frame 1 (decoding ignores it)
    d1 = jnp.concatenate([d1[:1], d1])
    Y = Y.at[:, c0].add(d0).at[:, c1].add(d1)
    sp = sp.at[h0].add(dx[0, 0]).at[h1].add(dx[0, 1])
    return Y, sp


solve_edit_gn_jit = eqx.filter_jit(solve_edit_gn)
