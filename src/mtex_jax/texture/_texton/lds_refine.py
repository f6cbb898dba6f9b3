"""Refinement of a texton beyond the closed form: maximum exact likelihood (design §6).

The closed-form fit (:func:`mtex_jax.texture.fit_texton`) regresses the *projected* states
``x_t = Cᵀ(y_t − μ)``, which contain the observation noise ``Cᵀ w_t``. With noticeable noise
the regression is biased (errors in variables: ``A1, A2`` shrink towards 0, ``Q`` is inflated).
:func:`refine_texton` removes that bias by maximising the exact marginal likelihood of the full
LDS (Kalman filter, design §3) over ``(A1, A2, d, B, σ²)`` with ``optimistix.BFGS``, in an
unconstrained parameterisation:

.. code-block:: text

    A1, A2, d           free
    B = tril(L, −1) + diag(exp(ℓ))        (lower-triangular, positive diagonal ⇒ Q ≻ 0)
    σ² = exp(s)

``μ``, ``C`` (orthonormal, so the ``D``-dimensional likelihood reduces to ``k`` dimensions) and
the initial-state Gaussian ``(m0, S0)`` are kept. The result never has a lower exact
log-likelihood than the input (if the optimiser fails to improve, the input is returned) and a
:class:`RefineReport` says what changed.
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import optimistix as optx
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .checks import (
    as_float_array,
    check_finite,
    check_mask,
    check_positive,
    error_if_nonfinite,
    float_dtype,
    sym,
)
from .texton import Texton, check_texton

__all__ = ["RefineReport", "exact_log_likelihood_segments", "refine_texton"]

LOG_2PI = math.log(2.0 * math.pi)


# --------------------------------------------------------------------------------------------
# Exact likelihood of many segments in one masked scan
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
    texton = check_texton("texton", texton, stacked=False)
    Y = as_float_array("Y", Y, (2, 3), "(T, D) or (S, T, D)")
    if Y.shape[-1] != texton.obs_dim:
        raise ValueError(f"Y has shape {tuple(Y.shape)}, the texton expects D={texton.obs_dim}")
    check_finite("Y", Y)
    mask = check_mask(mask, tuple(Y.shape[:-1]))
    return _segments_ll_jit(texton, Y, mask)


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


def _segments_ll_impl(tex: Texton, Y: Array, mask: Array) -> Array:
    Y = error_if_nonfinite(Y, "Y")
    dtype = float_dtype(Y, tex.mu)
    Y = Y.astype(dtype)
    tex = jax.tree.map(lambda a: a.astype(dtype), tex)
    if Y.ndim == 2:
        return _segments_ll_seq(tex, Y, mask)
    return jnp.sum(jax.vmap(_segments_ll_seq, in_axes=(None, 0, 0))(tex, Y, mask))


_segments_ll_jit = eqx.filter_jit(_segments_ll_impl)


# --------------------------------------------------------------------------------------------
# Refinement
# --------------------------------------------------------------------------------------------


class RefineReport(eqx.Module):
    """What :func:`refine_texton` did, measured.

    Attributes:
        log_likelihood_before: exact log-likelihood of the input texton on the data.
        log_likelihood_after: exact log-likelihood of the returned texton (``>=`` before).
        n_frames: number of frames used (for per-frame comparisons).
        num_steps: BFGS iterations taken.
        converged: whether optimistix reported success (tolerances met within
            ``max_steps``).
        accepted: whether the optimised parameters were kept (``False`` only if they did not
            improve the likelihood, in which case the input is returned unchanged).
    """

    log_likelihood_before: Float[Array, ""]
    log_likelihood_after: Float[Array, ""]
    n_frames: Float[Array, ""]
    num_steps: Int[Array, ""]
    converged: Bool[Array, ""]
    accepted: Bool[Array, ""]

    @property
    def improvement_per_frame(self) -> Float[Array, ""]:
        """``(after − before) / n_frames`` (nats per frame)."""
        return (self.log_likelihood_after - self.log_likelihood_before) / jnp.maximum(
            self.n_frames, 1.0
        )


def _pack(tex: Texton) -> dict[str, Array]:
    diag = jnp.diagonal(tex.B)
    return dict(
        A1=tex.A1,
        A2=tex.A2,
        d=tex.d,
        L=jnp.tril(tex.B, -1),
        log_diag=jnp.log(jnp.maximum(diag, jnp.finfo(diag.dtype).tiny)),
        log_sigma2=jnp.log(tex.sigma2),
    )


def _unpack(theta: dict[str, Array], tex: Texton) -> Texton:
    B = jnp.tril(theta["L"], -1) + jnp.diag(jnp.exp(theta["log_diag"]))
    return eqx.tree_at(
        lambda t: (t.A1, t.A2, t.d, t.B, t.sigma2),
        tex,
        (theta["A1"], theta["A2"], theta["d"], B, jnp.exp(theta["log_sigma2"])),
    )


def refine_texton(
    texton: Texton,
    Y: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    max_steps: int = 200,
    rtol: float = 1e-8,
    atol: float = 1e-8,
) -> tuple[Texton, RefineReport]:
    """Maximise the exact LDS log-likelihood over ``(A1, A2, d, B, σ²)`` with BFGS (design §6).

    Objective: ``−exact_log_likelihood_segments(texton, Y, mask) / n_frames``, minimised with
    ``optimistix.BFGS(rtol, atol)`` in the unconstrained parameterisation of the module
    docstring, starting from ``texton`` (typically the closed-form fit). ``μ``, ``C``, ``m0``
    and ``S0`` are kept fixed. No stability constraint is imposed during refinement.

    Args:
        texton: a single texton (the starting point).
        Y: ``(T, D)`` or ``(S, T, D)`` observations.
        mask: segment ids (``-1`` = unused), as for :func:`mtex_jax.texture.fit_texton`.
        max_steps: maximum BFGS iterations (static).
        rtol: BFGS relative tolerance.
        atol: BFGS absolute tolerance.

    Returns:
        ``(refined texton, RefineReport)``. The refined texton's exact log-likelihood is never
        below the input's: if the optimiser does not improve it, the input is returned and
        ``report.accepted`` is ``False``.
    """
    texton = check_texton("texton", texton, stacked=False)
    Y = as_float_array("Y", Y, (2, 3), "(T, D) or (S, T, D)")
    if Y.shape[-1] != texton.obs_dim:
        raise ValueError(f"Y has shape {tuple(Y.shape)}, the texton expects D={texton.obs_dim}")
    check_finite("Y", Y)
    mask = check_mask(mask, tuple(Y.shape[:-1]))
    if isinstance(max_steps, bool) or not isinstance(max_steps, int | np.integer) or max_steps < 1:
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}")
    rtol = check_positive("rtol", rtol)
    atol = check_positive("atol", atol)
    return _refine_jit(texton, Y, mask, int(max_steps), rtol, atol)


def _refine_impl(
    tex: Texton, Y: Array, mask: Array, max_steps: int, rtol: float, atol: float
) -> tuple[Texton, RefineReport]:
    dtype = float_dtype(Y, tex.mu)
    Y = Y.astype(dtype)
    tex = jax.tree.map(lambda a: a.astype(dtype), tex)
    n_frames = jnp.sum(mask >= 0).astype(dtype)
    scale = jnp.maximum(n_frames, 1.0)

    def loss(theta: dict[str, Array], _: Any) -> Array:
        return -_segments_ll_impl(_unpack(theta, tex), Y, mask) / scale

    theta0 = _pack(tex)
    solver = optx.BFGS(rtol=rtol, atol=atol)
    sol = optx.minimise(loss, solver, theta0, max_steps=max_steps, throw=False)
    new = _unpack(sol.value, tex)
    ll_before = _segments_ll_impl(tex, Y, mask)
    ll_after = _segments_ll_impl(new, Y, mask)
    accept = jnp.isfinite(ll_after) & (ll_after >= ll_before)
    out = jax.tree.map(lambda a, b: jnp.where(accept, a, b), new, tex)
    report = RefineReport(
        log_likelihood_before=ll_before,
        log_likelihood_after=jnp.where(accept, ll_after, ll_before),
        n_frames=n_frames,
        num_steps=jnp.asarray(sol.stats["num_steps"]),
        converged=sol.result == optx.RESULTS.successful,
        accepted=accept,
    )
    return out, report


_refine_jit = eqx.filter_jit(_refine_impl)
