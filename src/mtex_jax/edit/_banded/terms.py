"""Residual terms of the banded solve (design §6.5, §12.2): a family with one small protocol.

A :class:`FrameResidual` is a per-frame residual ``r_t = f_t(P_t)`` of the kept joints'
positions ``P_t (K, 3)`` of frame ``t`` alone, priced by a loss ``Σ_t ρ(r_t)`` (a robust one is
allowed). :func:`~mtex_jax.edit._banded.solve.solve_banded` adds each term's cost to its
objective and, at every fresh Gauss–Newton step, its iteratively reweighted model
``½ Σ w (r + J δ)²`` to the normal equations: the rows ``J_t = ∂f_t/∂P_t · ∂P_t/∂y_t`` come
from the step's per-frame Jacobians of the positions and from forward-mode products of the
residual (one per joint coordinate, every frame at once, because ``f`` is separable over
frames). The 2-D reprojection of a tracker is such a term (:mod:`mtex_jax.tracking`).
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["FrameResidual", "residual_rows"]


class FrameResidual(eqx.Module):
    """A per-frame residual term of the banded solve (module notes)."""

    @abc.abstractmethod
    def residual(self, P: Float[Array, "T K 3"]) -> Float[Array, "T R"]:
        """``(T, R)`` residuals, frame ``t``'s a function of ``P[t]`` alone."""

    @abc.abstractmethod
    def loss(self, r: Float[Array, "T R"]) -> Float[Array, ""]:
        """The term's cost ``Σ ρ`` at residuals ``r`` (``½ Σ w r²`` for a least-squares term)."""

    @abc.abstractmethod
    def weights(self, r: Float[Array, "T R"]) -> Float[Array, "T R"]:
        """Non-negative weights ``w`` of the reweighted model ``½ Σ w r²`` at ``r`` (IRLS:
        ``ρ'(r) / r`` per residual for a loss of ``r`` alone; constant for least squares)."""


def residual_rows(
    term: FrameResidual, P: Float[Array, "T K 3"], Jp: Float[Array, "T K 3 D"]
) -> tuple[Float[Array, "T R D"], Float[Array, "T R"]]:
    """The weighted rows ``√w ⊙ J_t`` and residuals ``√w ⊙ r_t`` of a term at ``P``.

    ``Jp`` holds the per-frame Jacobians of the positions with respect to the channels.
    """
    T, K = P.shape[:2]
    r, lin = jax.linearize(term.residual, P)
    eye = jnp.eye(3 * K, dtype=P.dtype).reshape(3 * K, 1, K, 3)
    dr = jax.lax.map(lambda e: lin(jnp.broadcast_to(e, P.shape)), eye)  # (3K, T, R)
    dr = jnp.moveaxis(dr.reshape(K, 3, T, -1), (0, 1), (2, 3))  # (T, R, K, 3)
    sw = jnp.sqrt(jnp.maximum(term.weights(r), 0.0))
    rows = jnp.einsum("trka,tkad->trd", dr, Jp) * sw[..., None]
    return rows, r * sw
