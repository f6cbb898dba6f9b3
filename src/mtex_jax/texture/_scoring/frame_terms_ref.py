"""Per-frame terms by the per-texton algorithm (design §3): the independent reference of the
blocked kernel in ``_frame_terms`` (:func:`frame_terms_per_texton`) and the initial-state terms
(:func:`init_terms`)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jax import lax
from jaxtyping import Array, ArrayLike, Float

from .._texton.checks import (
    LOG_2PI,
    check_obs,
    check_positive_int,
    error_if_nonfinite,
    float_dtype,
    innovation_logpdf,
    psd_cholesky,
)
from .._texton.texton import Texton, check_texton


def _terms_single(
    tex: Texton, Yc: Array, yn: Array, ybar: Array, with_dyn_obs: bool, with_init: bool
) -> tuple[Array | None, Array | None, Array | None]:
    """Per-frame terms of one texton on centred frames ``Yc = Y − ȳ`` (``yn = ‖Yc‖²``)."""
    T, D = Yc.shape
    k = tex.C.shape[-1]
    dtype = Yc.dtype
    tex = jax.tree.map(lambda a: a.astype(dtype), tex)
    mc = tex.mu - ybar
    off = mc @ tex.C
    # one GEMM gives the states and the y·μ term: Yc [C | μ − ȳ]
    P = Yc @ jnp.concatenate([tex.C, mc[:, None]], axis=1)
    X = P[:, :k] - off  # x_t = Cᵀ(y_t − μ)
    dyn = obs = init = None
    if with_dyn_obs:
        # whitened dynamics residual w_t = B⁻¹(x_t − A1 x_{t−1} − A2 x_{t−2} − d)
        Binv = jsl.solve_triangular(tex.B, jnp.eye(k, dtype=dtype), lower=True)
        G1 = -(Binv @ tex.A1)
        G2 = -(Binv @ tex.A2)
        logdet_q = 2.0 * jnp.sum(jnp.log(jnp.diagonal(tex.B)))
        if T >= 3:
            W = X[2:] @ Binv.T + X[1:-1] @ G1.T + X[:-2] @ G2.T - Binv @ tex.d
            dyn_t = innovation_logpdf(jnp.sum(W * W, axis=1), logdet_q, k, tex.dof)
            dyn = jnp.concatenate([jnp.zeros((2,), dtype), dyn_t])
        else:
            dyn = jnp.zeros((T,), dtype)
        # ‖r_t‖² = ‖y_t − μ‖² − ‖x_t‖², clamped at 0 (r outside the subspace)
        r2 = yn - 2.0 * P[:, k] + mc @ mc - jnp.sum(X * X, axis=1)
        r2 = jnp.maximum(r2, 0.0)
        n_res = D - k
        obs = -0.5 * (n_res * (LOG_2PI + jnp.log(tex.sigma2)) + r2 / tex.sigma2)
        if n_res == 0:
            obs = jnp.zeros_like(obs)
        else:
            extra = tex.observation.residual_terms(tex.C, Yc - mc, obs[2:]) if T >= 3 else None
            if extra is not None:  # the observation model's own terms (design §10.3)
                dyn = dyn + jnp.concatenate([jnp.zeros((2,), dtype), extra])
    if with_init:
        L0 = psd_cholesky(tex.S0, jnp.zeros((), dtype))
        L0inv = jsl.solve_triangular(L0, jnp.eye(2 * k, dtype=dtype), lower=True)
        if T >= 2:
            # L0⁻¹([x_b; x_{b+1}] − m0) without forming the stacked pairs
            U = X[:-1] @ L0inv[:, :k].T + X[1:] @ L0inv[:, k:].T - L0inv @ tex.m0
            logdet0 = 2.0 * jnp.sum(jnp.log(jnp.diagonal(L0)))
            init_b = -0.5 * (2 * k * LOG_2PI + logdet0 + jnp.sum(U * U, axis=1))
            init = jnp.concatenate([init_b, jnp.full((1,), -jnp.inf, dtype)])
        else:
            init = jnp.full((T,), -jnp.inf, dtype)
    return dyn, obs, init


def _all_terms_impl(
    textons: Texton, Y: Array, with_dyn_obs: bool, with_init: bool, chunk: int
) -> tuple[Array | None, Array | None, Array | None]:
    Y = error_if_nonfinite(Y, "Y")
    dtype = float_dtype(Y, textons.mu)
    Y = Y.astype(dtype)
    ybar = jnp.mean(Y, axis=0)
    Yc = Y - ybar
    yn = jnp.sum(Yc * Yc, axis=1)

    def one(tex: Texton) -> tuple[Array | None, Array | None, Array | None]:
        return _terms_single(tex, Yc, yn, ybar, with_dyn_obs, with_init)

    if not textons.is_stacked:
        return one(textons)
    return lax.map(one, textons, batch_size=chunk if chunk > 1 else None)


_all_terms_jit = eqx.filter_jit(_all_terms_impl)


def frame_terms_per_texton(
    textons: Texton, Y: ArrayLike, *, chunk_size: int = 1
) -> tuple[Float[Array, "*n T"], Float[Array, "*n T"]]:
    """:func:`frame_terms` by the per-texton algorithm: ``lax.map`` over textons,
    ``chunk_size`` per step; each texton projects all frames with one GEMM and forms
    ``B⁻¹(x_t − A1 x_{t−1} − A2 x_{t−2} − d)`` with three ``k × k`` GEMMs. Slower than the
    blocked kernel; an independent implementation of the same formulas (the tests' reference)."""
    textons = check_texton("textons", textons)
    Y = check_obs("Y", Y, textons.obs_dim)
    dyn, obs, _ = _all_terms_jit(
        textons, Y, True, False, check_positive_int("chunk_size", chunk_size)
    )
    assert dyn is not None and obs is not None
    return dyn, obs


def init_terms(textons: Texton, Y: ArrayLike, *, chunk_size: int = 1) -> Float[Array, "*n T"]:
    """Initial-state log-density of a segment starting at each frame (design §3).

    .. code-block:: text

        init[i, b] = log N([x_b; x_{b+1}]; m0_i, S0_i)    for b <= T − 2
        init[i, T−1] = −inf                               (no second frame)

    Args:
        textons: a stack of ``N_t`` textons (or a single texton).
        Y: observations ``(T, D)``.
        chunk_size: textons vectorised per ``lax.map`` step (static).

    Returns:
        ``(N_t, T)`` (``(T,)`` for a single texton).
    """
    textons = check_texton("textons", textons)
    Y = check_obs("Y", Y, textons.obs_dim)
    _, _, init = _all_terms_jit(
        textons, Y, False, True, check_positive_int("chunk_size", chunk_size)
    )
    assert init is not None
    return init
