"""Gauss–Newton with the banded normal equations: the fast solver of edits and cleaning.

With the root's horizontal trajectory held (the channels ``root.d*``, whose running sums place
every later frame), a joint's world position at frame ``t`` depends on ``y_t`` only. Every
constraint residual of a point target or a one-sided height bound then has a per-frame
Jacobian ``J_t``, and the Gauss–Newton normal equations of

.. code-block:: text

    ½ zᵀ H z + ½ Σ_t ‖W_t r_t(Y₀ + z)‖²        (H: prior + smoothness + anchor, block-banded)

are ``(H + Σ_t J_tᵀ W_t² J_t) z⁺ = Σ_t J_tᵀ W_t² (J_t z − r_t)``: the prior's band (two frames
wide) plus block-diagonal terms. One block Cholesky factorisation of two-frame blocks solves it
in ``O(T·D³)``, with no iterative linear solver. The per-frame Jacobians are ``D``
Jacobian-vector products of the whole decode and forward kinematics (a tangent that moves one
channel in every frame at once gives every frame's column, because frames do not interact).

A Gauss–Newton step is ``z⁺ = z − B⁻¹ ∇f(z)`` with ``B`` the normal matrix at ``z``. The
factorisation of ``B`` and the ``D`` products cost far more than the gradient (one reverse
pass) and a substitution with the stored factor, so with ``chord`` (the default for edits)
later steps are *chord* steps ``z⁺ = z − B₀⁻¹ ∇f(z)`` with the last factor ``B₀``, while they
work: a chord step that has to be halved, or that gains less than half of what its own model
promised (``½ ∇fᵀ B₀⁻¹ ∇f``), is followed by a fresh Gauss–Newton step. An edit's few point
targets change ``B`` little from step to step, so a 20 s edit takes two factorisations
instead of about ten; a clean's plants and floor change their active sets between steps, and
clean takes fresh steps only.

The iteration is damped by backtracking (a step that raises the cost is halved, up to four
times). It stops when the cost changes by less than ``rtol`` relatively or the step is below
``xtol`` (z-scored units), and not on a poor chord step; ``converged`` reports exactly that.
Point targets are met by
multiplier rounds (their target is shifted by the remaining error between rounds), as in the
Levenberg–Marquardt solver. Everything is traced, so the solve batches with ``vmap``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from ..linalg import BlockPentaCholesky, block_penta_cholesky, block_penta_solve, sym
from ..motion import FeatureMap, Skeleton
from ._fk import fk_positions
from ._prior import smoothness_hessian
from ._whiten import band_matvec

__all__ = [
    "BandedSolve",
    "Colouring",
    "PointTargets",
    "channel_colouring",
    "frame_jacobians",
    "kept_positions",
    "root_free_channels",
    "solve_banded",
]


class PointTargets(eqx.Module):
    """Joint world positions wanted at frames, with per-coordinate weights.

    Attributes:
        slot: ``(P,)`` index of the joint among the solve's kept joints.
        frame: ``(P,)`` frame of each target.
        target: ``(P, 3)`` world positions (metres).
        weight: ``(P, 3)`` per metre (0: that coordinate is free; an inactive slot is all 0).
        exact: ``(P,)`` whether multiplier rounds shift this target (meet it exactly).
    """

    slot: Int[Array, " P"]
    frame: Int[Array, " P"]
    target: Float[Array, "P 3"]
    weight: Float[Array, "P 3"]
    exact: Bool[Array, " P"]


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


def kept_positions(
    fm: FeatureMap, sub: Skeleton, keep: tuple[int, ...], Y: Array, sp: Array, sh: Array
) -> Array:
    """World positions ``(T, K, 3)`` of the kept joints (decode + forward kinematics)."""
    m = fm.decode(Y, sp, sh)
    k = list(keep)
    lp = None if m.local_positions is None else m.local_positions[:, k]
    return fk_positions(sub, m.root_positions, m.rotations[:, k], lp)


class Colouring(eqx.Module):
    """Channels grouped so that one tangent carries several Jacobian columns (static).

    Two channels may share a tangent when no kept joint's position depends on both (say the
    left knee and the right elbow): the joint positions a tangent moves then split by joint
    into the channels' columns.

    Attributes:
        colour: ``(D,)`` the tangent of each channel.
        support: ``(D, K)`` 1 where the channel may move the kept joint (its descendants).
        n_colours: number of tangents.
    """

    colour: tuple[int, ...] = eqx.field(static=True)
    support: tuple[tuple[bool, ...], ...] = eqx.field(static=True)
    n_colours: int = eqx.field(static=True)


def channel_colouring(fm: FeatureMap, keep: tuple[int, ...]) -> Colouring:
    """Greedy colouring of the observation channels for :func:`frame_jacobians`.

    A channel named ``joint.*`` rotates that joint, so it moves the kept joints below it (and,
    to be safe, the joint itself); any other channel (``root.*``, or a name that is not a
    joint's) is taken to move every kept joint and gets a tangent of its own. Channels are
    placed, most far-reaching first, in the first colour none of whose channels moves a joint
    they move.

    Args:
        fm: the feature map (its skeleton and channel names).
        keep: the kept joints (skeleton indices, in the order of the positions' axis 1).

    Returns:
        :class:`Colouring`.
    """
    sk = fm.skeleton
    parents = list(sk.parents)
    K = len(keep)

    def below(j: int) -> np.ndarray:
        out = np.zeros(K, bool)
        for i, k in enumerate(keep):
            a = k
            while a >= 0 and a != j:
                a = parents[a]
            out[i] = a == j
        return out

    names = fm.active_names
    support = np.ones((len(names), K), bool)
    for c, n in enumerate(names):
        joint = n.split(".", 1)[0]
        if joint != "root" and joint in sk.names and sk.index(joint) != 0:
            support[c] = below(sk.index(joint))
    colour = np.zeros(len(names), np.int32)
    used: list[np.ndarray] = []
    for c in np.argsort(-support.sum(axis=1), kind="stable"):
        for i, u in enumerate(used):
            if not np.any(u & support[c]):
                colour[c] = i
                used[i] = u | support[c]
                break
        else:
            colour[c] = len(used)
            used.append(support[c].copy())
    return Colouring(
        colour=tuple(int(c) for c in colour),
        support=tuple(tuple(bool(b) for b in row) for row in support),
        n_colours=len(used),
    )


def frame_jacobians(
    fn, Y: Array, free_ch: Array, colouring: Colouring | None = None
) -> tuple[Array, Array]:
    """``P = fn(Y)`` ``(T, K, 3)`` and its per-frame Jacobians ``(T, K, 3, D)`` with respect
    to the free channels (held channels' columns are zero).

    Valid when frames do not interact through the free channels (module notes). With a
    ``colouring`` one Jacobian-vector product serves every channel of a colour, and each
    channel's column is its colour's tangent restricted to the joints it moves.
    """
    D = Y.shape[1]
    P, lin = jax.linearize(fn, Y)
    eye = jnp.eye(D, dtype=Y.dtype) * free_ch[None, :]
    if colouring is None:
        cols = jax.vmap(lambda e: lin(jnp.broadcast_to(e, Y.shape)))(eye)  # (D, T, K, 3)
        return P, jnp.moveaxis(cols, 0, -1)
    colour = np.asarray(colouring.colour)
    groups = jnp.asarray(np.eye(colouring.n_colours)[colour].T, Y.dtype)  # (C, D)
    tang = groups * free_ch[None, :]
    cols = jax.vmap(lambda e: lin(jnp.broadcast_to(e, Y.shape)))(tang)  # (C, T, K, 3)
    sup = jnp.asarray(np.asarray(colouring.support), Y.dtype) * free_ch[:, None]  # (D, K)
    J = cols[colour] * sup[:, None, :, None]  # (D, T, K, 3)
    return P, jnp.moveaxis(J, 0, -1)


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
    xtol: float = 1e-4,
    colouring: Colouring | None = None,
    chord: bool = True,
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
        rtol: relative change of the cost below which a round stops.
        xtol: largest step (z-scored units) below which a round stops.
        colouring: channels that share a Jacobian-vector product (:func:`channel_colouring`);
            ``None``: one product per channel.
        chord: reuse the last factorisation for later steps (module notes) until a step
            gains less than half of what its model promised; ``False``: every step is a
            fresh Gauss–Newton step (for problems far from linear, e.g. cleaning, whose
            active sets change from step to step).

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

    def cost_of(z: Array, shift: Array) -> Array:
        P = fn(edited(z)) + offset(z)
        r = point_res(P, shift)
        low = jnp.maximum(lower - P[..., up], 0.0)
        hz = _band_quad(bands, anchor, jnp.where(held[:, None], delta, z * var_ch))
        return 0.5 * (hz + jnp.sum(w2 * r * r) + jnp.sum((lw * low) ** 2))

    def gn_step(z: Array, shift: Array, active: Array):
        P, J = frame_jacobians(fn, edited(z), free_ch, colouring)
        P = P + offset(z)
        if move_root is not None:
            (c0, c1), (h0, h1) = move_root
            J = J.at[:, :, h0, c0].set(1.0).at[:, :, h1, c1].set(1.0)
        r = point_res(P, shift)
        Jp = J[points.frame, points.slot]  # (P, 3, D)
        zp = z[points.frame]
        # Σ Jᵀ W² J and Σ Jᵀ W² (J z − r), scattered to the frames
        A_p = jnp.einsum("pcd,pc,pce->pde", Jp, w2, Jp)
        b_p = jnp.einsum("pcd,pc,pc->pd", Jp, w2, jnp.einsum("pce,pe->pc", Jp, zp) - r)
        A = jnp.zeros((T, D, D), dt).at[points.frame].add(A_p)
        b = jnp.zeros((T, D), dt).at[points.frame].add(b_p)
        h = P[..., up]
        act = (h < lower).astype(dt)  # (T, K): one-sided, the active set at z
        Ju = J[:, :, up, :] * (lw * act)[..., None]  # (T, K, D)
        ru = lw * act * (h - jnp.where(act > 0, lower, h))
        A = A + jnp.einsum("tkd,tke->tde", Ju, Ju)
        b = b + jnp.einsum("tkd,tk->td", Ju, jnp.einsum("tke,te->tk", Ju, z) - ru)
        H0, H1, H2 = bands
        A = A * (var_ch[:, None] * var_ch[None, :])
        z_star, fac = _normal_solve(H0 + A, H1, H2, anchor, held, delta, -(b * var_ch), active)
        return z_star - delta, fac

    keep_rows = (~held)[:, None].astype(dt) * var_ch[None, :]
    grad_of = jax.grad(cost_of)

    def chord_step(z: Array, g: Array, fac: BlockPentaCholesky) -> Array:
        """``z − B⁻¹ g`` with the factor of an earlier step's normal matrix ``B``."""
        return z - block_penta_solve(fac, g) * keep_rows

    def one_round(carry, _):
        z, shift, _conv, steps, fok, fac = carry

        def cond(s):
            _z, _c, k, done, _ok, _fac, _fresh = s
            return (k < max_steps) & ~done

        def body(s):
            z, c, k, done, ok, fac, fresh = s
            running = (k < max_steps) & ~done
            zero = jnp.zeros((), dt)
            if chord:
                full = fresh

                def full_branch(_):
                    return (*gn_step(z, shift, running & full), zero)

                def chord_branch(_):
                    g = grad_of(z, shift) * keep_rows
                    z_c = chord_step(z, g, fac)
                    return z_c, fac, -0.5 * jnp.sum((z_c - z) * g)  # the model's ½ gᵀB₀⁻¹g

                z_gn, fac, pred = lax.cond(full, full_branch, chord_branch, None)
            else:
                full, pred = jnp.asarray(True), zero
                z_gn, fac = gn_step(z, shift, running)
            dz = z_gn - z

            def worse(b):
                _zt, ct, i = b
                return ~((ct < c) & jnp.isfinite(ct)) & (i < 5)

            def halve(b):
                _zt, _ct, i = b
                zt = z + (0.5 ** (i + 1)) * dz
                return zt, cost_of(zt, shift), i + 1

            c_gn = cost_of(z_gn, shift)
            zt, ct, i = lax.while_loop(worse, halve, (z_gn, c_gn, 0))
            better = (ct < c) & jnp.isfinite(ct)
            z_new, c_new = jnp.where(better, zt, z), jnp.where(better, ct, c)
            step = jnp.max(jnp.abs(z_new - z))
            stop = (c - c_new <= rtol * jnp.maximum(c, 1e-30)) | (step <= xtol)
            # a chord step that needed halving or gained less than half of what its model
            # promised (pred) is poor: the next step refactors, and a poor chord step never
            # ends the round (for a fresh step ``poor`` is not used)
            poor = (i > 0) | ~better | (c - c_new < 0.5 * pred)
            done = stop & (full | ~poor)
            return z_new, c_new, k + 1, done, ok & fac.ok, fac, ~full & poor

        cost0 = cost_of(z, shift)
        k0 = jnp.asarray(0, jnp.int32)
        init = (z, cost0, k0, jnp.asarray(False), jnp.asarray(True), fac, steps == 0)
        z, c, k, done, ok, fac, _f = lax.while_loop(cond, body, init)
        P = fn(edited(z)) + offset(z)
        err = P[points.frame, points.slot] - points.target
        new_shift = shift - jnp.where(points.exact[:, None], err, 0.0)
        return (z, new_shift, done, steps + k, fok & ok, fac), c

    shift0 = jnp.zeros_like(points.target)
    init = (jnp.zeros((T, D), dt), shift0, jnp.asarray(False), jnp.asarray(0, jnp.int32))
    init = (*init, jnp.asarray(True), _no_factor(T, D, dt))
    (z, _shift, conv, steps, fok, _fac), costs = lax.scan(one_round, init, None, length=rounds)
    z = jnp.where(held[:, None], delta, z * var_ch)
    return BandedSolve(z=z, converged=conv & fok, steps=steps, cost=costs[-1], factor_ok=fok)


def _no_factor(T: int, D: int, dt) -> BlockPentaCholesky:
    """A zero factor (the loop carry before the first factorisation, a skipped one)."""
    z = jnp.zeros((T, D, D), dt)
    return BlockPentaCholesky(
        Linv=z, L1=z, L2=z, ok=jnp.asarray(True), first_bad=jnp.asarray(-1, jnp.int32)
    )


@jax.custom_batching.custom_vmap
def _normal_solve(H0, H1, H2, anchor, held, delta, linear, active):
    """The Gauss–Newton normal equations' solution and their factor (its ``ok``: the status).

    The matrix is ``H + diag(anchor²)`` over the free frames, with an identity block at each
    held frame, whose displacement is ``delta``; the right-hand side is ``−(linear + H δ)``.
    Factorised with one frame per block (:func:`~mtex_jax.linalg.block_penta_cholesky`).

    ``active`` (a bool) says whether the caller will use the result: a motion of a ``vmap``
    batch that has already stopped (or takes a chord step) still runs the loop body until
    every motion has, and its factorisation is skipped (zeros returned). Without ``vmap`` the
    solve always runs.

    Under ``vmap`` the motions are factorised one after the other (``lax.map``, with
    ``lax.cond`` on ``active``): a batched block Cholesky hands LAPACK a batch of triangular
    solves, which XLA's CPU backend runs orders of magnitude slower (measured with the
    frame-pair factor's ``108 × 108`` pivot blocks: an inverse 0.09 ms alone, 21 ms in a
    batch of 4; a batch of 4 motions of 600 frames did not finish in 5 minutes, one took
    0.13 s); everything else in the solve stays batched."""
    del active
    D = H0.shape[-1]
    dt = H0.dtype
    f = (~held).astype(dt)
    b = linear + band_matvec((H0, H1, H2), delta)
    A0 = jnp.where(held[:, None, None], jnp.eye(D, dtype=dt), sym(H0) + jnp.diag(anchor**2))
    A1 = H1 * (f * jnp.concatenate([jnp.zeros((1,), dt), f[:-1]]))[:, None, None]
    A2 = H2 * (f * jnp.concatenate([jnp.zeros((2,), dt), f[:-2]]))[:, None, None]
    fac = block_penta_cholesky(A0, A1, A2)
    z_star = block_penta_solve(fac, -b * f[:, None]) * f[:, None]
    return z_star + delta, fac


@_normal_solve.def_vmap
def _normal_solve_vmap(axis_size: int, in_batched, *args):
    full = tuple(
        a if b else jnp.broadcast_to(a, (axis_size, *jnp.shape(a)))
        for a, b in zip(args, in_batched, strict=True)
    )

    def one(xs):
        *a, active = xs
        T, D = a[-1].shape
        skip = lambda *_: (jnp.zeros_like(a[-1]), _no_factor(T, D, a[-1].dtype))
        return lax.cond(active, lambda *b: _normal_solve(*b, active), skip, *a)

    out = lax.map(one, full)
    return out, jax.tree.map(lambda _: True, out)


def _band_quad(bands, anchor: Array, v: Array) -> Array:
    """``vᵀ (H + diag(anchor²)) v`` for the symmetric block band."""
    H0, H1, H2 = bands
    q = jnp.einsum("td,tde,te->", v, H0, v) + jnp.sum((anchor * v) ** 2)
    q = q + 2.0 * jnp.einsum("td,tde,te->", v[1:], H1[1:], v[:-1])
    return q + 2.0 * jnp.einsum("td,tde,te->", v[2:], H2[2:], v[:-2])


def root_free_channels(fm: FeatureMap) -> np.ndarray:
    """``(D,)`` 1 for every channel but the root's integrated ones (``root.d*``)."""
    return np.array([0.0 if n.startswith("root.d") else 1.0 for n in fm.active_names])
