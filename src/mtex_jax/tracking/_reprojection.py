"""The observation term of the smoothers: robust 2-D reprojection of the joints (design §12.2).

For joint ``k`` at frame ``t`` with pixel residual ``r_{tk} = π(x_{tk}) − o_{tk}`` and confidence
``c_{tk}`` the cost is ``c_{tk} ρ(‖r_{tk}‖² / σ²)``, with ``σ`` the pixel noise and ``ρ`` one of
the losses below (a family: one class per member, chosen by passing it):

* :class:`Gaussian`: ``ρ(u) = u / 2``, least squares;
* :class:`StudentT`: ``ρ(u) = (ν + 2)/2 · log(1 + u/ν)``, the negative log-density of a 2-D
  Student-t of ``ν`` degrees of freedom, whose heavy tails let an outlier 50–200 px off cost
  little more than a few pixels' error;
* :class:`Huber`: quadratic up to ``δ`` standard deviations, linear beyond.

Gauss–Newton uses the reweighted model ``½ w ‖r‖²`` with ``w = 2 c ρ'(u) / σ²`` (IRLS),
renewed at every fresh step. A missing joint has ``c = 0`` and costs nothing.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..edit import FrameResidual
from ._camera import Camera

__all__ = ["Gaussian", "Huber", "PixelLoss", "Reprojection", "StudentT"]

_MIN_DEPTH = 1e-3  # metres: a point behind the camera is projected as if just in front


class PixelLoss(eqx.Module):
    """A loss ``ρ(u)`` of a joint's squared whitened pixel residual ``u = ‖r‖²/σ²``."""

    @abc.abstractmethod
    def rho(self, u: Array) -> Array:
        """``ρ(u)``, with ``ρ(0) = 0``."""

    @abc.abstractmethod
    def drho(self, u: Array) -> Array:
        """``ρ'(u)``."""


class Gaussian(PixelLoss):
    """Least squares: ``ρ(u) = u / 2``."""

    def rho(self, u: Array) -> Array:
        return 0.5 * u

    def drho(self, u: Array) -> Array:
        return jnp.full_like(u, 0.5)


class StudentT(PixelLoss):
    """The 2-D Student-t: ``ρ(u) = (ν + 2)/2 · log(1 + u/ν)``.

    Attributes:
        nu: degrees of freedom (``> 0``; small: heavier tails).
    """

    nu: float = eqx.field(static=True, default=4.0)

    def __check_init__(self) -> None:
        if not (np.isfinite(self.nu) and self.nu > 0):
            raise ValueError(f"StudentT: nu must be positive and finite, got {self.nu}")

    def rho(self, u: Array) -> Array:
        return 0.5 * (self.nu + 2.0) * jnp.log1p(u / self.nu)

    def drho(self, u: Array) -> Array:
        return 0.5 * (self.nu + 2.0) / (self.nu + u)


class Huber(PixelLoss):
    """Huber's loss of ``s = √u``: ``s²/2`` for ``s ≤ δ``, ``δ s − δ²/2`` beyond.

    Attributes:
        delta: the threshold, in standard deviations (``> 0``).
    """

    delta: float = eqx.field(static=True, default=3.0)

    def __check_init__(self) -> None:
        if not (np.isfinite(self.delta) and self.delta > 0):
            raise ValueError(f"Huber: delta must be positive and finite, got {self.delta}")

    def rho(self, u: Array) -> Array:
        s = jnp.sqrt(jnp.maximum(u, 0.0))
        d = self.delta
        return jnp.where(s <= d, 0.5 * u, d * s - 0.5 * d * d)

    def drho(self, u: Array) -> Array:
        s = jnp.sqrt(jnp.maximum(u, 1e-300))
        return 0.5 * jnp.minimum(1.0, self.delta / s)


def project(camera: Camera, x: Float[Array, "*batch 3"]) -> Float[Array, "*batch 2"]:
    """:meth:`Camera.project` with the depth held at least ``1 mm`` (finite behind the camera)."""
    xc = x @ camera.rotation.astype(x.dtype).T + camera.translation.astype(x.dtype)
    z = jnp.maximum(xc[..., 2:3], _MIN_DEPTH)
    return camera.focal.astype(x.dtype) * xc[..., :2] / z + camera.center.astype(x.dtype)


class Reprojection(FrameResidual):
    """The robust reprojection term of ``K`` observed joints (module notes).

    Attributes:
        camera: the camera.
        slots: ``(K,)`` index of each observed joint among the solve's kept joints (static).
        observations: ``(T, K, 2)`` pixels.
        confidence: ``(T, K)`` weights in ``[0, 1]`` (``0``: missing).
        sigma: pixel standard deviation.
        pixel_loss: the loss ``ρ``.
    """

    camera: Camera
    slots: tuple[int, ...] = eqx.field(static=True)
    observations: Float[Array, "T K 2"]
    confidence: Float[Array, "T K"]
    sigma: Float[Array, ""]
    pixel_loss: PixelLoss = eqx.field(default_factory=StudentT)

    def __check_init__(self) -> None:
        T, K = np.shape(self.confidence)
        if np.shape(self.observations) != (T, K, 2) or len(self.slots) != K:
            raise ValueError("Reprojection: observations (T, K, 2), confidence (T, K), K slots")

    def residual(self, P: Float[Array, "T Kp 3"]) -> Float[Array, "T R"]:
        x = P[:, np.asarray(self.slots)]
        r = project(self.camera, x) - self.observations.astype(P.dtype)
        return r.reshape(r.shape[0], -1)

    def _u(self, r: Array) -> Array:
        rr = r.reshape(r.shape[0], -1, 2)
        return jnp.sum(rr * rr, axis=-1) / self.sigma.astype(r.dtype) ** 2  # (T, K)

    def loss(self, r: Float[Array, "T R"]) -> Float[Array, ""]:
        return jnp.sum(self.confidence.astype(r.dtype) * self.pixel_loss.rho(self._u(r)))

    def weights(self, r: Float[Array, "T R"]) -> Float[Array, "T R"]:
        c = self.confidence.astype(r.dtype)
        w = 2.0 * c * self.pixel_loss.drho(self._u(r)) / self.sigma.astype(r.dtype) ** 2
        return jnp.repeat(w, 2, axis=1)
