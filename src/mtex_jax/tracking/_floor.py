"""The floor term of the smoothers: some foot is on the floor (design §12.2).

Monocular observations leave the body's size and its distance traded against each other: a
figure 4 % smaller and 4 % nearer projects almost alike. A dancer stands on the floor, so the
lowest of the feet's heights at frame ``t``, ``m_t = −τ log Σ_f exp(−h_{tf}/τ)`` (a soft minimum,
``τ = 1 cm``), should be the height the texture's training feet stand at (its contact model's
stance height ``h_stance``, the median over the training frames of the lowest foot's height;
the ankle joints stand some 5 cm above the floor). The residual
``(m_t − h_stance − floor) / s`` is priced by a Student-t loss of
``ν = 1`` (a jump, with both feet up, costs only the logarithm of its height): ``s = 3 cm``.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..edit import FrameResidual

__all__ = ["FloorContact"]


class FloorContact(FrameResidual):
    """Some foot on the floor (module notes).

    Attributes:
        slots: the feet's indices among the solve's kept joints (static).
        up: the up axis (static).
        height: the height the feet's joints stand at (the training stance height plus the
            world's floor).
        valid: ``(T,)`` 1 at a frame the term applies to (0: padding, held frames).
        scale: ``s``, metres.
        tau: the soft minimum's temperature, metres.
        nu: the Student-t's degrees of freedom.
    """

    slots: tuple[int, ...] = eqx.field(static=True)
    up: int = eqx.field(static=True)
    height: Float[Array, ""]
    valid: Float[Array, " T"]
    scale: float = eqx.field(static=True, default=0.03)
    tau: float = eqx.field(static=True, default=0.01)
    nu: float = eqx.field(static=True, default=1.0)

    def residual(self, P: Float[Array, "T K 3"]) -> Float[Array, "T 1"]:
        h = P[:, np.asarray(self.slots), self.up]
        m = -self.tau * jnp.log(jnp.sum(jnp.exp(-(h - jnp.min(h, 1, keepdims=True)) / self.tau), 1))
        m = m + jnp.min(h, 1)
        return ((m - self.height.astype(P.dtype)) / self.scale)[:, None]

    def loss(self, r: Float[Array, "T 1"]) -> Float[Array, ""]:
        u = r[:, 0] ** 2
        return jnp.sum(self.valid.astype(r.dtype) * 0.5 * (self.nu + 1) * jnp.log1p(u / self.nu))

    def weights(self, r: Float[Array, "T 1"]) -> Float[Array, "T 1"]:
        u = r[:, 0] ** 2
        return (self.valid.astype(r.dtype) * (self.nu + 1) / (self.nu + u))[:, None]
