"""The closed-form texton fit (design §2; MT App. B): from sufficient statistics to a
:class:`~mtex_jax.texture.Texton`, optionally with the dynamics' spectral radius bounded."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, ArrayLike

from .._observation import ObservationModel, PaperObservation, check_observation
from .checks import (
    check_positive,
    check_state_dim,
    project_radius,
    psd_cholesky,
    student_weights,
    sym,
)
from .options import SolveOptions
from .stats import (
    DynamicsStats,
    Subspace,
    check_fit_inputs,
    dynamics_stats_impl,
    frame_stats_impl,
    subspace_impl,
)
from .texton import Texton

# --------------------------------------------------------------------------------------------
# Solve: statistics -> texton
# --------------------------------------------------------------------------------------------


def texton_from_stats(
    subspace: Subspace,
    stats: DynamicsStats,
    *,
    ridge: float = 1e-6,
    q_floor: float = 1e-6,
    rho_max: float | None = None,
    init_prior_weight: float = 4.0,
    observation: ObservationModel = PaperObservation(),
    sigma2_floor: float = 1e-6,
) -> Texton:
    """Closed-form texton from summed statistics (design §2 step 3, corrected regression).

    With ``N`` valid triples, means ``x̄_i = Σ x_{t−i} / N`` and centred scatters
    ``R_ij = Σ x_{t−i} x_{t−j}ᵀ − N x̄_i x̄_jᵀ``, ``P = [[R11, R12], [R21, R22]]``:

    .. code-block:: text

        [A1 A2] = [R01 R02] (P + λ I)⁻¹,   λ = ridge·(tr P / 2k + N·q_floor) + jitter
        d = x̄_0 − A1 x̄_1 − A2 x̄_2                        (= (Q0 − A1 Q1 − A2 Q2) / N)
        Q = E R Eᵀ / N + q_floor I,   E = [I, −A1, −A2]   (residual covariance; equals
                                                             design §2.5 for the LS [A1 A2])

    ``jitter = 10·eps·(tr P / 2k + N·q_floor)`` keeps the system solvable even for
    ``ridge = 0`` (which otherwise gives plain least squares). With ``rho_max`` set, the
    companion matrix ``[[A1, A2], [I, 0]]`` is projected to spectral radius ``≤ rho_max`` by
    *radial scaling*: ``A1 ← s A1``, ``A2 ← s² A2`` with ``s = min(1, rho_max / ρ)``, which
    multiplies every companion eigenvalue by ``s`` (if ``z`` solves
    ``det(z² I − A1 z − A2) = 0`` then ``s z`` solves it for the scaled pair) while keeping the
    second-order structure; ``d`` and ``Q`` are then re-estimated for the scaled matrices.

    Initial-state Gaussian with shrinkage (``κ = init_prior_weight`` pseudo-observations):
    with ``n_s`` segment starts ``s_b = [x_b; x_{b+1}]`` and the mean/covariance
    ``(m_p, S_p)`` of all consecutive pairs ``[x_{t−1}; x_t]`` of the texton (the empirical
    stationary pair distribution; ``(0, diag(state_var, state_var))`` if there are none),

    .. code-block:: text

        m0 = (Σ s_b + κ m_p) / (n_s + κ)
        S0 = (Σ (s_b − m0)(s_b − m0)ᵀ + κ (S_p + (m_p − m0)(m_p − m0)ᵀ)) / (n_s + κ)
             + q_floor I

    i.e. the start frames pooled with ``κ`` pseudo-samples of the pair distribution; it tends
    to the empirical start distribution when there are many segments and is always PD.

    Residual AR(2) (``observation=ResidualObservation()``, ``k < D``): with the residual lag Gram
    ``G_ab = Σ r_{t−a}·r_{t−b} = sum_uu[a, b] − tr(sum_zz block (a, b))`` over the valid
    triples (``r = (I − C Cᵀ)(y − μ)``, so ``r_s·r_t = u_s·u_t − x_s·x_t``),

    .. code-block:: text

        (a₁, a₂) = G[1:, 1:]⁻¹ G[1:, 0]                      (least squares, same ridge)
        s_r² = (G00 − 2 aᵀG[1:, 0] + aᵀ G[1:, 1:] a) / (N (D − k))   floored at σ²_floor

    the maximum-likelihood isotropic AR(2) of the residual (projected to spectral radius
    ``≤ rho_max`` by the same radial scaling). Otherwise ``a = 0`` and ``s_r² = σ²``.

    Args:
        subspace: pass-1 result (``μ``, ``C``, ``σ²``, state variances).
        stats: pass-2 sums computed with that subspace.
        ridge: relative ridge on the regression normal matrix, ``>= 0``.
        q_floor: absolute floor added to ``Q`` and ``S0`` (units of ``x²`` = ``y²``), ``> 0``.
        rho_max: optional bound on the companion spectral radius, ``> 0``.
        init_prior_weight: shrinkage pseudo-count ``κ >= 0`` for ``(m0, S0)``.
        observation: the observation model's member (see :class:`Texton`; the full and
            tied models need ``k = D``); its M-step gives the texton's member.
        sigma2_floor: floor of the residual innovation variance ``s_r²``.

    Returns:
        A single :class:`Texton` in the dtype of the statistics.
    """
    if not isinstance(subspace, Subspace):
        raise ValueError(f"subspace must be a Subspace, got {type(subspace).__name__}")
    if not isinstance(stats, DynamicsStats):
        raise ValueError(f"stats must be a DynamicsStats, got {type(stats).__name__}")
    k = int(subspace.C.shape[-1])
    if stats.sum_zz.shape != (3 * k, 3 * k):
        raise ValueError(
            f"stats.sum_zz has shape {stats.sum_zz.shape}, expected {(3 * k, 3 * k)} for k={k}"
        )
    observation = check_observation(observation)
    opts = SolveOptions.make(ridge, q_floor, rho_max, init_prior_weight, observation, sigma2_floor)
    observation.check_state_dim(int(subspace.C.shape[0]), k)
    return _texton_from_stats_jit(subspace, stats, opts)


def texton_from_stats_impl(subspace: Subspace, stats: DynamicsStats, opts: SolveOptions) -> Texton:
    dtype = stats.sum_zz.dtype
    k = subspace.C.shape[-1]
    eye_k = jnp.eye(k, dtype=dtype)
    eye_2k = jnp.eye(2 * k, dtype=dtype)
    eps = jnp.finfo(dtype).eps
    q_floor = jnp.asarray(opts.q_floor, dtype)

    # --- dynamics: regression of x_t on [x_{t-1}, x_{t-2}, 1] ---
    N = stats.n3
    Ns = jnp.maximum(N, 1.0)
    mz = stats.sum_z / Ns
    R = sym(stats.sum_zz - Ns * jnp.outer(mz, mz))
    R = jnp.where(N > 0, R, jnp.zeros_like(R))
    R0p = R[:k, k:]
    Rpp = R[k:, k:]
    scale = jnp.trace(Rpp) / (2 * k) + Ns * q_floor
    lam = opts.ridge * scale + 10 * eps * scale
    Lp = psd_cholesky(Rpp, lam)
    A = jsl.cho_solve((Lp, True), R0p.T).T  # (k, 2k) = R0p (P + λI)^-1
    A1, A2 = A[:, :k], A[:, k:]
    if opts.rho_max is not None:
        A1, A2 = project_radius(A1, A2, opts.rho_max)
    d = mz[:k] - A1 @ mz[k : 2 * k] - A2 @ mz[2 * k :]
    E = jnp.concatenate([eye_k, -A1, -A2], axis=1)
    Q = E @ R @ E.T / Ns
    B = psd_cholesky(Q, q_floor)

    # --- initial two-state Gaussian with shrinkage ---
    kappa = jnp.asarray(opts.init_prior_weight, dtype)
    n2 = stats.n2
    n2s = jnp.maximum(n2, 1.0)
    m_pair = stats.sum_p / n2s
    S_pair = sym(stats.sum_pp / n2s - jnp.outer(m_pair, m_pair))
    var = jnp.concatenate([subspace.state_var, subspace.state_var]).astype(dtype)
    m_tgt = jnp.where(n2 > 0, m_pair, 0.0)
    S_tgt = jnp.where(n2 > 0, S_pair, jnp.diag(var))
    ns = stats.n_start
    denom = ns + kappa
    denom_s = jnp.where(denom > 0, denom, 1.0)
    m0 = (stats.sum_s + kappa * m_tgt) / denom_s
    scat = (
        stats.sum_ss
        - jnp.outer(stats.sum_s, m0)
        - jnp.outer(m0, stats.sum_s)
        + ns * jnp.outer(m0, m0)
    )
    dm = m_tgt - m0
    S0 = sym((scat + kappa * (S_tgt + jnp.outer(dm, dm))) / denom_s)
    S0 = jnp.where(denom > 0, S0, jnp.zeros_like(S0)) + q_floor * eye_2k

    D = subspace.C.shape[0]
    observation = opts.observation.fit(stats, k, D, subspace.sigma2, opts)
    return Texton(
        mu=subspace.mu.astype(dtype),
        C=subspace.C.astype(dtype),
        A1=A1,
        A2=A2,
        d=d,
        B=B,
        sigma2=subspace.sigma2.astype(dtype),
        m0=m0,
        S0=S0,
        observation=observation,
        dof=opts.dof,
    )


_texton_from_stats_jit = eqx.filter_jit(texton_from_stats_impl)


# --------------------------------------------------------------------------------------------
# fit_texton
# --------------------------------------------------------------------------------------------


def fit_texton(
    Y: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    state_dim: int,
    ridge: float = 1e-6,
    q_floor: float = 1e-6,
    sigma2_floor: float = 1e-6,
    rho_max: float | None = None,
    init_prior_weight: float = 4.0,
    observation: ObservationModel = PaperObservation(),
    dof: float | None = None,
) -> Texton:
    """Closed-form fit of one texton on one or several segments (design §2; MT App. B).

    Equivalent to ``texton_from_stats(sub, dynamics_stats(Y, mask, sub))`` with
    ``sub = subspace_from_stats(frame_stats(Y, mask))``, in one jit-compiled call. Use that
    two-pass path to sum statistics over sequences or devices before solving.

    Segments: ``mask`` holds a non-negative segment id per frame (``-1`` = frame unused). A
    dynamics term at ``t`` is used only if frames ``t−2, t−1, t`` are consecutive frames of one
    sequence with the same id; adjacent segments therefore need different ids. Frames of
    every segment (including segments of one or two frames) enter ``μ``, ``C`` and ``σ²``.

    Args:
        Y: observations ``(T, D)`` or a batch of sequences ``(S, T, D)`` (sequences never
            connect). Must be finite.
        mask: integer segment ids with Y's leading shape, or ``None`` (each sequence is one
            segment); a boolean mask means ``True`` = frame used, one segment per run.
        state_dim: ``k`` with ``1 <= k <= D`` (static).
        ridge: relative ridge of the dynamics regression (see :func:`texton_from_stats`).
        q_floor: absolute floor added to ``Q`` and ``S0`` (units of ``y²``).
        sigma2_floor: absolute floor of ``σ²`` (units of ``y²``).
        rho_max: optional bound on the spectral radius of ``[[A1, A2], [I, 0]]``.
        init_prior_weight: shrinkage pseudo-count of the initial-state Gaussian.
        observation: the observation model's member, e.g. ``ResidualObservation()`` (the
            full and tied models need ``state_dim = D``; one tied texton is a full one); see
            :class:`Texton`.
        dof: ``None`` (Gaussian innovations) or the degrees of freedom ``ν > 0`` of Student-t
            innovations (the full-dimensional models, full and tied). The t is
            fitted by 10 steps of iteratively reweighted least squares from the Gaussian fit:
            frame ``t``'s dynamics term gets the weight ``w_t = (ν + k) / (ν + q_t)``
            (``q_t`` its squared Mahalanobis innovation under the current fit) and the weighted
            closed form
            above is solved again, with ``Σ w`` in place of ``N`` (the parameter-expanded EM
            of the t, whose fixed point is the maximum-likelihood fit, where ``Σ w = N``).

    Returns:
        A single :class:`Texton` in Y's floating dtype. Differentiable w.r.t. ``Y`` (the
        subspace needs distinct top-``k`` eigenvalues for meaningful gradients).

    Raises:
        ValueError: on wrong shapes, NaN/inf in ``Y`` (eagerly when ``Y`` is concrete; under
            an outer ``jit`` an ``eqx.error_if`` runtime error), ``state_dim`` outside
            ``[1, D]`` or invalid floors.
    """
    Y, mask = check_fit_inputs(Y, mask)
    k = check_state_dim(state_dim, int(Y.shape[-1]), tuple(Y.shape))
    floor = check_positive("sigma2_floor", sigma2_floor)
    observation = check_observation(observation)
    dof = observation.check_dof(dof)
    opts = SolveOptions.make(
        ridge, q_floor, rho_max, init_prior_weight, observation, floor, dof=dof
    )
    observation.check_state_dim(int(Y.shape[-1]), k)
    return _fit_texton_jit(Y, mask, k, floor, opts)


def _fit_texton_impl(
    Y: Array, mask: Array, k: int, sigma2_floor: float, opts: SolveOptions
) -> Texton:
    fs = frame_stats_impl(Y, mask)
    sub = subspace_impl(fs, k, sigma2_floor)
    ds = dynamics_stats_impl(Y, mask, sub)
    tex = texton_from_stats_impl(sub, ds, opts)
    dof = opts.dof
    if dof is None:
        return tex

    def irls(_: Any, tex: Texton) -> Texton:
        w = student_frame_weights(tex, Y, dof)
        return texton_from_stats_impl(sub, dynamics_stats_impl(Y, mask, sub, weights=w), opts)

    return jax.lax.fori_loop(0, opts.irls_steps, irls, tex)


def student_frame_weights(tex: Texton, Y: Array, dof: float) -> Array:
    """Per-frame weights ``(…, T)`` of a Student-t texton on frames ``Y (…, T, D)``:
    ``w_t = (ν + k) / (ν + q_t)``, ``q_t = ‖B⁻¹(x_t − A1 x_{t−1} − A2 x_{t−2} − d)‖²``,
    ``x = Cᵀ(y − μ)``; 1 on the first two frames (they have no dynamics term). Only the
    frames of valid triples use them (:func:`~._stats._dynamics_stats_seq`)."""
    dtype = Y.dtype
    k = tex.A1.shape[-1]
    X = (Y - tex.mu.astype(dtype)) @ tex.C.astype(dtype)
    E = X[..., 2:, :] - X[..., 1:-1, :] @ tex.A1.T - X[..., :-2, :] @ tex.A2.T - tex.d
    U = jsl.solve_triangular(tex.B, jnp.moveaxis(E, -1, 0).reshape(k, -1), lower=True)
    q = jnp.sum(U * U, axis=0).reshape(E.shape[:-1])
    w = student_weights(q, k, dof)
    return jnp.concatenate([jnp.ones((*w.shape[:-1], 2), dtype), w.astype(dtype)], axis=-1)


_fit_texton_jit = eqx.filter_jit(_fit_texton_impl)
