"""The arrays of the implicit model (IP §4): the window database and its PCA sign tree.

:class:`MotionDatabase` is what every kernel of the implicit model takes (tree search,
samplers, synthesis, tracking), in the style of dynamax's parameter structures: a pytree of
arrays with static sizes, checked once when built. :class:`~mtex_jax.implicit.ImplicitModel`
holds one beside its :class:`~mtex_jax.FeatureMap`; the coordinates, the tree and the
temperature convention are described in the docstring of ``_model``.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._windows import MAX_BITS, time_weights


class MotionDatabase(eqx.Module):
    """Database of motion windows with a PCA sign tree (IP §4; see the docstring of ``_model``).

    Arrays are JAX arrays in the dtype of the training data; ``P = 2D`` is the pose-vector
    size, ``W = d·P`` the window size, ``n`` the number of examples, ``b`` the tree depth
    and ``F`` the number of feet.

    Attributes:
        window: ``d``, pose vectors per window (static).
        n_components: ``b``, PCA components = tree depth (static).
        leaf_max: largest number of examples in one leaf (static; sizes the weighted leaf).
        clip_sizes: number of examples contributed by each training clip (static).
        recent_weight: ``w``: the newest pose vector of a window is scaled by ``√(1 + w)``
            in model coordinates (static; ``0``: the paper).
        feet: foot joint indices (static; :func:`mtex_jax.motion.foot_joints`), ``()`` if the
            skeleton has none.
        gamma: ``(P,)`` scale of each pose parameter in model coordinates (``Γ = diag(γ²)``).
        pose_std: ``(P,)`` database standard deviation of each pose parameter (the unit of
            the synthesis and tracking noise).
        mean: ``(W,)`` mean window ``Ψ̄`` in model coordinates.
        basis: ``(W, b)`` principal directions ``Ũ`` (orthonormal columns).
        sigma: ``(b,)`` standard deviation ``σ_l`` of each coefficient.
        windows: ``(n, W)`` example windows in model coordinates (example order).
        successors: ``(n, P)`` pose vector ``ψ_{i+1}`` following each window (FeatureMap
            units).
        codes: ``(n,)`` sign code of each example (int32).
        order: ``(n,)`` example indices sorted by code (stable).
        sorted_codes: ``(n,)`` ``codes[order]``, non-decreasing.
        sorted_coeffs: ``(n, b)`` PCA coefficients in sorted order.
        clip_index: ``(n,)`` training clip of each example.
        frame_index: ``(n,)`` frame (of the possibly resampled clip) of the window's newest
            pose ``ψ_i``; the successor is frame ``frame_index + 1``.
        acceleration_std: ``(D,)`` innovation scale of a constant-velocity prior: database
            standard deviation of ``y_{t+1} − 2y_t + y_{t−1}``, except for the channels that
            already are velocities (root displacement and yaw change,
            :func:`~mtex_jax.implicit.velocity_channels`), where it is that of ``y_{t+1} − y_t``.
        neighbour_radius: ``(n,)`` mean squared distance ``r_i`` of each window to its 10
            nearest database windows (not overlapping it), the local scale of the synthesis
            kernel's hubness correction (:mod:`~mtex_jax.implicit._hubness`).
        foot_contact: ``(n, F)`` contact weight of each foot in each example's successor
            frame, for the synthesis foot lock (:mod:`~mtex_jax.implicit._feet`).
    """

    window: int = eqx.field(static=True)
    n_components: int = eqx.field(static=True)
    leaf_max: int = eqx.field(static=True)
    clip_sizes: tuple[int, ...] = eqx.field(static=True)
    recent_weight: float = eqx.field(static=True)
    feet: tuple[int, ...] = eqx.field(static=True)
    gamma: Float[Array, " P"]
    pose_std: Float[Array, " P"]
    mean: Float[Array, " W"]
    basis: Float[Array, "W b"]
    sigma: Float[Array, " b"]
    windows: Float[Array, "n W"]
    successors: Float[Array, "n P"]
    codes: Int[Array, " n"]
    order: Int[Array, " n"]
    sorted_codes: Int[Array, " n"]
    sorted_coeffs: Float[Array, "n b"]
    clip_index: Int[Array, " n"]
    frame_index: Int[Array, " n"]
    acceleration_std: Float[Array, " D"]
    neighbour_radius: Float[Array, " n"]
    foot_contact: Float[Array, "n F"]

    def __check_init__(self) -> None:
        d, b = self.window, self.n_components
        p = np.shape(self.gamma)[0] if np.ndim(self.gamma) == 1 else -1
        w = d * p
        n = np.shape(self.windows)[0] if np.ndim(self.windows) == 2 else -1
        if d < 1:
            raise ValueError(f"MotionDatabase.window must be ≥ 1, got {d}")
        if not 0 <= self.recent_weight < np.inf:
            raise ValueError(f"MotionDatabase.recent_weight must be ≥ 0, got {self.recent_weight}")
        if not 1 <= b <= MAX_BITS:
            raise ValueError(f"MotionDatabase.n_components must be in 1..{MAX_BITS}, got {b}")
        if n < 1:
            raise ValueError("MotionDatabase: empty database")
        if p < 2 or p % 2:
            raise ValueError(
                f"MotionDatabase.gamma must have shape (2D,), got {np.shape(self.gamma)}"
            )
        expected = {
            "pose_std": (p,),
            "mean": (w,),
            "basis": (w, b),
            "sigma": (b,),
            "windows": (n, w),
            "successors": (n, p),
            "codes": (n,),
            "order": (n,),
            "sorted_codes": (n,),
            "sorted_coeffs": (n, b),
            "clip_index": (n,),
            "frame_index": (n,),
            "acceleration_std": (p // 2,),
            "neighbour_radius": (n,),
            "foot_contact": (n, len(self.feet)),
        }
        for name, shape in expected.items():
            got = np.shape(getattr(self, name))
            if got != shape:
                raise ValueError(f"MotionDatabase.{name} must have shape {shape}, got {got}")
        if sum(self.clip_sizes) != n:
            raise ValueError("MotionDatabase.clip_sizes must add up to the number of examples")

    # ------------------------------------------------------------------ sizes
    @property
    def n_examples(self) -> int:
        """``n``, number of database windows."""
        return int(np.shape(self.windows)[0])

    @property
    def pose_dim(self) -> int:
        """``P = 2D``, numbers per pose vector."""
        return int(np.shape(self.gamma)[0])

    @property
    def window_dim(self) -> int:
        """``W = d·P``, numbers per window (model coordinates)."""
        return self.window * self.pose_dim

    # ------------------------------------------------------------------ coordinates
    def scale_windows(self, poses: Float[ArrayLike, "*batch d P"]) -> Float[Array, "*batch W"]:
        """Model coordinates of windows of pose vectors: ``vec(ψ_k / γ · τ_k)`` with ``τ_k = 1``
        except ``τ_d = √(1 + w)`` for the newest (``w = recent_weight``; pure JAX)."""
        poses = jnp.asarray(poses)
        if poses.shape[-2:] != (self.window, self.pose_dim):
            raise ValueError(
                f"scale_windows: expected (..., {self.window}, {self.pose_dim}), got {poses.shape}"
            )
        g = self.gamma.astype(poses.dtype)
        tw = jnp.asarray(time_weights(self.window, self.recent_weight), poses.dtype)[:, None]
        return (poses / g * tw).reshape(*poses.shape[:-2], self.window_dim)

    def coefficients(self, probes: Float[ArrayLike, "*batch W"]) -> Float[Array, "*batch b"]:
        """PCA coefficients ``c = Ũᵀ(Φ − Ψ̄)`` of probes in model coordinates."""
        probes = jnp.asarray(probes)
        return (probes - self.mean.astype(probes.dtype)) @ self.basis.astype(probes.dtype)

    def distance2(
        self, probes: Float[ArrayLike, "*batch W"], indices: Int[ArrayLike, "*batch"]
    ) -> Float[Array, "*batch"]:
        """Squared Mahalanobis distance (IP Eq. 3) between probes and database examples."""
        probes = jnp.asarray(probes)
        diff = self.windows[jnp.asarray(indices)].astype(probes.dtype) - probes
        return jnp.sum(diff * diff, axis=-1)

    def node_range(
        self, level: int, prefix: Int[ArrayLike, "*batch"]
    ) -> tuple[Int[Array, "*batch"], Int[Array, "*batch"]]:
        """Sorted-order range ``[lo, hi)`` of the examples under a tree node.

        A node at ``level`` (0 = root, ``b`` = leaf) is identified by the ``level``-bit code
        prefix of its examples; its range is found by binary search of the smallest codes of
        ``prefix`` and ``prefix + 1``.
        """
        if not 0 <= level <= self.n_components:
            raise ValueError(f"node_range: level must be in 0..{self.n_components}, got {level}")
        shift = self.n_components - level
        prefix = jnp.asarray(prefix, jnp.int32)
        lo = jnp.searchsorted(self.sorted_codes, jnp.left_shift(prefix, shift), side="left")
        hi = jnp.searchsorted(self.sorted_codes, jnp.left_shift(prefix + 1, shift), side="left")
        return lo.astype(jnp.int32), hi.astype(jnp.int32)
