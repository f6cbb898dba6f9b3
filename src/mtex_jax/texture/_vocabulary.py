"""The vocabulary of a motion texture as data (:class:`Vocabulary`, ``MotionTexture.summary()``):
how often each texton was used in training, for how long, and what follows it (MT §3, the
texton distribution; design §10.10)."""

from __future__ import annotations

from typing import Any, Protocol

import equinox as eqx
import numpy as np
from jaxtyping import Float, Int

__all__ = ["SUCCESSOR_MIN", "Vocabulary", "vocabulary"]

#: A texton ``j ≠ i`` is a successor of ``i`` when ``M[i, j]`` is at least this.
SUCCESSOR_MIN = 0.1


class Vocabulary(eqx.Module):
    """Per-texton figures of a learned texture, from its training segmentation and ``M``.

    Attributes:
        segments: ``(K,)`` training segments of each texton.
        frames: ``(K,)`` training frames of each texton.
        mean_length: ``(K,)`` mean segment length in frames.
        self_transition: ``(K,)`` ``M[i, i]``.
        M: ``(K, K)`` the transition matrix.
        fps: frames per second of the training clips (``None``: raw arrays without a rate).
    """

    segments: Int[np.ndarray, " K"]
    frames: Int[np.ndarray, " K"]
    mean_length: Float[np.ndarray, " K"]
    self_transition: Float[np.ndarray, " K"]
    M: Float[np.ndarray, "K K"]
    fps: float | None = eqx.field(static=True, default=None)

    def __check_init__(self) -> None:
        K = np.shape(self.segments)[0]
        for name in ("frames", "mean_length", "self_transition"):
            if np.shape(getattr(self, name)) != (K,):
                raise ValueError(f"Vocabulary.{name} must have shape ({K},)")
        if np.shape(self.M) != (K, K):
            raise ValueError(f"Vocabulary.M must have shape ({K}, {K}), got {np.shape(self.M)}")

    @property
    def n_textons(self) -> int:
        return int(np.shape(self.segments)[0])

    def successors(self, i: int, min_prob: float = SUCCESSOR_MIN) -> list[tuple[int, float]]:
        """The textons ``j ≠ i`` with ``M[i, j] ≥ min_prob``, most likely first.

        Raises:
            IndexError: ``i`` is not a texton of this vocabulary.
        """
        K = self.n_textons
        if isinstance(i, bool) or not isinstance(i, int | np.integer) or not 0 <= i < K:
            raise IndexError(f"texton {i!r} out of range: the vocabulary has {K} textons")
        row = np.asarray(self.M)[i]
        order = [int(j) for j in np.argsort(-row, kind="stable") if j != i]
        return [(j, float(row[j])) for j in order if row[j] >= min_prob]

    @property
    def largest_share(self) -> float:
        """The share of the training segments held by the most used texton."""
        seg = np.asarray(self.segments)
        return float(seg.max() / max(seg.sum(), 1))

    @property
    def median_successors(self) -> float:
        """The median over textons of the number of successors other than itself."""
        return float(np.median([len(self.successors(i)) for i in range(self.n_textons)]))

    def rows(self) -> list[dict[str, Any]]:
        """One dict per texton: ``texton``, ``segments``, ``share``, ``frames``,
        ``mean_length`` (frames), ``mean_seconds`` (``None`` without ``fps``), ``self`` and
        ``successors`` (``[(j, M[i, j]), …]``)."""
        seg = np.asarray(self.segments)
        total = max(int(seg.sum()), 1)
        out = []
        for i in range(self.n_textons):
            mean = float(np.asarray(self.mean_length)[i])
            out.append(
                dict(
                    texton=i,
                    segments=int(seg[i]),
                    share=float(seg[i] / total),
                    frames=int(np.asarray(self.frames)[i]),
                    mean_length=mean,
                    mean_seconds=None if self.fps is None else mean / self.fps,
                    self=float(np.asarray(self.self_transition)[i]),
                    successors=self.successors(i),
                )
            )
        return out

    def __str__(self) -> str:
        unit = "s" if self.fps is not None else "frames"
        lines = [
            f"{self.n_textons} textons; largest {100 * self.largest_share:.0f} % of the segments; "
            f"median successors {self.median_successors:g} (M >= {SUCCESSOR_MIN:g})",
            f"texton  segments  share  mean ({unit})  stay   successors",
        ]
        for r in self.rows():
            mean = r["mean_seconds"] if r["mean_seconds"] is not None else r["mean_length"]
            succ = ", ".join(f"{j} ({p:.2f})" for j, p in r["successors"][:4]) or "-"
            lines.append(
                f"{r['texton']:6d}  {r['segments']:8d}  {100 * r['share']:4.0f}%  "
                f"{mean:9.2f}  {r['self']:5.2f}  {succ}"
            )
        return "\n".join(lines)


class _Learned(Protocol):
    """What a vocabulary reads of a learned texture (a
    :class:`~mtex_jax.texture.MotionTexture`): its training segmentation (rows
    ``(clip, start, length, texton)``), its transition matrix and its configuration."""

    @property
    def segments(self) -> Any: ...

    @property
    def M(self) -> Any: ...

    @property
    def config(self) -> Any: ...


def vocabulary(tex: _Learned) -> Vocabulary:
    """The :class:`Vocabulary` of a learned texture (its training segmentation and ``M``)."""
    K = int(np.shape(tex.M)[0])
    segs = np.asarray(tex.segments, dtype=np.int64).reshape(-1, 4)
    lab, length = segs[:, 3], segs[:, 2]
    counts = np.bincount(lab, minlength=K)[:K]
    frames = np.bincount(lab, weights=length, minlength=K)[:K].astype(np.int64)
    mean = np.where(counts > 0, frames / np.maximum(counts, 1), 0.0)
    M = np.asarray(tex.M, dtype=np.float64)
    return Vocabulary(
        segments=counts,
        frames=frames,
        mean_length=mean,
        self_transition=np.diag(M).copy(),
        M=M,
        fps=None if tex.config.fps is None else float(tex.config.fps),
    )
