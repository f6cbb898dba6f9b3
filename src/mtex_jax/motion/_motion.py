"""`Motion`: a skeleton plus per-frame root positions and local joint rotations."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import equinox as eqx
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, Float

from ..core import MAX_FRAMES
from ._skeleton import Skeleton

__all__ = ["Motion", "concatenate_motions", "slerp"]

ArrayF = Float[Array, "..."] | Float[np.ndarray, "..."]

#: Quaternions whose norm is within this of 1 are normalised by :class:`Motion`; others are
#: refused (a zero, NaN or inf quaternion always).
QUAT_NORM_TOL = 1e-3


#: Frames per block of the quaternion checks of a long clip (bounded temporaries).
_BLOCK = 65_536


def _norm_blocks(q: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """``(first frame, (t, J) float64 norms)`` of ``q (T, J, 4)`` in blocks of :data:`_BLOCK`
    frames, so that a long clip's checks hold no float64 copy of it."""
    for a in range(0, q.shape[0], _BLOCK):
        yield a, np.linalg.norm(q[a : a + _BLOCK].astype(np.float64), axis=-1)


class Motion(eqx.Module):
    """A motion clip: skeleton, frame rate, root trajectory and local joint rotations.

    Rotations are unit quaternions ``(w, x, y, z)``, local to the parent joint (for the root:
    relative to the world). A joint's world position is
    ``p_j = p_parent + R_parent_world @ t_j`` with ``t_j`` the skeleton offset (or
    ``local_positions[:, j]`` where a non-root joint has BVH position channels), and
    ``R_j_world = R_parent_world @ R(rotations[:, j])``. The root is at ``root_positions``.

    Arrays may be NumPy (as returned by the readers, always float64) or JAX arrays (as
    returned by differentiable decoders); every function accepts either.

    Attributes:
        skeleton: the figure (static).
        fps: frames per second (static).
        root_positions: ``(T, 3)`` world position of the root joint.
        rotations: ``(T, J, 4)`` local unit quaternions, w first.
        local_positions: ``(T, J, 3)`` per-frame local translations, or ``None`` when no
            non-root joint has position channels (then the skeleton offsets are used).
    """

    skeleton: Skeleton = eqx.field(static=True)
    fps: float = eqx.field(static=True)
    root_positions: ArrayF
    rotations: ArrayF
    local_positions: ArrayF | None = None

    def __post_init__(self) -> None:
        # integer or boolean arrays (a list of ints, np.int64) become float64: an integer
        # quaternion would otherwise skip the unit check and round in every product
        for name in ("root_positions", "rotations", "local_positions"):
            a = getattr(self, name)
            if a is None or isinstance(a, Tracer):
                continue
            if not hasattr(a, "dtype") or np.asarray(a).dtype.kind in "biu":
                arr = np.asarray(a)
                if arr.dtype.kind in "biuf":
                    setattr(self, name, arr.astype(np.float64))
        # normalise near-unit quaternions (the rest is checked by __check_init__)
        q = self._concrete_quaternions()
        if q is None:
            return
        # the largest deviation from a unit norm, in blocks of frames (bounded temporaries)
        worst = 0.0
        for _, n in _norm_blocks(q):
            if not np.isfinite(n).all():
                return
            worst = max(worst, float(np.abs(n - 1.0).max()))
        if worst <= QUAT_NORM_TOL and worst > 8 * np.finfo(q.dtype).eps:
            unit = np.empty_like(q)
            for a, n in _norm_blocks(q):
                unit[a : a + n.shape[0]] = (q[a : a + n.shape[0]] / n[..., None]).astype(q.dtype)
            rot = self.rotations
            self.rotations = unit if isinstance(rot, np.ndarray) else _type_like(rot, unit)

    def _concrete_quaternions(self) -> np.ndarray | None:
        """The concrete rotations, or ``None`` (traced, empty or misshapen)."""
        rot = self.rotations
        if isinstance(rot, Tracer) or len(np.shape(rot)) != 3 or np.shape(rot)[2] != 4:
            return None
        q = np.asarray(rot)
        if not np.issubdtype(q.dtype, np.floating) or q.size == 0:
            return None
        return q

    def _check_quaternions(self) -> None:
        """The value check at the door: finite unit quaternions (traced arrays skipped)."""
        q = self._concrete_quaternions()
        if q is None:
            return
        for a, n in _norm_blocks(q):
            bad = ~np.isfinite(n) | (n < 1e-6) | (np.abs(n - 1.0) > QUAT_NORM_TOL)
            if bad.any():
                t, j = (int(i[0]) for i in np.nonzero(bad))
                self._bad_quaternion(q, n, a + t, j, t)

    def _bad_quaternion(self, q: np.ndarray, n: np.ndarray, t: int, j: int, tb: int) -> None:
        if not np.isfinite(n[tb, j]):
            what = "NaN or inf"
        elif n[tb, j] < 1e-6:
            what = "zero"
        else:
            what = f"norm {n[tb, j]:.6g}, not a unit"
        raise ValueError(
            f"Motion.rotations: frame {t}, joint {j} ({self.skeleton.names[j]!r}): {what} "
            f"quaternion {q[t, j].tolist()} (norms within {QUAT_NORM_TOL:g} of 1 are normalised)"
        )

    def __check_init__(self) -> None:
        if not isinstance(self.skeleton, Skeleton):
            raise TypeError(
                f"Motion.skeleton must be a Skeleton, got {type(self.skeleton).__name__}"
            )
        if not (isinstance(self.fps, int | float) and np.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"Motion.fps must be a positive finite number, got {self.fps!r}")
        j = self.skeleton.n_joints
        rs = np.shape(self.root_positions)
        qs = np.shape(self.rotations)
        if len(rs) != 2 or rs[1] != 3:
            raise ValueError(f"Motion.root_positions must have shape (T, 3), got {rs}")
        if len(qs) != 3 or qs[1:] != (j, 4):
            raise ValueError(f"Motion.rotations must have shape (T, {j}, 4), got {qs}")
        if qs[0] != rs[0]:
            raise ValueError(f"Motion.rotations has {qs[0]} frames but root_positions has {rs[0]}")
        if self.local_positions is not None:
            ls = np.shape(self.local_positions)
            if ls != (rs[0], j, 3):
                raise ValueError(
                    f"Motion.local_positions must have shape ({rs[0]}, {j}, 3), got {ls}"
                )
        self._check_quaternions()
        self._check_finite_positions()

    def _check_finite_positions(self) -> None:
        """Root and local positions finite (traced arrays skipped): a NaN root position would
        make every joint position NaN."""
        for name in ("root_positions", "local_positions"):
            a = getattr(self, name)
            if a is None or isinstance(a, Tracer):
                continue
            arr = np.asarray(a)
            if arr.dtype.kind == "f" and not np.isfinite(arr).all():
                t = int(np.nonzero(~np.isfinite(arr.reshape(arr.shape[0], -1)).all(axis=1))[0][0])
                raise ValueError(f"Motion.{name}: frame {t} holds NaN or inf")
            if arr.dtype.kind not in "f":
                raise TypeError(f"Motion.{name} must be a float array, got dtype {arr.dtype}")

    # ------------------------------------------------------------------ basic facts
    @property
    def n_frames(self) -> int:
        return int(np.shape(self.root_positions)[0])

    @property
    def n_joints(self) -> int:
        return self.skeleton.n_joints

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame, ``(T − 1) / fps``."""
        return max(self.n_frames - 1, 0) / self.fps

    def __len__(self) -> int:
        return self.n_frames

    def __getitem__(self, frames: slice | Sequence[int] | np.ndarray) -> Motion:
        """Select frames (a slice or an index array); an integer is rejected (use ``m[i:i+1]``)."""
        if isinstance(frames, int | np.integer):
            raise TypeError("index a Motion with a slice or an index array, e.g. m[i:i + 1]")
        if isinstance(frames, slice) and frames.step is not None and frames.step != 1:
            fps = self.fps / abs(frames.step)
        else:
            fps = self.fps
        idx = frames if isinstance(frames, slice) else np.asarray(frames)
        if isinstance(idx, np.ndarray) and idx.dtype.kind in "iu" and idx.size:
            n = self.n_frames
            if idx.min() < -n or idx.max() >= n:
                raise IndexError(f"frame index out of range for a motion of {n} frames")
        lp = None if self.local_positions is None else self.local_positions[idx]
        return Motion(self.skeleton, fps, self.root_positions[idx], self.rotations[idx], lp)

    def numpy(self) -> Motion:
        """The same motion with NumPy arrays (copies device arrays to host)."""
        lp = None if self.local_positions is None else np.asarray(self.local_positions)
        return Motion(
            self.skeleton, self.fps, np.asarray(self.root_positions), np.asarray(self.rotations), lp
        )

    def with_skeleton(self, skeleton: Skeleton) -> Motion:
        """The same frames on another skeleton of identical structure (e.g. rescaled offsets)."""
        if skeleton.n_joints != self.skeleton.n_joints:
            raise ValueError(
                f"skeleton has {skeleton.n_joints} joints, motion has {self.skeleton.n_joints}"
            )
        return Motion(skeleton, self.fps, self.root_positions, self.rotations, self.local_positions)

    # ------------------------------------------------------------------ left and right
    def mirror(self, axis: int | None = None) -> Motion:
        """The motion reflected left to right, on the same skeleton: what the other side of
        the body would have danced (new motion for a model, and an animator's mirror).

        Every joint takes the reflected rotation of its left-right partner
        (:meth:`Skeleton.mirror_pairs`); the root's path is reflected through the vertical
        plane normal to the lateral ``axis`` (default :meth:`Skeleton.lateral_axis`). A
        reflection ``M`` maps a rotation ``R`` to ``M R M``: the quaternion keeps ``w`` and its
        component along ``axis`` and negates the other two. On a skeleton that is symmetric
        under ``M`` (each partner's offset the reflection of the joint's, midline offsets in
        the plane) the joint positions are exactly the reflected ones; mirroring twice gives
        the motion back.

        Args:
            axis: the world axis to reflect (0, 1 or 2, not the up axis); ``None`` infers it.

        Raises:
            ValueError: for an axis that is the up axis or not 0, 1, 2, or (``axis=None``) a
                skeleton without joints named by side.
        """
        sk = self.skeleton
        if axis is None:
            axis = sk.lateral_axis()
        elif (
            isinstance(axis, bool)
            or not isinstance(axis, int | np.integer)
            or axis
            not in (
                0,
                1,
                2,
            )
        ):
            raise ValueError(f"mirror: axis must be 0, 1 or 2, got {axis!r}")
        elif axis == sk.up_axis:
            raise ValueError(
                f"mirror: axis {axis} is the up axis; a mirror reflects a horizontal axis"
            )
        m = self.numpy()
        partner = np.asarray(sk.mirror_pairs())
        flip = np.ones(3)
        flip[axis] = -1.0  # positions: M p
        qsign = np.concatenate([[1.0], -flip])  # quaternions: (w, −M v)
        q = np.asarray(m.rotations)[:, partner] * qsign
        root = np.asarray(m.root_positions) * flip
        lp = None
        if m.local_positions is not None:
            lp = np.asarray(m.local_positions)[:, partner] * flip
        return Motion(sk, self.fps, root, q, lp)

    # ------------------------------------------------------------------ resampling
    def resample(self, fps: float, *, max_frames: int = MAX_FRAMES) -> Motion:
        """Resample to another frame rate over the same time span.

        Root positions (and local positions) are interpolated linearly; rotations by spherical
        linear interpolation (slerp) between the two neighbouring frames. The new clip has
        ``floor(duration · fps) + 1`` frames starting at the same time, at most ``max_frames``
        (default :data:`~mtex_jax.core.MAX_FRAMES`; more is a ``ValueError`` before anything
        is allocated).
        """
        if not (np.isfinite(fps) and fps > 0):
            raise ValueError(f"resample: fps must be positive and finite, got {fps!r}")
        m = self.numpy()
        t_old = m.n_frames
        if t_old == 1:
            return Motion(m.skeleton, float(fps), m.root_positions, m.rotations, m.local_positions)
        n_float = np.floor(m.duration * fps + 1e-9) + 1
        if not n_float <= max_frames:
            raise ValueError(
                f"resample: {m.duration:g} s at {fps:g} fps would be {n_float:,.0f} frames, "
                f"more than the limit of {max_frames:,} (max_frames)"
            )
        n_new = int(n_float)
        u = np.arange(n_new) * (self.fps / fps)
        i0 = np.clip(np.floor(u).astype(np.int64), 0, t_old - 2)
        frac = np.clip(u - i0, 0.0, 1.0)
        lin = lambda a: a[i0] + (a[i0 + 1] - a[i0]) * frac.reshape((-1,) + (1,) * (a.ndim - 1))
        rot = slerp_frames(np.asarray(m.rotations), i0, frac)
        lp = None if m.local_positions is None else lin(m.local_positions)
        return Motion(m.skeleton, float(fps), lin(m.root_positions), rot, lp)


def _type_like(like: object, a: np.ndarray) -> ArrayF:
    """``a`` as a JAX array when ``like`` is one (NumPy otherwise)."""
    import jax.numpy as jnp

    return jnp.asarray(a) if not isinstance(like, np.ndarray) else a


def slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (NumPy, float64).

    Args:
        q0: ``(..., 4)`` unit quaternions at ``u = 0``.
        q1: ``(..., 4)`` unit quaternions at ``u = 1``.
        u: interpolation fractions in ``[0, 1]``, broadcastable to ``q0.shape[:-1]``.

    Returns:
        ``(..., 4)``: ``q0 (q0* q1)^u`` along the shorter arc (``q1`` is negated if needed).
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    sin_t = np.sin(theta)
    small = sin_t < 1e-9
    safe = np.where(small, 1.0, sin_t)
    w0 = np.where(small, 1.0 - u, np.sin((1.0 - u) * theta) / safe)
    w1 = np.where(small, u, np.sin(u * theta) / safe)
    out = w0 * q0 + w1 * q1
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def slerp_frames(q: np.ndarray, i0: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``slerp(q[i0], q[i0 + 1], u[:, None])`` for the frames of a resampling, in blocks of
    frames: the same values, with the temporaries of one block (a million frames of a clip
    would otherwise hold a dozen float64 copies of it).

    Args:
        q: ``(T, J, 4)`` unit quaternions of a clip.
        i0: ``(n,)`` frame before each new frame (``0 <= i0 < T - 1``).
        u: ``(n,)`` fractions in ``[0, 1]`` between frames ``i0`` and ``i0 + 1``.

    Returns:
        ``(n, J, 4)`` float64 quaternions.
    """
    q = np.asarray(q)
    out = np.empty((i0.shape[0], *q.shape[1:]), np.float64)
    for a in range(0, i0.shape[0], _BLOCK):
        i, f = i0[a : a + _BLOCK], u[a : a + _BLOCK]
        out[a : a + i.shape[0]] = slerp(q[i], q[i + 1], f[:, None])
    return out


def check_compatible(motions: Sequence[Motion], where: str, hint: str) -> None:
    """Raise ``ValueError`` unless every motion has the first one's skeleton structure, frame
    rate and (absence of) per-frame local positions."""
    first = motions[0]
    for i, m in enumerate(motions[1:], start=1):
        if not m.skeleton.same_structure(first.skeleton):
            raise ValueError(f"{where}: motion {i} has a different skeleton")
        if m.fps != first.fps:
            raise ValueError(
                f"{where}: motion {i} has fps {m.fps:g}, motion 0 has {first.fps:g}; {hint}"
            )
        if (m.local_positions is None) != (first.local_positions is None):
            raise ValueError(f"{where}: local_positions present in some motions only")


def concatenate_motions(motions: Sequence[Motion]) -> Motion:
    """Join clips of one skeleton and frame rate end to end (frames are appended as they are)."""
    if not motions:
        raise ValueError("concatenate_motions: empty list")
    first = motions[0]
    check_compatible(motions, "concatenate_motions", "resample first")
    lp = None
    if first.local_positions is not None:
        lp = np.concatenate([np.asarray(m.local_positions) for m in motions])
    return Motion(
        first.skeleton,
        first.fps,
        np.concatenate([np.asarray(m.root_positions) for m in motions]),
        np.concatenate([np.asarray(m.rotations) for m in motions]),
        lp,
    )
