"""Per-texton synthesis: noise-driven and constrained (SPEC §5; MT §5.4, Eq. 6–9, Fig. 4, 10, 11).

For a texton (SPEC §2) and a length ``l``, the states ``x_0 … x_{l−1}`` (0-based) obey the
``l − 2`` dynamics equations

.. code-block:: text

    e_j(x) = x_j − A1 x_{j−1} − A2 x_{j−2} − d = B v_j,     j = 2 … l−1,   v_j ~ N(0, I_k).

Constrained synthesis holds a set ``F`` of frames (the first two, the last two, and any edited
frames) at given states and solves the over-determined system in the free states in the
least-squares sense

.. code-block:: text

    min_{x_free}  Σ_j ‖ W (e_j(x) − B v_j) ‖²,     W = B⁻¹ ("whitened") or I ("paper").

With ``W = B⁻¹`` the objective is ``Σ_j ‖B⁻¹ e_j − v_j‖²``; with ``v = 0`` its minimiser is the
mean of the LDS conditioned on ``x_F`` and with ``v ~ N(0, I)`` it is an exact sample of that
conditional (perturb-and-MAP: the minimiser is ``J⁻¹ Gᵀ(c + v)``, whose covariance is
``J⁻¹ Gᵀ G J⁻¹ = J⁻¹``, the conditional covariance). The normal matrix ``J = Σ_j G_jᵀ G_j``
is block pentadiagonal in frames; fixed frames are eliminated by masks (their rows and columns
replaced by the identity, their contribution moved to the right-hand side) so that every edit
has the same static shapes, and the system is solved by :func:`mtex_jax._linalg` in
``O(l·k³)``.

With both ends held and no edits (the case of a texton between two key poses) the same
solution comes from the dynamics recursion itself (:func:`_bridge`): the free motion from the
start frames plus the control, found from a ``2k × 2k`` system, that brings it to the end
frames; ``O(l·k²)`` per sample, 3–4× faster than the banded solve for one texton.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jax import lax
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Bool, Float

from ._linalg import _pair_blocks, _sym, _tridiag_solve_rows
from ._texton import Texton

__all__ = ["synthesize_texton"]

Weighting = Literal["whitened", "paper"]


def _check_frames(name: str, y: Any, shape: tuple[int, ...]) -> Array:
    if y is None:
        raise ValueError(f"{name} must be an array of shape {shape}, got None")
    y = jnp.asarray(y)
    if tuple(y.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(y.shape)}")
    if not jnp.issubdtype(y.dtype, jnp.floating):
        y = y.astype(jnp.result_type(float))
    if not isinstance(y, Tracer) and not np.isfinite(np.asarray(y)).all():
        raise ValueError(f"{name} contains NaN or inf")
    return y


def synthesize_texton(
    key: Array | None,
    texton: Texton,
    length: int,
    start: Float[ArrayLike, "2 D"],
    end: Float[ArrayLike, "2 D"] | None = None,
    fixed: tuple[Bool[ArrayLike, " l"], Float[ArrayLike, "l D"]] | None = None,
    weighting: Weighting = "whitened",
) -> Float[Array, "l D"]:
    """Synthesise ``length`` frames from one texton, noise-driven or constrained (MT §5.4).

    Key poses are projected to states with ``x = Cᵀ(y − μ)``; the result is ``μ + C x_t``.

    * ``end is None and fixed is None``: noise-driven (MT Fig. 4):
      ``x_t = A1 x_{t−1} + A2 x_{t−2} + d + B v_t`` from the two start states.
    * otherwise constrained (MT Eq. 6–9): the first two frames, the last two (if ``end`` is
      given) and every frame with ``fixed[0][t]`` true (MT Fig. 11, editing; pose
      ``fixed[1][t]``) are held; the free states minimise
      ``Σ_{j=2}^{l−1} ‖W(x_j − A1 x_{j−1} − A2 x_{j−2} − d − B v_j)‖²`` with ``W = B⁻¹``
      (``weighting="whitened"``, an exact sample of the LDS conditioned on the held states,
      or its mean when ``key is None``) or ``W = I`` (``weighting="paper"``, MT Eq. 9). With
      ``end=None`` the frames after the last held one follow the dynamics with the same
      noise, i.e. noise-driven continuation (computed by the recursion: they and their
      equations are not part of the least squares, which for an unstable texton would be
      as ill-conditioned as ``ρ^(2·tail)``).

    How the key is used: in every mode it gives the noise of the dynamics equations,
    ``v`` ``(l−2, k)`` standard normal, by the Box–Muller transform of
    ``jax.random.uniform(key, (2, ⌈(l−2)k/2⌉))`` (cheaper than ``jax.random.normal`` in
    float64 on CPU; cosines first, then sines, in row-major order). The
    constrained sample is the perturb-and-MAP solution of the equations with that noise: with
    ``W = B⁻¹`` an exact sample of the LDS conditioned on the held frames (the mean when
    ``key is None``), and with the same key the noise-driven motion and the constrained one
    share their noise (the constrained motion is the noise-driven one plus the control that
    brings it to the end frames, see :func:`_bridge`).

    How it is computed. Both ends held and no edits (the usual constrained case,
    ``length ≥ 6``): from the dynamics recursion and a ``2k × 2k`` system (:func:`_bridge`,
    ``O(l·k²)`` per sample after ``O(log l)`` products of ``2k × 2k`` matrices), unless the
    texton amplifies over the segment so much that the recursion would lose accuracy; then,
    and with edits or an open end, the masked normal equations and the banded solver
    (``O(l·k³)``). Both give the same least-squares solution (to rounding; tested against
    dense least squares at 1e-9 relative). Under
    ``vmap`` over keys everything that does not depend on the noise is computed once.

    ``length`` is static; the mask and poses are arrays, so different edits do not recompile.
    Any ``length ≥ 4`` (``≥ 2`` without ``end``) works: the same texton extrapolates (MT Fig. 10).
    ``vmap`` over ``key`` (or over the poses) works.

    Args:
        texton: a single :class:`~mtex_jax._texton.Texton` (``D``, ``k``).
        key: JAX PRNG key (see above); ``None`` for zero noise (the conditional mean).
        length: number of frames ``l``.
        start: ``(2, D)`` first two frames.
        end: ``(2, D)`` last two frames, or ``None``.
        fixed: ``(mask (l,) bool, poses (l, D))`` extra held frames, or ``None``.
        weighting: ``"whitened"`` (default) or ``"paper"``.

    Returns:
        ``(l, D)`` observations ``μ + C x_t``; held frames equal ``μ + C Cᵀ(y − μ)`` of the
        given poses (the poses themselves when they lie in the texton's subspace).

    Raises:
        ValueError: bad shapes, non-finite poses, unknown weighting or too short ``length``.
    """
    if not isinstance(texton, Texton) or texton.is_stacked:
        raise ValueError("texton must be a single (unstacked) Texton")
    if weighting not in ("whitened", "paper"):
        raise ValueError(f"weighting must be 'whitened' or 'paper', got {weighting!r}")
    if isinstance(length, bool) or not isinstance(length, int | np.integer):
        raise ValueError(f"length must be an int, got {length!r}")
    length = int(length)
    min_len = 2 if end is None else 4
    if length < min_len:
        raise ValueError(f"length must be >= {min_len}, got {length}")
    D = texton.obs_dim
    start_a = _check_frames("start", start, (2, D))
    end_a = None if end is None else _check_frames("end", end, (2, D))
    fixed_a: tuple[Array, Array] | None = None
    if fixed is not None:
        if not isinstance(fixed, tuple | list) or len(fixed) != 2:
            raise ValueError("fixed must be a pair (mask (length,) bool, poses (length, D))")
        mask = jnp.asarray(fixed[0])
        if tuple(mask.shape) != (length,) or mask.dtype != jnp.bool_:
            raise ValueError(
                f"fixed mask must be bool of shape ({length},), got {mask.dtype}"
                f" {tuple(mask.shape)}"
            )
        poses = _check_frames("fixed poses", fixed[1], (length, D))
        fixed_a = (mask, poses)
    # the noise is drawn inside the jitted core: one dispatch per call, not two
    if end_a is None and fixed_a is None:
        return _noise_driven_key_jit(texton, key, length, start_a)
    return _constrained_key_jit(texton, key, length, start_a, end_a, fixed_a, weighting)


def _sincos_turn(u: Array) -> tuple[Array, Array]:
    """``(cos 2πu, sin 2πu)`` for ``u ∈ [0, 1)``: quadrant from ``⌊4u⌋``, then Taylor
    polynomials of degree 24/25 on ``[0, π/2)`` (truncation below 1e-18; measured error
    ≤ 8e-16 in float64 against numpy). On CPU about 8× cheaper than ``jnp.cos`` and
    ``jnp.sin`` in float64, whose general range reduction is the cost of Box–Muller.
    """
    q4 = 4 * u
    q = jnp.floor(q4)
    phi = (q4 - q) * (np.pi / 2)
    x2 = phi * phi
    sp = jnp.zeros_like(phi)
    cp = jnp.zeros_like(phi)
    for j in range(12, -1, -1):  # Horner in φ²: Σ (−1)^j φ^{2j+1}/(2j+1)!, Σ (−1)^j φ^{2j}/(2j)!
        sp = sp * x2 + (-1) ** j / math.factorial(2 * j + 1)
        cp = cp * x2 + (-1) ** j / math.factorial(2 * j)
    sp = phi * sp
    quad = q.astype(jnp.int32) & 3  # rotate by quad · 90°
    cos = jnp.where(quad == 0, cp, jnp.where(quad == 1, -sp, jnp.where(quad == 2, -cp, sp)))
    sin = jnp.where(quad == 0, sp, jnp.where(quad == 1, cp, jnp.where(quad == 2, -sp, -cp)))
    return cos, sin


def _standard_normal(key: Array, shape: tuple[int, ...], dtype: Any) -> Array:
    """Standard normal variates from ``key`` by the Box–Muller transform.

    ``z = √(−2 log(1 − u₁)) (cos 2πu₂, sin 2πu₂)`` for ``u = jax.random.uniform(key, (2, h))``
    (``h = ⌈size/2⌉``; the cosines first, then the sines, truncated to ``size``;
    :func:`_sincos_turn`). Exactly ``N(0, 1)`` up to the resolution of the uniforms; on CPU
    about a third of the cost of ``jax.random.normal`` in float64, whose inverse error
    function dominated the time of a synthesis.
    """
    size = int(np.prod(shape))
    u = jax.random.uniform(key, (2, (size + 1) // 2), dtype)
    r = jnp.sqrt(-2.0 * jnp.log1p(-u[0]))  # 1 − u ∈ (0, 1]
    cos, sin = _sincos_turn(u[1])
    return jnp.concatenate([r * cos, r * sin])[:size].reshape(shape)


def _draw_noise(tex: Texton, key: Array | None, length: int) -> Array:
    """``v_j ~ N(0, I_k)``, ``j = 2 … l−1``: ``(l−2, k)`` from :func:`_standard_normal`; 0 if
    no key."""
    shape = (length - 2, tex.C.shape[-1])
    if key is None:
        return jnp.zeros(shape, tex.mu.dtype)
    return _standard_normal(key, shape, tex.mu.dtype)


# --------------------------------------------------------------------------------------------
# noise-driven
# --------------------------------------------------------------------------------------------


def _noise_driven(tex: Texton, v: Array, start: Array) -> Array:
    dt = tex.mu.dtype
    x01 = (start.astype(dt) - tex.mu) @ tex.C

    def step(carry: tuple[Array, Array], vj: Array) -> tuple[tuple[Array, Array], Array]:
        xm1, xm2 = carry
        x = tex.A1 @ xm1 + tex.A2 @ xm2 + tex.d + tex.B @ vj
        return (x, xm1), x

    _, rest = lax.scan(step, (x01[1], x01[0]), v)
    states = jnp.concatenate([x01, rest], axis=0)
    return tex.mu + states @ tex.C.T


def _noise_driven_key(tex: Texton, key: Array | None, length: int, start: Array) -> Array:
    return _noise_driven(tex, _draw_noise(tex, key, length), start)


_noise_driven_key_jit = eqx.filter_jit(_noise_driven_key)


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
    """

    held: Bool[Array, " l"]
    x_held: Float[Array, "l k"]
    K: Float[Array, "3k 3k"]
    rhs: Float[Array, "l k"]
    tail: Bool[Array, " l"] | None = None
    eq_on: Bool[Array, " l"] | None = None


def _equations(
    tex: Texton,
    length: int,
    w: Array | None,
    start: Array,
    end: Array | None,
    fixed: tuple[Array, Array] | None,
    weighting: str,
) -> _Equations:
    """Held frames, Gram matrix ``K = [P0, P1, P2]ᵀ[P0, P1, P2]`` and right-hand side.

    See :func:`_normal_system` for the equations; ``w`` ``(l−2, k)`` is the noise in state
    units, ``w_j = B v_j``; ``w=None`` leaves the noise out.
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
    h = (
        jnp.pad(U[:, :k], ((2, 0), (0, 0)))
        + jnp.pad(U[:, k : 2 * k], ((1, 1), (0, 0)))
        + jnp.pad(U[:, 2 * k :], ((0, 2), (0, 0)))
    )
    rhs = jnp.where(held[:, None], x_held, h)
    return _Equations(held=held, x_held=x_held, K=P.T @ P, rhs=rhs, tail=tail, eq_on=eq_on)


def _frame_blocks(
    K: Array, held: Array, n: int, eq_on: Array | None = None
) -> tuple[Array, Array, Array]:
    """Masked normal-matrix blocks of ``n`` frames: ``(n, k, k)``, ``(n−1, …)``, ``(n−2, …)``.

    ``J_ii = Σ_s [eq i+s exists] P_sᵀ P_s``, ``J_{i+1,i} = [eq i+1] P0ᵀ P1 + [eq i+2] P1ᵀ P2``,
    ``J_{i+2,i} = [eq i+2] P0ᵀ P2`` (equations ``j = 2 … l−1`` exist, ``l = len(held)``, or
    those marked by ``eq_on`` ``(l,)``); identity rows and columns at held frames. ``n ≥ l``
    pads with held frames.
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
    w = lambda m: jnp.asarray(m, dt)[:, None, None]
    diag = w(eq[:n]) * Kb(0, 0) + w(eq[1 : n + 1]) * Kb(1, 1) + w(eq[2 : n + 2]) * Kb(2, 2)
    off1 = w(eq[1:n]) * Kb(0, 1) + w(eq[2 : n + 1]) * Kb(1, 2)  # block (i+1, i)
    off2 = w(eq[2:n]) * Kb(0, 2)  # block (i+2, i)
    diag = jnp.where(held[:, None, None], jnp.eye(k, dtype=dt), diag)
    off1 = jnp.where((held[1:] | held[:-1])[:, None, None], 0.0, off1)
    off2 = jnp.where((held[2:] | held[:-2])[:, None, None], 0.0, off2)
    return diag, off1, off2


def _normal_system(
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
    eqs = _equations(tex, v.shape[0] + 2, w, start, end, fixed, weighting)
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


def _solve_constrained(tex: Texton, eqs: _Equations, w: Array | None = None) -> tuple[Array, Array]:
    """Banded solve of the masked normal equations: states ``(l, k)`` and the status flag.

    An open tail (``eqs.tail``) is then continued by the dynamics with the noise ``w``
    (state units, ``w_j = B v_j``).
    """
    length, k = eqs.rhs.shape
    nb = (length + 1) // 2
    diag, off1, off2 = _frame_blocks(eqs.K, eqs.held, 2 * nb, eqs.eq_on)
    pdiag, psub = _pair_blocks(diag, off1, off2)
    r = jnp.pad(eqs.rhs, ((0, 2 * nb - length), (0, 0))).reshape(nb, 1, 2 * k)
    x, ok, _ = _tridiag_solve_rows(pdiag, psub, r)
    x = jnp.where(eqs.held[:, None], eqs.x_held, x.reshape(2 * nb, k)[:length])
    if eqs.tail is not None:
        x = _continue_tail(
            tex, x, jnp.zeros((length - 2, k), x.dtype) if w is None else w, eqs.tail
        )
    return x, ok


def _observe(tex: Texton, x: Array, ok: Array) -> Array:
    """``μ + C x_t`` as one GEMM ``[x, 1] [Cᵀ; μ]``; a failed solve or non-finite states
    (e.g. a texton with NaN in ``d``) raise (``eqx.error_if``)."""
    proj = jnp.concatenate([tex.C.T, tex.mu[None, :]], axis=0)  # (k+1, D)
    proj = eqx.error_if(
        proj,
        ~(ok & jnp.all(jnp.isfinite(x))),
        "synthesize_texton: normal matrix not positive definite or non-finite states"
        " (non-finite or singular texton parameters?)",
    )
    x1 = jnp.concatenate([x, jnp.ones((x.shape[0], 1), x.dtype)], axis=1)
    return x1 @ proj


# --------------------------------------------------------------------------------------------
# constrained, both ends held, no edits: the bridge recursion
# --------------------------------------------------------------------------------------------

# frames per step of the blocked forward recursion of the batched bridge
_BRIDGE_BLOCK = 4
# Largest entry of the propagators [I 0] F̃^p (p = 1, 2, 4, …, n) for which the bridge is
# used, by floating-point item size; beyond it (a texton that amplifies over the segment) the
# banded solve is used instead (the same least-squares solution). The bridge's relative error
# grows roughly like eps·growth²: float64 (length 172, k = 15) 1e-13 or less for contracting
# textons, 1.5e-11 at growth 20, 8.6e-8 at 2,600; float32 2.6e-5 at growth 7.7 (the banded
# solve: 7e-6), 8.4e-4 at 40. The textons learned from the CMU salsa clips have growth 4–8 over
# their longest segments (one 31, one 160: that one is solved banded).
_BRIDGE_MAX_GROWTH = {8: 100.0, 4: 10.0}


def _adjoint_rows(Fa: Array, k: int, n: int) -> Array:
    """``V_m = [I_k 0] F̃ᵐ`` for ``m = 1 … n`` ``(n, k, 2k)`` by doubling: one GEMM per round.

    ``V_{m+p} = V_m F̃ᵖ``: with ``V_1 … V_p`` known, ``V_{p+1} … V_{2p}`` is one product of
    the stack with ``F̃ᵖ`` (``⌈log₂ n⌉`` rounds instead of ``n`` dependent products).
    """
    V = Fa[None, :k, :]
    P = Fa
    while V.shape[0] < n:
        c = min(V.shape[0], n - V.shape[0])
        V = jnp.concatenate([V, V[:c] @ P], axis=0)
        if V.shape[0] < n:
            P = P @ P
    return V


def _gramian(Fa: Array, Pm: Array, n: int) -> Array:
    """``X_n = Σ_{m=1}^n (F̃ᵐ)ᵀ Pm F̃ᵐ`` by doubling.

    ``X_{a+b} = X_a + (F̃ᵃ)ᵀ X_b F̃ᵃ``: ``O(log n)`` products of ``2k × 2k`` matrices.
    """
    RF: Array | None = None
    RX: Array | None = None
    PF, PX = Fa, Fa.T @ Pm @ Fa  # F̃¹, X_1
    j = n
    while j:
        if j & 1:
            if RF is None or RX is None:
                RF, RX = PF, PX
            else:
                RX = RX + RF.T @ PX @ RF
                RF = PF @ RF
        j >>= 1
        if j:
            PX = PX + PF.T @ PX @ PF
            PF = PF @ PF
    assert RX is not None
    return RX


def _bridge_usable(A1: Array, A2: Array, n: int) -> Array:
    """Whether the bridge recursion is accurate for this texton over ``n`` free frames.

    The growth ``max |[I 0] F̃ᵖ|`` over ``p = 1, 2, 4, … ≤ n`` and ``p = n`` (a proxy for
    the largest propagator over the segment, from ``O(log n)`` squarings of
    ``F̃ = [[A1ᵀ, A2ᵀ], [I, 0]]``, no derivatives) must be finite and at most
    ``_BRIDGE_MAX_GROWTH`` for the dtype.
    """
    A1, A2 = lax.stop_gradient(A1), lax.stop_gradient(A2)
    k = A1.shape[0]
    eye, zero = jnp.eye(k, dtype=A1.dtype), jnp.zeros((k, k), A1.dtype)
    PF = jnp.block([[A1.T, A2.T], [eye, zero]])
    growth = jnp.max(jnp.abs(PF[:k]))
    RF: Array | None = None
    j = n
    while j:
        if j & 1:
            RF = PF if RF is None else PF @ RF
        j >>= 1
        if j:
            PF = PF @ PF
            growth = jnp.maximum(growth, jnp.max(jnp.abs(PF[:k])))
    assert RF is not None
    growth = jnp.maximum(growth, jnp.max(jnp.abs(RF[:k])))
    limit = _BRIDGE_MAX_GROWTH.get(jnp.dtype(A1.dtype).itemsize, 10.0)
    return jnp.isfinite(growth) & (growth <= limit)


def _recursion(A1: Array, A2: Array, u: Array, reverse: bool = False) -> Array:
    """``x_j = A1 x_{j−1} + A2 x_{j−2} + u_j`` from zeros, ``(n, k)`` (one ``lax.scan``).

    ``reverse``: the adjoint direction, ``x_j = A1 x_{j+1} + A2 x_{j+2} + u_j`` from the end.
    """
    A = jnp.concatenate([A1, A2], axis=1).T  # row form: x = [x_{j−1}, x_{j−2}] Aᵀ + u

    def step(c: Array, uj: Array) -> tuple[Array, Array]:
        x = c @ A + uj
        return jnp.concatenate([x, c[: x.shape[0]]]), x

    k = u.shape[1]
    return lax.scan(step, jnp.zeros(2 * k, u.dtype), u, reverse=reverse)[1]


class _BridgeInputs(eqx.Module):
    """The arrays of :func:`_bridge` (a pytree, so that ``custom_vmap`` sees what is batched)."""

    A1: Array
    A2: Array
    B: Array
    d: Array
    w: Array
    x01: Array
    xe: Array


def _bridge_parts(p: _BridgeInputs, whitened: bool) -> tuple[Array, Array, Array, Array]:
    """``Wᵀ``, ``M = (WᵀW)⁻¹``, ``F̃`` and ``S`` of :func:`_bridge`."""
    k = p.A1.shape[0]
    dt = p.A1.dtype
    eye, zero = jnp.eye(k, dtype=dt), jnp.zeros((k, k), dt)
    Wt = jsl.solve_triangular(p.B, eye, lower=True).T if whitened else eye
    M = p.B @ p.B.T if whitened else eye
    Fa = jnp.block([[p.A1.T, p.A2.T], [eye, zero]])
    S = -jnp.block([[Wt, zero], [zero, Wt]])
    return Wt, M, Fa, S


def _start_terms(A1: Array, A2: Array, x01: Array, n: int) -> Array:
    """``(n, k)``: the held start states moved right in equations 2 and 3 (``n ≥ 2``)."""
    st = jnp.stack([A1 @ x01[1] + A2 @ x01[0], A2 @ x01[1]])
    return jnp.pad(st, ((0, n - 2), (0, 0)))


def _bridge_single(p: _BridgeInputs, whitened: bool) -> tuple[Array, Array]:
    """:func:`_bridge` for one sample: ``O(log n)`` small products and three vector scans.

    ``ZᵀZ = Sᵀ X_n S`` with the Gramian ``X_n = Σ_m (F̃ᵐ)ᵀ [[M, 0], [0, 0]] F̃ᵐ``
    (:func:`_gramian`); ``Zᵀ c_a = G_b G_a⁻¹ c_a`` from the free motion ``x_u = G_a⁻¹ c_a``
    (the noise-driven recursion, forward scan); ``U_i α`` by the adjoint recursion (backward
    scan); the correction ``G_a⁻¹ (Z α)`` by a third scan.
    """
    dt = p.A1.dtype
    n, k = p.w.shape[0] - 2, p.A1.shape[0]
    Wt, M, Fa, S = _bridge_parts(p, whitened)
    Pm = jnp.zeros((2 * k, 2 * k), dt).at[:k, :k].set(M)
    X = _gramian(Fa, Pm, n)
    Lc = jnp.linalg.cholesky(jnp.eye(2 * k, dtype=dt) + _sym(S.T @ X @ S))
    f = p.d + p.w  # (l−2, k): f_j = d + B v_j, row j−2
    fa = f[:n] + _start_terms(p.A1, p.A2, p.x01, n)
    xu = _recursion(p.A1, p.A2, fa)  # the free (noise-driven) motion, frames 2 … l−3
    xl3, xl4 = xu[-1], xu[-2]
    xe = p.xe
    # c_b − G_b x_u: the two end equations' residuals at the free motion (units of W·)
    e = jnp.concatenate(
        [
            (f[n] - xe[0] + p.A1 @ xl3 + p.A2 @ xl4) @ Wt,
            (f[n + 1] - xe[1] + p.A1 @ xe[0] + p.A2 @ xl3) @ Wt,
        ]
    )
    alpha = jsl.cho_solve((Lc, True), e)
    Sa = S @ alpha  # [U_{l−2} α; U_{l−1} α]
    # U_i α for i = l−3 … 2: the adjoint recursion u_i = A1ᵀ u_{i+1} + A2ᵀ u_{i+2} from
    # the two end values, entered as inputs of its first two steps
    ua, ub = Sa[:k], Sa[k:]
    seed = jnp.zeros((n, k), dt).at[-1].set(p.A1.T @ ua + p.A2.T @ ub)
    seed = seed.at[-2].add(p.A2.T @ ua)
    u = _recursion(p.A1.T, p.A2.T, seed, reverse=True)
    x = xu + _recursion(p.A1, p.A2, u @ M.T)
    return jnp.concatenate([p.x01, x, p.xe], axis=0), _chol_ok(Lc)


def _chol_ok(Lc: Array) -> Array:
    diag = jnp.diagonal(Lc)
    return jnp.all(jnp.isfinite(diag) & (diag > 0))


def _block_propagators(A1: Array, A2: Array, m: int) -> tuple[Array, Array]:
    """Propagators of ``m`` frames of ``x_j = A1 x_{j−1} + A2 x_{j−2} + u_j``.

    With ``Φ_0 = I``, ``Φ_1 = A1``, ``Φ_s = A1 Φ_{s−1} + A2 Φ_{s−2}``, the frames of a block
    are ``X = T c + H u`` for ``c = [x_{−1}; x_{−2}]`` the two frames before it:
    ``T`` ``(mk, 2k)`` and ``H`` ``(mk, mk)``, block lower-triangular Toeplitz in ``Φ``.
    """
    k = A1.shape[0]
    dt = A1.dtype
    eye, zero = jnp.eye(k, dtype=dt), jnp.zeros((k, k), dt)
    p1, p2 = jnp.concatenate([eye, zero], 1), jnp.concatenate([zero, eye], 1)
    rows = []
    for _ in range(m):
        p1, p2 = A1 @ p1 + A2 @ p2, p1
        rows.append(p1)
    phi = [eye, A1]
    while len(phi) < m:
        phi.append(A1 @ phi[-1] + A2 @ phi[-2])
    H = jnp.block([[phi[r - c] if r >= c else zero for c in range(m)] for r in range(m)])
    return jnp.concatenate(rows, axis=0), H


def _bridge_batched(
    p: _BridgeInputs, whitened: bool, w_b: bool, poses_b: bool, N: int
) -> tuple[Array, Array]:
    """:func:`_bridge` for a batch of ``N`` noises and/or key poses of one texton.

    ``p.w`` is ``(N, l−2, k)`` if ``w_b`` (else ``(l−2, k)``, shared), ``p.x01`` and ``p.xe``
    ``(N, 2, k)`` if ``poses_b``. The parts that depend only on the texton are built once,
    with ``U_i`` explicit (:func:`_adjoint_rows`); every sample is then linear in its noise
    and poses: ``α`` from one GEMM with ``Zᵀ`` (the rows ``U_i``), the right-hand sides of
    the recursion blocked by ``m`` frames (:func:`_block_propagators`)
    ``R = w Hᵀ + α P + R₀`` from two GEMMs, and ``⌈n/m⌉`` sequential GEMMs
    ``X_b = c_b Tᵀ + R_b`` over the batch, in place in ``R`` (batch-major, so that no
    transposed copy of the batch is made).

    Returns:
        states ``(N, l, k)`` and ``ok`` (unbatched).
    """
    w = p.w
    dt = w.dtype
    n, k = w.shape[-2] - 2, p.A1.shape[0]
    m = _BRIDGE_BLOCK
    nb = -(-n // m)
    Wt, M, Fa, S = _bridge_parts(p, whitened)
    V = _adjoint_rows(Fa, k, n)  # V_m, m = 1 … n
    U = (V.reshape(n * k, 2 * k) @ S).reshape(n, k, 2 * k)[::-1]  # U_i, i = 2 … l−3
    Uf = U.reshape(n * k, 2 * k)
    MU = jnp.einsum("ab,ibc->iac", M, U)
    Lc = jnp.linalg.cholesky(jnp.eye(2 * k, dtype=dt) + _sym(Uf.T @ MU.reshape(n * k, 2 * k)))
    T, H = _block_propagators(p.A1, p.A2, m)
    blocks = lambda a: jnp.pad(a, ((0, nb * m - n), (0, 0), *[(0, 0)] * (a.ndim - 2)))
    P = jnp.moveaxis(H @ blocks(MU).reshape(nb, m * k, 2 * k), 2, 0).reshape(2 * k, -1)

    def pose_terms(x01: Array, xe: Array) -> tuple[Array, Array]:
        # without noise: f⁰_j = d, the held states moved right
        fa0 = p.d + _start_terms(p.A1, p.A2, x01, n)
        cb0 = jnp.concatenate([(p.d - xe[0]) @ Wt, (p.d - xe[1] + p.A1 @ xe[0]) @ Wt])
        e0 = cb0 - fa0.reshape(n * k) @ Uf  # c_b − Zᵀ c_a  (Z_iᵀ c_a,i = U_iᵀ W⁻¹ c_a,i)
        return e0, blocks(fa0).reshape(nb, m * k) @ H.T

    e0, R0 = (jax.vmap(pose_terms) if poses_b else pose_terms)(p.x01, p.xe)
    # per sample: the noise w_j = B v_j
    if not w_b:
        w = jnp.broadcast_to(w, (N, *w.shape))
    wa = w[:, :n]
    e = e0 - wa.reshape(N, n * k) @ Uf + jnp.concatenate([w[:, n] @ Wt, w[:, n + 1] @ Wt], 1)
    # (I + ZᵀZ)⁻¹ explicitly (2k × 2k, ≥ I so well conditioned): one GEMM for the batch
    # instead of two triangular solves with N right-hand sides
    Ginv = jsl.cho_solve((Lc, True), jnp.eye(2 * k, dtype=dt))
    alpha = e @ _sym(Ginv)  # (N, 2k)
    wb = jnp.pad(wa, ((0, 0), (0, nb * m - n), (0, 0))).reshape(N, nb, m * k)
    R = wb @ H.T + (alpha @ P).reshape(N, nb, m * k) + R0
    # X_b = c_b Tᵀ + R_b with c_b = [x_last, x_before_last] of block b−1: the last 2k
    # columns of X_{b−1} times Tᵀ with its two row blocks swapped
    Ts = jnp.concatenate([T[:, k:], T[:, :k]], axis=1).T  # (2k, mk)

    def body(b: Array, carry: tuple[Array, Array]) -> tuple[Array, Array]:
        X_prev, R = carry
        X = X_prev[:, -2 * k :] @ Ts + lax.dynamic_index_in_dim(R, b, axis=1, keepdims=False)
        return X, lax.dynamic_update_index_in_dim(R, X, b, axis=1)

    _, R = lax.fori_loop(0, nb, body, (jnp.zeros((N, m * k), dt), R))
    ends = lambda a: a if poses_b else jnp.broadcast_to(a, (N, 2, k))
    x = jnp.concatenate([ends(p.x01), R.reshape(N, nb * m, k)[:, :n], ends(p.xe)], axis=1)
    return x, _chol_ok(Lc)


def _make_bridge(whitened: bool) -> Any:
    """:func:`_bridge` for one weighting: ``custom_vmap`` picks the batched form when the
    texton is shared (only noises and/or key poses batched); derivatives (``custom_jvp``) are
    those of the single form."""
    single = lambda p: _bridge_single(p, whitened)

    @jax.custom_batching.custom_vmap
    def vmappable(p: _BridgeInputs) -> tuple[Array, Array]:
        return single(p)

    @vmappable.def_vmap
    def rule(axis_size: int, in_batched: list[Any], p: _BridgeInputs) -> Any:
        f = in_batched[0]
        if not (f.A1 or f.A2 or f.B or f.d):
            poses_b = bool(f.x01 or f.xe)
            if poses_b:  # both poses batched (or broadcast) together
                bc = lambda a, b: a if b else jnp.broadcast_to(a, (axis_size, *a.shape))
                p = eqx.tree_at(lambda q: (q.x01, q.xe), p, (bc(p.x01, f.x01), bc(p.xe, f.xe)))
            return _bridge_batched(p, whitened, bool(f.w), poses_b, axis_size), (True, False)
        bcast = lambda a, b: a if b else jnp.broadcast_to(a, (axis_size, *a.shape))
        out = jax.vmap(single)(jax.tree_util.tree_map(bcast, p, f))
        return out, (True, True)

    @jax.custom_jvp
    def bridge(p: _BridgeInputs) -> tuple[Array, Array]:
        return vmappable(p)

    @bridge.defjvp
    def _jvp(primals: tuple[_BridgeInputs], tangents: tuple[_BridgeInputs]) -> Any:
        return jax.jvp(single, primals, tangents)

    return bridge


_BRIDGES = {True: _make_bridge(True), False: _make_bridge(False)}


def _bridge(tex: Texton, w: Array, x01: Array, xe: Array, weighting: str) -> tuple[Array, Array]:
    """Constrained synthesis with both ends held and no edits, without the banded solve.

    The same least-squares solution as :func:`_solve_constrained`, computed from the
    recursion. Free frames ``i = 2 … l−3`` (``n = l − 4``); split the equations into the
    ``n`` square ones ``G_a`` (``j = 2 … l−3``, block lower triangular: the dynamics) and the
    two of the end, ``G_b`` (``j = l−2, l−1``). With ``c`` the right-hand sides (noise, ``d``
    and the held states moved right) and ``Z = G_a⁻ᵀ G_bᵀ`` (``(nk, 2k)``), ``y = G_a x``
    turns ``min ‖G_a x − c_a‖² + ‖G_b x − c_b‖²`` into ``min ‖y − c_a‖² + ‖Zᵀ y − c_b‖²``,
    whose solution (Woodbury) is

    .. code-block:: text

        y = c_a + Z α,   (I + ZᵀZ) α = c_b − Zᵀ c_a,   x = G_a⁻¹ y.

    ``G_a⁻¹`` is the dynamics recursion, so ``x`` is the noise-driven motion from the start
    frames with the extra input ``W⁻¹ Z_i α = M U_i α`` (``M = (WᵀW)⁻¹``: ``B Bᵀ`` whitened,
    ``I`` paper), the control that brings it to the end frames. ``U_i = Wᵀ Z_i`` obey the
    adjoint recursion ``U_i = A1ᵀ U_{i+1} + A2ᵀ U_{i+2}`` from ``U_{l−2} = −[Wᵀ, 0]``,
    ``U_{l−1} = −[0, Wᵀ]``, i.e. ``U_i = [I 0] F̃^{l−2−i} S`` with ``F̃ = [[A1ᵀ, A2ᵀ], [I, 0]]``
    and ``S = −diag(Wᵀ, Wᵀ)``. One sample: :func:`_bridge_single`; a batch for one texton
    (``vmap`` over keys and/or key poses): :func:`_bridge_batched`. Accurate only for a
    texton that does not amplify much over the segment (:func:`_bridge_usable`): the caller
    checks that first.

    Returns:
        states ``(l, k)`` and ``ok`` (the ``2k × 2k`` factorisation is finite).
    """
    p = _BridgeInputs(A1=tex.A1, A2=tex.A2, B=tex.B, d=tex.d, w=w, x01=x01, xe=xe)
    return _BRIDGES[weighting == "whitened"](p)


def _constrained(
    tex: Texton,
    v: Array,
    start: Array,
    end: Array | None,
    fixed: tuple[Array, Array] | None,
    weighting: str,
) -> Array:
    """Constrained synthesis by perturb-and-MAP with the equation noise ``v`` ``(l−2, k)``.

    Both ends held and no edits (``l ≥ 6``): :func:`_bridge`, unless the texton amplifies
    over the segment so much (:func:`_bridge_usable`) that the recursion would lose
    accuracy; then, and in every other case, the masked normal
    equations and the banded solve (:func:`_solve_constrained`; the pair blocks of the
    block-tridiagonal form are built directly from the Gram matrix and the held mask, an
    odd length padded with one held frame). Under ``vmap`` over ``v`` alone (many samples of
    one texton) the factorisations and propagators are shared and the samples become the
    rows of GEMMs. Returns ``(l, D)``: one GEMM ``[x, 1] [Cᵀ; μ]``.
    """
    length = v.shape[0] + 2
    dt = tex.mu.dtype
    w = v.astype(dt) @ tex.B.T  # the noise in state units, w_j = B v_j (the one reader of v)
    if end is None or fixed is not None or length < 6:
        eqs = _equations(tex, length, w, start, end, fixed, weighting)
        return _observe(tex, *_solve_constrained(tex, eqs, w))
    proj = lambda y: (y.astype(dt) - tex.mu) @ tex.C
    x01, xe = proj(start), proj(end)
    # the bridge where the texton does not amplify too much over the segment (decided from
    # the dynamics alone, so unbatched under vmap over keys or poses); an amplifying texton
    # enters the bridge as A1 = A2 = 0, so that its unused result stays finite (for
    # derivatives under a batched lax.cond too), and is solved banded
    usable = _bridge_usable(tex.A1, tex.A2, length - 4)
    safe = eqx.tree_at(
        lambda t: (t.A1, t.A2),
        tex,
        (jnp.where(usable, tex.A1, 0.0), jnp.where(usable, tex.A2, 0.0)),
    )
    x, ok = _bridge(safe, w, x01, xe, weighting)

    def banded(_: Any) -> tuple[Array, Array]:
        eqs = _equations(tex, length, w, start, end, None, weighting)
        return _solve_constrained(tex, eqs, w)

    x, ok = lax.cond(usable, lambda _: (x, ok), banded, None)
    return _observe(tex, x, ok)


def _constrained_key(
    tex: Texton,
    key: Array | None,
    length: int,
    start: Array,
    end: Array | None,
    fixed: tuple[Array, Array] | None,
    weighting: str,
) -> Array:
    return _constrained(tex, _draw_noise(tex, key, length), start, end, fixed, weighting)


_constrained_key_jit = eqx.filter_jit(_constrained_key)
