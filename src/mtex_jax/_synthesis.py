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

With a key and an end constraint the whitened sample is drawn in state space instead,
``x̄ + L⁻ᵀ ξ`` with ``J = L Lᵀ`` the banded Cholesky factorisation and ``ξ ~ N(0, I)``: the
same law (covariance ``L⁻ᵀ L⁻¹ = J⁻¹``) without the noise right-hand side ``Gᵀ v`` and its
forward substitution (see :func:`synthesize_texton`).
"""

from __future__ import annotations

from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jax import lax
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Bool, Float

from mtex_jax._linalg import _pair_blocks, _tridiag_sample_rows, _tridiag_solve_rows
from mtex_jax._texton import Texton

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
    texton: Texton,
    key: Array | None,
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
      or its mean when ``key is None``; with ``end`` given the same law is sampled in state
      space, see below) or ``W = I`` (``weighting="paper"``, MT Eq. 9). With
      ``end=None`` the frames after the last held one follow the dynamics with the same
      noise, i.e. noise-driven continuation (computed by the recursion: they and their
      equations are not part of the least squares, which for an unstable texton would be
      as ill-conditioned as ``ρ^(2·tail)``).

    How the key is used. Noise-driven, ``weighting="paper"``, and whitened without ``end``:
    ``v = jax.random.normal(key, (l−2, k))`` enters the equations above (perturb-and-MAP).
    Whitened with ``end`` (the usual constrained case): the same conditional law is sampled
    in state space, ``x = x̄ + L⁻ᵀ ξ`` with ``ξ = jax.random.normal(key, (2⌈l/2⌉, k))``,
    ``x̄`` the conditional mean and ``L Lᵀ = J = GᵀG`` the banded Cholesky factorisation of the
    normal matrix of the whitened equations ``G`` in the free states. Both are exact samples of
    ``N(x̄, J⁻¹)`` (``L⁻¹Gᵀv`` is itself standard normal); the state-space form needs no
    noise right-hand side and no forward substitution of it, and under ``vmap`` over keys
    only the backward substitution is batched. Rows of ``ξ`` at held frames are unused.

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


def _draw_noise(tex: Texton, key: Array | None, length: int) -> Array:
    """``v_j ~ N(0, I_k)``, ``j = 2 … l−1``: ``jax.random.normal(key, (l−2, k))``; 0 if no key."""
    shape = (length - 2, tex.C.shape[-1])
    if key is None:
        return jnp.zeros(shape, tex.mu.dtype)
    return jax.random.normal(key, shape, tex.mu.dtype)


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
    v: Array | None,
    start: Array,
    end: Array | None,
    fixed: tuple[Array, Array] | None,
    weighting: str,
) -> _Equations:
    """Held frames, Gram matrix ``K = [P0, P1, P2]ᵀ[P0, P1, P2]`` and right-hand side.

    See :func:`_normal_system` for the equations; ``v=None`` leaves the noise out.
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
    Q = P if whitened else tex.B.T @ P  # noise enters c_j = W d + (W B) v_j
    # residual of the equations at the held states, u_j = W d − G_j x̂ (+ noise, below)
    X3 = jnp.concatenate([x_held[2:], x_held[1:-1], x_held[:-2]], axis=1)  # (l−2, 3k)
    U0 = ((W @ tex.d)[None, :] - X3 @ P.T) @ P
    U = U0 if v is None else v.astype(dt) @ Q + U0  # (l−2, 3k): [P0ᵀu_j, P1ᵀu_j, P2ᵀu_j]
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
    ``U = v Q + U₀`` with ``Q = (W B)ᵀ [P0, P1, P2]`` (``= [P0, P1, P2]`` when whitened,
    ``W B = I``) and three shifted slices of ``U``; only this GEMM depends on the noise ``v``.
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
    eqs = _equations(tex, v.shape[0] + 2, v, start, end, fixed, weighting)
    diag, off1, off2 = _frame_blocks(eqs.K, eqs.held, eqs.held.shape[0], eqs.eq_on)
    return NormalSystem(
        diag=diag, off1=off1, off2=off2, rhs=eqs.rhs, held=eqs.held, x_held=eqs.x_held
    )


def _continue_tail(tex: Texton, x: Array, v: Array, tail: Array) -> Array:
    """Frames with ``tail[t]`` follow ``x_t = A1 x_{t−1} + A2 x_{t−2} + d + B v_t``.

    ``x`` ``(l, k)``, ``v`` ``(l−2, k)`` (``v_t`` is row ``t−2``); the other frames are kept.
    """

    def step(carry: tuple[Array, Array], inp: tuple[Array, Array, Array]) -> Any:
        xm1, xm2 = carry
        xj, vj, tj = inp
        xj = jnp.where(tj, tex.A1 @ xm1 + tex.A2 @ xm2 + tex.d + tex.B @ vj, xj)
        return (xj, xm1), xj

    _, rest = lax.scan(step, (x[1], x[0]), (x[2:], v.astype(x.dtype), tail[2:]))
    return jnp.concatenate([x[:2], rest], axis=0)


def _solve_constrained(
    tex: Texton, eqs: _Equations, xi: Array | None, v: Array | None = None
) -> Array:
    """Banded solve of the masked normal equations and ``μ + C x`` (see :func:`_constrained`).

    With ``xi`` (``(2⌈l/2⌉, k)``) the result is ``x̄ + L⁻ᵀ ξ`` (:func:`_constrained_sample`).
    An open tail (``eqs.tail``) is then continued by the dynamics with the noise ``v``.
    """
    length, k = eqs.rhs.shape
    nb = (length + 1) // 2
    diag, off1, off2 = _frame_blocks(eqs.K, eqs.held, 2 * nb, eqs.eq_on)
    pdiag, psub = _pair_blocks(diag, off1, off2)
    r = jnp.pad(eqs.rhs, ((0, 2 * nb - length), (0, 0))).reshape(nb, 1, 2 * k)
    if xi is None:
        x, ok, _ = _tridiag_solve_rows(pdiag, psub, r)
    else:
        x, ok, _ = _tridiag_sample_rows(pdiag, psub, r, xi.astype(r.dtype).reshape(nb, 1, 2 * k))
    x = jnp.where(eqs.held[:, None], eqs.x_held, x.reshape(2 * nb, k)[:length])
    if eqs.tail is not None:
        x = _continue_tail(
            tex, x, jnp.zeros((length - 2, k), x.dtype) if v is None else v, eqs.tail
        )
    proj = jnp.concatenate([tex.C.T, tex.mu[None, :]], axis=0)  # (k+1, D)
    proj = eqx.error_if(
        proj,
        ~ok,
        "synthesize_texton: normal matrix not positive definite (non-finite or singular texton B?)",
    )
    x1 = jnp.concatenate([x, jnp.ones((length, 1), x.dtype)], axis=1)
    return x1 @ proj


def _constrained(
    tex: Texton,
    v: Array,
    start: Array,
    end: Array | None,
    fixed: tuple[Array, Array] | None,
    weighting: str,
) -> Array:
    """Constrained synthesis by perturb-and-MAP: masked normal equations with the equation
    noise ``v``, banded solve, ``μ + C x``.

    ``v`` ``(l−2, k)``; returns ``(l, D)``. The pair blocks of the block-tridiagonal form
    (:mod:`mtex_jax._linalg`) are built directly from the Gram matrix and the held mask (one
    pass each, symmetric by construction); an odd length is padded with one held frame. Under
    ``vmap`` over ``v`` alone (many samples of one texton) the factorisation is shared and the
    samples become the rows of GEMMs. The output is one GEMM ``[x, 1] [Cᵀ; μ]``.
    """
    eqs = _equations(tex, v.shape[0] + 2, v, start, end, fixed, weighting)
    return _solve_constrained(tex, eqs, None, v)


def _constrained_sample(
    tex: Texton,
    xi: Array,
    length: int,
    start: Array,
    end: Array | None,
    fixed: tuple[Array, Array] | None,
) -> Array:
    """Exact conditional sample (whitened weighting) drawn in state space.

    With ``G`` the whitened equations in the free states, ``x̄`` the conditional mean (the
    noise-free least-squares solution) and ``L Lᵀ = J = GᵀG`` the banded Cholesky factor of
    the masked normal matrix, ``x = x̄ + L⁻ᵀ ξ`` with ``ξ ~ N(0, I)`` ``(2⌈l/2⌉, k)`` has the
    law ``N(x̄, J⁻¹)`` of the LDS conditioned on the held states — the law of the
    perturb-and-MAP sample ``x̄ + J⁻¹Gᵀv`` (:func:`_constrained`), since ``L⁻¹Gᵀv`` is itself
    ``N(0, I)``. It skips the noise's right-hand side and its forward substitution, and under
    ``vmap`` over ``ξ`` the mean's forward pass is shared: only the backward pass is batched.
    Rows of ``ξ`` at held (and padding) frames are ignored.
    """
    if xi.shape[0] != 2 * ((length + 1) // 2):
        raise ValueError(f"xi must have {2 * ((length + 1) // 2)} rows, got {xi.shape[0]}")
    eqs = _equations(tex, length, None, start, end, fixed, "whitened")
    return _solve_constrained(tex, eqs, xi)


def _constrained_key(
    tex: Texton,
    key: Array | None,
    length: int,
    start: Array,
    end: Array | None,
    fixed: tuple[Array, Array] | None,
    weighting: str,
) -> Array:
    if key is not None and weighting == "whitened" and end is not None:
        nb = (length + 1) // 2
        xi = jax.random.normal(key, (2 * nb, tex.C.shape[-1]), tex.mu.dtype)
        return _constrained_sample(tex, xi, length, start, end, fixed)
    return _constrained(tex, _draw_noise(tex, key, length), start, end, fixed, weighting)


_constrained_key_jit = eqx.filter_jit(_constrained_key)
