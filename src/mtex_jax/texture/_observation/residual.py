"""The residual AR(2) observation model (design §2.9, §10.3): the first two frames of a
segment as in the paper, then an isotropic AR(2) on the residual,

.. code-block:: text

    r_t = a₁ r_{t−1} + a₂ r_{t−2} + e_t,    e_t ~ N(0, s_r² I_{D−k})

in the residual subspace (``Texton.res_a = (a₁, a₂)``, ``Texton.res_s2 = s_r²``). The residual
of smooth motion is smooth, so its one-step prediction error is far smaller than its variance.
In the frame terms the AR(2) replaces the white term on frames ``t ≥ b + 2``: the difference
goes into ``dyn``, so a segment's score keeps its prefix-sum form.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, ClassVar

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._texton.checks import LOG_2PI, UNROLL_MAX_K, project_radius, sym
from .base import ObservationModel, TextonView

if TYPE_CHECKING:
    from .._texton.options import SolveOptions
    from .._texton.stats import DynamicsStats

__all__ = ["ResidualObservation", "window_ar_terms"]


class ResidualObservation(ObservationModel):
    """An isotropic AR(2) on the residual outside the state subspace: 3 more parameters per
    texton (``a₁, a₂, s_r²``); no exact Kalman form."""

    name: ClassVar[str] = "residual"
    kalman: ClassVar[bool] = False

    def extra_params(self, D: int, k: int) -> int:
        return 3 if k < D else 0

    def fit_residual(
        self, stats: DynamicsStats, k: int, D: int, sigma2: Array, opts: SolveOptions
    ) -> tuple[Array, Array]:
        """``(res_a (2,), res_s2 ())`` of the residual AR(2) (see :func:`texton_from_stats`)."""
        dtype = stats.sum_zz.dtype
        if k >= D:
            return jnp.zeros((2,), dtype), sigma2.astype(dtype)
        zz = stats.sum_zz
        tr = jnp.stack(
            [
                jnp.stack(
                    [jnp.trace(zz[a * k : (a + 1) * k, b * k : (b + 1) * k]) for b in range(3)]
                )
                for a in range(3)
            ]
        )
        G = sym(stats.sum_uu - tr)
        Gp = G[1:, 1:]
        scale = jnp.trace(Gp) / 2 + jnp.finfo(dtype).tiny
        eps = jnp.finfo(dtype).eps
        Gp = Gp + (opts.ridge * scale + 10 * eps * scale) * jnp.eye(2, dtype=dtype)
        a = jnp.linalg.solve(Gp, G[1:, 0])
        if opts.rho_max is not None:
            a1, a2 = project_radius(a[:1, None], a[1:, None], opts.rho_max)
            a = jnp.concatenate([a1[0], a2[0]])
        n = jnp.maximum(stats.n3, 1.0) * (D - k)
        e2 = G[0, 0] - 2.0 * a @ G[1:, 0] + a @ G[1:, 1:] @ a
        s2 = jnp.maximum(e2 / n, opts.sigma2_floor)
        ok = stats.n3 > 0
        return jnp.where(ok, a, 0.0), jnp.where(ok, s2, sigma2).astype(dtype)

    def window_dyn_terms(
        self, Yw: Array, Z: Array, s2: Array, mcmc: Array, textons: TextonView, obs: Array, k: int
    ) -> Array | None:
        D = Yw.shape[1]
        if D <= k:
            return None
        ra1, ra2 = textons.res_a[:, 0, None], textons.res_a[:, 1, None]
        res_s2 = textons.res_s2[:, None]
        res_const = (D - k) * (LOG_2PI + jnp.log(res_s2))
        return window_ar_terms(Yw, Z, s2, ra1, ra2, res_s2, res_const, mcmc, k) - obs[:, 2:]

    def reference_dyn_terms(self, tex: TextonView, U: Array, obs: Array) -> Array | None:
        D, k = tex.C.shape
        if U.shape[0] < 3 or D <= k:
            return None
        # e_t = r_t − a₁ r_{t−1} − a₂ r_{t−2} directly: ‖e‖² = ‖w‖² − ‖Cᵀw‖², with
        # w_t = u_t − a₁ u_{t−1} − a₂ u_{t−2}, u = y − μ
        a1, a2 = tex.res_a[0], tex.res_a[1]
        Wv = U[2:] - a1 * U[1:-1] - a2 * U[:-2]
        e2 = jnp.maximum(jnp.sum(Wv * Wv, axis=1) - jnp.sum((Wv @ tex.C) ** 2, axis=1), 0.0)
        res = -0.5 * ((D - k) * (LOG_2PI + jnp.log(tex.res_s2)) + e2 / tex.res_s2)
        return res - obs[2:]

    def segment_dyn_term(self, tex: TextonView, Rres: Array) -> Array | None:
        D, k = tex.C.shape
        if D <= k or Rres.shape[0] <= 2:
            return None
        # frames 3.. of the residual by its AR(2) instead of white noise
        r2 = jnp.sum(Rres * Rres, axis=1)[2:]
        white = -0.5 * ((D - k) * (LOG_2PI + jnp.log(tex.sigma2)) + r2 / tex.sigma2)
        E = Rres[2:] - tex.res_a[0] * Rres[1:-1] - tex.res_a[1] * Rres[:-2]
        e2 = jnp.sum(E * E, axis=1)
        ar = -0.5 * ((D - k) * (LOG_2PI + jnp.log(tex.res_s2)) + e2 / tex.res_s2)
        return jnp.sum(ar - white)

    def residual_loglik(
        self, w: np.ndarray, V: np.ndarray, S: np.ndarray, n: int, N: int, k: int
    ) -> float:
        D = w.shape[0]
        # r = (I − CCᵀ) u = P Pᵀ u with P = V[:, k:]: Σ r_a·r_b = tr(Pᵀ S_ab P)
        P = V[:, k:]
        Pb = np.kron(np.eye(3), P)
        Sr = Pb.T @ S @ Pb
        r = D - k
        R = np.array(
            [
                [np.trace(Sr[i * r : (i + 1) * r, j * r : (j + 1) * r]) for j in range(3)]
                for i in range(3)
            ]
        )
        Gr, g = R[1:, 1:], R[0, 1:]
        a = np.linalg.solve(Gr + 1e-12 * np.trace(Gr) * np.eye(2), g)
        ee = R[0, 0] - 2 * a @ g + a @ Gr @ a  # Σ‖r_t − a₁ r_{t−1} − a₂ r_{t−2}‖²
        s2 = max(float(ee) / (N * (D - k)), 1e-12)
        return -0.5 * N * (D - k) * (math.log(s2) + LOG_2PI + 1)


def window_ar_terms(
    Yw: Array,
    Z: Array,
    s2: Array,
    a1: Array,
    a2: Array,
    res_s2: Array,
    res_const: Array,
    mcmc: Array,
    k: int,
) -> Array:
    """Residual AR(2) log-density on frames ``2 … W−1`` of a window, ``(N_t, W − 2)``.

    ``e_t = r_t − a₁ r_{t−1} − a₂ r_{t−2}`` has ``‖e_t‖² = ‖w_t‖² − ‖Cᵀw_t‖²`` with
    ``w_t = u_t − a₁ u_{t−1} − a₂ u_{t−2}`` (``u = y − μ``). Written with the texton-free
    differences ``δ₁ = ŷ_t − ŷ_{t−1}``, ``δ₂ = ŷ_{t−1} − ŷ_{t−2}`` of the centred frames ``ŷ``,
    ``q = 1 − a₁`` and ``c = 1 − a₁ − a₂``,

    .. code-block:: text

        w_t = δ₁ + q δ₂ + c (ŷ_{t−2} − (μ − ȳ))
        ‖w_t‖² = ‖δ₁‖² + q²‖δ₂‖² + 2q δ₁·δ₂ + 2c (δ₁ + q δ₂)·(ŷ_{t−2} − (μ − ȳ))
                 + c² ‖ŷ_{t−2} − (μ − ȳ)‖²

    so that only the frame-to-frame differences (small for smooth motion) are squared, not
    the frames, and the per-texton work is on the ``y·μ`` row and the states ``z`` of ``Z``:
    ``Cᵀw_t = U diag(s)(z_t − a₁ z_{t−1} − a₂ z_{t−2})``.
    """
    d1 = Yw[2:] - Yw[1:-1]
    d2 = Yw[1:-1] - Yw[:-2]
    y0 = Yw[:-2]
    n11 = jnp.sum(d1 * d1, axis=1)
    n22 = jnp.sum(d2 * d2, axis=1)
    n12 = jnp.sum(d1 * d2, axis=1)
    g1 = jnp.sum(d1 * y0, axis=1)
    g2 = jnp.sum(d2 * y0, axis=1)
    yn0 = jnp.sum(y0 * y0, axis=1)
    mk = Z[:, k]
    q = 1.0 - a1
    c = 1.0 - a1 - a2
    cross = g1 + q * g2 - (mk[:, 2:] - mk[:, 1:-1]) - q * (mk[:, 1:-1] - mk[:, :-2])
    ww = (
        n11
        + q * q * n22
        + 2.0 * q * n12
        + 2.0 * c * cross
        + c * c * (yn0 - 2.0 * mk[:, :-2] + mcmc)
    )
    v2: Array | float = 0.0
    if k <= UNROLL_MAX_K:
        for j in range(k):
            v = Z[:, j, 2:] - a1 * Z[:, j, 1:-1] - a2 * Z[:, j, :-2]
            v2 = v2 + s2[:, j, None] * v * v
    else:
        a1_, a2_ = a1[:, :, None], a2[:, :, None]
        v = Z[:, :k, 2:] - a1_ * Z[:, :k, 1:-1] - a2_ * Z[:, :k, :-2]
        v2 = jnp.einsum("nj,njt->nt", s2, v * v)
    e2 = jnp.maximum(ww - v2, 0.0)
    return -0.5 * (res_const + e2 / res_s2)
