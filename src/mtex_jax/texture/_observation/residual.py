"""The residual AR(2) observation model (design §2.9, §10.3): the first two frames of a
segment as in the paper, then an isotropic AR(2) on the residual,

.. code-block:: text

    r_t = a₁ r_{t−1} + a₂ r_{t−2} + e_t,    e_t ~ N(0, s_r² I_{D−k})

in the residual subspace: the member's parameters ``a = (a₁, a₂)`` and ``s2 = s_r²``. The residual
of smooth motion is smooth, so its one-step prediction error is far smaller than its variance.
In the frame terms the AR(2) replaces the white term on frames ``t ≥ b + 2``: the difference
goes into ``dyn``, so a segment's score keeps its prefix-sum form.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, ClassVar

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._texton.checks import LOG_2PI, UNROLL_MAX_K, project_radius, sym
from .base import MEMBER_FIELDS, FitOptions, ObservationModel, ResidualArrays

if TYPE_CHECKING:
    from .._texton.stats import DynamicsStats

__all__ = ["ResidualObservation", "window_ar_terms"]


class ResidualObservation(ObservationModel):
    """An isotropic AR(2) on the residual outside the state subspace: 3 more parameters per
    texton (``a₁, a₂, s_r²``); no exact Kalman form.

    Attributes:
        a: ``(*batch, 2)`` the residual's AR(2) coefficients ``(a₁, a₂)``; ``None`` in a
            member that only chooses the model (what a learn or a fit is given).
        s2: ``(*batch,)`` the residual's innovation variance ``s_r²`` (``None`` with ``a``).
    """

    name: ClassVar[str] = "residual"
    kalman: ClassVar[bool] = False

    a: Float[Array, "*batch 2"] | None = None
    s2: Float[Array, "*batch"] | None = None

    def __check_init__(self) -> None:
        if (self.a is None) != (self.s2 is None):
            raise ValueError("ResidualObservation needs both a and s2, or neither")

    @property
    def fitted(self) -> bool:
        return self.a is not None

    def check_shapes(self, batch: tuple[int, ...], D: int, k: int) -> None:
        if self.a is None or self.s2 is None:
            raise ValueError(
                "observation ResidualObservation() holds no parameters: a texton needs the "
                "fitted member, ResidualObservation(a=(*batch, 2), s2=(*batch,))"
            )
        a, s2 = getattr(self.a, "shape", None), getattr(self.s2, "shape", None)
        if a is None or s2 is None:
            return  # non-array leaves (jax.eval_shape sentinels): nothing to check
        if tuple(a) != (*batch, 2) or tuple(s2) != batch:
            raise ValueError(
                f"ResidualObservation.a and .s2 must have shapes {(*batch, 2)} and {batch} "
                f"(the texton's batch), got {tuple(a)} and {tuple(s2)}"
            )

    def extra_params(self, D: int, k: int) -> int:
        return 3 if k < D else 0

    def to_arrays(self, sigma2: Array) -> ResidualArrays:
        assert self.a is not None
        return {"res_a": self.a, "res_s2": self.s2}

    def from_arrays(self, arrays: ResidualArrays) -> ResidualObservation:
        missing = [f"texton.{f}" for f in MEMBER_FIELDS if f not in arrays]
        if missing:
            raise ValueError(f"a residual texture needs the arrays {missing}")
        return ResidualObservation(a=arrays["res_a"], s2=arrays["res_s2"])

    def fit(
        self, stats: DynamicsStats, k: int, D: int, sigma2: Array, opts: FitOptions
    ) -> ResidualObservation:
        """The residual AR(2) of one texton from its dynamics statistics: least squares on
        the residual's lag Gram (see :func:`~mtex_jax.texture.texton_from_stats`)."""
        dtype = stats.sum_zz.dtype
        if k >= D:
            return ResidualObservation(a=jnp.zeros((2,), dtype), s2=sigma2.astype(dtype))
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
        return ResidualObservation(
            a=jnp.where(ok, a, 0.0), s2=jnp.where(ok, s2, sigma2).astype(dtype)
        )

    def window_dyn_terms(
        self, Yw: Array, Z: Array, s2: Array, mcmc: Array, obs: Array, k: int
    ) -> Array | None:
        D = Yw.shape[1]
        if D <= k:
            return None
        assert self.a is not None and self.s2 is not None
        ra1, ra2 = self.a[:, 0, None], self.a[:, 1, None]
        res_s2 = self.s2[:, None]
        res_const = (D - k) * (LOG_2PI + jnp.log(res_s2))
        return window_ar_terms(Yw, Z, s2, ra1, ra2, res_s2, res_const, mcmc, k) - obs[:, 2:]

    def residual_terms(self, C: Array, U: Array, white: Array) -> Array | None:
        D, k = C.shape
        if U.shape[0] < 3 or D <= k:
            return None
        assert self.a is not None and self.s2 is not None
        # e_t = r_t − a₁ r_{t−1} − a₂ r_{t−2} directly: ‖e‖² = ‖w‖² − ‖Cᵀw‖², with
        # w_t = u_t − a₁ u_{t−1} − a₂ u_{t−2}, u = y − μ
        a1, a2 = self.a[0], self.a[1]
        Wv = U[2:] - a1 * U[1:-1] - a2 * U[:-2]
        e2 = jnp.maximum(jnp.sum(Wv * Wv, axis=1) - jnp.sum((Wv @ C) ** 2, axis=1), 0.0)
        res = -0.5 * ((D - k) * (LOG_2PI + jnp.log(self.s2)) + e2 / self.s2)
        return res - white

    def predict_residual(self, r1: Array, r2: Array) -> Array | None:
        assert self.a is not None
        return self.a[:, :1] * r1 + self.a[:, 1:] * r2

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
