"""Implicit probabilistic motion model (Sidenbladh, Black & Sigal, ECCV 2002; SPEC §7).

The database *is* the model: every window of ``d`` consecutive pose vectors of the training
clips, each with the pose that follows it. Sampling the successor of a new history means
sampling a database window near that history (IP Eq. 3), approximately and in sub-linear time
by a probabilistic search down a binary tree of PCA sign splits (IP §4.1, Eq. 7–8).

Coordinates
-----------
*Pose vector* ``ψ_t`` (``P = 2D`` numbers) of frame ``t`` of a clip:
``ψ_t = [y_t, y_t − y_{t−1}]`` where ``y_t`` is the clip's observation vector from the model's
:class:`~mtex_jax.FeatureMap` (z-scored root displacement in the heading frame, yaw change,
height and joint exponential maps, SPEC §1) and the second half is its frame difference
(velocity). ``ψ`` is defined for frames ``1 … T−1`` of a clip (frame 0 has no predecessor).
Pose vectors are kept in these *FeatureMap units* (``successors``, :meth:`pose_vectors`).

*Window* of frame ``i``: the ``d`` pose vectors ``ψ_{i−d+1}, …, ψ_i`` (oldest first; the paper
writes ``Ψ_i = [ψ_i, …, ψ_{i−d}]`` newest first — the order changes no distance), divided
parameter-wise by the database standard deviation ``γ`` (``Γ = diag(γ²)``, IP Eq. 2–3), the
newest one multiplied by ``√(1 + w)`` (``w = recent_weight``; ``0`` in the paper) and
flattened to ``W = d·P`` numbers. These *model coordinates* are what :meth:`windows_of`
returns and what the samplers take as probes. In them the Mahalanobis distance of IP Eq. 3,
``(Ψ_i − Φ_t)ᵀ Γ_d⁻¹ (Ψ_i − Φ_t)`` (plus ``w`` times that of the newest pose vectors), is the
squared Euclidean distance (:meth:`distance2`).
Database windows never straddle two clips, and each has its successor ``ψ_{i+1}`` in the same
clip, so a clip of ``T`` frames gives ``T − 1 − d`` examples.

Tree
----
PCA (SVD of the mean-subtracted windows) keeps ``b = ⌊log₂ n⌋`` components (capped by the
dimension, the numerical rank and ``max_components``); ``c_i = Ũᵀ(Ψ_i − Ψ̄)`` and ``σ_l`` is
the standard deviation of coefficient ``l``. The sign code of an example is the ``b``-bit
integer whose bit ``b−1−l`` is ``[c_{i,l} > 0]`` (level ``l`` = component ``l``, most
significant first). Examples are stored sorted by code, so a tree node — a code prefix of
length ``l`` — owns a contiguous range of the sorted examples, found by binary search
(``jnp.searchsorted``) of the prefix's smallest code; a leaf is a full code.

Temperature convention (both samplers)
--------------------------------------
``β > 0`` scales the *variance* of the sampling kernel relative to the database variance:

* exact (IP Eq. 3): ``p(i | Φ_t) ∝ exp(−‖Ψ_i − Φ_t‖²_Γ / (2β))`` — kernel ``N(Φ_t, β Γ_d)``;
* tree (IP Eq. 7–8): at level ``l`` go right with probability ``Φ_N(c_{t,l} / (√β σ_l))``,
  i.e. the probability that a coefficient drawn from ``N(c_{t,l}, β σ_l²)`` is positive; the
  weighted leaf rule uses the same kernel, ``p(c_i | c_t) ∝ exp(−Σ_l (c_{i,l} − c_{t,l})² /
  (2 β σ_l²))``.

So β = 1 means "as wide as the database" for both; β → 0 concentrates both on the probe and
β → ∞ makes both uniform (the tree walk then takes each non-empty branch with probability ½).
The two kernels are not identical (the exact one is isotropic in ``Γ``-scaled window space, the
tree's is measured in units of each principal component's spread), so at equal β the tree is
broader than the exact sampler; ``benchmarks/results/implicit.md`` reports the measured ratio.
"""

from __future__ import annotations

from typing import Any, Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from ..core import check_key
from ..motion import FeatureMap, Motion
from ._synthesis_api import SynthesisConfig, SynthLeafRule, synthesize, synthesize_poses
from ._tree import _sample_exact_jit, _sample_tree_jit
from ._windows import (
    _MAX_BITS,
    _check_beta,
    _check_candidates,
    _is_concrete,
    _window_view,
    pose_vectors,
    time_weights,
)

LeafRule = Literal["uniform", "weighted"]


# --------------------------------------------------------------------------- the model
class ImplicitModel(eqx.Module):
    """Database of motion windows with a PCA sign tree (IP §4; see the module docstring).

    Build with :meth:`build`. Sample successors with :meth:`sample` (tree, IP Eq. 7–8) or
    :meth:`sample_exact` (IP Eq. 3); generate motion with :meth:`synthesize` (IP §5); track
    with :func:`mtex_jax._tracking.track` (IP §3, §6). Arrays are JAX arrays in the dtype of
    the training data (as allowed by the JAX configuration).

    Attributes:
        feature_map: the observation map ``motion ↔ y`` (fixes skeleton and frame rate).
        window: ``d``, pose vectors per window (static).
        n_components: ``b``, PCA components = tree depth (static).
        leaf_max: largest number of examples in one leaf (static; sizes the weighted leaf).
        explained_variance: fraction of the windows' variance kept by the ``b`` components
            (static float).
        clip_sizes: number of examples contributed by each training clip (static).
        weighting: how ``γ`` was chosen (static): ``"channel"`` (the paper: ``γ`` is each
            parameter's database standard deviation) or ``"body"`` (joint-reach weights,
            pose and velocity groups whitened; see :func:`~mtex_jax.implicit.learn`).
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
            :func:`velocity_channels`), where it is that of ``y_{t+1} − y_t``.
        neighbour_radius: ``(n,)`` mean squared distance ``r_i`` of each window to its 10
            nearest database windows (not overlapping it), the local scale of the synthesis
            kernel's hubness correction (:mod:`~mtex_jax.implicit._hubness`).
        foot_contact: ``(n, F)`` contact weight of each foot in each example's successor
            frame, for the synthesis foot lock (:mod:`~mtex_jax.implicit._feet`).
    """

    feature_map: FeatureMap
    window: int = eqx.field(static=True)
    n_components: int = eqx.field(static=True)
    leaf_max: int = eqx.field(static=True)
    explained_variance: float = eqx.field(static=True)
    clip_sizes: tuple[int, ...] = eqx.field(static=True)
    weighting: str = eqx.field(static=True)
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
        p = 2 * self.feature_map.dim
        w = d * p
        n = np.shape(self.windows)[0] if np.ndim(self.windows) == 2 else -1
        if d < 1:
            raise ValueError(f"ImplicitModel.window must be ≥ 1, got {d}")
        if not 0 <= self.recent_weight < np.inf:
            raise ValueError(f"ImplicitModel.recent_weight must be ≥ 0, got {self.recent_weight}")
        if self.weighting not in ("body", "channel"):
            raise ValueError(
                f"ImplicitModel.weighting must be 'body' or 'channel', got {self.weighting!r}"
            )
        if not 1 <= b <= _MAX_BITS:
            raise ValueError(f"ImplicitModel.n_components must be in 1..{_MAX_BITS}, got {b}")
        if n < 1:
            raise ValueError("ImplicitModel: empty database")
        expected = {
            "gamma": (p,),
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
                raise ValueError(f"ImplicitModel.{name} must have shape {shape}, got {got}")
        if sum(self.clip_sizes) != n:
            raise ValueError("ImplicitModel.clip_sizes must add up to the number of examples")

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

    @property
    def fps(self) -> float:
        return self.feature_map.fps

    def summary(self) -> dict[str, Any]:
        """Sizes of the database and the tree (for reports)."""
        counts = np.bincount(np.asarray(self.codes), minlength=0)
        nonempty = int(np.count_nonzero(counts))
        return {
            "n_examples": self.n_examples,
            "window": self.window,
            "fps": self.fps,
            "pose_dim": self.pose_dim,
            "window_dim": self.window_dim,
            "n_components": self.n_components,
            "explained_variance": self.explained_variance,
            "weighting": self.weighting,
            "recent_weight": self.recent_weight,
            "leaf_max": self.leaf_max,
            "nonempty_leaves": nonempty,
            "leaves": 1 << self.n_components,
            "mean_leaf_size": self.n_examples / max(nonempty, 1),
            "clips": len(self.clip_sizes),
        }

    # ------------------------------------------------------------------ coordinates
    def pose_vectors(self, motion: Motion) -> np.ndarray:
        """Pose vectors ``(T − 1, P)`` of frames ``1 … T−1`` (FeatureMap units)."""
        self.feature_map._check_motion(motion)
        return pose_vectors(self.feature_map, motion)

    def windows_of(self, motion: Motion) -> Float[Array, "m W"]:
        """All probe windows of a clip in model coordinates, ``(T − d, W)``.

        Row ``k`` is the window whose newest pose is frame ``d + k`` (frames
        ``k + 1 … k + d``). The clip needs ``d + 1`` frames and the model's frame rate.
        """
        self.feature_map._check_motion(motion)
        if motion.n_frames < self.window + 1:
            raise ValueError(
                f"windows_of: the window ({self.window} pose vectors) is longer than the clip "
                f"allows ({motion.n_frames} frames, need at least {self.window + 1})"
            )
        psi = pose_vectors(self.feature_map, motion)
        return self.scale_windows(_window_view(psi, self.window))

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

    # ------------------------------------------------------------------ sampling
    def _prepare(self, probes: Any, beta: Any, fn: str) -> tuple[Array, Array, bool]:
        _check_beta(beta, fn)
        probes = jnp.asarray(probes)
        if not jnp.issubdtype(probes.dtype, jnp.floating):
            probes = probes.astype(self.windows.dtype)
        single = probes.ndim == 1
        if single:
            probes = probes[None]
        if probes.ndim != 2 or probes.shape[1] != self.window_dim:
            raise ValueError(
                f"{fn}: probes must have shape (N, {self.window_dim}) or ({self.window_dim},) "
                f"(model coordinates, see windows_of), got {probes.shape}"
            )
        if _is_concrete(probes) and not bool(jnp.all(jnp.isfinite(probes))):
            raise ValueError(f"{fn}: probes contain NaN or inf")
        return probes, jnp.asarray(beta, probes.dtype), single

    def sample(
        self,
        key: PRNGKeyArray,
        probes: Float[ArrayLike, "N W"],
        beta: float | Float[ArrayLike, ""],
        leaf: LeafRule = "uniform",
        *,
        candidates: int = 1,
    ) -> tuple[Int[Array, " N"], Float[Array, "N P"]]:
        """Probabilistic tree search (IP Eq. 7–8): one example per probe, ``O(b log n + leaf)``.

        At level ``l`` the walk goes right with probability ``Φ_N(c_{t,l} / (√β σ_l))`` and
        left otherwise; if the chosen child holds no example it takes the other. In the leaf
        it picks uniformly (``leaf="uniform"``, ``O(1)``) or with probability ``∝ p(c_i | c_t)
        = exp(−Σ_l (c_{i,l} − c_{t,l})² / (2βσ_l²))`` (``leaf="weighted"``; a masked gather of
        ``leaf_max`` candidates, since leaf sizes vary). Jit-compiled once per probe shape and
        leaf rule (``beta`` is traced), ``vmap`` over probes.

        ``candidates = K > 1`` is an extension beyond the paper: ``K`` walks per probe, of
        which one is kept with probability ``∝ p(i | Φ_t) / q(i)`` — the exact kernel of IP
        Eq. 3 over the walk's own probability of proposing ``i`` (sampling-importance-
        resampling). It tends to :meth:`sample_exact` as ``K → ∞`` at ``O(K (b log n + W))``
        per probe; ``K = 1`` is the paper's sampler.

        Args:
            key: PRNG key.
            probes: ``(N, W)`` (or ``(W,)``) windows in model coordinates.
            beta: temperature ``> 0`` (variance scale, see the module docstring).
            leaf: leaf rule.
            candidates: walks per probe (static; default 1 = IP Eq. 7–8 as published).

        Returns:
            example indices ``(N,)`` and their successor pose vectors ``(N, P)``.
        """
        if leaf not in ("uniform", "weighted"):
            raise ValueError(f"sample: leaf must be 'uniform' or 'weighted', got {leaf!r}")
        _check_candidates(candidates, "sample")
        check_key(key, "sample")
        probes, beta_a, single = self._prepare(probes, beta, "sample")
        idx = _sample_tree_jit(self, key, probes, beta_a, leaf, int(candidates))
        succ = self.successors[idx]
        return (idx[0], succ[0]) if single else (idx, succ)

    def sample_exact(
        self,
        key: PRNGKeyArray,
        probes: Float[ArrayLike, "N W"],
        beta: float | Float[ArrayLike, ""],
    ) -> tuple[Int[Array, " N"], Float[Array, "N P"]]:
        """Exact O(n) reference sampler (IP Eq. 3): ``p(i | Φ_t) ∝ exp(−‖Ψ_i − Φ_t‖²_Γ/(2β))``.

        Args:
            key: PRNG key.
            probes: ``(N, W)`` (or ``(W,)``) windows in model coordinates.
            beta: temperature ``> 0`` (same convention as :meth:`sample`).

        Returns:
            example indices ``(N,)`` and their successor pose vectors ``(N, P)``.
        """
        check_key(key, "sample_exact")
        probes, beta_a, single = self._prepare(probes, beta, "sample_exact")
        idx = _sample_exact_jit(self, key, probes, beta_a)
        succ = self.successors[idx]
        return (idx[0], succ[0]) if single else (idx, succ)

    # ------------------------------------------------------------------ synthesis
    def synthesize(
        self,
        key: PRNGKeyArray,
        start_window: Motion | Float[ArrayLike, "d P"],
        n_frames: int,
        beta: float | Float[ArrayLike, ""],
        noise: float | Float[ArrayLike, ""] = 0.0,
        *,
        sampler: Literal["tree", "exact"] = "tree",
        config: SynthesisConfig | None = None,
        leaf: SynthLeafRule | None = None,
        candidates: int | None = None,
        start_position: Float[ArrayLike, " 3"] | None = None,
        start_heading: float | None = None,
    ) -> Motion:
        """Generate motion (IP §5 and the extensions of :class:`SynthesisConfig`) as a
        :class:`Motion`; see :func:`~mtex_jax.implicit.synthesize` for the arguments."""
        return synthesize(
            self,
            key,
            start_window,
            n_frames,
            beta,
            noise,
            sampler=sampler,
            config=config,
            leaf=leaf,
            candidates=candidates,
            start_position=start_position,
            start_heading=start_heading,
        )

    def synthesize_poses(
        self,
        key: PRNGKeyArray,
        start_window: Motion | Float[ArrayLike, "d P"],
        n_frames: int,
        beta: float | Float[ArrayLike, ""],
        noise: float | Float[ArrayLike, ""] = 0.0,
        *,
        sampler: Literal["tree", "exact"] = "tree",
        config: SynthesisConfig | None = None,
        leaf: SynthLeafRule | None = None,
        candidates: int | None = None,
    ) -> tuple[Float[Array, "T D"], Int[Array, " n_frames"]]:
        """Like :meth:`synthesize` but returns observation vectors ``(d + n_frames, D)`` (seed
        then generated, FeatureMap units) and the database example of each generated frame."""
        return synthesize_poses(
            self,
            key,
            start_window,
            n_frames,
            beta,
            noise,
            sampler=sampler,
            config=config,
            leaf=leaf,
            candidates=candidates,
        )
