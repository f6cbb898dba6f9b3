"""What a tracker returns, and the error measures of tracking (design §12.5).

Errors are in the skeleton's length unit (metres for the CMU salsa and DeepMimic data: × 1000
for millimetres), per tracked frame, averaged over the ``K`` observed joints:

* ``error``: Euclidean distance between the estimated and the true world joint positions
  (MPJPE in world coordinates);
* ``error_root_relative``: the same after subtracting each skeleton's first observed joint
  (the root with the default joints) from its joints;
* ``error_aligned``: the same after the similarity (rotation, translation, scale) that best
  aligns the estimate with the truth at that frame (PA-MPJPE; Procrustes by SVD).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..motion import Motion

__all__ = ["TrackResult", "joint_errors", "procrustes_errors"]


class TrackResult(eqx.Module):
    """Output of :func:`~mtex_jax.tracking.track` (per tracked frame ``t``).

    Attributes:
        prior: the temporal prior (static): ``"implicit"`` or ``"constant_velocity"`` for a
            particle filter, ``"texture"`` for the texture's MAP smoother, ``"smooth"`` for a
            MAP with a smoothness-only prior.
        n_particles: particles of a particle filter (static; ``0`` for a MAP smoother).
        mean_joints: ``(T, K, 3)`` estimated world joint positions (a filter's posterior
            mean, a smoother's MAP).
        mean_pose: ``(T, P)`` the estimate in the prior's coordinates (pose vectors of the
            implicit model, observation vectors of a texture).
        mean_root: ``(T, 3)`` estimated root position.
        ess: ``(T,)`` a particle filter's effective sample size ``1 / Σ w²`` before
            resampling (``None`` for a smoother).
        error: ``(T,)`` mean per-joint distance to the truth, world coordinates (``None``
            without a truth).
        error_root_relative: ``(T,)`` the same relative to the first observed joint.
        error_aligned: ``(T,)`` the same after Procrustes alignment (PA-MPJPE).
        labels: ``(T,)`` a texture smoother's texton of every frame (``None`` otherwise).
        bone_scale: ``(J,)`` the bone scales estimated for the person (``None``: the
            skeleton's own bones were used).
        motion: the tracked motion (decodable to BVH), or ``None``.
    """

    prior: str = eqx.field(static=True)
    n_particles: int = eqx.field(static=True)
    mean_joints: Float[Array, "T K 3"]
    mean_pose: Float[Array, "T P"]
    mean_root: Float[Array, "T 3"]
    ess: Float[Array, " T"] | None = None
    error: Float[Array, " T"] | None = None
    error_root_relative: Float[Array, " T"] | None = None
    error_aligned: Float[Array, " T"] | None = None
    labels: Int[Array, " T"] | None = None
    bone_scale: Float[Array, " J"] | None = None
    motion: Motion | None = None

    def __check_init__(self) -> None:
        T, _K = np.shape(self.mean_joints)[:2]
        if np.shape(self.mean_joints)[2:] != (3,) or np.shape(self.mean_root) != (T, 3):
            raise ValueError("TrackResult: mean_joints (T, K, 3) and mean_root (T, 3) expected")
        for name in ("ess", "error", "error_root_relative", "error_aligned", "labels"):
            v = getattr(self, name)
            if v is not None and np.shape(v) != (T,):
                raise ValueError(f"TrackResult.{name} must have shape ({T},)")

    @property
    def mean_error(self) -> float:
        """Mean of :attr:`error` over frames."""
        if self.error is None:
            raise ValueError("TrackResult: no ground truth, so no error")
        return float(jnp.mean(self.error))


def procrustes_errors(
    pred: Float[Any, "T K 3"], truth: Float[Any, "T K 3"]
) -> Float[np.ndarray, " T"]:
    """Per-frame mean joint error after the best similarity transform of ``pred`` onto
    ``truth`` (PA-MPJPE: rotation by SVD, no reflection, isotropic scale, translation)."""
    p = np.asarray(pred, dtype=np.float64)
    q = np.asarray(truth, dtype=np.float64)
    pc = p - p.mean(axis=1, keepdims=True)
    qc = q - q.mean(axis=1, keepdims=True)
    cov = np.einsum("tki,tkj->tij", pc, qc)  # Σ p qᵀ
    u, s, vt = np.linalg.svd(cov)
    sign = np.sign(np.linalg.det(np.einsum("tij,tjk->tik", u, vt)))
    s = s.copy()
    s[:, -1] *= sign
    u = u.copy()
    u[:, :, -1] *= sign[:, None]
    rot = np.einsum("tij,tjk->tik", u, vt)  # maps p to q as p @ rot
    var = np.maximum(np.sum(pc * pc, axis=(1, 2)), 1e-300)
    scale = s.sum(axis=1) / var
    aligned = scale[:, None, None] * np.einsum("tki,tij->tkj", pc, rot) + q.mean(
        axis=1, keepdims=True
    )
    return np.mean(np.linalg.norm(aligned - q, axis=-1), axis=-1)


def joint_errors(
    pred: Float[Any, "T K 3"], truth: Float[Any, "T K 3"]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(error, error_root_relative, error_aligned)`` per frame (module notes)."""
    p = np.asarray(pred, dtype=np.float64)
    q = np.asarray(truth, dtype=np.float64)
    if p.shape != q.shape or p.ndim != 3 or p.shape[-1] != 3:
        raise ValueError(
            f"joint_errors: shapes {p.shape} and {q.shape} differ or are not (T, K, 3)"
        )
    err = np.mean(np.linalg.norm(p - q, axis=-1), axis=-1)
    rel = (p - p[:, :1]) - (q - q[:, :1])
    err_rel = np.mean(np.linalg.norm(rel, axis=-1), axis=-1)
    return err, err_rel, procrustes_errors(p, q)
