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
parameter-wise by the database standard deviation ``γ`` (``Γ = diag(γ²)``, IP Eq. 2–3) and
flattened to ``W = d·P`` numbers. These *model coordinates* are what :meth:`windows_of`
returns and what the samplers take as probes. In them the Mahalanobis distance of IP Eq. 3,
``(Ψ_i − Φ_t)ᵀ Γ_d⁻¹ (Ψ_i − Φ_t)``, is the squared Euclidean distance (:meth:`distance2`).
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

import math
from collections.abc import Sequence
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.core import Tracer
from jax.scipy.special import log_ndtr, ndtr
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from ..motion import FeatureMap, Motion

__all__ = ["ImplicitModel", "pose_vectors", "sign_codes", "velocity_channels"]

LeafRule = Literal["uniform", "weighted"]
_MAX_BITS = 30  # sign codes are int32


# --------------------------------------------------------------------------- helpers
def _is_concrete(x: Any) -> bool:
    return not isinstance(x, Tracer)


def _check_beta(beta: Any, fn: str) -> None:
    if _is_concrete(beta):
        b = np.asarray(beta)
        if b.shape != ():
            raise ValueError(f"{fn}: beta must be a scalar, got shape {b.shape}")
        if not (np.isfinite(b) and b > 0):
            raise ValueError(f"{fn}: beta (temperature) must be positive and finite, got {b!r}")


def _check_candidates(candidates: Any, fn: str) -> None:
    if isinstance(candidates, bool) or not isinstance(candidates, int | np.integer):
        raise ValueError(f"{fn}: candidates must be an integer, got {candidates!r}")
    if candidates < 1:
        raise ValueError(f"{fn}: candidates must be ≥ 1, got {candidates}")


def _check_motion_values(m: Motion, what: str) -> None:
    for name in ("root_positions", "rotations"):
        a = np.asarray(getattr(m, name))
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{what}: non-finite values (NaN/inf) in {name}")


def _encode(fm: FeatureMap, motion: Motion) -> np.ndarray:
    """``fm.encode(motion)`` as NumPy, padded to a power-of-two length to share compilations.

    The observation channels of frame ``t`` depend only on frames ``≤ t`` (frame 0 on frame
    1), so appending copies of the last frame leaves the first ``T`` rows unchanged.
    """
    t = motion.n_frames
    length = max(64, 1 << (max(t, 2) - 1).bit_length())
    pad = length - t
    m = motion.numpy()
    if pad:
        rep = lambda a: np.concatenate([a, np.repeat(a[-1:], pad, axis=0)], axis=0)
        lp = None if m.local_positions is None else rep(m.local_positions)
        m = Motion(m.skeleton, m.fps, rep(m.root_positions), rep(m.rotations), lp)
    return np.asarray(fm.encode(m))[:t]


def pose_vectors(fm: FeatureMap, motion: Motion) -> np.ndarray:
    """Pose vectors ``ψ_t = [y_t, y_t − y_{t−1}]`` of frames ``1 … T−1`` of a clip.

    Args:
        fm: the feature map giving ``y_t`` (its units are the pose vector's units).
        motion: a clip with at least 2 frames at ``fm.fps``.

    Returns:
        ``(T − 1, 2D)`` NumPy array; row ``k`` belongs to frame ``k + 1``.
    """
    if motion.n_frames < 2:
        raise ValueError(f"pose_vectors: a clip needs at least 2 frames, got {motion.n_frames}")
    _check_motion_values(motion, "pose_vectors")
    y = _encode(fm, motion)
    return np.concatenate([y[1:], y[1:] - y[:-1]], axis=1)


def velocity_channels(fm: FeatureMap) -> tuple[int, ...]:
    """Indices (into ``y``) of the channels that are per-frame changes: the root's horizontal
    displacement and yaw change (names ``root.d…``)."""
    return tuple(i for i, name in enumerate(fm.active_names) if name.startswith("root.d"))


def _window_view(psi: np.ndarray, d: int) -> np.ndarray:
    """All ``(T' − d + 1, d, P)`` windows of consecutive rows (oldest first)."""
    v = np.lib.stride_tricks.sliding_window_view(psi, d, axis=0)  # (n, P, d)
    return np.ascontiguousarray(np.moveaxis(v, -1, 1))


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
        gamma: ``(P,)`` database standard deviation of each pose parameter (``Γ = diag(γ²)``).
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
    """

    feature_map: FeatureMap
    window: int = eqx.field(static=True)
    n_components: int = eqx.field(static=True)
    leaf_max: int = eqx.field(static=True)
    explained_variance: float = eqx.field(static=True)
    clip_sizes: tuple[int, ...] = eqx.field(static=True)
    gamma: Float[Array, " P"]
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

    def __check_init__(self) -> None:
        d, b = self.window, self.n_components
        p = 2 * self.feature_map.dim
        w = d * p
        n = np.shape(self.windows)[0] if np.ndim(self.windows) == 2 else -1
        if d < 1:
            raise ValueError(f"ImplicitModel.window must be ≥ 1, got {d}")
        if not 1 <= b <= _MAX_BITS:
            raise ValueError(f"ImplicitModel.n_components must be in 1..{_MAX_BITS}, got {b}")
        if n < 1:
            raise ValueError("ImplicitModel: empty database")
        expected = {
            "gamma": (p,),
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
            "leaf_max": self.leaf_max,
            "nonempty_leaves": nonempty,
            "leaves": 1 << self.n_components,
            "mean_leaf_size": self.n_examples / max(nonempty, 1),
            "clips": len(self.clip_sizes),
        }

    # ------------------------------------------------------------------ building
    @classmethod
    def build(
        cls,
        motions: Motion | Sequence[Motion],
        window: int,
        *,
        fps: float | None = None,
        n_components: int | None = None,
        max_components: int | None = None,
        feature_map: FeatureMap | None = None,
        min_std: float = 1e-8,
    ) -> ImplicitModel:
        """Build the database and its sign tree from training clips (IP §4, SPEC §7).

        Args:
            motions: one clip or a list (same skeleton); windows never straddle two clips.
            window: ``d``, pose vectors per window (the paper: ``d = 10`` at 30 Hz ≈ 1/3 s).
            fps: resample every clip to this rate first (default: keep; clips must agree).
            n_components: ``b``; default ``⌊log₂ n⌋``. Always capped by the window dimension
                and the numerical rank of the windows.
            max_components: optional further cap on ``b`` (at most 30: codes are int32).
            feature_map: observation map to use (default ``FeatureMap.fit(motions)``).
            min_std: floor on each parameter's ``γ`` (relative to the largest ``γ``).

        Returns:
            the model (``summary()`` reports ``b``, the explained variance and leaf sizes).

        Raises:
            ValueError: empty database, a clip shorter than ``window + 2`` frames, non-finite
                poses, ``window < 1``, bad component counts, mismatched frame rates.
        """
        if isinstance(motions, Motion):
            motions = [motions]
        motions = list(motions)
        if not motions:
            raise ValueError("ImplicitModel.build: empty database (no motions given)")
        for i, m in enumerate(motions):
            if not isinstance(m, Motion):
                raise TypeError(f"ImplicitModel.build: item {i} is {type(m).__name__}, not Motion")
        if isinstance(window, bool) or not isinstance(window, int | np.integer) or window < 1:
            raise ValueError(f"ImplicitModel.build: window must be an integer ≥ 1, got {window!r}")
        d = int(window)
        for i, m in enumerate(motions):
            _check_motion_values(m, f"ImplicitModel.build: motion {i}")
        if fps is not None:
            motions = [m if m.fps == fps else m.resample(fps) for m in motions]
        for i, m in enumerate(motions):
            if m.n_frames < d + 2:
                raise ValueError(
                    f"ImplicitModel.build: window ({d} pose vectors) is longer than motion {i} "
                    f"allows: it has {m.n_frames} frames, a window plus its successor needs "
                    f"at least {d + 2}"
                )
        if feature_map is None:
            fm = FeatureMap.fit(motions)
        else:
            fm = feature_map
            for m in motions:
                fm._check_motion(m)
        for arg, name in ((n_components, "n_components"), (max_components, "max_components")):
            if arg is not None and (not isinstance(arg, int | np.integer) or arg < 1):
                raise ValueError(f"ImplicitModel.build: {name} must be a positive integer")

        psis = [pose_vectors(fm, m) for m in motions]
        allpsi = np.concatenate(psis, axis=0)
        if not np.all(np.isfinite(allpsi)):
            raise ValueError("ImplicitModel.build: non-finite pose vectors")
        gamma = allpsi.std(axis=0)
        gamma = np.maximum(gamma, min_std * max(float(gamma.max()), 1e-300))
        p = allpsi.shape[1]
        vel_ch = np.asarray(velocity_channels(fm), dtype=np.int64)

        wins, succ, clip_idx, frame_idx, sizes, accs = [], [], [], [], [], []
        for c, psi in enumerate(psis):
            # rows k of psi = frame k+1; window ending at row k needs k+1 < len(psi)
            v = _window_view(psi / gamma, d)[:-1]  # drop the window without a successor
            wins.append(v.reshape(v.shape[0], -1))
            succ.append(psi[d:])
            clip_idx.append(np.full(v.shape[0], c))
            frame_idx.append(np.arange(v.shape[0]) + d)  # newest row d-1+j = frame d+j
            sizes.append(int(v.shape[0]))
            y = psi[:, : p // 2]
            if y.shape[0] >= 3:
                dd = y[2:] - 2 * y[1:-1] + y[:-2]
                dd[:, vel_ch] = (y[2:] - y[1:-1])[:, vel_ch]
                accs.append(dd)
        windows = np.concatenate(wins, axis=0)
        n, w = windows.shape
        if n < 2:
            raise ValueError(f"ImplicitModel.build: database too small ({n} window), need ≥ 2")
        acc = np.concatenate(accs, axis=0) if accs else np.zeros((1, p // 2))
        acc_std = np.maximum(acc.std(axis=0), 1e-12)

        mean = windows.mean(axis=0)
        x = windows - mean
        s, vt = _right_svd(x)
        rank = int(np.sum(s > s[0] * 1e-10)) if s[0] > 0 else 0
        if rank == 0:
            raise ValueError("ImplicitModel.build: all windows are identical")
        b = math.floor(math.log2(n)) if n_components is None else int(n_components)
        b = min(b, w, rank, _MAX_BITS)
        if max_components is not None:
            b = min(b, int(max_components))
        b = max(b, 1)
        basis = vt[:b].T.copy()
        # fix the SVD's sign ambiguity: largest-magnitude loading of each direction positive
        flip = np.sign(basis[np.argmax(np.abs(basis), axis=0), np.arange(b)])
        basis = basis * np.where(flip == 0, 1.0, flip)
        coeffs = x @ basis
        sigma = coeffs.std(axis=0)
        explained = float(np.sum(s[:b] ** 2) / np.sum(s**2))
        codes = _codes_np(coeffs)
        order = np.argsort(codes, kind="stable").astype(np.int32)
        leaf_max = int(np.bincount(codes).max())

        dtype = np.result_type(*[np.asarray(m.rotations).dtype for m in motions], np.float32)
        f = lambda a: jnp.asarray(np.asarray(a, dtype=dtype))
        i32 = lambda a: jnp.asarray(np.asarray(a, dtype=np.int32))
        return cls(
            feature_map=fm,
            window=d,
            n_components=b,
            leaf_max=leaf_max,
            explained_variance=explained,
            clip_sizes=tuple(sizes),
            gamma=f(gamma),
            mean=f(mean),
            basis=f(basis),
            sigma=f(sigma),
            windows=f(windows),
            successors=f(np.concatenate(succ, axis=0)),
            codes=i32(codes),
            order=i32(order),
            sorted_codes=i32(codes[order]),
            sorted_coeffs=f(coeffs[order]),
            clip_index=i32(np.concatenate(clip_idx)),
            frame_index=i32(np.concatenate(frame_idx)),
            acceleration_std=f(acc_std),
        )

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
        """Model coordinates of windows of pose vectors: ``vec(ψ / γ)`` (pure JAX)."""
        poses = jnp.asarray(poses)
        if poses.shape[-2:] != (self.window, self.pose_dim):
            raise ValueError(
                f"scale_windows: expected (..., {self.window}, {self.pose_dim}), got {poses.shape}"
            )
        g = self.gamma.astype(poses.dtype)
        return (poses / g).reshape(*poses.shape[:-2], self.window_dim)

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
        leaf: LeafRule = "uniform",
        sampler: Literal["tree", "exact"] = "tree",
        candidates: int = 1,
        start_position: Float[ArrayLike, " 3"] | None = None,
        start_heading: float | None = None,
    ) -> Motion:
        """Generate motion frame by frame (IP §5) and decode it to a :class:`Motion`.

        Each step samples a database example for the current ``d``-frame history (tree or
        exact sampler) and appends its successor's pose ``y_{i+1}`` plus Gaussian noise of
        standard deviation ``noise · γ`` (per parameter, database units); the velocity half of
        the new pose vector is recomputed as the frame difference of the generated poses, so
        the history always describes the generated motion. One ``lax.scan``.

        Args:
            key: PRNG key.
            start_window: a clip (its frames ``0 … d`` seed the history, and its frame 1 fixes
                the start position and heading) or a ``(d, P)`` array of pose vectors.
            n_frames: frames to generate after the ``d`` seed frames.
            beta: sampling temperature ``> 0``.
            noise: innovation scale ``≥ 0``.
            leaf: leaf rule of the tree sampler.
            sampler: ``"tree"`` (IP Eq. 7–8) or ``"exact"`` (IP Eq. 3).
            candidates: tree walks per step (see :meth:`sample`; 1 = the paper's sampler).
            start_position, start_heading: root position and yaw of the first output frame
                (default: from ``start_window`` if it is a clip, else the origin and 0).

        Returns:
            a clip of ``d + n_frames`` frames: the seed poses followed by the generated ones.
        """
        poses, _ = self.synthesize_poses(
            key,
            start_window,
            n_frames,
            beta,
            noise,
            leaf=leaf,
            sampler=sampler,
            candidates=candidates,
        )
        sp, sh = start_position, start_heading
        if isinstance(start_window, Motion):
            p0, h0 = self.feature_map.start_of(start_window[1:])
            sp = p0 if sp is None else sp
            sh = h0 if sh is None else sh
        return self.feature_map.decode(poses, sp, sh)

    def synthesize_poses(
        self,
        key: PRNGKeyArray,
        start_window: Motion | Float[ArrayLike, "d P"],
        n_frames: int,
        beta: float | Float[ArrayLike, ""],
        noise: float | Float[ArrayLike, ""] = 0.0,
        *,
        leaf: LeafRule = "uniform",
        sampler: Literal["tree", "exact"] = "tree",
        candidates: int = 1,
    ) -> tuple[Float[Array, "T D"], Int[Array, " n_frames"]]:
        """Like :meth:`synthesize` but returns observation vectors ``(d + n_frames, D)`` (seed
        then generated, FeatureMap units) and the sampled example of each generated frame."""
        _check_beta(beta, "synthesize")
        if isinstance(n_frames, bool) or not isinstance(n_frames, int | np.integer):
            raise ValueError(f"synthesize: n_frames must be an integer, got {n_frames!r}")
        if n_frames < 1:
            raise ValueError(f"synthesize: n_frames must be ≥ 1, got {n_frames}")
        if leaf not in ("uniform", "weighted"):
            raise ValueError(f"synthesize: leaf must be 'uniform' or 'weighted', got {leaf!r}")
        if sampler not in ("tree", "exact"):
            raise ValueError(f"synthesize: sampler must be 'tree' or 'exact', got {sampler!r}")
        _check_candidates(candidates, "synthesize")
        if _is_concrete(noise):
            nz = np.asarray(noise)
            if nz.shape != () or not (np.isfinite(nz) and nz >= 0):
                raise ValueError(f"synthesize: noise must be a finite scalar ≥ 0, got {noise!r}")
        if isinstance(start_window, Motion):
            self.feature_map._check_motion(start_window)
            if start_window.n_frames < self.window + 1:
                raise ValueError(
                    f"synthesize: the start clip needs at least {self.window + 1} frames, "
                    f"got {start_window.n_frames}"
                )
            win = jnp.asarray(pose_vectors(self.feature_map, start_window[: self.window + 1]))
        else:
            win = jnp.asarray(start_window)
            if win.shape != (self.window, self.pose_dim):
                raise ValueError(
                    f"synthesize: start_window must be a Motion or a ({self.window}, "
                    f"{self.pose_dim}) array of pose vectors, got shape {win.shape}"
                )
            if _is_concrete(win) and not bool(jnp.all(jnp.isfinite(win))):
                raise ValueError("synthesize: start_window contains NaN or inf")
        dtype = self.windows.dtype
        win = win.astype(dtype)
        gen, idx = _synthesize_jit(
            self,
            key,
            win,
            int(n_frames),
            jnp.asarray(beta, dtype),
            jnp.asarray(noise, dtype),
            leaf,
            sampler,
            int(candidates),
        )
        dim = self.feature_map.dim
        return jnp.concatenate([win[:, :dim], gen], axis=0), idx


# --------------------------------------------------------------------------- pure kernels
@jax.jit
def _right_svd_jit(x: Array) -> tuple[Array, Array]:
    if x.shape[0] > x.shape[1]:
        # X = Q R and R = U S Vᵀ give X = (Q U) S Vᵀ: the same S and V, from a square SVD
        x = jnp.linalg.qr(x, mode="r")
    _, s, vt = jnp.linalg.svd(x, full_matrices=False)
    return s, vt


def _right_svd(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Singular values and right singular vectors of ``x`` (``n × W``), in JAX."""
    s, vt = _right_svd_jit(jnp.asarray(x))
    return np.asarray(s, dtype=np.float64), np.asarray(vt, dtype=np.float64)


def _codes_np(coeffs: np.ndarray) -> np.ndarray:
    b = coeffs.shape[1]
    weights = (1 << np.arange(b - 1, -1, -1)).astype(np.int64)
    return ((coeffs > 0).astype(np.int64) @ weights).astype(np.int32)


def sign_codes(coeffs: Float[ArrayLike, "*batch b"]) -> Int[Array, "*batch"]:
    """``b``-bit sign codes (bit ``b−1−l`` = ``[c_l > 0]``) of coefficient vectors (int32)."""
    coeffs = jnp.asarray(coeffs)
    b = coeffs.shape[-1]
    weights = jnp.left_shift(jnp.int32(1), jnp.arange(b - 1, -1, -1, dtype=jnp.int32))
    return jnp.sum(jnp.where(coeffs > 0, weights, 0), axis=-1).astype(jnp.int32)


def _descend(
    sorted_codes: Int[Array, " n"], z: Float[Array, " b"], u: Float[Array, " b"]
) -> tuple[Array, Array, Array]:
    """Walk the sign tree (IP Eq. 7–8) for one probe with ``z_l = c_{t,l} / (√β σ_l)``.

    At level ``l`` go right iff ``u_l < Φ_N(z_l)``; an empty child forces the other branch.

    Returns:
        the leaf's sorted-order range ``[lo, hi)`` (never empty) and the log-probability of
        the path taken (forced moves count as probability 1).
    """
    b = z.shape[0]
    n = sorted_codes.shape[0]
    p_right = ndtr(z)
    log_r, log_l = log_ndtr(z), log_ndtr(-z)

    def level(lev, carry):
        lo, hi, prefix, logq = carry
        split = jnp.left_shift(2 * prefix + 1, b - 1 - lev)  # smallest code of right child
        mid = jnp.searchsorted(sorted_codes, split, side="left").astype(jnp.int32)
        forced = (mid >= hi) | (mid <= lo)
        right = jnp.where(mid >= hi, False, jnp.where(mid <= lo, True, u[lev] < p_right[lev]))
        logq = logq + jnp.where(forced, 0.0, jnp.where(right, log_r[lev], log_l[lev]))
        lo = jnp.where(right, mid, lo)
        hi = jnp.where(right, hi, mid)
        return lo, hi, 2 * prefix + right.astype(jnp.int32), logq

    init = (jnp.int32(0), jnp.int32(n), jnp.int32(0), jnp.zeros((), z.dtype))
    lo, hi, _, logq = lax.fori_loop(0, b, level, init)
    return lo, hi, logq


def _tree_one(
    model: ImplicitModel, key: PRNGKeyArray, c: Float[Array, " b"], beta: Array, leaf: str
) -> tuple[Int[Array, ""], Float[Array, ""]]:
    """One tree sample for coefficient vector ``c`` → (example index, log proposal prob.)."""
    k_walk, k_leaf = jax.random.split(key)
    b = model.n_components
    scale = jnp.sqrt(beta) * model.sigma.astype(c.dtype)
    u = jax.random.uniform(k_walk, (b,), dtype=c.dtype)
    lo, hi, logq = _descend(model.sorted_codes, c / scale, u)
    if leaf == "uniform":
        v = jax.random.uniform(k_leaf, (), dtype=c.dtype)
        size = (hi - lo).astype(c.dtype)
        pos = jnp.minimum(lo + jnp.floor(v * size).astype(jnp.int32), hi - 1)
        logq = logq - jnp.log(size)
    else:
        cand = lo + jnp.arange(model.leaf_max, dtype=jnp.int32)
        valid = cand < hi
        safe = jnp.minimum(cand, model.n_examples - 1)
        zz = (model.sorted_coeffs[safe].astype(c.dtype) - c) / scale
        logw = jnp.where(valid, -0.5 * jnp.sum(zz * zz, axis=-1), -jnp.inf)
        pick = jax.random.categorical(k_leaf, logw)
        pos = cand[pick]
        logq = logq + logw[pick] - jax.nn.logsumexp(logw)
    return model.order[pos], logq


def tree_sample_indices(
    model: ImplicitModel,
    key: PRNGKeyArray,
    probes: Float[Array, "N W"],
    beta: Array,
    leaf: str,
    candidates: int = 1,
) -> Int[Array, " N"]:
    """Traceable core of :meth:`ImplicitModel.sample` (no checks; usable inside ``jit``).

    With ``candidates = K > 1``: ``K`` independent walks per probe, then one of them chosen
    with probability ``∝ p(i_k | Φ_t) / q(i_k)`` (exact kernel of IP Eq. 3 over the walk's
    proposal probability) — sampling-importance-resampling, ``O(K (b log n + W))``.
    """
    c = model.coefficients(probes)
    n = probes.shape[0]
    one = lambda k, ci: _tree_one(model, k, ci, beta, leaf)
    if candidates == 1:
        return jax.vmap(one)(jax.random.split(key, n), c)[0]
    k_walk, k_pick = jax.random.split(key)
    keys = jax.random.split(k_walk, (n, candidates))
    idx, logq = jax.vmap(jax.vmap(one, in_axes=(0, None)))(keys, c)  # (N, K)
    diff = model.windows[idx].astype(probes.dtype) - probes[:, None, :]
    logp = -0.5 * jnp.sum(diff * diff, axis=-1) / beta
    pick = jax.random.categorical(k_pick, logp - logq, axis=-1)
    return jnp.take_along_axis(idx, pick[:, None], axis=1)[:, 0]


def exact_sample_indices(
    model: ImplicitModel, key: PRNGKeyArray, probes: Float[Array, "N W"], beta: Array
) -> Int[Array, " N"]:
    """Traceable core of :meth:`ImplicitModel.sample_exact`: ``O(n·W)`` per probe."""
    w = model.windows.astype(probes.dtype)
    d2 = (
        jnp.sum(probes * probes, axis=-1, keepdims=True)
        + jnp.sum(w * w, axis=-1)[None, :]
        - 2.0 * probes @ w.T
    )
    logits = -0.5 * jnp.maximum(d2, 0.0) / beta
    return jax.random.categorical(key, logits, axis=-1).astype(jnp.int32)


# The jit entry points count their traces (eqx.debug.get_num_traces) so tests can show that
# new probes of the same shape never recompile.
_sample_tree_traced = eqx.debug.assert_max_traces(tree_sample_indices, max_traces=None)
_sample_tree_jit = eqx.filter_jit(_sample_tree_traced)
_sample_exact_traced = eqx.debug.assert_max_traces(exact_sample_indices, max_traces=None)
_sample_exact_jit = eqx.filter_jit(_sample_exact_traced)


def _synthesize_impl(
    model: ImplicitModel,
    key: PRNGKeyArray,
    win0: Float[Array, "d P"],
    n_frames: int,
    beta: Array,
    noise: Array,
    leaf: str,
    sampler: str,
    candidates: int,
) -> tuple[Array, Array]:
    dim = model.feature_map.dim
    g = model.gamma.astype(win0.dtype)

    def step(win, k):
        k_s, k_n = jax.random.split(k)
        probe = model.scale_windows(win)[None]
        if sampler == "tree":
            idx = tree_sample_indices(model, k_s, probe, beta, leaf, candidates)[0]
        else:
            idx = exact_sample_indices(model, k_s, probe, beta)[0]
        pose = model.successors[idx, :dim].astype(win.dtype)
        pose = pose + noise * g[:dim] * jax.random.normal(k_n, (dim,), win.dtype)
        psi = jnp.concatenate([pose, pose - win[-1, :dim]])
        return jnp.concatenate([win[1:], psi[None]], axis=0), (pose, idx)

    _, (poses, idx) = lax.scan(step, win0, jax.random.split(key, n_frames))
    return poses, idx


_synthesize_jit = eqx.filter_jit(_synthesize_impl)
