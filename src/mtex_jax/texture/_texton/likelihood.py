"""Texton likelihoods: the direct per-segment reference (:func:`segment_log_likelihood`) and the
exact marginal likelihood of the full LDS by a Kalman filter (:func:`exact_log_likelihood`)."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jax import lax
from jaxtyping import Array, ArrayLike, Float

from .._observation import observation_model
from .checks import (
    LOG_2PI,
    check_obs,
    error_if_nonfinite,
    float_dtype,
    gauss_logpdf_chol,
    psd_cholesky,
    sym,
)
from .texton import Texton, check_texton, companion_blocks

# --------------------------------------------------------------------------------------------
# Direct per-segment likelihood (reference) and the exact Kalman likelihood
# --------------------------------------------------------------------------------------------


def segment_log_likelihood(texton: Texton, Y_segment: ArrayLike) -> Float[Array, ""]:
    """Projected-state log-likelihood of one segment, computed directly (design §3).

    .. code-block:: text

        log p(Y_{b:e}) = log N([x_b; x_{b+1}]; m0, S0)
                       + Σ_{t=b+2..e} log N(x_t; A1 x_{t−1} + A2 x_{t−2} + d, Q)
                       + Σ_{t=b..e}   log N(r_t; 0, σ² I_{D−k})

    (for a ``"residual"`` texton the residual terms of ``t >= b+2`` are
    ``log N(r_t − a₁ r_{t−1} − a₂ r_{t−2}; 0, s_r² I_{D−k})`` instead; with Student-t
    innovations, ``Texton.dof = ν``, the dynamics terms are ``log t_ν(x_t; …, Q)``) with
    ``x_t = Cᵀ(y_t − μ)`` and the explicit residual ``r_t = (y_t − μ) − C x_t``
    (triangular solves with ``B`` and ``chol(S0)``). This is the reference for
    :class:`SegmentScorer`; it handles one texton (``jax.vmap`` it for a stack).

    Args:
        texton: a single texton.
        Y_segment: ``(L, D)`` frames of the segment, ``L >= 2``.

    Returns:
        Scalar log-likelihood.
    """
    texton = check_texton("texton", texton, stacked=False)
    Y = check_obs("Y_segment", Y_segment, texton.obs_dim, min_len=2)
    return _segment_ll_jit(texton, Y)


def _segment_ll_impl(tex: Texton, Y: Array) -> Array:
    Y = error_if_nonfinite(Y, "Y_segment")
    dtype = float_dtype(Y, tex.mu)
    Y = Y.astype(dtype)
    tex = jax.tree.map(lambda a: a.astype(dtype), tex)
    D, k = tex.C.shape
    Yc = Y - tex.mu
    X = Yc @ tex.C
    Rres = Yc - X @ tex.C.T
    ll_obs = jnp.asarray(0.0, dtype)
    if D > k:
        r2 = jnp.sum(Rres * Rres, axis=1)
        ll_obs = jnp.sum(-0.5 * ((D - k) * (LOG_2PI + jnp.log(tex.sigma2)) + r2 / tex.sigma2))
    L0 = psd_cholesky(tex.S0, jnp.zeros((), dtype))
    ll_init = gauss_logpdf_chol(jnp.concatenate([X[0], X[1]]) - tex.m0, L0)
    ll_dyn = jnp.asarray(0.0, dtype)
    if Y.shape[0] > 2:
        res = X[2:] - X[1:-1] @ tex.A1.T - X[:-2] @ tex.A2.T - tex.d
        ll_dyn = jnp.sum(gauss_logpdf_chol(res, tex.B, tex.dof))
        extra = observation_model(tex.observation).segment_dyn_term(tex, Rres)
        if extra is not None:  # the observation model's own terms (design §10.3)
            ll_dyn = ll_dyn + extra
    return ll_init + ll_dyn + ll_obs


_segment_ll_jit = eqx.filter_jit(_segment_ll_impl)


def exact_log_likelihood(texton: Texton, Y_segment: ArrayLike) -> Float[Array, ""]:
    """Exact marginal log-likelihood ``log p(y_1, …, y_L)`` of the full LDS (design §3).

    Model: ``[x_1; x_2] ~ N(m0, S0)``, ``x_t = A1 x_{t−1} + A2 x_{t−2} + d + B v_t``,
    ``y_t = μ + C x_t + w_t``, ``w_t ~ N(0, σ² I_D)``.

    Because ``C`` has orthonormal columns and ``R = σ² I``, rotate ``y_t − μ`` into
    ``z_t = Cᵀ(y_t − μ) = x_t + Cᵀ w_t`` and the residual ``r_t = (I − C Cᵀ)(y_t − μ)``: the
    two are independent, the rotation has unit Jacobian, and

    .. code-block:: text

        log p(y_{1:L}) = Σ_t log N(r_t; 0, σ² I_{D−k}) + log p(z_{1:L}),
        z_t = x_t + e_t,  e_t ~ N(0, σ² I_k)

    so no ``D × D`` matrix is ever formed (the information/Woodbury reduction of the
    ``D``-dimensional innovation covariance). ``log p(z_{1:L})`` is a Kalman filter in the
    stacked state ``X_t = [x_t; x_{t−1}]``: a joint update of the prior of ``[x_1; x_2]`` with
    ``[z_1; z_2]``, then ``lax.scan`` over ``t = 3..L`` of predict
    (``X⁻ = F X + [d; 0]``, ``P⁻ = F P Fᵀ + diag(Q, 0)``) and update with ``H = [I, 0]``
    (innovation covariance ``S = H P⁻ Hᵀ + σ² I_k`` by Cholesky, Joseph-form covariance
    update). Differentiable in the texton parameters and the data.

    Args:
        texton: a single texton.
        Y_segment: ``(L, D)``, ``L >= 2``.

    Returns:
        Scalar log-likelihood.
    """
    texton = check_texton("texton", texton, stacked=False)
    if texton.dof is not None:
        raise ValueError(
            "exact_log_likelihood is the Kalman likelihood of Gaussian textons; this texton "
            f"has Student-t innovations (dof={texton.dof:g}): use segment_log_likelihood"
        )
    if not observation_model(texton.observation).kalman:
        raise ValueError(
            "exact_log_likelihood is the Kalman likelihood of the paper's model (white "
            f"observation noise); a {texton.observation!r} texton has no such form"
        )
    Y = check_obs("Y_segment", Y_segment, texton.obs_dim, min_len=2)
    return _exact_ll_jit(texton, Y)


def _exact_ll_impl(tex: Texton, Y: Array) -> Array:
    Y = error_if_nonfinite(Y, "Y_segment")
    dtype = float_dtype(Y, tex.mu)
    Y = Y.astype(dtype)
    tex = jax.tree.map(lambda a: a.astype(dtype), tex)
    D, k = tex.C.shape
    s2 = tex.sigma2
    Yc = Y - tex.mu
    Z = Yc @ tex.C
    ll = jnp.asarray(0.0, dtype)
    if D > k:
        Rres = Yc - Z @ tex.C.T
        r2 = jnp.sum(Rres * Rres)
        ll = ll - 0.5 * (Y.shape[0] * (D - k) * (LOG_2PI + jnp.log(s2)) + r2 / s2)

    eye_k = jnp.eye(k, dtype=dtype)
    eye_2k = jnp.eye(2 * k, dtype=dtype)

    # joint update of the prior on [x_1; x_2] with [z_1; z_2] (H = I_2k)
    z12 = jnp.concatenate([Z[0], Z[1]])
    S = sym(tex.S0) + s2 * eye_2k
    Ls = jnp.linalg.cholesky(S)
    v = z12 - tex.m0
    ll = ll + gauss_logpdf_chol(v, Ls)
    K = jsl.cho_solve((Ls, True), tex.S0).T  # S0 S⁻¹
    m = tex.m0 + K @ v
    IK = eye_2k - K
    P = IK @ tex.S0 @ IK.T + s2 * (K @ K.T)
    # reorder [x_1; x_2] -> stacked state [x_2; x_1]
    perm = jnp.concatenate([jnp.arange(k, 2 * k), jnp.arange(k)])
    m = m[perm]
    P = sym(P[perm][:, perm])

    F = companion_blocks(tex.A1, tex.A2)
    dvec = jnp.concatenate([tex.d, jnp.zeros((k,), dtype)])
    Qfull = jnp.zeros((2 * k, 2 * k), dtype).at[:k, :k].set(tex.B @ tex.B.T)

    def step(carry: tuple[Array, Array, Array], z: Array) -> tuple[Any, None]:
        m, P, ll = carry
        m = F @ m + dvec
        P = F @ P @ F.T + Qfull
        Sk = sym(P[:k, :k]) + s2 * eye_k
        Lk = jnp.linalg.cholesky(Sk)
        v = z - m[:k]
        ll = ll + gauss_logpdf_chol(v, Lk)
        K = jsl.cho_solve((Lk, True), P[:k, :]).T  # P Hᵀ S⁻¹, (2k, k)
        m = m + K @ v
        IKH = eye_2k.at[:, :k].add(-K)
        P = sym(IKH @ P @ IKH.T + s2 * (K @ K.T))
        return (m, P, ll), None

    (_, _, ll), _ = lax.scan(step, (m, P, ll), Z[2:])
    return ll


_exact_ll_jit = eqx.filter_jit(_exact_ll_impl)
