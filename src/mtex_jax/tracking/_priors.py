"""The motion priors of a MAP smoother: a family of quadratic priors over the tracker's
coordinates (design §12.2), chosen by passing one to :class:`~mtex_jax.tracking.MapSmoother`.

Each member gives, at the current estimate ``X₀``, the prior's Hessian as three bands of
``D × D`` blocks (bandwidth two frames) and its gradient, so that the prior is
``½ zᵀ H z + gᵀ z`` in the displacement ``z = X − X₀``, up to a constant:

* :class:`TexturePrior`: the texture's negative log-likelihood along a segmentation (the
  texton dynamics, initial pairs and out-of-subspace terms of design §6.1, exactly quadratic),
  over every channel but the root's three world channels, which the texture models as
  displacements; for those, a second-difference prior of the root's world trajectory
  (``root_accel`` m/s², ``turn_accel`` rad/s² standard deviations);
* :class:`SmoothPrior`: the second-difference prior on every channel (a baseline with no
  texture: ``accel`` z-scored units per second² for the texture's channels), with each
  texture channel's training marginal, ``N(0, pose_sd²)`` in z-scored units, so that
  channels the camera cannot see (a foot's twist) stay where the training poses were.
"""

from __future__ import annotations

import abc
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..edit import (
    FrameSegments,
    WhitenedTextons,
    prior_hessian,
    prior_residuals,
    smoothness_hessian,
)

__all__ = ["MotionPrior", "SmoothPrior", "TexturePrior", "root_weights"]

Bands = tuple[Array, Array, Array]


class MotionPrior(eqx.Module):
    """A quadratic motion prior of the smoother (module notes)."""

    #: whether the prior needs a segmentation of the estimate (re-estimated between rounds)
    segmented: bool = eqx.field(static=True, default=False)

    def whitened(self, textons: Any, dtype: Any) -> WhitenedTextons:
        """The texture's textons as this prior uses them (whitened, in ``dtype``)."""
        return WhitenedTextons.of(textons, dtype)

    @abc.abstractmethod
    def quadratic(
        self,
        tx: WhitenedTextons,
        seg: FrameSegments,
        X0: Float[Array, "T D"],
        Y0: Float[Array, "T D"],
        root_w: Float[Array, " D"],
        fps: float,
        n_valid: Int[Array, ""] | int,
    ) -> tuple[Bands, Float[Array, "T D"]]:
        """``(bands, gradient)`` at ``X₀`` (``Y₀`` its observation vectors; ``root_w`` the
        weights of the root's world channels per unit of second difference, zero elsewhere;
        ``fps`` the frame rate)."""


def _second_difference(T: int, D: int, w: Array, X0: Array, n_valid: Any) -> tuple[Bands, Array]:
    """Bands and gradient of ``½ Σ_t ‖w ⊙ (x_t − 2 x_{t−1} + x_{t−2})‖²`` at ``X₀``."""
    dt = X0.dtype
    sm = smoothness_hessian(T, D, dt, n_valid)
    ww = jnp.diag(w * w)
    bands = (sm[0] * ww, sm[1] * ww, sm[2] * ww)
    ok = (jnp.arange(T) < n_valid).astype(dt)

    def cost(X: Array) -> Array:
        d2 = (X[2:] - 2 * X[1:-1] + X[:-2]) * w * ok[2:, None]
        return 0.5 * jnp.sum(d2 * d2)

    return bands, jax.grad(cost)(X0)


class TexturePrior(MotionPrior):
    """The texture's prior along a segmentation, root by its world trajectory (module notes).

    Attributes:
        weight: multiplies the texture's negative log-likelihood (1: the MAP estimate).
        noise: process-noise inflation, z-scored units per frame: ``noise²·I`` is added to
            every texton's noise covariances (:meth:`~mtex_jax.edit.WhitenedTextons.of`), a
            prior for a dancer a little off the training dancer's dynamics; it also bounds
            the prior's stiffness, which single precision needs (0.03 chosen on folds of the
            training clips, design §12.2; ``0``: the texture itself).
    """

    segmented: bool = eqx.field(static=True, default=True)
    weight: float = eqx.field(static=True, default=1.0)
    noise: float = eqx.field(static=True, default=0.03)

    def __check_init__(self) -> None:
        if not (np.isfinite(self.weight) and self.weight > 0):
            raise ValueError(f"TexturePrior: weight must be positive, got {self.weight}")
        if isinstance(self.noise, bool) or not (np.isfinite(self.noise) and self.noise >= 0):
            raise ValueError(f"TexturePrior: noise must be ≥ 0 and finite, got {self.noise!r}")

    def whitened(self, textons, dtype):
        return WhitenedTextons.of(textons, dtype, self.noise)

    def quadratic(self, tx, seg, X0, Y0, root_w, fps, n_valid):
        del fps
        T, D = X0.shape
        dt = X0.dtype
        keep = (root_w == 0).astype(dt)  # the texture's own channels
        mm = keep[:, None] * keep[None, :]
        H = prior_hessian(tx, seg, dt, n_valid)

        def nll(Y: Array) -> Array:
            e, g, o = prior_residuals(tx, seg, Y, n_valid)
            return 0.5 * (jnp.sum(e * e) + jnp.sum(g * g) + jnp.sum(o * o))

        grad = jax.grad(nll)(Y0) * keep * self.weight
        s = self.weight
        bands = (H[0] * mm * s, H[1] * mm * s, H[2] * mm * s)
        rb, rg = _second_difference(T, D, root_w, X0, n_valid)
        return (bands[0] + rb[0], bands[1] + rb[1], bands[2] + rb[2]), grad + rg


class SmoothPrior(MotionPrior):
    """A second-difference prior on every channel, no texture (module notes).

    Attributes:
        accel: standard deviation of each texture channel's second derivative, in z-scored
            units per second² (the root's world channels use the smoother's root settings).
        pose_sd: standard deviation of each texture channel about its training mean, in
            z-scored units (1: the training marginal; ``None``: no such term).
    """

    accel: float = eqx.field(static=True, default=150.0)
    pose_sd: float | None = eqx.field(static=True, default=1.0)

    def __check_init__(self) -> None:
        if not (np.isfinite(self.accel) and self.accel > 0):
            raise ValueError(f"SmoothPrior: accel must be positive, got {self.accel}")
        if self.pose_sd is not None and not (np.isfinite(self.pose_sd) and self.pose_sd > 0):
            raise ValueError(f"SmoothPrior: pose_sd must be positive or None, got {self.pose_sd}")

    def quadratic(self, tx, seg, X0, Y0, root_w, fps, n_valid):
        T, D = X0.shape
        del tx, seg
        dt = X0.dtype
        w = jnp.where(root_w > 0, root_w, fps * fps / self.accel)
        bands, grad = _second_difference(T, D, w.astype(dt), X0, n_valid)
        if self.pose_sd is None:
            return bands, grad
        # ½ Σ_t ‖y_t / pose_sd‖² over the texture's channels (z-scored: the training mean is 0)
        ok = (jnp.arange(T) < n_valid).astype(dt)
        p = (root_w == 0).astype(dt) / self.pose_sd**2
        H0 = bands[0] + ok[:, None, None] * jnp.diag(p)
        return (H0, bands[1], bands[2]), grad + ok[:, None] * p * Y0


def root_weights(
    D: int, cols: tuple[int, int, int], fps: float, root_accel: float, turn_accel: float
) -> np.ndarray:
    """``(D,)`` weights of the root's world channels per unit of second difference
    (``fps² / accel``), zero elsewhere."""
    w = np.zeros(D)
    w[cols[0]] = w[cols[1]] = fps * fps / root_accel
    w[cols[2]] = fps * fps / turn_accel
    return w
