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

from mtex_jax._linalg import _solve_frames, block_banded_matvec
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
      or its mean when ``key is None``) or ``W = I`` (``weighting="paper"``, MT Eq. 9). With
      ``end=None`` the frames after the last held one follow the dynamics with the same
      noise, i.e. noise-driven continuation.

    ``length`` is static; the mask and poses are arrays, so different edits do not recompile.
    Any ``length ≥ 4`` (``≥ 2`` without ``end``) works: the same texton extrapolates (MT Fig. 10).
    ``vmap`` over ``key`` (or over the poses) works.

    Args:
        texton: a single :class:`~mtex_jax._texton.Texton` (``D``, ``k``).
        key: JAX PRNG key for ``v_j ~ N(0, I_k)``, ``j = 2 … l−1``; ``None`` for ``v = 0``.
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
    if key is None:
        v = jnp.zeros((length - 2, texton.state_dim), texton.mu.dtype)
    else:
        v = jax.random.normal(key, (length - 2, texton.state_dim), texton.mu.dtype)
    if end_a is None and fixed_a is None:
        return _noise_driven_jit(texton, v, start_a)
    return _constrained_jit(texton, v, start_a, end_a, fixed_a, weighting)


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


_noise_driven_jit = eqx.filter_jit(_noise_driven)


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


def _normal_system(
    tex: Texton,
    v: Array,
    start: Array,
    end: Array | None,
    fixed: tuple[Array, Array] | None,
    weighting: str,
) -> NormalSystem:
    dt = tex.mu.dtype
    k = tex.C.shape[-1]
    length = v.shape[0] + 2
    eye = jnp.eye(k, dtype=dt)
    proj = lambda y: (y.astype(dt) - tex.mu) @ tex.C
    idx = jnp.arange(length)
    held = idx < 2
    x_held = jnp.concatenate([proj(start), jnp.zeros((length - 2, k), dt)], axis=0)
    if fixed is not None:
        held = held | fixed[0]
        x_held = jnp.where(fixed[0][:, None], proj(fixed[1]), x_held)
    if end is not None:
        last = idx >= length - 2
        held = held | last
        x_end = jnp.concatenate([jnp.zeros((length - 2, k), dt), proj(end)], axis=0)
        x_held = jnp.where(last[:, None], x_end, x_held)

    W = jsl.solve_triangular(tex.B, eye, lower=True) if weighting == "whitened" else eye
    P0, P1, P2 = W, -W @ tex.A1, -W @ tex.A2  # coefficients of x_j, x_{j−1}, x_{j−2} in eq j
    c = (W @ tex.d)[None, :] + v @ (W @ tex.B).T  # (l−2, k): W(d + B v_j), j = 2 … l−1

    # which equations exist: eq j for j = 2 … l−1 (frame index of its newest state)
    eq = (idx >= 2).astype(dt)  # eq[i] = 1 if equation i exists
    eq_p1 = jnp.concatenate([eq[1:], jnp.zeros((1,), dt)])  # eq[i+1]
    eq_p2 = jnp.concatenate([eq[2:], jnp.zeros((2,), dt)])  # eq[i+2]
    s = lambda w, M: w[:, None, None] * M[None]
    diag = s(eq, P0.T @ P0) + s(eq_p1, P1.T @ P1) + s(eq_p2, P2.T @ P2)
    off1 = s(eq[1:], P0.T @ P1) + s(eq_p2[:-1], P1.T @ P2)  # block (i+1, i)
    off2 = s(eq[2:], P0.T @ P2)  # block (i+2, i)

    cf = jnp.concatenate([jnp.zeros((2, k), dt), c], axis=0)  # c at frame index j
    # h_i = P0ᵀ c_i + P1ᵀ c_{i+1} + P2ᵀ c_{i+2} (padding, not scatter: fast under vmap)
    U = cf @ jnp.concatenate([P0, P1, P2], axis=1)  # one GEMM, then shifts
    h = (
        U[:, :k]
        + jnp.pad(U[1:, k : 2 * k], ((0, 1), (0, 0)))
        + jnp.pad(U[2:, 2 * k :], ((0, 2), (0, 0)))
    )
    Jx = block_banded_matvec(diag, off1, off2, x_held[:, :, None])[:, :, 0]
    rhs = jnp.where(held[:, None], x_held, h - Jx)

    diag = jnp.where(held[:, None, None], eye, diag)
    off1 = jnp.where((held[1:] | held[:-1])[:, None, None], 0.0, off1)
    off2 = jnp.where((held[2:] | held[:-2])[:, None, None], 0.0, off2)
    return NormalSystem(diag=diag, off1=off1, off2=off2, rhs=rhs, held=held, x_held=x_held)


def _constrained(
    tex: Texton,
    v: Array,
    start: Array,
    end: Array | None,
    fixed: tuple[Array, Array] | None,
    weighting: str,
) -> Array:
    sysm = _normal_system(tex, v, start, end, fixed, weighting)
    sol = _solve_frames(sysm.diag, sysm.off1, sysm.off2, sysm.rhs[:, :, None])
    x = jnp.where(sysm.held[:, None], sysm.x_held, sol.x[:, :, 0])
    x = eqx.error_if(
        x,
        ~sol.ok,
        "synthesize_texton: normal matrix not positive definite (non-finite or singular texton B?)",
    )
    return tex.mu + x @ tex.C.T


_constrained_jit = eqx.filter_jit(_constrained)
