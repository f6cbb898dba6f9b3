"""Gauss–Newton with the banded normal equations: the solver of edits, cleaning and tracking.

With the root's horizontal trajectory held (the channels ``root.d*``, whose running sums place
every later frame), a joint's world position at frame ``t`` depends on ``y_t`` only. Every
residual of a term (:mod:`.terms`: point targets, height bounds, a tracker's reprojection)
then has a per-frame Jacobian ``J_t``, and the Gauss–Newton normal equations of the problem
(:class:`BandedProblem`)

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
clean takes fresh steps only.

The solver is an optimistix minimiser (:class:`BandedGaussNewton`, run by
``optimistix.minimise`` with the problem as ``args``). One of its steps is one factorisation, a
fresh Gauss–Newton step, followed by the chord steps that reuse it while they work: two nested
loops, the inner one with the factor as a loop invariant, so the 90 MB factor of a 1,280-frame
edit is carried once per factorisation, in the solver state (with the terms' multiplier shifts
and the round), and not by every chord step. The multiplier rounds run inside the same loops.

The iteration is damped by backtracking (a step that raises the cost is halved, up to four
times). It stops when the cost changes by less than ``rtol`` relatively or the step is below
``atol`` (z-scored units), and not on a poor chord step; ``converged`` reports exactly that.
Constraints are met by multiplier rounds (each term moves its shift by the remaining error
between rounds, :meth:`~.terms.ResidualTerm.next_round`), as in the Levenberg–Marquardt
solver; rounds before the last stop at a looser ``100·rtol``, and the rounds end early when no
term needs another.

A step gathers from the Jacobian-vector products only the rows its terms need. Everything is
traced, so the solve batches with ``vmap``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from ...linalg import BlockPentaCholesky, block_penta_solve
from .._jacobians import Colouring, frame_columns
from .._prior import smoothness_hessian
from .._whiten import band_quad
from .normal import no_factor, normal_solve
from .terms import Columns, ResidualTerm, RootOffset

__all__ = ["BandedGaussNewton", "BandedProblem", "BandedSolve", "solve_banded"]


class BandedProblem(eqx.Module):
    """The banded objective of the displacement ``z`` of the observation vectors (module notes).

    ``½ vᵀ H v + ½ ‖anchor ⊙ v‖² + Σ terms(P) (+ linear · v)`` with ``v = z`` on the free
    channels of the free frames, ``P`` the kept joint positions of ``Y₀ + v`` (plus the root
    offset), and the held frames replaced by ``poses``.

    Attributes:
        positions: ``Y ↦ (T, K, 3)`` kept joint positions (frames must not interact through the
            free channels).
        Y0: ``(T, D)`` the motion before the solve.
        bands: ``(H0, H1, H2)`` weighted prior + smoothness Hessian bands.
        anchor: ``(D,)`` per-channel anchor weights.
        free_ch: ``(D,)`` 1 for a free channel, 0 for a held one (e.g. ``root.d*``).
        terms: the residual terms (:class:`~.terms.ResidualTerm` members).
        held: ``(T,)`` frames replaced exactly by ``poses`` (``None``: none).
        poses: ``(T, D)`` the held frames' observation vectors (``None``: ``Y0``).
        root: let the root move horizontally (:class:`~.terms.RootOffset`; ``None``: held).
        linear: ``(T, D)`` a linear term ``Σ linear ⊙ v``: with it the prior is absolute,
            ``½ (Y₀+v)ᵀ H (Y₀+v) + …`` up to a constant, when ``linear`` is the prior's
            gradient at ``Y₀`` (``None``: the prior prices the displacement alone).
        colouring: channels that share a Jacobian-vector product
            (:func:`~mtex_jax.edit.channel_colouring`); ``None``: one product per channel.
    """

    positions: Callable[[Array], Array]
    Y0: Float[Array, "T D"]
    bands: tuple[Array, Array, Array]
    anchor: Float[Array, " D"]
    free_ch: Float[Array, " D"]
    terms: tuple[ResidualTerm, ...] = ()
    held: Bool[Array, " T"] | None = None
    poses: Float[Array, "T D"] | None = None
    root: RootOffset | None = None
    linear: Float[Array, "T D"] | None = None
    colouring: Colouring | None = None

    def __check_init__(self) -> None:
        T, D = jnp.shape(self.Y0)
        for name, a, shape in (
            ("bands[0]", self.bands[0], (T, D, D)),
            ("anchor", self.anchor, (D,)),
            ("free_ch", self.free_ch, (D,)),
            ("held", self.held, (T,)),
            ("poses", self.poses, (T, D)),
            ("linear", self.linear, (T, D)),
        ):
            if a is not None and jnp.shape(a) != shape:
                raise ValueError(f"BandedProblem: {name} has shape {jnp.shape(a)}, not {shape}")
        if not all(isinstance(t, ResidualTerm) for t in self.terms):
            raise TypeError("BandedProblem: every term must be a ResidualTerm")


class _Objective(eqx.Module):
    """A :class:`BandedProblem` prepared for the iteration: held channels masked out of the
    bands, the root offset's smoothness added."""

    pb: BandedProblem
    bands: tuple[Array, Array, Array]
    anchor: Array
    var_ch: Array
    held: Array
    poses: Array
    delta: Array

    @classmethod
    def of(cls, pb: BandedProblem) -> _Objective:
        dt = pb.Y0.dtype
        T, D = pb.Y0.shape
        free = pb.free_ch
        mm = free[:, None] * free[None, :]
        H0, H1, H2 = pb.bands
        bands = (H0 * mm + jnp.diag(1.0 - free), H1 * mm, H2 * mm)
        var_ch = free
        if pb.root is not None:
            e = jnp.zeros((D,), dt).at[jnp.array(pb.root.channels)].set(1.0)
            ee = jnp.asarray(pb.root.smooth, dt) ** 2 * jnp.diag(e)
            sm = smoothness_hessian(T, D, dt, pb.root.n_valid)
            bands = (bands[0] + sm[0] * ee, bands[1] + sm[1] * ee, bands[2] + sm[2] * ee)
            var_ch = free + e
        held = jnp.zeros((T,), bool) if pb.held is None else pb.held
        poses = pb.Y0 if pb.poses is None else pb.poses
        delta = jnp.where(held[:, None], poses - pb.Y0, 0.0)
        return cls(pb, bands, pb.anchor * free, var_ch, held, poses, delta)

    def edited(self, z: Array) -> Array:
        return jnp.where(self.held[:, None], self.poses, self.pb.Y0 + z * self.pb.free_ch)

    def offset(self, z: Array) -> Array:
        """``(T, 1, 3)`` the root offset's world shift of every joint."""
        T, dt = z.shape[0], z.dtype
        out = jnp.zeros((T, 1, 3), dt)
        if self.pb.root is None:
            return out
        (c0, c1), (h0, h1) = self.pb.root.channels, self.pb.root.axes
        return out.at[:, 0, h0].set(z[:, c0]).at[:, 0, h1].set(z[:, c1])

    def at(self, z: Array) -> Array:
        """The kept positions at ``z``."""
        return self.pb.positions(self.edited(z)) + self.offset(z)

    def displacement(self, z: Array) -> Array:
        return jnp.where(self.held[:, None], self.delta, z * self.var_ch)

    def cost(self, z: Array, shifts: tuple[Any, ...]) -> Array:
        P = self.at(z)
        v = self.displacement(z)
        c = 0.5 * (band_quad(self.bands, v) + jnp.sum((self.anchor * v) ** 2))
        for term, sh in zip(self.pb.terms, shifts, strict=True):
            c = c + term.cost(P, sh)
        if self.pb.linear is not None:
            c = c + jnp.sum(self.pb.linear * v)
        return c

    def gn_step(self, z: Array, shifts: tuple[Any, ...], active: Array):
        """The fresh Gauss–Newton step from ``z``: ``(z⁺, factor, ok)``."""
        pb = self.pb
        T, D = z.shape
        fc = frame_columns(pb.positions, self.edited(z), pb.free_ch, pb.colouring)
        cols = Columns(P=fc.P + self.offset(z), fc=fc, root=pb.root)
        rows = [r for t, sh in zip(pb.terms, shifts, strict=True) for r in t.rows(cols.P, cols, sh)]
        A, b = jnp.zeros((T, D, D), z.dtype), jnp.zeros((T, D), z.dtype)
        # Σ Jᵀ W² J and Σ Jᵀ W² (J z − r): frame-wise rows stacked per frame, one batched
        # product; the rows of sparse frames scattered to their frames
        wise = [r for r in rows if r.frame is None]
        if wise:
            Jf = jnp.concatenate([r.J for r in wise], axis=1)
            rf = jnp.concatenate([r.r for r in wise], axis=1)
            A = jnp.einsum("trd,tre->tde", Jf, Jf)
            b = jnp.einsum("trd,tr->td", Jf, jnp.einsum("tre,te->tr", Jf, z) - rf)
        for r in rows:
            if r.frame is None or r.w is None:
                continue
            zs = z[r.frame]
            A_p = jnp.einsum("pcd,pc,pce->pde", r.J, r.w, r.J)
            b_p = jnp.einsum("pcd,pc,pc->pd", r.J, r.w, jnp.einsum("pce,pe->pc", r.J, zs) - r.r)
            A, b = A.at[r.frame].add(A_p), b.at[r.frame].add(b_p)
        H0, H1, H2 = self.bands
        v = self.var_ch
        rhs = -(b * v) if pb.linear is None else (pb.linear - b) * v
        z_star, fac, ok = normal_solve(
            H0, A, H1, H2, v, self.anchor, self.held, self.delta, rhs, active
        )
        return z_star - self.delta, fac, ok


class BandedSolve(eqx.Module):
    """Result of :func:`solve_banded`.

    Attributes:
        z: ``(T, D)`` displacement of the observation vectors.
        converged: the last round's stopping test held (not just the step cap).
        steps: Gauss–Newton steps (fresh and chord) over all rounds.
        cost: final objective (with the last round's shifts).
        factor_ok: every block Cholesky factorisation succeeded.
    """

    z: Float[Array, "T D"]
    converged: Bool[Array, ""]
    steps: Int[Array, ""]
    cost: Float[Array, ""]
    factor_ok: Bool[Array, ""]


class _State(eqx.Module):
    """The state of :class:`BandedGaussNewton` (all rounds in one loop)."""

    z: Float[Array, "T D"]  # the iterate (optimistix's ``y``)
    shifts: tuple[Any, ...]  # each term's multiplier shift
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
    factor: BlockPentaCholesky  # the last fresh step's factor (chord steps reuse it)


class BandedGaussNewton(optx.AbstractMinimiser):
    """Gauss–Newton with the banded normal equations, chord steps and multiplier rounds.

    An ``optimistix`` minimiser of a :class:`BandedProblem` (passed as ``args``; module
    notes): each step factorises once and takes chord steps with that factor while they work.

    Attributes:
        rtol: relative change of the cost below which the last round stops.
        atol: largest step (z-scored units, in ``norm``) below which a round stops.
        norm: the step's norm.
        rounds: multiplier rounds (``≥ 1``).
        max_steps: Gauss–Newton steps per round.
        early_rtol: ``rtol`` of the rounds before the last (``None``: ``100·rtol``; their
            shifts move again: on four benchmark edits 62 steps instead of 71, every target
            met, position errors within 0.12 mm of those of tight early rounds).
        chord: reuse the last factorisation for later steps until a step gains less than half
            of what its model promised; ``False``: every step is a fresh Gauss–Newton step
            (for problems far from linear, e.g. cleaning, whose active sets change from step
            to step).
    """

    rtol: float = 1e-6
    atol: float = 1e-4
    norm: Callable[..., Array] = optx.max_norm
    rounds: int = eqx.field(static=True, default=3)
    max_steps: int = eqx.field(static=True, default=8)
    early_rtol: float | None = None
    chord: bool = eqx.field(static=True, default=True)

    def __check_init__(self) -> None:
        if self.rounds < 1 or self.max_steps < 1:
            raise ValueError("BandedGaussNewton: rounds and max_steps must be at least 1")

    def init(self, fn, y, args, options, f_struct, aux_struct, tags) -> _State:
        del fn, options, f_struct, aux_struct, tags
        q = _Objective.of(args)
        T, D = y.shape
        shifts = tuple(t.start() for t in args.terms)
        i0 = jnp.asarray(0, jnp.int32)
        false = jnp.asarray(False)
        return _State(
            z=y,
            shifts=shifts,
            cost=q.cost(y, shifts),
            round=i0,
            k=i0,
            steps=i0,
            converged=false,
            finished=false,
            fresh=jnp.asarray(True),
            ok=jnp.asarray(True),
            g=jnp.zeros_like(y),
            g_ok=false,
            factor=no_factor(T, D, y.dtype),
        )

    def _advance(
        self, q: _Objective, s: _State, z_try: Array, fac_ok: Array, pred: Array, full: bool
    ) -> _State:
        """Take the step to ``z_try`` (halved while it does not lower the cost), test the
        round's stop, and start the next multiplier round when this one ends."""
        z, c = s.z, s.cost
        dz = z_try - z
        cost_of = q.cost

        def worse(b):
            _zt, ct, i = b
            return ~((ct < c) & jnp.isfinite(ct)) & (i < 5)

        def halve(b):
            _zt, _ct, i = b
            zt = z + (0.5 ** (i + 1)) * dz
            return zt, cost_of(zt, s.shifts), i + 1

        if self.chord:  # the cost and the gradient the next chord step needs, in one pass
            c_try, g_try = jax.value_and_grad(cost_of)(z_try, s.shifts)
        else:
            c_try, g_try = cost_of(z_try, s.shifts), s.g
        zt, ct, i = lax.while_loop(worse, halve, (z_try, c_try, 0))
        better = (ct < c) & jnp.isfinite(ct)
        z_new, c_new = jnp.where(better, zt, z), jnp.where(better, ct, c)
        # the gradient at z_new: z_try's if taken whole, the old one if no step was taken
        g_new = jnp.where(better, g_try, s.g)
        g_ok = jnp.where(better, i == 0, s.g_ok)
        step = self.norm(z_new - z)
        # rounds before the last stop early: their shifts move again anyway
        early = 100.0 * self.rtol if self.early_rtol is None else self.early_rtol
        tol = jnp.where(s.round + 1 < self.rounds, early, self.rtol)
        stop = (c - c_new <= tol * jnp.maximum(c, 1e-30)) | (step <= self.atol)
        # a chord step that needed halving or gained less than half of what its model
        # promised (pred) is poor: the next step refactors, and a poor chord step never
        # ends the round
        poor = jnp.asarray(False) if full else (i > 0) | ~better | (c - c_new < 0.5 * pred)
        done = stop & ~poor
        k = s.k + 1
        end = done | (k >= self.max_steps)
        last = end & (s.round + 1 >= self.rounds)
        new_round = end & ~last

        def next_round():  # every term's shift moved by its remaining error
            P = q.at(z_new)
            moved = [t.next_round(P, sh) for t, sh in zip(q.pb.terms, s.shifts, strict=True)]
            needed = jnp.any(jnp.stack([jnp.asarray(m[1]) for m in moved] or [False]))
            shifts = tuple(
                jax.tree.map(lambda a, b: jnp.where(needed, a, b), m[0], sh)
                for m, sh in zip(moved, s.shifts, strict=True)
            )
            return shifts, jnp.where(needed, cost_of(z_new, shifts), c_new), ~needed

        same = lambda: (s.shifts, c_new, jnp.asarray(False))
        shifts, c_next, met = lax.cond(new_round, next_round, same)
        last, new_round = last | met, new_round & ~met
        return dataclasses.replace(
            s,
            z=z_new,
            shifts=shifts,
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

    def step(self, fn, y, args, options, state, tags):
        """One fresh Gauss–Newton step, then chord steps with its factor while they work."""
        del fn, options, tags
        q = _Objective.of(args)
        s = eqx.tree_at(lambda s: s.z, state, y)
        z_gn, fac, ok = q.gn_step(s.z, s.shifts, ~s.finished)
        s = self._advance(q, s, z_gn, ok, jnp.zeros((), y.dtype), full=True)
        s = eqx.tree_at(lambda s: s.factor, s, fac)
        if not self.chord:
            return s.z, s, None
        # a single-precision factor that failed (the step was solved in double precision)
        # is not used: the next step is a fresh one
        s = eqx.tree_at(lambda s: s.fresh, s, s.fresh | ~fac.ok)
        keep_rows = (~q.held)[:, None].astype(y.dtype) * q.var_ch[None, :]
        grad_of = jax.grad(q.cost)

        def chord_step(s: _State) -> _State:
            # z − B₀⁻¹ g with the factor B₀ of the last fresh step (a loop invariant: the
            # factor is not carried by this loop), and the model's promise ½ gᵀB₀⁻¹g
            g = lax.cond(s.g_ok, lambda: s.g, lambda: grad_of(s.z, s.shifts))
            g = g * keep_rows
            z_c = s.z - block_penta_solve(fac, g) * keep_rows
            return self._advance(q, s, z_c, fac.ok, -0.5 * jnp.sum((z_c - s.z) * g), False)

        s = lax.while_loop(lambda s: ~s.finished & ~s.fresh, chord_step, s)
        return s.z, s, None

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, args, options, tags
        return state.finished, optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        del fn, args, options, state, tags, result
        return y, aux, {}


def _objective_value(z: Array, pb: BandedProblem) -> Array:
    q = _Objective.of(pb)
    return q.cost(z, tuple(t.start() for t in pb.terms))


def solve_banded(problem: BandedProblem, solver: BandedGaussNewton | None = None) -> BandedSolve:
    """Minimise a :class:`BandedProblem` by :class:`BandedGaussNewton` (module notes).

    Everything is traced, so the solve batches with ``vmap``.

    Args:
        problem: the objective.
        solver: the solver's settings (``None``: the defaults).

    Returns:
        :class:`BandedSolve` (``z`` is the displacement, with the held frames' ``poses − Y₀``).
    """
    solver = BandedGaussNewton() if solver is None else solver
    z0 = jnp.zeros_like(problem.Y0)
    sol = optx.minimise(
        _objective_value,
        solver,
        z0,
        problem,
        max_steps=solver.rounds * solver.max_steps,
        throw=False,
    )
    s: _State = sol.state
    q = _Objective.of(problem)
    return BandedSolve(
        z=q.displacement(s.z),
        converged=s.converged & s.ok,
        steps=s.steps,
        cost=s.cost,
        factor_ok=s.ok,
    )
