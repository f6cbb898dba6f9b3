"""Observation vectors ``y_t`` (design §1, MT §6.1) and their inverse.

Raw channels of frame ``t`` (before dropping constants and z-scaling), with ``u`` the up axis
and ``h0, h1`` the two horizontal axes in cyclic order after ``u``:

====================  =====  ===================================================================
channel               size   definition
====================  =====  ===================================================================
root.dh0, root.dh1    2      ``R(ψ_{t−1})⁻¹ (p_t − p_{t−1})`` along ``h0, h1`` (heading frame)
root.height           1      ``p_t[u]`` (absolute)
root.dyaw             1      ``wrap(ψ_t − ψ_{t−1})``, ``ψ`` = twist angle of the root about ``u``
root.tilt             3      exp map of ``R(ψ_t)⁻¹ q_root,t`` (the root rotation without yaw)
<joint>.r             3      exp map of the joint's local rotation, for every non-root joint
<joint>.p             3      local translation, only if the motion has ``local_positions``
====================  =====  ===================================================================

Frame 0 has no predecessor: its displacement and yaw change repeat frame 1's (decoding ignores
them). Exponential maps are made continuous in time (Grassia 1998): of the equivalent vectors
``(θ + 2πn) v/θ`` the one nearest the previous frame's is kept. Channels whose standard
deviation over the training set is ``≤ const_tol`` are dropped and restored as constants; the
others are z-scored. ``decode ∘ encode`` is the identity up to float error.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float

from ..core import (
    as_array,
    bucket_length,
    cut_frames,
    load_arrays_json,
    pad_frames,
    save_arrays_json,
)
from ._channels import decode_raw, raw_features, unit_axis
from ._kinematics import forward_kinematics_arrays
from ._motion import Motion, check_compatible
from ._skeleton import Skeleton, ground_axes

__all__ = ["FeatureMap", "load_feature_map"]

FORMAT_VERSION = 1


class FeatureMap(eqx.Module):
    """Invertible map between a :class:`Motion` and observation vectors ``Y (T, D)``.

    Build it with :meth:`fit` on training clips; then :meth:`encode` and :meth:`decode`.
    ``decode`` is pure JAX and differentiable, so pose objectives on joint positions can be
    differentiated with respect to ``Y``.

    Attributes:
        skeleton: the figure every clip shares (static).
        fps: frame rate of the training clips (static).
        has_local_positions: whether non-root joints carry position channels (static).
        channel_names: names of the ``R`` raw channels (static).
        active: indices of the ``D`` raw channels kept in ``Y`` (static).
        offset: ``(R,)`` per raw channel: training mean (constants: their value).
        scale: ``(R,)`` per raw channel: training standard deviation (constants: 1).
    """

    skeleton: Skeleton = eqx.field(static=True)
    fps: float = eqx.field(static=True)
    has_local_positions: bool = eqx.field(static=True)
    channel_names: tuple[str, ...] = eqx.field(static=True)
    active: tuple[int, ...] = eqx.field(static=True)
    offset: Float[Array, " R"]
    scale: Float[Array, " R"]

    def __check_init__(self) -> None:
        r = len(self.channel_names)
        for name in ("offset", "scale"):
            if np.shape(getattr(self, name)) != (r,):
                raise ValueError(
                    f"FeatureMap.{name} must have shape ({r},), got {np.shape(getattr(self, name))}"
                )
        if any(not 0 <= a < r for a in self.active) or len(set(self.active)) != len(self.active):
            raise ValueError("FeatureMap.active must be distinct channel indices")
        fps = self.fps
        ok = isinstance(fps, int | float) and not isinstance(fps, bool)
        if not (ok and math.isfinite(fps) and 0 < fps <= 10_000):
            raise ValueError(f"FeatureMap.fps must be in (0, 10000] frames per second, got {fps!r}")

    @property
    def dim(self) -> int:
        """Observation dimension ``D``."""
        return len(self.active)

    @property
    def active_names(self) -> tuple[str, ...]:
        return tuple(self.channel_names[a] for a in self.active)

    # ------------------------------------------------------------------ fitting
    @classmethod
    def fit(
        cls,
        motions: Motion | Sequence[Motion],
        *,
        const_tol: float = 1e-6,
        min_scale: float = 0.0,
    ) -> FeatureMap:
        """Fit channel statistics on training clips (same skeleton structure and frame rate).

        Args:
            motions: one clip or a list.
            const_tol: channels whose standard deviation is at most this are constant (raised
                to ``1000·eps·max(1, |mean|)`` of the working precision, so float32 round-off
                never keeps a constant channel).
            min_scale: floor on the per-channel scale, ``scale = max(std, min_scale)``; the
                default 0 is plain z-scoring. A floor (e.g. ``1e-2``) keeps nearly static
                channels (a hand that barely turns) from amplifying capture noise.

        Raises:
            ValueError: empty list, different skeletons or frame rates, non-finite values.
        """
        motions = _fit_inputs(motions)
        return cls._fit_raws(motions, _raws(motions), const_tol, min_scale)

    @classmethod
    def fit_encode(
        cls, motions: Sequence[Motion], *, const_tol: float = 1e-6, min_scale: float = 0.0
    ) -> tuple[FeatureMap, list[np.ndarray]]:
        """:meth:`fit` on ``motions`` and :meth:`encode` of each, with the raw channels
        computed once (for the learner: equal to ``fit`` then ``encode``, in half the work).

        Returns:
            ``(feature map, [Y (T_s, D) as NumPy arrays])``.
        """
        motions = _fit_inputs(motions)
        raws = _raws(motions)
        fm = cls._fit_raws(motions, raws, const_tol, min_scale)
        return fm, [np.asarray(_scale(fm, r)) for r in raws]

    @classmethod
    def _fit_raws(
        cls, motions: list[Motion], raws: list[np.ndarray], const_tol: float, min_scale: float
    ) -> FeatureMap:
        first = motions[0]
        allr = np.concatenate(raws, axis=0)
        if not np.all(np.isfinite(allr)):
            raise ValueError("FeatureMap.fit: non-finite values in the motions")
        mean = allr.astype(np.float64).mean(axis=0)
        std = allr.astype(np.float64).std(axis=0)
        # round-off of the feature computation in the working precision (float32 without x64)
        # must not make a constant channel look as if it moved
        eps = float(np.finfo(allr.dtype).eps) if allr.dtype.kind == "f" else 0.0
        tol = np.maximum(const_tol, 1e3 * eps * np.maximum(1.0, np.abs(mean)))
        moving = std > tol
        active = tuple(int(i) for i in np.nonzero(moving)[0])
        scale = np.where(moving, np.maximum(std, min_scale), 1.0)
        names = _channel_names(first.skeleton, first.local_positions is not None)
        return cls(
            skeleton=first.skeleton,
            fps=float(first.fps),
            has_local_positions=first.local_positions is not None,
            channel_names=names,
            active=active,
            offset=np.asarray(mean),  # type: ignore[arg-type]
            scale=np.asarray(scale),  # type: ignore[arg-type]
        )

    # ------------------------------------------------------------------ encode / decode
    def encode(self, motion: Motion) -> Float[Array, "T D"]:
        """Observation vectors ``Y (T, D)`` of a clip (z-scored active channels); a clip at
        another frame rate is resampled to the map's first (so every function that takes
        motions accepts a 120 Hz clip for a 30 Hz model); a traced one must have its rate."""
        arrays = (getattr(motion, "rotations", None), getattr(motion, "root_positions", None))
        traced = any(isinstance(a, Tracer) for a in arrays)
        if isinstance(motion, Motion) and motion.fps != self.fps and not traced:
            motion = motion.resample(self.fps)
        self._check_motion(motion)
        return _scale(self, _raw(motion))

    def start_of(self, motion: Motion) -> tuple[np.ndarray, float]:
        """Root position ``(3,)`` and heading (radians) of a clip's first frame.

        ``decode(encode(m), *fm.start_of(m))`` reproduces ``m``.
        """
        up = unit_axis(self.skeleton.up_axis)
        # index on the host: an eager index of a JAX array compiles once per clip length
        q0 = np.asarray(motion.rotations, dtype=np.float64)[0, 0]
        heading = float(2.0 * np.arctan2(np.dot(q0[1:], up), q0[0]))
        heading = float((heading + np.pi) % (2 * np.pi) - np.pi)
        return np.asarray(motion.root_positions, dtype=np.float64)[0], heading

    def decode(
        self,
        Y: Float[ArrayLike, "T D"],
        start_position: Float[ArrayLike, 3] | None = None,
        start_heading: float | Float[ArrayLike, ""] | None = None,
    ) -> Motion:
        """Motion from observation vectors (inverse of :meth:`encode`).

        The root yaw and horizontal displacement are integrated from ``start_heading``
        (radians about the up axis, default 0) and ``start_position`` (its up component is
        ignored; the height comes from ``Y``; default the origin). Pure JAX, differentiable.

        Args:
            Y: ``(T, D)`` observations.
            start_position: ``(3,)`` root position of frame 0.
            start_heading: yaw of frame 0.

        Returns:
            a :class:`Motion` with JAX arrays on this map's skeleton.
        """
        Y = as_array(Y)
        if Y.ndim != 2 or Y.shape[1] != self.dim:
            raise ValueError(f"decode: Y must have shape (T, {self.dim}), got {Y.shape}")
        if Y.shape[0] < 1:
            raise ValueError("decode: Y has no frames")
        dtype = Y.dtype if jnp.issubdtype(Y.dtype, jnp.floating) else jnp.result_type(float)
        sp, sh = _start(dtype, start_position, start_heading)
        try:  # a concrete Y is decoded in a shape bucket (design §11; the decoding is causal)
            Yn = np.asarray(Y, dtype=dtype)
        except jax.errors.TracerArrayConversionError:
            pos, rot, lp, _ = _decode(self, Y.astype(dtype), sp, sh)
            return Motion(self.skeleton, self.fps, pos, rot, lp)
        (pos, rot, lp), _ = _decode_host(self, Yn, sp, sh)
        put = jax.device_put
        return Motion(self.skeleton, self.fps, put(pos), put(rot), None if lp is None else put(lp))

    def decode_chunks(
        self,
        chunks: Iterable[Float[ArrayLike, "t D"]],
        start_position: Float[ArrayLike, 3] | None = None,
        start_heading: float | None = None,
    ) -> Iterator[Motion]:
        """Decode one long sequence given as consecutive pieces: a :class:`Motion` per piece.

        Each piece continues the last: its first frame's root displacement and yaw change are
        applied to the previous piece's last root position and heading, carried exactly (the
        heading as integrated, not measured again from a quaternion). The pieces together are
        the motion :meth:`decode` gives for the whole sequence, up to the rounding of the
        running sums, whose order differs; the memory is that of one piece. The first piece
        is exactly :meth:`decode`'s. The arrays are NumPy (host) arrays. Long syntheses are
        decoded and written this way (design §5.11).

        Args:
            chunks: ``(t_i, D)`` concrete observation arrays, in order.
            start_position: ``(3,)`` root position of the first frame (as :meth:`decode`).
            start_heading: yaw of the first frame (radians).

        Yields:
            a :class:`Motion` of ``t_i`` frames per piece.

        Raises:
            ValueError / TypeError: a piece of the wrong shape, or a traced one.
        """
        prev: np.ndarray | None = None
        sp: Any = start_position
        sh: Any = start_heading
        for Yc in chunks:
            if isinstance(Yc, Tracer):
                raise TypeError("decode_chunks: the pieces must be concrete arrays")
            Yn = np.asarray(Yc)
            if Yn.ndim != 2 or Yn.shape[1] != self.dim or Yn.shape[0] < 1:
                raise ValueError(
                    f"decode_chunks: each piece must have shape (t, {self.dim}) with t >= 1, "
                    f"got {Yn.shape}"
                )
            dtype = Yn.dtype if Yn.dtype.kind == "f" else np.dtype(jnp.result_type(float))
            Yn = Yn.astype(dtype, copy=False)
            # after the first piece, the previous piece's last frame anchors this one
            rows = Yn if prev is None else np.concatenate([prev.astype(dtype), Yn])
            (pos, rot, lp), psi = _decode_host(self, rows, *_start(dtype, sp, sh))
            drop = rows.shape[0] - Yn.shape[0]
            pos, rot = pos[drop:], rot[drop:]
            lp = None if lp is None else lp[drop:]
            sp, sh, prev = pos[-1], psi, Yn[-1:]
            yield Motion(self.skeleton, self.fps, pos, rot, lp)

    def joint_positions(
        self,
        Y: Float[ArrayLike, "T D"],
        start_position: Float[ArrayLike, 3] | None = None,
        start_heading: float | Float[ArrayLike, ""] | None = None,
        *,
        end_sites: bool = False,
    ) -> Float[Array, "T J 3"]:
        """World joint positions straight from ``Y`` (``decode`` then forward kinematics).

        A concrete ``Y`` is decoded and posed in a shape bucket, as :meth:`decode` (design §11).
        """
        Y = as_array(Y)
        try:
            Yn = np.asarray(Y)
        except jax.errors.TracerArrayConversionError:
            Yn = None
        T = int(Y.shape[0]) if Y.ndim == 2 else 0
        if Yn is not None and T > 0:
            Y = pad_frames(Yn, bucket_length(T, DECODE_FRAMES))
        m = self.decode(Y, start_position, start_heading)
        P = forward_kinematics_arrays(
            m.skeleton, m.root_positions, m.rotations, m.local_positions, end_sites=end_sites
        )
        return P if Yn is None or T == 0 else cut_frames(P, T)

    def _check_motion(self, motion: Motion) -> None:
        if not isinstance(motion, Motion):
            raise TypeError(f"expected a Motion, got {type(motion).__name__}")
        if not motion.skeleton.same_structure(self.skeleton):
            raise ValueError("motion's skeleton differs from the feature map's skeleton")
        if motion.fps != self.fps:
            raise ValueError(
                f"motion has fps {motion.fps:g}, the feature map {self.fps:g}; "
                f"use motion.resample({self.fps:g})"
            )
        if (motion.local_positions is not None) != self.has_local_positions:
            raise ValueError("motion and feature map disagree on local_positions")

    # ------------------------------------------------------------------ serialisation
    def to_arrays_json(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Plain arrays and a JSON-serialisable dict that describe this map."""
        arrays = {"offset": np.asarray(self.offset), "scale": np.asarray(self.scale)}
        meta = {
            "kind": "mtex_jax.FeatureMap",
            "format_version": FORMAT_VERSION,
            "skeleton": self.skeleton.to_json_dict(),
            "fps": self.fps,
            "has_local_positions": self.has_local_positions,
            "channel_names": list(self.channel_names),
            "active": list(self.active),
        }
        return arrays, meta

    @classmethod
    def from_arrays_json(cls, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> FeatureMap:
        """Inverse of :meth:`to_arrays_json` (validates versions and shapes)."""
        if meta.get("format_version") != FORMAT_VERSION:
            raise ValueError(
                f"FeatureMap format version {meta.get('format_version')!r} is not supported "
                f"(expected {FORMAT_VERSION})"
            )
        try:
            return cls(
                skeleton=Skeleton.from_json_dict(meta["skeleton"]),
                fps=float(meta["fps"]),
                has_local_positions=bool(meta["has_local_positions"]),
                channel_names=tuple(str(c) for c in meta["channel_names"]),
                active=tuple(int(a) for a in meta["active"]),
                offset=np.asarray(arrays["offset"], dtype=np.float64),  # type: ignore[arg-type]
                scale=np.asarray(arrays["scale"], dtype=np.float64),  # type: ignore[arg-type]
            )
        except KeyError as e:
            raise ValueError(f"FeatureMap description lacks {e}") from None

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write this map to a ``.npz`` file (arrays + JSON metadata, no pickle)."""
        arrays, meta = self.to_arrays_json()
        save_arrays_json(path, arrays, meta)


def load_feature_map(path: str | os.PathLike[str]) -> FeatureMap:
    """Read a :class:`FeatureMap` written by :meth:`FeatureMap.save`.

    Raises:
        ValueError: naming the file: not a model file, unknown or too large arrays, NaN or
            inf values, a non-positive scale, an invalid description.
    """
    arrays, meta = load_arrays_json(
        path, kind="mtex_jax.FeatureMap", required=("offset", "scale"), allowed=()
    )
    off, sc = arrays["offset"], arrays["scale"]
    if not (np.isfinite(off).all() and np.isfinite(sc).all() and (sc > 0).all()):
        raise ValueError(f"{path}: offset must be finite and scale finite and positive")
    try:
        return FeatureMap.from_arrays_json(arrays, meta)
    except (ValueError, TypeError, KeyError, AttributeError, OverflowError, IndexError) as e:
        raise ValueError(f"{path}: invalid feature map file: {e}") from None


def _channel_names(sk: Skeleton, has_lp: bool) -> tuple[str, ...]:
    ax = "xyz"
    u, h0, h1 = ground_axes(sk.up_axis)
    names = [f"root.d{ax[h0]}", f"root.d{ax[h1]}", f"root.{ax[u]}", "root.dyaw"]
    names += [f"root.tilt.{c}" for c in ax]
    for j in range(1, sk.n_joints):
        names += [f"{sk.names[j]}.r{c}" for c in ax]
    if has_lp:
        for j in range(1, sk.n_joints):
            names += [f"{sk.names[j]}.p{c}" for c in ax]
    return tuple(names)


_BUCKET = 256
# frames of the decoding's shape bucket (design §11): decoding is cheap, so one program serves
# every motion of up to this many frames
DECODE_FRAMES = 4096


def _fit_inputs(motions: Motion | Sequence[Motion]) -> list[Motion]:
    """The clips of :meth:`FeatureMap.fit`, checked: a non-empty list of Motions with one
    skeleton structure and frame rate."""
    motions = [motions] if isinstance(motions, Motion) else list(motions)
    if not motions:
        raise ValueError("FeatureMap.fit: no motions given")
    for i, m in enumerate(motions):
        if not isinstance(m, Motion):
            raise TypeError(f"FeatureMap.fit: item {i} is {type(m).__name__}, not a Motion")
    check_compatible(motions, "FeatureMap.fit", "resample with motion.resample(fps) first")
    return motions


def _raws(motions: list[Motion]) -> list[np.ndarray]:
    """Raw channels of clips, all padded to the longest one's bucket: one compiled function
    for the lot (the channels are causal in time, so the padding changes no real frame)."""
    tp = max(-(-m.n_frames // _BUCKET) * _BUCKET for m in motions)
    return [np.asarray(_raw(m, tp)) for m in motions]


def _raw(m: Motion, tp: int | None = None) -> Array:
    """Raw channels of a clip; frames are padded (last frame repeated) to ``tp`` frames
    (default: a multiple of 256) so that clips of similar length share one compiled
    function."""
    t = m.n_frames
    if tp is None:
        tp = -(-t // _BUCKET) * _BUCKET
    # pad_frames repeats the last frame on the host for concrete arrays (an eager gather of a
    # JAX array compiles once per clip length)
    pad = lambda a: pad_frames(a, tp, axis=0)
    lp = None if m.local_positions is None else pad(m.local_positions)
    raw = _raw_jit(m.skeleton.up_axis, pad(m.root_positions), pad(m.rotations), lp)
    return cut_frames(raw, t)  # on the host: an eager slice compiles once per clip length


@eqx.filter_jit
def _raw_jit(up_axis: int, root_positions, rotations, local_positions) -> Array:
    return raw_features(root_positions, rotations, local_positions, up_axis=up_axis)


def _scale(fm: FeatureMap, raw: Array | np.ndarray) -> Array:
    # elementwise on the host (the same IEEE operations): eager JAX ops here would compile
    # once per clip length
    r = np.asarray(raw)
    act = np.asarray(fm.active, dtype=np.int64)
    off = np.asarray(fm.offset, r.dtype)[act]
    sc = np.asarray(fm.scale, r.dtype)[act]
    return jax.device_put((r[:, act] - off) / sc)


def _start(dtype: Any, start_position: Any, start_heading: Any) -> tuple[Array, Array]:
    """The checked start position ``(3,)`` and heading ``()`` of a decoding, in ``dtype``."""
    sp = jnp.zeros(3, dtype) if start_position is None else jnp.asarray(start_position, dtype)
    if sp.shape != (3,):
        raise ValueError(f"decode: start_position must have shape (3,), got {sp.shape}")
    sh = jnp.zeros((), dtype) if start_heading is None else jnp.asarray(start_heading, dtype)
    if sh.shape != ():
        raise ValueError(f"decode: start_heading must be a scalar, got shape {sh.shape}")
    return sp, sh


def _decode_host(
    fm: FeatureMap, Yn: np.ndarray, sp: Array, sh: Array
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray | None], np.ndarray]:
    """Decode a concrete ``Yn (T, D)`` in its shape bucket (design §11): the root positions,
    rotations and local positions as host arrays, and the last frame's integrated heading."""
    T = int(Yn.shape[0])
    pos, rot, lp, psi = _decode(fm, pad_frames(Yn, bucket_length(T, DECODE_FRAMES)), sp, sh)
    cut = lambda a: np.asarray(a)[:T]
    return (cut(pos), cut(rot), None if lp is None else cut(lp)), np.asarray(psi)[T - 1]


@eqx.filter_jit
def _decode(fm: FeatureMap, Y: Array, sp: Array, sh: Array):
    t = Y.shape[0]
    act = np.asarray(fm.active, dtype=np.int64)
    off = jnp.asarray(fm.offset, Y.dtype)
    sc = jnp.asarray(fm.scale, Y.dtype)
    raw = jnp.broadcast_to(off, (t, off.shape[0]))
    raw = raw.at[:, act].set(Y * sc[act] + off[act])
    return decode_raw(
        raw, fm.skeleton.n_joints, fm.has_local_positions, fm.skeleton.up_axis, sp, sh
    )
