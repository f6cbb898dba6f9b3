"""Texton likelihoods: the direct per-segment reference (:func:`segment_log_likelihood`) and the
exact marginal likelihood of the full LDS by the one Kalman filter of textons
(:func:`exact_log_likelihood`, :func:`exact_log_likelihood_segments`; the refinement of
``lds_refine`` maximises it)."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jax import lax
from jaxtyping import Array, ArrayLike, Float

from .checks import (
    LOG_2PI,
    as_float_array,
    check_finite,
    check_mask,
    check_obs,
    error_if_nonfinite,
    float_dtype,
    gauss_logpdf_chol,
    psd_cholesky,
    sym,
)
from .texton import Texton, check_texton

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
        if D > k:  # the observation model's own terms (design §10.3)
            r2 = jnp.sum(Rres * Rres, axis=1)[2:]
            white = -0.5 * ((D - k) * (LOG_2PI + jnp.log(tex.sigma2)) + r2 / tex.sigma2)
            extra = tex.observation.residual_terms(tex.C, Yc, white)
            if extra is not None:
                ll_dyn = ll_dyn + jnp.sum(extra)
    return ll_init + ll_dyn + ll_obs


_segment_ll_jit = eqx.filter_jit(_segment_ll_impl)


def check_kalman(texton: Texton) -> Texton:
    """``texton`` if the Kalman likelihood of the paper's LDS is its likelihood: Gaussian
    innovations and an observation model with that form (``ObservationModel.kalman``);
    ``ValueError`` otherwise."""
    if texton.dof is not None:
        raise ValueError(
            "exact_log_likelihood is the Kalman likelihood of Gaussian textons; this texton "
            f"has Student-t innovations (dof={texton.dof:g}): use segment_log_likelihood"
        )
    if not texton.observation.kalman:
        raise ValueError(
            "exact_log_likelihood is the Kalman likelihood of the paper's model (white "
            f"observation noise); a {texton.observation.name!r} texton has no such form"
        )
    return texton


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
    stacked state ``X_t = [x_t; x_{t−1}]`` (the one filter of textons, that of
    :func:`exact_log_likelihood_segments`): the prior of ``[x_1; x_2]`` updated with ``z_1``,
    then with ``z_2``, then ``lax.scan`` over ``t = 3..L`` of predict
    (``X⁻ = F X + [d; 0]``, ``P⁻ = F P Fᵀ + diag(Q, 0)``) and update with ``H = [I, 0]``
    (innovation covariance ``S = H P⁻ Hᵀ + σ² I_k`` by Cholesky, Joseph-form covariance
    update). Differentiable in the texton parameters and the data.

    Args:
        texton: a single texton.
        Y_segment: ``(L, D)``, ``L >= 2``.

    Returns:
        Scalar log-likelihood.
    """
    texton = check_kalman(check_texton("texton", texton, stacked=False))
    Y = check_obs("Y_segment", Y_segment, texton.obs_dim, min_len=2)
    return _exact_ll_jit(texton, Y)


def _exact_ll_impl(tex: Texton, Y: Array) -> Array:
    Y = error_if_nonfinite(Y, "Y_segment")
    return kalman_log_likelihood(tex, Y, jnp.zeros(Y.shape[:1], jnp.int32))


_exact_ll_jit = eqx.filter_jit(_exact_ll_impl)


# --------------------------------------------------------------------------------------------
# The Kalman filter: the exact likelihood of many segments in one masked scan
# --------------------------------------------------------------------------------------------


def exact_log_likelihood_segments(
    texton: Texton, Y: ArrayLike, mask: ArrayLike | None = None
) -> Float[Array, ""]:
    """Sum over segments of the exact LDS log-likelihood, in one ``lax.scan`` over frames.

    Equals ``Σ_segments exact_log_likelihood(texton, Y[segment])`` (a segment is a maximal
    run of equal non-negative ids; sequences of a batched input never connect; frames with id
    ``-1`` are skipped). Each segment starts from ``[x_b; x_{b+1}] ~ N(m0, S0)``. The filter is
    sequential: at a segment start the prior pair is updated with ``z_b`` (observing its first
    block), at the second frame with ``z_{b+1}``, and afterwards predict/update as in
    :func:`mtex_jax.texture.exact_log_likelihood`. A one-frame segment contributes the
    marginal density of its frame. Static shapes: new data of the same shape do not recompile.

    Args:
        texton: a single texton.
        Y: ``(T, D)`` or ``(S, T, D)`` observations.
        mask: segment ids with Y's leading shape (``-1`` = unused), ``None`` = one segment per
            sequence.

    Returns:
        Scalar log-likelihood.
    """
    texton, Y, mask = check_segments_inputs(texton, Y, mask)
    return _segments_ll_jit(texton, Y, mask)


def check_segments_inputs(texton: Any, Y: Any, mask: Any) -> tuple[Texton, Array, Array]:
    """The inputs of the Kalman likelihood of segments (and of its refinement) checked: a
    single texton whose likelihood it is (:func:`check_kalman`), finite ``(T, D)`` or
    ``(S, T, D)`` frames of its ``D`` and segment ids of their leading shape."""
    texton = check_kalman(check_texton("texton", texton, stacked=False))
    Y = as_float_array("Y", Y, (2, 3), "(T, D) or (S, T, D)")
    if Y.shape[-1] != texton.obs_dim:
        raise ValueError(f"Y has shape {tuple(Y.shape)}, the texton expects D={texton.obs_dim}")
    check_finite("Y", Y)
    return texton, Y, check_mask(mask, tuple(Y.shape[:-1]))


def _segments_ll_seq(tex: Texton, Y: Array, ids: Array) -> Array:
    dtype = Y.dtype
    D, k = tex.C.shape
    s2 = tex.sigma2
    T = Y.shape[0]
    used = ids >= 0
    prev = jnp.concatenate([jnp.full((1,), -2, ids.dtype), ids[:-1]])
    start = used & (prev != ids)
    second = used & ~start & jnp.concatenate([jnp.zeros((1,), bool), start[:-1]])

    Yc = Y - tex.mu
    Z = Yc @ tex.C
    ll_res = jnp.asarray(0.0, dtype)
    if D > k:
        Rres = Yc - Z @ tex.C.T
        r2 = jnp.sum(Rres * Rres, axis=1)
        per = -0.5 * ((D - k) * (LOG_2PI + jnp.log(s2)) + r2 / s2)
        ll_res = jnp.sum(jnp.where(used, per, 0.0))

    eye_k = jnp.eye(k, dtype=dtype)
    eye_2k = jnp.eye(2 * k, dtype=dtype)
    F = jnp.block([[tex.A1, tex.A2], [eye_k, jnp.zeros((k, k), dtype)]])
    dvec = jnp.concatenate([tex.d, jnp.zeros((k,), dtype)])
    Qfull = jnp.zeros((2 * k, 2 * k), dtype).at[:k, :k].set(tex.B @ tex.B.T)
    perm = jnp.concatenate([jnp.arange(k, 2 * k), jnp.arange(k)])
    S0 = sym(tex.S0)

    def step(carry: tuple[Array, Array, Array], inp: tuple[Array, ...]) -> tuple[Any, None]:
        m, P, ll = carry
        z, is_used, is_start, is_second = inp
        m_pred = F @ m + dvec
        P_pred = F @ P @ F.T + Qfull
        m_pri = jnp.where(is_start, tex.m0, jnp.where(is_second, m, m_pred))
        P_pri = jnp.where(is_start, S0, jnp.where(is_second, P, P_pred))
        # update with z = x_top + e, e ~ N(0, σ² I_k)
        Sk = sym(P_pri[:k, :k]) + s2 * eye_k
        Lk = jnp.linalg.cholesky(Sk)
        v = z - m_pri[:k]
        u = jsl.solve_triangular(Lk, v, lower=True)
        ll_t = -0.5 * (k * LOG_2PI + 2.0 * jnp.sum(jnp.log(jnp.diagonal(Lk))) + u @ u)
        K = jsl.cho_solve((Lk, True), P_pri[:k, :]).T
        m_new = m_pri + K @ v
        IKH = eye_2k.at[:, :k].add(-K)
        P_new = sym(IKH @ P_pri @ IKH.T + s2 * (K @ K.T))
        # after the first frame of a segment, reorder [x_b; x_{b+1}] -> [x_{b+1}; x_b]
        m_new = jnp.where(is_start, m_new[perm], m_new)
        P_new = jnp.where(is_start, P_new[perm][:, perm], P_new)
        m_out = jnp.where(is_used, m_new, m)
        P_out = jnp.where(is_used, P_new, P)
        ll_out = ll + jnp.where(is_used, ll_t, 0.0)
        return (m_out, P_out, ll_out), None

    init = (tex.m0, S0, jnp.asarray(0.0, dtype))
    (_, _, ll), _ = lax.scan(step, init, (Z, used, start, second), length=T)
    return ll + ll_res


def kalman_log_likelihood(tex: Texton, Y: Array, mask: Array) -> Array:
    """The one Kalman filter of textons (traced): the exact log-likelihood of the segments of
    ``mask`` in ``Y`` ``(T, D)`` or ``(S, T, D)``, by :func:`_segments_ll_seq`."""
    dtype = float_dtype(Y, tex.mu)
    Y = Y.astype(dtype)
    tex = jax.tree.map(lambda a: a.astype(dtype), tex)
    if Y.ndim == 2:
        return _segments_ll_seq(tex, Y, mask)
    return jnp.sum(jax.vmap(_segments_ll_seq, in_axes=(None, 0, 0))(tex, Y, mask))


def _segments_ll_impl(tex: Texton, Y: Array, mask: Array) -> Array:
    return kalman_log_likelihood(tex, error_if_nonfinite(Y, "Y"), mask)


_segments_ll_jit = eqx.filter_jit(_segments_ll_impl)
