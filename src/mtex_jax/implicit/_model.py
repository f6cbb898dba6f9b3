"""Implicit probabilistic motion model (Sidenbladh, Black & Sigal, ECCV 2002; design §7).

The database *is* the model: every window of ``d`` consecutive pose vectors of the training
clips, each with the pose that follows it. Sampling the successor of a new history means
sampling a database window near that history (IP Eq. 3), approximately and in sub-linear time
by a probabilistic search down a binary tree of PCA sign splits (IP §4.1, Eq. 7–8).

Coordinates
-----------
*Pose vector* ``ψ_t`` (``P = 2D`` numbers) of frame ``t`` of a clip:
``ψ_t = [y_t, y_t − y_{t−1}]`` where ``y_t`` is the clip's observation vector from the model's
:class:`~mtex_jax.FeatureMap` (z-scored root displacement in the heading frame, yaw change,
height and joint exponential maps, design §1) and the second half is its frame difference
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
broader than the exact sampler (design §7.3–§7.4).

Structure
---------
The arrays live in a :class:`MotionDatabase` (``_database``), which is all that the kernels
take (tree search and samplers ``_tree``, synthesis ``_synthesis``, tracking ``_tracking``).
:class:`ImplicitModel` holds it beside the :class:`~mtex_jax.FeatureMap`; its methods check
their arguments and call the kernels, and its synthesis methods are the functions of
``_synthesis_api``. Imports go one way: ``_model`` → ``_synthesis_api`` → ``_synthesis`` →
``_tree`` → ``_database``.
"""

from __future__ import annotations

from typing import Any, Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from ..core import check_key
from ..motion import FeatureMap, Motion
from ._database import MotionDatabase
from ._synthesis_api import synthesize, synthesize_poses
from ._tree import sample_exact_jit, sample_tree_jit
from ._windows import check_beta, check_candidates, is_concrete, pose_vectors, window_view

LeafRule = Literal["uniform", "weighted"]


# --------------------------------------------------------------------------- the model
class ImplicitModel(eqx.Module):
    """Database of motion windows with a PCA sign tree (IP §4; see the module docstring).

    Build with :func:`~mtex_jax.implicit.learn`. Sample successors with :meth:`sample` (tree,
    IP Eq. 7–8) or :meth:`sample_exact` (IP Eq. 3); generate motion with :meth:`synthesize`
    (IP §5); track with :func:`~mtex_jax.tracking.track` (IP §3, §6). Arrays are JAX arrays in
    the dtype of the training data (as allowed by the JAX configuration).

    The windows, the tree and their sizes are the database's (``model.database.windows``,
    ``model.database.n_examples``; see :class:`MotionDatabase`).

    Attributes:
        feature_map: the observation map ``motion ↔ y`` (fixes skeleton and frame rate).
        database: the windows, their successors and the tree (:class:`MotionDatabase`), what
            the kernels take.
        explained_variance: fraction of the windows' variance kept by the ``b`` components
            (static float).
        weighting: how ``γ`` was chosen (static): ``"channel"`` (the paper: ``γ`` is each
            parameter's database standard deviation) or ``"body"`` (joint-reach weights,
            pose and velocity groups whitened; see :func:`~mtex_jax.implicit.learn`).
    """

    feature_map: FeatureMap
    database: MotionDatabase
    explained_variance: float = eqx.field(static=True)
    weighting: str = eqx.field(static=True)

    def __check_init__(self) -> None:
        if self.weighting not in ("body", "channel"):
            raise ValueError(
                f"ImplicitModel.weighting must be 'body' or 'channel', got {self.weighting!r}"
            )
        if self.database.pose_dim != 2 * self.feature_map.dim:
            raise ValueError(
                f"ImplicitModel: the database's pose vectors have {self.database.pose_dim} "
                f"numbers, the feature map's {2 * self.feature_map.dim}"
            )

    # ------------------------------------------------------------------ sizes
    @property
    def fps(self) -> float:
        return self.feature_map.fps

    def summary(self) -> dict[str, Any]:
        """Sizes of the database and the tree (for reports)."""
        counts = np.bincount(np.asarray(self.database.codes), minlength=0)
        nonempty = int(np.count_nonzero(counts))
        return {
            "n_examples": self.database.n_examples,
            "window": self.database.window,
            "fps": self.fps,
            "pose_dim": self.database.pose_dim,
            "window_dim": self.database.window_dim,
            "n_components": self.database.n_components,
            "explained_variance": self.explained_variance,
            "weighting": self.weighting,
            "recent_weight": self.database.recent_weight,
            "leaf_max": self.database.leaf_max,
            "nonempty_leaves": nonempty,
            "leaves": 1 << self.database.n_components,
            "mean_leaf_size": self.database.n_examples / max(nonempty, 1),
            "clips": len(self.database.clip_sizes),
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
        if motion.n_frames < self.database.window + 1:
            raise ValueError(
                f"windows_of: the window ({self.database.window} pose vectors) is longer than "
                f"the clip allows ({motion.n_frames} frames, need at least "
                f"{self.database.window + 1})"
            )
        psi = pose_vectors(self.feature_map, motion)
        return self.database.scale_windows(window_view(psi, self.database.window))

    def scale_windows(self, poses: Float[ArrayLike, "*batch d P"]) -> Float[Array, "*batch W"]:
        """Model coordinates of windows of pose vectors (:meth:`MotionDatabase.scale_windows`)."""
        return self.database.scale_windows(poses)

    def coefficients(self, probes: Float[ArrayLike, "*batch W"]) -> Float[Array, "*batch b"]:
        """PCA coefficients of probes (:meth:`MotionDatabase.coefficients`)."""
        return self.database.coefficients(probes)

    def distance2(
        self, probes: Float[ArrayLike, "*batch W"], indices: Int[ArrayLike, "*batch"]
    ) -> Float[Array, "*batch"]:
        """Squared Mahalanobis distance (IP Eq. 3, :meth:`MotionDatabase.distance2`)."""
        return self.database.distance2(probes, indices)

    def node_range(
        self, level: int, prefix: Int[ArrayLike, "*batch"]
    ) -> tuple[Int[Array, "*batch"], Int[Array, "*batch"]]:
        """Sorted-order range of a tree node's examples (:meth:`MotionDatabase.node_range`)."""
        return self.database.node_range(level, prefix)

    # ------------------------------------------------------------------ sampling
    def _prepare(self, probes: Any, beta: Any, fn: str) -> tuple[Array, Array, bool]:
        check_beta(beta, fn)
        probes = jnp.asarray(probes)
        if not jnp.issubdtype(probes.dtype, jnp.floating):
            probes = probes.astype(self.database.windows.dtype)
        single = probes.ndim == 1
        if single:
            probes = probes[None]
        if probes.ndim != 2 or probes.shape[1] != self.database.window_dim:
            raise ValueError(
                f"{fn}: probes must have shape (N, {self.database.window_dim}) or "
                f"({self.database.window_dim},) "
                f"(model coordinates, see windows_of), got {probes.shape}"
            )
        if is_concrete(probes) and not bool(jnp.all(jnp.isfinite(probes))):
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
        check_candidates(candidates, "sample")
        check_key(key, "sample")
        probes, beta_a, single = self._prepare(probes, beta, "sample")
        idx = sample_tree_jit(self.database, key, probes, beta_a, leaf, int(candidates))
        succ = self.database.successors[idx]
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
        idx = sample_exact_jit(self.database, key, probes, beta_a)
        succ = self.database.successors[idx]
        return (idx[0], succ[0]) if single else (idx, succ)

    # ------------------------------------------------------------------ synthesis
    # ``model.synthesize(key, ...)`` is ``synthesize(model, key, ...)``: one signature, one
    # docstring (``_synthesis_api``), and the full signature for type checkers and ``help``.
    synthesize = synthesize
    synthesize_poses = synthesize_poses
