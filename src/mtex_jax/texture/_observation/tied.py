"""Tied full-dimensional textons (design §10.10): a vocabulary of textons that share what need
not be their own.

Every texton is a full-dimensional texton (``k = D``, see :mod:`.full`): an AR(2) on ``y``. What
is per texton and what is shared:

.. code-block:: text

    y_t = A1 y_{t−1} + A2 y_{t−2} + d_i + ε_t,     ε_t ~ t_ν(0, Q_i)     (texton i)

    [A1 A2] = R_yx R_xx⁻¹          shared, from the scatter pooled within textons:
                                    R = Σ_i R_i,  R_i the centred (t-weighted) scatter of
                                    [y_t; y_{t−1}; y_{t−2}] over texton i's frames
    d_i = ȳ_i − A1 ȳ_{i,−1} − A2 ȳ_{i,−2}        per texton: where the dance is
    Q_i = (S_i + ν₀ Q̄) / (N_i + ν₀)              per texton, shrunk towards the pooled
                                                 Q̄ = Σ S_i / Σ N_i (the posterior mean of
                                                 an inverse-Wishart prior centred on Q̄)

with ``S_i = E R_i Eᵀ``, ``E = [I, −A1, −A2]``, the texton's residual scatter, and the
initial two-frame Gaussian of each texton as for every texton. A texton is then a *move*
(its mean pose and velocity through ``d_i``, and its own noise shape), the dynamics that make
motion smooth are learned once from every frame, and a new texton costs ``D`` parameters plus
its shrunk covariance rather than ``2D²`` more. Frame terms, segmentation, the forward
algorithm and synthesis are those of full textons: only the M-step is new.

The statistics of each texton arrive in its own coordinates ``z = Cᵢᵀ(y − μᵢ)`` (the
full texton's rotation); they are rotated into ``y`` to pool them and the solution is
rotated back, so a stack of tied textons is an ordinary stack of full
:class:`~mtex_jax.texture.Texton` that holds this member.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, ClassVar

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array

from .._texton.checks import project_radius, psd_cholesky, sym
from .base import FitOptions, T
from .full import FullObservation

if TYPE_CHECKING:
    from .._texton.stats import DynamicsStats, Subspace

__all__ = ["TiedObservation", "tied_dynamics", "tied_initial_state"]

#: Pseudo-starts ``κ`` of the initial two-frame Gaussian's shrinkage towards the pooled pair
#: covariance (chosen by cross-validation over folds of the training clips).
INIT_STARTS = 30.0

#: Pseudo-frames ``ν₀`` of the inverse-Wishart shrinkage of each texton's covariance towards
#: the pooled one (chosen by cross-validation over folds of the training clips).
IW_FRAMES = 500.0


class TiedObservation(FullObservation):
    """Full-dimensional textons with shared dynamics matrices, per-texton offsets and
    per-texton covariances shrunk to a shared one (design §10.10)."""

    name: ClassVar[str] = "tied"

    def n_params(self, n_t: int, D: int, k: int, frames: Any = None, starts: Any = None) -> float:
        """Shared ``A1, A2`` (``2D²``) and ``Q̄`` (``D(D+1)/2``) once; per texton ``d`` (D),
        ``m0`` (2D), the shrunk ``Q_i`` and ``S0`` (design §10.10).

        A shrunk estimate ``(S_i + ν₀ Q̄) / (N_i + ν₀)`` follows its own data with the weight
        ``N_i / (N_i + ν₀)``: that is its effective number of parameters per entry (the trace
        of the map from the texton's data to its estimate, as for a ridge or a conjugate
        hierarchical model). With ``frames`` (each texton's dynamics terms ``N_i``) and
        ``starts`` (its segments), ``Q_i`` counts ``D(D+1)/2 · N_i/(N_i+ν₀)`` and ``S0``
        ``D(2D+1) · s_i/(s_i+κ)``; without them, in full."""
        shared = 2 * D * D + D * (D + 1) // 2
        n_q, n_s0 = D * (D + 1) // 2, D * (2 * D + 1)
        if frames is None or starts is None:
            return float(shared + n_t * (D + 2 * D + n_q + n_s0))
        N = np.asarray(frames, dtype=np.float64)
        s = np.asarray(starts, dtype=np.float64)
        if N.shape != (n_t,) or s.shape != (n_t,):
            raise ValueError(
                f"n_params: frames and starts need one entry per texton ({n_t}), "
                f"got shapes {N.shape} and {s.shape}"
            )
        eff = n_q * N / (N + IW_FRAMES) + n_s0 * s / (s + INIT_STARTS)
        return float(shared + n_t * 3 * D + np.sum(eff))

    def solve(
        self,
        fit_one: Callable[[Subspace, DynamicsStats], T],
        make: Callable[..., T],
        sub: Subspace,
        ds: DynamicsStats,
        opts: FitOptions,
    ) -> T:
        """Every parameter but the subspace's (``μ``, ``C``, ``σ²``) from the tied closed
        form, built by ``make`` (the texton class); no untied fit is computed."""
        del fit_one
        A1, A2, d, B = tied_dynamics(sub.C, ds, opts.ridge, opts.q_floor, opts.rho_max)
        m0, S0 = tied_initial_state(sub.C, ds, opts.q_floor)
        dtype = ds.sum_zz.dtype
        return make(
            mu=sub.mu.astype(dtype),
            C=sub.C.astype(dtype),
            A1=A1,
            A2=A2,
            d=d,
            B=B,
            sigma2=sub.sigma2.astype(dtype),
            m0=m0,
            S0=S0,
            observation=self,
            dof=opts.dof,
        )


def tied_dynamics(
    C: Array,
    ds: DynamicsStats,
    ridge: float,
    q_floor: float,
    rho_max: float | None,
    iw_frames: float = IW_FRAMES,
) -> tuple[Array, Array, Array, Array]:
    """``(A1, A2, d, B)`` of every texton of a stack (each in its own coordinates, ``C (n, D,
    D)``) from their summed dynamics statistics, with ``[A1 A2]`` shared and ``Q_i`` shrunk
    (module doc). The ridge and the stability bound are those of the untied fit."""
    D = C.shape[1]
    dtype = ds.sum_zz.dtype
    eps = jnp.finfo(dtype).eps
    N = ds.n3
    Ns = jnp.maximum(N, 1.0)
    m = ds.sum_z / Ns[:, None]  # (n, 3D) means in texton coordinates
    R = sym(ds.sum_zz - Ns[:, None, None] * m[:, :, None] * m[:, None, :])
    R = jnp.where((N > 0)[:, None, None], R, 0.0)
    C3 = jax.vmap(lambda c: jsl.block_diag(c, c, c))(C)  # z → y − μ for the three lags
    Ry = jnp.einsum("nab,nbc,ndc->nad", C3, R, C3)  # centred scatters in y coordinates
    Rp = jnp.sum(Ry, axis=0)
    Ntot = jnp.maximum(jnp.sum(N), 1.0)
    Rpp = Rp[D:, D:]
    scale = jnp.trace(Rpp) / (2 * D) + Ntot * q_floor
    lam = ridge * scale + 10 * eps * scale
    Lp = psd_cholesky(Rpp, lam)
    A = jsl.cho_solve((Lp, True), Rp[:D, D:].T).T  # (D, 2D)
    A1, A2 = A[:, :D], A[:, D:]
    if rho_max is not None:
        A1, A2 = project_radius(A1, A2, rho_max)
    E = jnp.concatenate([jnp.eye(D, dtype=dtype), -A1, -A2], axis=1)
    S = jnp.einsum("ab,nbc,dc->nad", E, Ry, E)  # residual scatters (n, D, D)
    Qbar = jnp.sum(S, axis=0) / Ntot
    Q = (S + iw_frames * Qbar) / (N + iw_frames)[:, None, None]
    # back to each texton's coordinates: A_z = Cᵀ A C, Q_z = Cᵀ Q C, d from the texton means
    Ct = jnp.swapaxes(C, -1, -2)
    A1z = Ct @ A1 @ C
    A2z = Ct @ A2 @ C
    Qz = Ct @ Q @ C
    dz = (
        m[:, :D]
        - jnp.einsum("nab,nb->na", A1z, m[:, D : 2 * D])
        - jnp.einsum("nab,nb->na", A2z, m[:, 2 * D :])
    )
    B = jax.lax.map(lambda q: psd_cholesky(q, jnp.asarray(q_floor, dtype)), Qz)
    return A1z, A2z, dz, B


def tied_initial_state(
    C: Array, ds: DynamicsStats, q_floor: float, kappa: float = INIT_STARTS
) -> tuple[Array, Array]:
    """``(m0, S0)`` of every texton: the initial two-frame Gaussian of design §2.8 with
    ``kappa`` pseudo-starts, its covariance shrunk towards the pair covariance pooled within
    textons (rather than the texton's own), each in its own coordinates."""
    D = C.shape[1]
    dtype = ds.sum_pp.dtype
    n2 = ds.n2
    n2s = jnp.maximum(n2, 1.0)
    mp = ds.sum_p / n2s[:, None]
    P = ds.sum_pp - n2s[:, None, None] * mp[:, :, None] * mp[:, None, :]
    P = jnp.where((n2 > 0)[:, None, None], P, 0.0)
    C2 = jax.vmap(lambda c: jsl.block_diag(c, c))(C)
    Spool = jnp.einsum("nab,nbc,ndc->ad", C2, P, C2) / jnp.maximum(jnp.sum(n2), 1.0)
    S_tgt = jnp.einsum("nba,bc,ncd->nad", C2, Spool, C2)  # C2ᵀ S C2 per texton
    m_tgt = jnp.where((n2 > 0)[:, None], mp, 0.0)
    ns = ds.n_start
    denom = ns + kappa
    m0 = (ds.sum_s + kappa * m_tgt) / denom[:, None]
    outer = lambda a, b: a[:, :, None] * b[:, None, :]
    scat = ds.sum_ss - outer(ds.sum_s, m0) - outer(m0, ds.sum_s) + ns[:, None, None] * outer(m0, m0)
    dm = m_tgt - m0
    S0 = sym((scat + kappa * (S_tgt + outer(dm, dm))) / denom[:, None, None])
    S0 = S0 + jnp.asarray(q_floor, dtype) * jnp.eye(2 * D, dtype=dtype)
    return m0, S0
