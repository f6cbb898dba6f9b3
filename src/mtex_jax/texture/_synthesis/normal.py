"""The constrained least squares of per-texton synthesis (MT Eq. 6-9, design §5) as a block-banded
normal system: its equations, assembly and solve."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float

from ...linalg import pair_blocks, tridiag_solve_rows
from .._texton.texton import Texton

# --------------------------------------------------------------------------------------------
# constrained
# --------------------------------------------------------------------------------------------


class NormalSystem(eqx.Module):
    """Masked normal equations of constrained synthesis (block bandwidth 2 in frames).

    Attributes:
        diag: ``(l, k, k)`` blocks ``J'_ii`` (identity at held frames).
        off1: ``(l−1, k, k)`` blocks ``J'_{i+1,i}`` (zero where a held frame is involved).
        off2: ``(l−2, k, k)`` blocks ``J'_{i+2,i}``.
        rhs: ``(l, k)``: ``(Gᵀ c − J x_F)_i`` at free frames, the held state at held frames.
        held: ``(l,)`` bool, held frames.
        x_held: ``(l, k)`` held states (zero at free frames).
    """

    diag: Float[Array, "l k k"]
    off1: Float[Array, "l1 k k"]
    off2: Float[Array, "l2 k k"]
    rhs: Float[Array, "l k"]
    held: Bool[Array, " l"]
    x_held: Float[Array, "l k"]


class _Equations(eqx.Module):
    """The least-squares problem of constrained synthesis before blocking (internal).

    ``tail`` (open end only, ``end=None`` with edits): the frames after the last held one.
    They are left out of the least squares (held at 0, their equations dropped: ``eq_on``
    marks the equations kept, ``j = 2 … last held``) and continued by the dynamics
    recursion afterwards (:func:`_continue_tail`).

    ``eq_weight``: the weight of equation ``j`` in the least squares (rows 0 and 1 unused),
    or ``None`` (all 1: the exact conditional sample).
    """

    held: Bool[Array, " l"]
    x_held: Float[Array, "l k"]
    K: Float[Array, "3k 3k"]
    rhs: Float[Array, "l k"]
    tail: Bool[Array, " l"] | None = None
    eq_on: Bool[Array, " l"] | None = None
    eq_weight: Float[Array, " l"] | None = None


def constrained_equations(
    tex: Texton,
    length: int,
    w: Array | None,
    start: Array,
    end: Array | None,
    fixed: tuple[Array, Array] | None,
    weighting: str,
    eq_weight: Array | None = None,
) -> _Equations:
    """Held frames, Gram matrix ``K = [P0, P1, P2]ᵀ[P0, P1, P2]`` and right-hand side.

    See :func:`normal_system` for the equations; ``w`` ``(l−2, k)`` is the noise in state
    units, ``w_j = B v_j``; ``w=None`` leaves the noise out. ``eq_weight`` ``(l,)``: equation
    ``j`` enters the least squares as ``ω_j ‖G_j x − c_j‖²`` (rows 0 and 1 unused; ``None``:
    every ``ω_j = 1``, the exact conditional sample; design §10.11).
    """
    dt = tex.mu.dtype
    k = tex.C.shape[-1]
    eye = jnp.eye(k, dtype=dt)
    proj = lambda y: (y.astype(dt) - tex.mu) @ tex.C
    idx = np.arange(length)
    held = jnp.asarray(idx < 2)
    x_held = jnp.concatenate([proj(start), jnp.zeros((length - 2, k), dt)], axis=0)
    if fixed is not None:
        held = held | fixed[0]
        x_held = jnp.where(fixed[0][:, None], proj(fixed[1]), x_held)
    if end is not None:
        last = idx >= length - 2
        held = held | last
        x_end = jnp.concatenate([jnp.zeros((length - 2, k), dt), proj(end)], axis=0)
        x_held = jnp.where(last[:, None], x_end, x_held)
    tail = eq_on = None
    if end is None and fixed is not None:
        # open end: the equations after the last held frame are square in the frames after
        # it and are met exactly by the dynamics recursion, so they carry no information on
        # the other frames; solving them by least squares would only make the normal matrix
        # of an unstable texton as ill-conditioned as ρ^(2·tail). Drop them, hold the tail.
        last_held = jnp.max(jnp.where(held, idx, 0))
        tail = jnp.asarray(idx) > last_held
        eq_on = (jnp.asarray(idx) >= 2) & ~tail
        held = held | tail

    whitened = weighting == "whitened"
    W = jsl.solve_triangular(tex.B, eye, lower=True) if whitened else eye
    P = jnp.concatenate([W, -W @ tex.A1, -W @ tex.A2], axis=1)  # (k, 3k) = [P0, P1, P2]
    Q = W.T @ P  # the noise enters c_j = W (d + w_j)
    # residual of the equations at the held states, u_j = W d − G_j x̂ (+ noise, below)
    X3 = jnp.concatenate([x_held[2:], x_held[1:-1], x_held[:-2]], axis=1)  # (l−2, 3k)
    U0 = ((W @ tex.d)[None, :] - X3 @ P.T) @ P
    U = U0 if w is None else w.astype(dt) @ Q + U0  # (l−2, 3k): [P0ᵀu_j, P1ᵀu_j, P2ᵀu_j]
    if eq_on is not None:
        U = jnp.where(eq_on[2:, None], U, 0.0)
    if eq_weight is not None:
        U = U * eq_weight[2:, None].astype(dt)
    h = (
        jnp.pad(U[:, :k], ((2, 0), (0, 0)))
        + jnp.pad(U[:, k : 2 * k], ((1, 1), (0, 0)))
        + jnp.pad(U[:, 2 * k :], ((0, 2), (0, 0)))
    )
    rhs = jnp.where(held[:, None], x_held, h)
    return _Equations(
        held=held, x_held=x_held, K=P.T @ P, rhs=rhs, tail=tail, eq_on=eq_on, eq_weight=eq_weight
    )


def _frame_blocks(
    K: Array,
    held: Array,
    n: int,
    eq_on: Array | None = None,
    eq_weight: Array | None = None,
) -> tuple[Array, Array, Array]:
    """Masked normal-matrix blocks of ``n`` frames: ``(n, k, k)``, ``(n−1, …)``, ``(n−2, …)``.

    ``J_ii = Σ_s [eq i+s exists] P_sᵀ P_s``, ``J_{i+1,i} = [eq i+1] P0ᵀ P1 + [eq i+2] P1ᵀ P2``,
    ``J_{i+2,i} = [eq i+2] P0ᵀ P2`` (equations ``j = 2 … l−1`` exist, ``l = len(held)``, or
    those marked by ``eq_on`` ``(l,)``), each times its weight ``ω`` (``eq_weight`` ``(l,)``,
    or 1); identity rows and columns at held frames. ``n ≥ l`` pads with held frames.
    """
    k = K.shape[0] // 3
    dt = K.dtype
    length = held.shape[0]
    if n > length:
        held = jnp.concatenate([held, jnp.ones((n - length,), bool)])
    Kb = lambda a, b: K[a * k : (a + 1) * k, b * k : (b + 1) * k]
    idx = np.arange(n + 2)
    eq: Any = ((idx >= 2) & (idx < length)).astype(np.float64)  # equation i exists (static)
    if eq_on is not None:
        eq = jnp.pad(eq_on.astype(dt), (0, n + 2 - length))
    if eq_weight is not None:
        eq = eq * jnp.pad(eq_weight.astype(dt), (0, n + 2 - length))
    w = lambda m: jnp.asarray(m, dt)[:, None, None]
    diag = w(eq[:n]) * Kb(0, 0) + w(eq[1 : n + 1]) * Kb(1, 1) + w(eq[2 : n + 2]) * Kb(2, 2)
    off1 = w(eq[1:n]) * Kb(0, 1) + w(eq[2 : n + 1]) * Kb(1, 2)  # block (i+1, i)
    off2 = w(eq[2:n]) * Kb(0, 2)  # block (i+2, i)
    diag = jnp.where(held[:, None, None], jnp.eye(k, dtype=dt), diag)
    off1 = jnp.where((held[1:] | held[:-1])[:, None, None], 0.0, off1)
    off2 = jnp.where((held[2:] | held[:-2])[:, None, None], 0.0, off2)
    return diag, off1, off2


def normal_system(
    tex: Texton,
    v: Array,
    start: Array,
    end: Array | None,
    fixed: tuple[Array, Array] | None,
    weighting: str,
) -> NormalSystem:
    """Assemble the masked normal equations ``J' x = g'`` of constrained synthesis.

    Equation ``j = 2 … l−1`` reads ``G_j x = P0 x_j + P1 x_{j−1} + P2 x_{j−2} = c_j`` with
    ``[P0, P1, P2] = W [I, −A1, −A2]`` and ``c_j = W(d + B v_j)``. With ``x̂`` the held states
    (zero at free frames) the right-hand side at free frames is
    ``g_i = (Gᵀ u)_i = P0ᵀ u_i + P1ᵀ u_{i+1} + P2ᵀ u_{i+2}``, ``u_j = c_j − G_j x̂``
    (``= Gᵀ c − J x̂``, the held states moved to the right), computed as one GEMM
    ``U = w Q + U₀`` with the noise in state units ``w_j = B v_j`` and ``Q = Wᵀ [P0, P1, P2]``,
    and three shifted slices of ``U``; only this GEMM depends on the noise.
    The blocks are ``J_ii = Σ_s [eq i+s exists] P_sᵀ P_s``, ``J_{i+1,i} = P0ᵀ P1 + P1ᵀ P2``
    (where the equations exist), ``J_{i+2,i} = P0ᵀ P2``; rows and columns of held frames are
    replaced by the identity (``g_i = x̂_i`` there).

    Args:
        tex: the texton.
        v: ``(l−2, k)`` noise ``v_j``, ``j = 2 … l−1``.
        start: ``(2, D)`` first two poses.
        end: ``(2, D)`` last two poses or ``None``.
        fixed: ``(mask (l,), poses (l, D))`` or ``None``.
        weighting: ``"whitened"`` (``W = B⁻¹``) or ``"paper"`` (``W = I``).

    Returns:
        The masked system.
    """
    w = v.astype(tex.mu.dtype) @ tex.B.T
    eqs = constrained_equations(tex, v.shape[0] + 2, w, start, end, fixed, weighting)
    diag, off1, off2 = _frame_blocks(eqs.K, eqs.held, eqs.held.shape[0], eqs.eq_on)
    return NormalSystem(
        diag=diag, off1=off1, off2=off2, rhs=eqs.rhs, held=eqs.held, x_held=eqs.x_held
    )


def _continue_tail(tex: Texton, x: Array, w: Array, tail: Array) -> Array:
    """Frames with ``tail[t]`` follow ``x_t = A1 x_{t−1} + A2 x_{t−2} + d + w_t``.

    ``x`` ``(l, k)``, ``w`` ``(l−2, k)`` (``w_t = B v_t`` is row ``t−2``); the other frames
    are kept.
    """

    def step(carry: tuple[Array, Array], inp: tuple[Array, Array, Array]) -> Any:
        xm1, xm2 = carry
        xj, vj, tj = inp
        xj = jnp.where(tj, tex.A1 @ xm1 + tex.A2 @ xm2 + tex.d + vj, xj)
        return (xj, xm1), xj

    _, rest = lax.scan(step, (x[1], x[0]), (x[2:], w.astype(x.dtype), tail[2:]))
    return jnp.concatenate([x[:2], rest], axis=0)


def solve_constrained(tex: Texton, eqs: _Equations, w: Array | None = None) -> tuple[Array, Array]:
    """Banded solve of the masked normal equations: states ``(l, k)`` and the status flag.

    An open tail (``eqs.tail``) is then continued by the dynamics with the noise ``w``
    (state units, ``w_j = B v_j``).
    """
    length, k = eqs.rhs.shape
    nb = (length + 1) // 2
    diag, off1, off2 = _frame_blocks(eqs.K, eqs.held, 2 * nb, eqs.eq_on, eqs.eq_weight)
    pdiag, psub = pair_blocks(diag, off1, off2)
    r = jnp.pad(eqs.rhs, ((0, 2 * nb - length), (0, 0))).reshape(nb, 1, 2 * k)
    x, ok, _ = tridiag_solve_rows(pdiag, psub, r)
    x = jnp.where(eqs.held[:, None], eqs.x_held, x.reshape(2 * nb, k)[:length])
    if eqs.tail is not None:
        x = _continue_tail(
            tex, x, jnp.zeros((length - 2, k), x.dtype) if w is None else w, eqs.tail
        )
    return x, ok


def observe(tex: Texton, x: Array, ok: Array, check: bool = True) -> Array:
    """``μ + C x_t`` as one GEMM ``[x, 1] [Cᵀ; μ]``; a failed solve or non-finite states
    (e.g. a texton with NaN in ``d``) raise (``eqx.error_if``), or with ``check=False`` give
    NaN frames (no host callback in the program, so the persistent compilation cache keeps
    it; the caller checks the result on the host)."""
    proj = jnp.concatenate([tex.C.T, tex.mu[None, :]], axis=0)  # (k+1, D)
    if check:
        proj = eqx.error_if(
            proj,
            ~(ok & jnp.all(jnp.isfinite(x))),
            "synthesize_texton: normal matrix not positive definite or non-finite states"
            " (non-finite or singular texton parameters?)",
        )
    x1 = jnp.concatenate([x, jnp.ones((x.shape[0], 1), x.dtype)], axis=1)
    y = x1 @ proj
    return y if check else jnp.where(ok, y, jnp.nan)


def transition_weights(length: int, decay: Array, at: Array, dtype) -> Array:
    """The weights ``(length,)`` of a texton's least-squares equations when it bends towards
    the frames held from row ``at`` on near its end (design §10.11): equation ``j`` weighted
    ``ω_j = exp(decay · max(at − j, 0))``, capped at ``ε^{-1/2}`` of the dtype."""
    cap = 0.5 * float(np.log(1.0 / np.finfo(dtype).eps))
    lag = jnp.maximum(at - jnp.arange(length), 0)
    return jnp.exp(jnp.minimum(jnp.asarray(decay).astype(dtype) * lag, cap))
