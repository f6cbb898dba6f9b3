"""Gauss–Newton with the banded normal equations: the fast solver of edits and cleaning.

With the root's horizontal trajectory held (the channels ``root.d*``, whose running sums place
every later frame), a joint's world position at frame ``t`` depends on ``y_t`` only. Every
constraint residual of a point target or a one-sided height bound then has a per-frame
Jacobian ``J_t``, and the Gauss–Newton normal equations of

.. code-block:: text

    ½ zᵀ H z + ½ Σ_t ‖W_t r_t(Y₀ + z)‖²        (H: prior + smoothness + anchor, block-banded)

are ``(H + Σ_t J_tᵀ W_t² J_t) z⁺ = Σ_t J_tᵀ W_t² (J_t z − r_t)``: the prior's band (two frames
wide) plus block-diagonal terms. One block Cholesky factorisation with one frame per block
(:func:`~mtex_jax.linalg.block_penta_cholesky`) solves it in ``O(T·D³)``, with no iterative
linear solver. The per-frame Jacobians are coloured Jacobian-vector products of the whole
decode and forward kinematics (:mod:`~mtex_jax.edit._jacobians`).

A Gauss–Newton step is ``z⁺ = z − B⁻¹ ∇f(z)`` with ``B`` the normal matrix at ``z``. The
factorisation of ``B`` and the ``D`` products cost far more than the gradient (one reverse
pass) and a substitution with the stored factor, so with ``chord`` (the default for edits)
later steps are *chord* steps ``z⁺ = z − B₀⁻¹ ∇f(z)`` with the last factor ``B₀``, while they
work: a chord step that has to be halved, or that gains less than half of what its own model
promised (``½ ∇fᵀ B₀⁻¹ ∇f``), is followed by a fresh Gauss–Newton step. An edit's few point
targets change ``B`` little from step to step, so a 20 s edit takes two factorisations
instead of about ten; a clean's plants and floor change their active sets between steps, and
clean takes fresh steps only. The loop is two nested loops: a fresh step, then the chord
steps that use its factor as a loop invariant (the 90 MB factor of a 1,280-frame edit is
never part of a loop's carry); the multiplier rounds run inside the same loops.

The iteration is damped by backtracking (a step that raises the cost is halved, up to four
times). It stops when the cost changes by less than ``rtol`` relatively or the step is below
``xtol`` (z-scored units), and not on a poor chord step; ``converged`` reports exactly that.
Point targets are met by
multiplier rounds (their target is shifted by the remaining error between rounds), as in the
Levenberg–Marquardt solver; rounds before the last stop at a looser ``100·rtol``.

A step gathers from the Jacobian-vector products only the rows it needs (the point targets'
and the height of every joint). Everything is traced, so the solve batches with ``vmap``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from ...linalg import block_penta_solve
from .._jacobians import Colouring, frame_columns
from .._prior import smoothness_hessian
from .._whiten import band_quad
from .normal import normal_solve
from .terms import FrameResidual, residual_rows

__all__ = ["BandedSolve", "PointTargets", "solve_banded"]


class PointTargets(eqx.Module):
    """Joint world positions wanted at frames, with per-coordinate weights.

    The first ``n_sparse`` targets may sit at any frames. The rest, if ``per_frame > 0``, are
    *frame-major*: ``per_frame`` targets at each frame ``0, 1, …`` in order (clean's planted
    and swing feet: one per foot and frame), so a solve assembles their normal equations per
    frame, without one ``D × D`` matrix per target (:func:`solve_banded`).

    Attributes:
        slot: ``(P,)`` index of the joint among the solve's kept joints.
        frame: ``(P,)`` frame of each target.
        target: ``(P, 3)`` world positions (metres).
        weight: ``(P, 3)`` per metre (0: that coordinate is free; an inactive slot is all 0).
        exact: ``(P,)`` whether multiplier rounds shift this target (meet it exactly).
        n_sparse: the leading targets at any frames (``None``: all of them).
        per_frame: the frame-major targets per frame (``0``: none).
    """

    slot: Int[Array, " P"]
    frame: Int[Array, " P"]
    target: Float[Array, "P 3"]
    weight: Float[Array, "P 3"]
    exact: Bool[Array, " P"]
    n_sparse: int | None = eqx.field(static=True, default=None)
    per_frame: int = eqx.field(static=True, default=0)

    def __check_init__(self) -> None:
        P = int(jnp.shape(self.frame)[-1])
        s = self.sparse_count
        if not 0 <= s <= P:
            raise ValueError(f"PointTargets: n_sparse={s} is not in [0, {P}]")
        if self.per_frame < 0 or (self.per_frame == 0 and s != P):
            raise ValueError("PointTargets: targets past n_sparse need per_frame > 0")
        if self.per_frame > 0 and (P - s) % self.per_frame:
            raise ValueError(
                f"PointTargets: {P - s} frame-major targets are not a multiple of "
                f"per_frame={self.per_frame}"
            )

    @property
    def sparse_count(self) -> int:
        """The number of leading targets at any frames."""
        return int(jnp.shape(self.frame)[-1]) if self.n_sparse is None else self.n_sparse


class BandedSolve(eqx.Module):
    """Result of :func:`solve_banded`.

    Attributes:
        z: ``(T, D)`` displacement of the observation vectors.
        converged: the last round's stopping test held (not just the step cap).
        steps: Gauss–Newton steps over all rounds.
        cost: final objective (with the last round's shifted targets).
        factor_ok: every block Cholesky factorisation succeeded.
    """

    z: Float[Array, "T D"]
    converged: Bool[Array, ""]
    steps: Int[Array, ""]
    cost: Float[Array, ""]
    factor_ok: Bool[Array, ""]


def _masked_bands(bands, anchor: Array, free_ch: Array):
    mm = free_ch[:, None] * free_ch[None, :]
    H0, H1, H2 = bands
    eye = jnp.diag(1.0 - free_ch)
    return (H0 * mm + eye, H1 * mm, H2 * mm), anchor * free_ch


def solve_banded(
    fn,
    Y0: Float[Array, "T D"],
    bands: tuple[Array, Array, Array],
    anchor: Float[Array, " D"],
    free_ch: Float[Array, " D"],
    held: Bool[Array, " T"],
    poses: Float[Array, "T D"],
    points: PointTargets,
    lower: Float[Array, "T K"],
    lower_weight: Float[Array, ""],
    up: int,
    *,
    move_root: tuple[tuple[int, int], tuple[int, int]] | None = None,
    root_smooth: float | Array = 0.0,
    n_valid: Int[Array, ""] | int | None = None,
    rounds: int = 3,
    max_steps: int = 8,
    rtol: float = 1e-6,
    early_rtol: float | None = None,
    exact_lower: Bool[Array, "T K"] | None = None,
    exact_points: bool = True,
    lower_tol: float = 0.0,
    xtol: float = 1e-4,
    colouring: Colouring | None = None,
    chord: bool = True,
    terms: tuple[FrameResidual, ...] = (),
    linear: Float[Array, "T D"] | None = None,
) -> BandedSolve:
    """Minimise the banded objective (module notes) by Gauss–Newton, with multiplier rounds.

    Args:
        fn: ``Y ↦ (T, K, 3)`` kept joint positions (frames must not interact through the free
            channels).
        Y0: ``(T, D)`` the motion before the edit.
        bands: ``(H0, H1, H2)`` weighted prior + smoothness Hessian bands.
        anchor: ``(D,)`` per-channel anchor weights.
        free_ch: ``(D,)`` 1 for a free channel, 0 for a held one (e.g. ``root.d*``).
        held: ``(T,)`` frames replaced exactly by ``poses``.
        poses: ``(T, D)`` the held frames' observation vectors.
        points: the point targets.
        lower: ``(T, K)`` lowest allowed height of each kept joint (``-inf``: none).
        lower_weight: per metre, the one-sided height penalty.
        up: the up axis.
        move_root: ``((c0, c1), (h0, h1))``: let the root move horizontally. Columns ``c0, c1`` of
            ``z`` (two held channels, e.g. ``root.d*``) then carry a world offset (metres)
            of the whole figure along axes ``h0, h1`` at each frame, priced by
            ``root_smooth`` per metre of its second difference (plus a unit ridge); the
            caller turns it into the root channels (:func:`mtex_jax.edit._gn.apply_shift`).
            Frames stay independent: the offset moves every joint of its frame alike.
        root_smooth: weight of the offset's second difference.
        n_valid: the motion's own frames (the rest pad it to a shape bucket and are held);
            the offset's smoothness stops there. ``None``: all ``T``.
        rounds: multiplier rounds (``≥ 1``).
        max_steps: Gauss–Newton steps per round.
        rtol: relative change of the cost below which the last round stops.
        early_rtol: the same for the rounds before it (``None``: ``100·rtol``; their targets
            are shifted again: on four benchmark edits 62 steps instead of 71, every target
            met, position errors within 0.12 mm of those of tight early rounds).
        exact_lower: ``(T, K)``: the multiplier rounds also shift every lower height (an
            augmented Lagrangian of the bound ``h ≥ lower``: ``s ← max(0, s + lower − h)``,
            the penalty on ``lower + s − h``), so the bounds are met instead of balanced
            against the prior; the mask marks the bounds that decide whether another round
            is needed (``lower_tol``). ``None``: the lower heights are plain penalties.
        exact_points: the multiplier rounds shift the point targets marked ``exact``;
            ``False``: the point targets stay penalties (only the lower heights are shifted).
        lower_tol: with ``exact_lower`` and not ``exact_points``, no further round starts once
            no bound of the mask is violated by more than this (the round's stop is final).
        xtol: largest step (z-scored units) below which a round stops.
        colouring: channels that share a Jacobian-vector product (:func:`channel_colouring`);
            ``None``: one product per channel.
        chord: reuse the last factorisation for later steps (module notes) until a step
            gains less than half of what its model promised; ``False``: every step is a
            fresh Gauss–Newton step (for problems far from linear, e.g. cleaning, whose
            active sets change from step to step).
        terms: further per-frame residual terms of the kept positions, robust ones included
            (:class:`~mtex_jax.edit.FrameResidual`; a tracker's 2-D reprojection); each fresh
            step takes their reweighted Gauss–Newton model.
        linear: ``(T, D)`` a linear term ``Σ linear ⊙ z`` of the objective: with it the prior is
            absolute, ``½ (Y₀+z)ᵀ H (Y₀+z) + …`` up to a constant, when ``linear`` is the prior's
            gradient at ``Y₀`` (``None``: the prior prices the displacement ``z`` alone).

    Returns:
        :class:`BandedSolve`.
    """
    dt = Y0.dtype
    T, D = Y0.shape
    bands, anchor = _masked_bands(bands, anchor, free_ch)
    var_ch = free_ch
    if move_root is not None:
        (c0, c1), _ = move_root
        e = jnp.zeros((D,), dt).at[jnp.array([c0, c1])].set(1.0)
        ee = jnp.asarray(root_smooth, dt) ** 2 * jnp.diag(e)
        sm = smoothness_hessian(T, D, dt, n_valid)
        bands = (bands[0] + sm[0] * ee, bands[1] + sm[1] * ee, bands[2] + sm[2] * ee)
        var_ch = free_ch + e

    def offset(z: Array) -> Array:  # (T, 1, 3) world offset of every joint
        if move_root is None:
            return jnp.zeros((T, 1, 3), dt)
        (c0, c1), (h0, h1) = move_root
        return jnp.zeros((T, 1, 3), dt).at[:, 0, h0].set(z[:, c0]).at[:, 0, h1].set(z[:, c1])

    delta = jnp.where(held[:, None], poses - Y0, 0.0)
    w2 = points.weight**2
    lw = jnp.asarray(lower_weight, dt)

    def edited(z: Array) -> Array:
        return jnp.where(held[:, None], poses, Y0 + z * free_ch)

    def point_res(P: Array, shift: Array) -> Array:
        return P[points.frame, points.slot] - points.target - shift  # (P, 3)

    def cost_of(z: Array, shift: Array, ls: Array) -> Array:
        P = fn(edited(z)) + offset(z)
        r = point_res(P, shift)
        low = jnp.maximum(lower + ls - P[..., up], 0.0)
        v = jnp.where(held[:, None], delta, z * var_ch)
        hz = band_quad(bands, v) + jnp.sum((anchor * v) ** 2)
        c = 0.5 * (hz + jnp.sum(w2 * r * r) + jnp.sum((lw * low) ** 2))
        for term in terms:
            c = c + term.loss(term.residual(P))
        if linear is not None:
            c = c + jnp.sum(linear * v)
        return c

    def gn_step(z: Array, shift: Array, ls: Array, active: Array):
        fc = frame_columns(fn, edited(z), free_ch, colouring)
        P = fc.P + offset(z)
        Jp = fc.rows(points.frame, points.slot)  # (P, 3, D)
        if move_root is not None:  # the offset moves every joint of its frame alike
            (c0, c1), (h0, h1) = move_root
            Jp = Jp.at[:, h0, c0].set(1.0).at[:, h1, c1].set(1.0)
        r = point_res(P, shift)
        # Σ Jᵀ W² J and Σ Jᵀ W² (J z − r). The frame-major targets' rows and the floor's
        # rows are weighted and stacked per frame, one batched product; the sparse targets'
        # terms are scattered to their frames (no D × D matrix per frame-major target)
        ns = points.sparse_count
        h, low = P[..., up], lower + ls
        act = (h < low).astype(dt)  # (T, K): one-sided, the active set at z
        rows = [fc.axis(up) * (lw * act)[..., None]]  # (T, K, D)
        res = [lw * act * (h - jnp.where(act > 0, low, h))]
        if points.per_frame:
            F = points.per_frame
            wd = points.weight[ns:].reshape(T, F, 3)
            rows.append((Jp[ns:].reshape(T, F, 3, D) * wd[..., None]).reshape(T, 3 * F, D))
            res.append((r[ns:].reshape(T, F, 3) * wd).reshape(T, 3 * F))
        if terms:
            Jall = jnp.stack([fc.axis(a) for a in range(3)], axis=2)  # (T, K, 3, D)
            if move_root is not None:
                (c0, c1), (h0, h1) = move_root
                Jall = Jall.at[:, :, h0, c0].set(1.0).at[:, :, h1, c1].set(1.0)
            for term in terms:
                rt, et = residual_rows(term, P, Jall)
                rows.append(rt)
                res.append(et)
        Jf, rf = jnp.concatenate(rows, axis=1), jnp.concatenate(res, axis=1)
        A = jnp.einsum("trd,tre->tde", Jf, Jf)
        b = jnp.einsum("trd,tr->td", Jf, jnp.einsum("tre,te->tr", Jf, z) - rf)
        if ns:
            Js, ws = Jp[:ns], w2[:ns]
            zs = z[points.frame[:ns]]
            A_p = jnp.einsum("pcd,pc,pce->pde", Js, ws, Js)
            b_p = jnp.einsum("pcd,pc,pc->pd", Js, ws, jnp.einsum("pce,pe->pc", Js, zs) - r[:ns])
            A = A.at[points.frame[:ns]].add(A_p)
            b = b.at[points.frame[:ns]].add(b_p)
        H0, H1, H2 = bands
        rhs = -(b * var_ch) if linear is None else (linear - b) * var_ch
        z_star, fac, ok = normal_solve(H0, A, H1, H2, var_ch, anchor, held, delta, rhs, active)
        return z_star - delta, fac, ok

    keep_rows = (~held)[:, None].astype(dt) * var_ch[None, :]
    grad_of = jax.grad(cost_of)
    value_and_grad_of = jax.value_and_grad(cost_of)
    early = 100.0 * rtol if early_rtol is None else early_rtol

    def advance(s: _Iterate, z_try: Array, fac_ok: Array, pred: Array, full: bool) -> _Iterate:
        """Take the step to ``z_try`` (halved while it does not lower the cost), test the
        round's stop, and start the next multiplier round when this one ends."""
        z, c = s.z, s.cost
        dz = z_try - z

        def worse(b):
            _zt, ct, i = b
            return ~((ct < c) & jnp.isfinite(ct)) & (i < 5)

        def halve(b):
            _zt, _ct, i = b
            zt = z + (0.5 ** (i + 1)) * dz
            return zt, cost_of(zt, s.shift, s.lshift), i + 1

        if chord:  # the cost and the gradient the next chord step needs, in one pass
            c_try, g_try = value_and_grad_of(z_try, s.shift, s.lshift)
        else:
            c_try, g_try = cost_of(z_try, s.shift, s.lshift), s.g
        zt, ct, i = lax.while_loop(worse, halve, (z_try, c_try, 0))
        better = (ct < c) & jnp.isfinite(ct)
        z_new, c_new = jnp.where(better, zt, z), jnp.where(better, ct, c)
        # the gradient at z_new: z_try's if taken whole, the old one if no step was taken
        g_new = jnp.where(better, g_try, s.g)
        g_ok = jnp.where(better, i == 0, s.g_ok)
        step = jnp.max(jnp.abs(z_new - z))
        # rounds before the last stop early: their targets are shifted again anyway
        tol = jnp.where(s.round + 1 < rounds, early, rtol)
        stop = (c - c_new <= tol * jnp.maximum(c, 1e-30)) | (step <= xtol)
        # a chord step that needed halving or gained less than half of what its model
        # promised (pred) is poor: the next step refactors, and a poor chord step never
        # ends the round
        poor = jnp.asarray(False) if full else (i > 0) | ~better | (c - c_new < 0.5 * pred)
        done = stop & ~poor
        k = s.k + 1
        end = done | (k >= max_steps)
        last = end & (s.round + 1 >= rounds)
        new_round = end & ~last

        def next_round():  # the exact targets shifted by their remaining error
            P = fn(edited(z_new)) + offset(z_new)
            err = P[points.frame, points.slot] - points.target
            shift = s.shift - jnp.where(points.exact[:, None] & exact_points, err, 0.0)
            gap = lower - P[..., up]  # > 0: a bound violated
            if exact_lower is None:
                return shift, s.lshift, cost_of(z_new, shift, s.lshift), jnp.asarray(False)
            # only bounds shifted, every one met to lower_tol: no further round (nothing moves)
            met = ~jnp.any(exact_lower & (gap > lower_tol)) & (not exact_points)
            ls = jnp.where(met, s.lshift, jnp.maximum(s.lshift + gap, 0.0))
            return shift, ls, jnp.where(met, c_new, cost_of(z_new, shift, ls)), met

        same = lambda: (s.shift, s.lshift, c_new, jnp.asarray(False))
        shift, lshift, c_next, met = lax.cond(new_round, next_round, same)
        last, new_round = last | met, new_round & ~met
        return _Iterate(
            z=z_new,
            shift=shift,
            lshift=lshift,
            cost=c_next,
            round=s.round + new_round.astype(jnp.int32),
            k=jnp.where(end, 0, k),
            steps=s.steps + 1,
            converged=jnp.where(end, done, s.converged),
            finished=last,
            fresh=~end & poor,  # a round starts with a chord step (as it ends)
            ok=s.ok & fac_ok,
            g=g_new,
            g_ok=g_ok & ~new_round,  # a new round's shift changes the gradient
        )

    def fresh_then_chords(s: _Iterate) -> _Iterate:
        """One fresh Gauss–Newton step, then chord steps with its factor while they work."""
        z_gn, fac, ok = gn_step(s.z, s.shift, s.lshift, ~s.finished)
        s = advance(s, z_gn, ok, jnp.zeros((), dt), full=True)
        if not chord:
            return s
        # a single-precision factor that failed (the step was solved in double precision)
        # is not used: the next step is a fresh one
        s = eqx.tree_at(lambda s: s.fresh, s, s.fresh | ~fac.ok)

        def chord_step(s: _Iterate) -> _Iterate:
            # z − B₀⁻¹ g with the factor B₀ of the last fresh step (a loop invariant: the
            # factor is not carried), and the model's promise ½ gᵀB₀⁻¹g
            g = lax.cond(s.g_ok, lambda: s.g, lambda: grad_of(s.z, s.shift, s.lshift))
            g = g * keep_rows
            z_c = s.z - block_penta_solve(fac, g) * keep_rows
            return advance(s, z_c, fac.ok, -0.5 * jnp.sum((z_c - s.z) * g), full=False)

        return lax.while_loop(lambda s: ~s.finished & ~s.fresh, chord_step, s)

    shift0 = jnp.zeros_like(points.target)
    ls0 = jnp.zeros_like(lower)
    z0 = jnp.zeros((T, D), dt)
    i0 = jnp.asarray(0, jnp.int32)
    init = _Iterate(
        z=z0,
        shift=shift0,
        lshift=ls0,
        cost=cost_of(z0, shift0, ls0),
        round=i0,
        k=i0,
        steps=i0,
        converged=jnp.asarray(False),
        finished=jnp.asarray(False),
        fresh=jnp.asarray(True),
        ok=jnp.asarray(True),
        g=z0,
        g_ok=jnp.asarray(False),
    )
    s = lax.while_loop(lambda s: ~s.finished, fresh_then_chords, init)
    z = jnp.where(held[:, None], delta, s.z * var_ch)
    return BandedSolve(
        z=z, converged=s.converged & s.ok, steps=s.steps, cost=s.cost, factor_ok=s.ok
    )


class _Iterate(eqx.Module):
    """The state of :func:`solve_banded`'s iteration (all rounds in one loop)."""

    z: Float[Array, "T D"]
    shift: Float[Array, "P 3"]  # the exact targets' multiplier shifts
    lshift: Float[Array, "T K"]  # the lower heights' shifts (exact_lower)
    cost: Float[Array, ""]
    round: Int[Array, ""]
    k: Int[Array, ""]  # steps in this round
    steps: Int[Array, ""]
    converged: Bool[Array, ""]
    finished: Bool[Array, ""]
    fresh: Bool[Array, ""]  # the next step refactors
    ok: Bool[Array, ""]
    g: Float[Array, "T D"]  # the cost's gradient at z (chord steps), valid if g_ok
    g_ok: Bool[Array, ""]
