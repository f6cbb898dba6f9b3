"""Novelty and verbatim copying of generated motion against the training clips.

**Pose representation.** Joint positions in a body-centred frame: frame ``t``'s positions minus
the root's *horizontal* position, rotated about the up axis by minus the root's heading
``ψ_t`` (the twist angle of the root rotation about up, ``ψ = 2 atan2(q_xyz · e_up, q_w)``);
heights stay absolute. This is invariant to where on the floor and which way the dancer faces,
which a copy placed elsewhere must not escape, while it keeps everything the eye sees of the
pose (unlike joint angles, whose errors are weighted by limb length only through FK). Only the
moving joints of the training clips are used (:func:`~mtex_jax.metrics.moving_joints`).

**Windows.** A window of ``L = round(window · f)`` frames starting at ``s`` is described by the
frames ``s, s + d, s + 2d, …`` (``d = round(f / sample_fps)``) expressed in the frame of its
*first* frame (one origin and heading for the whole window, so the root's path within the
window counts). Two windows are compared by the root-mean-square joint distance in metres,

    D(X, Y) = sqrt( (1 / (n K)) Σ_{k, j} ‖X_k(j) − Y_k(j)‖² ).

Every start frame of every training clip whose window fits inside the clip is a database window;
the nearest one is found by chunked brute force (``‖x‖² + ‖y‖² − 2 x·y`` in float32 blocks of
bounded memory, then the winner's distance recomputed in float64).

**Copying.** Each generated frame's nearest training frame (same pose representation, one frame)
indexes the concatenated training frames. Step ``t − 1 → t`` is *verbatim* when the nearest
frame of ``t`` is the successor, in the same training clip, of the nearest frame of ``t − 1``.
Reported: the share of verbatim steps and the longest run of consecutive verbatim steps, in
seconds (``k`` steps = ``k / f`` s). :func:`copying_from_indices` does the same from the database
indices a sampler actually chose and a successor array (design §10.4 "Copying").
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike

from ..motion import Motion, ground_axes
from ._kinematics import as_motion_list, joint_positions, moving_joints

__all__ = [
    "CopyResult",
    "NoveltyResult",
    "copying",
    "copying_from_indices",
    "novelty",
    "successor_array",
]

_CHUNK_BYTES = 64 * 2**20  # memory bound of one block of the distance matrix


def _headings(m: Motion) -> np.ndarray:
    q = np.asarray(m.rotations[:, 0], dtype=np.float64)
    return 2.0 * np.arctan2(q[:, 1 + m.skeleton.up_axis], q[:, 0])


def _prepare(
    ms: list[Motion], f: float, joints: np.ndarray, where: str, min_frames: int
) -> tuple[list[np.ndarray], list[np.ndarray], tuple[int, int, int]]:
    """Per clip at ``f``: ``(T, 1 + K, 3)`` world positions of the root followed by
    ``joints``, and the root headings ``(T,)``."""
    rs = [m if m.fps == f else m.resample(f) for m in ms]
    axes = ground_axes(ms[0].skeleton.up_axis)
    ps = joint_positions(rs, f, min_frames=min_frames, where=where)
    sel = np.concatenate([[0], joints]).astype(np.int64)
    return [p[:, sel] for p in ps], [_headings(r) for r in rs], axes


def _horizontal(root: np.ndarray, up: int) -> np.ndarray:
    out = root.copy()
    out[..., up] = 0.0
    return out


def _align(x: np.ndarray, psi: np.ndarray, axes: tuple[int, int, int]) -> np.ndarray:
    """Rotate ``x`` ``(N, ..., 3)`` about up by ``−psi`` ``(N,)``; returns ``(N, ..., 3)`` in
    ``(h0, h1, up)`` order."""
    up, h0, h1 = axes
    c = np.cos(psi).reshape((-1,) + (1,) * (x.ndim - 2))
    s = np.sin(psi).reshape(c.shape)
    a, b = x[..., h0], x[..., h1]
    return np.stack([c * a + s * b, -s * a + c * b, x[..., up]], axis=-1)


def _frame_features(p: np.ndarray, psi: np.ndarray, axes: tuple[int, int, int]) -> np.ndarray:
    """``(T, 3K)`` per-frame pose vectors (own origin and heading); ``p`` from ``_prepare``."""
    x = p[:, 1:] - _horizontal(p[:, 0], axes[0])[:, None, :]
    return _align(x, psi, axes).reshape(p.shape[0], -1)


def _window_features(
    p: np.ndarray, psi: np.ndarray, axes: tuple[int, int, int], length: int, d: int, hop: int
) -> np.ndarray:
    """``(N, n·3K)`` window vectors of the windows starting at ``0, hop, …`` (each in the frame
    of its first frame)."""
    offs = np.arange(0, length, d)
    starts = np.arange(0, p.shape[0] - length + 1, hop)
    origin = _horizontal(p[starts, 0], axes[0])  # the first frame's root on the floor
    x = p[starts[:, None] + offs[None, :], 1:] - origin[:, None, None, :]  # (N, n, K, 3)
    return _align(x, psi[starts], axes).reshape(starts.size, -1)


def _nearest(
    queries: np.ndarray, database: np.ndarray, k: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """Index of each query row's nearest database row and the squared distance (float64).

    Both sides are centred on the database mean; ``‖y‖² − 2 x·y`` is computed in float32 blocks
    of at most ``_CHUNK_BYTES``, its ``k`` smallest entries per row are re-ranked exactly in
    float64 (so near-ties, such as consecutive frames of a still pose, are resolved exactly).
    """
    mean = database.mean(axis=0)
    db = database - mean
    qs = queries - mean
    db32 = db.astype(np.float32)
    dn = np.sum(db * db, axis=1).astype(np.float32)
    k = min(k, db.shape[0])
    rows = max(1, _CHUNK_BYTES // (4 * max(db.shape[0], 1)))
    idx = np.empty(qs.shape[0], dtype=np.int64)
    d2 = np.empty(qs.shape[0])
    for s in range(0, qs.shape[0], rows):
        q = qs[s : s + rows]
        approx = dn[None, :] - 2.0 * (q.astype(np.float32) @ db32.T)
        cand = np.argpartition(approx, k - 1, axis=1)[:, :k] if k < db.shape[0] else None
        if cand is None:
            cand = np.broadcast_to(np.arange(db.shape[0]), (q.shape[0], db.shape[0]))
        exact = np.sum((q[:, None, :] - db[cand]) ** 2, axis=-1)
        # smallest distance, ties to the lowest database index
        order = np.lexsort((cand, exact), axis=1)[:, 0]
        rr = np.arange(q.shape[0])
        idx[s : s + rows] = cand[rr, order]
        d2[s : s + rows] = exact[rr, order]
    return idx, d2


@dataclasses.dataclass(frozen=True)
class NoveltyResult:
    """Distance of each generated window to its nearest training window.

    Attributes:
        distances: ``(N,)`` RMS joint distance (metres) of each generated window.
        nearest: ``(N,)`` start frame of the nearest training window, as an index into the
            concatenated training frames at ``fps``.
        nearest_clip: ``(N,)`` training clip of the nearest window.
        median: median of ``distances``.
        mean: mean of ``distances``.
        min: smallest distance.
        window: window length in seconds; ``fps``: the frame rate.
    """

    distances: np.ndarray
    nearest: np.ndarray
    nearest_clip: np.ndarray
    median: float
    mean: float
    min: float
    window: float
    fps: float


@dataclasses.dataclass(frozen=True)
class CopyResult:
    """Verbatim copying: steps whose example is the database successor of the previous one.

    Attributes:
        nearest: ``(T,)`` database index of each frame (generated clips concatenated).
        verbatim: ``(T,)`` bool, true where the step into the frame is verbatim (false at each
            clip's first frame).
        fraction: share of verbatim steps among all steps (``Σ (T_i − 1)``).
        longest_run: longest run of consecutive verbatim steps, in seconds (``k / fps``).
        fps: the frame rate of the steps.
    """

    nearest: np.ndarray
    verbatim: np.ndarray
    fraction: float
    longest_run: float
    fps: float


def _longest_true_run(x: np.ndarray) -> int:
    if not x.any():
        return 0
    padded = np.concatenate([[0], x.astype(np.int8), [0]])
    edges = np.diff(padded)
    return int(np.max(np.nonzero(edges == -1)[0] - np.nonzero(edges == 1)[0]))


def _copy_result(nearest: np.ndarray, verbatim: np.ndarray, n_steps: int, fps: float) -> CopyResult:
    return CopyResult(
        nearest=nearest,
        verbatim=verbatim,
        fraction=float(verbatim.sum() / max(n_steps, 1)),
        longest_run=_longest_true_run(verbatim) / fps,
        fps=fps,
    )


def _setup(
    generated: Motion | Sequence[Motion],
    training: Motion | Sequence[Motion],
    fps: float | None,
    joints: Sequence[str] | None,
    where: str,
) -> tuple[list[Motion], list[Motion], float, np.ndarray]:
    gen = as_motion_list(generated, f"{where} (generated)")
    tr = as_motion_list(training, f"{where} (training)")
    if not gen[0].skeleton.same_structure(tr[0].skeleton):
        raise ValueError(f"{where}: generated and training clips have different skeletons")
    f = tr[0].fps if fps is None else float(fps)
    sk = tr[0].skeleton
    idx = moving_joints(tr) if joints is None else np.array([sk.index(n) for n in joints])
    return gen, tr, f, idx


def novelty(
    generated: Motion | Sequence[Motion],
    training: Motion | Sequence[Motion],
    *,
    window: float = 1.0,
    fps: float | None = None,
    sample_fps: float = 10.0,
    hop: int = 1,
    joints: Sequence[str] | None = None,
) -> NoveltyResult:
    """Distance from each generated window to the nearest training window (module notes).

    Args:
        generated: the judged clips, each at least one window long.
        training: the training clips (the database: every window inside a clip).
        window: window length in seconds.
        fps: common frame rate (``None``: the first training clip's).
        sample_fps: rate of the frames kept inside a window (``d = round(fps / sample_fps)``).
        hop: frames between the starts of consecutive *generated* windows.
        joints: joint names (default: the moving joints of ``training``).

    Returns:
        A :class:`NoveltyResult`.
    """
    gen, tr, f, idx = _setup(generated, training, fps, joints, "novelty")
    if not (np.isfinite(window) and window > 0 and sample_fps > 0 and hop >= 1):
        raise ValueError(
            f"novelty: window, sample_fps must be positive and hop >= 1, got {window!r}, "
            f"{sample_fps!r}, {hop!r}"
        )
    length = max(1, round(window * f))
    d = max(1, round(f / sample_fps))
    tp, th, axes = _prepare(tr, f, idx, "novelty (training)", length)
    gp, gh, _ = _prepare(gen, f, idx, "novelty (generated)", length)
    db = [_window_features(p, h, axes, length, d, 1) for p, h in zip(tp, th, strict=True)]
    starts = np.concatenate([[0], np.cumsum([p.shape[0] for p in tp])[:-1]])
    db_start = np.concatenate([s + np.arange(w.shape[0]) for s, w in zip(starts, db, strict=True)])
    db_clip = np.concatenate([np.full(w.shape[0], i) for i, w in enumerate(db)])
    q = np.concatenate(
        [_window_features(p, h, axes, length, d, hop) for p, h in zip(gp, gh, strict=True)]
    )
    nn, d2 = _nearest(q, np.concatenate(db))
    dist = np.sqrt(np.maximum(d2, 0.0) / (q.shape[1] // 3))
    return NoveltyResult(
        distances=dist,
        nearest=db_start[nn],
        nearest_clip=db_clip[nn],
        median=float(np.median(dist)),
        mean=float(dist.mean()),
        min=float(dist.min()),
        window=length / f,
        fps=f,
    )


def copying(
    generated: Motion | Sequence[Motion],
    training: Motion | Sequence[Motion],
    *,
    fps: float | None = None,
    joints: Sequence[str] | None = None,
) -> CopyResult:
    """Verbatim copying from each frame's nearest training frame (module notes).

    Args:
        generated: the judged clips (runs never cross from one clip to the next).
        training: the training clips, concatenated in order into the database.
        fps: common frame rate (``None``: the first training clip's).
        joints: joint names (default: the moving joints of ``training``).

    Returns:
        A :class:`CopyResult` whose ``nearest`` indexes the concatenated training frames.
    """
    gen, tr, f, idx = _setup(generated, training, fps, joints, "copying")
    tp, th, axes = _prepare(tr, f, idx, "copying (training)", 1)
    gp, gh, _ = _prepare(gen, f, idx, "copying (generated)", 2)
    db = np.concatenate([_frame_features(p, h, axes) for p, h in zip(tp, th, strict=True)])
    sizes = np.array([p.shape[0] for p in tp])
    clip_index = np.repeat(np.arange(sizes.size), sizes)
    frame_index = np.concatenate([np.arange(n) for n in sizes])
    succ = successor_array(clip_index, frame_index)
    q = np.concatenate([_frame_features(p, h, axes) for p, h in zip(gp, gh, strict=True)])
    nn, _ = _nearest(q, db)
    return _verbatim(nn, succ, [p.shape[0] for p in gp], f)


def _verbatim(nn: np.ndarray, succ: np.ndarray, lengths: Sequence[int], fps: float) -> CopyResult:
    first = np.zeros(nn.size, dtype=bool)
    first[np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)] = True
    prev = np.concatenate([[0], nn[:-1]])
    verbatim = (succ[prev] == nn) & (succ[prev] >= 0) & ~first
    return _copy_result(nn, verbatim, nn.size - len(lengths), fps)


def successor_array(clip_index: ArrayLike, frame_index: ArrayLike) -> np.ndarray:
    """The database successor of each example: same clip, next frame.

    Args:
        clip_index: ``(n,)`` clip of each example (e.g. ``ImplicitModel.clip_index``).
        frame_index: ``(n,)`` frame of each example within its clip.

    Returns:
        ``(n,)`` int64: the index ``k`` with ``clip[k] = clip[i]`` and ``frame[k] = frame[i] + 1``,
        or ``−1`` where there is none.
    """
    c = np.asarray(clip_index, dtype=np.int64).ravel()
    fr = np.asarray(frame_index, dtype=np.int64).ravel()
    if c.shape != fr.shape:
        raise ValueError(f"successor_array: {c.size} clip indices but {fr.size} frame indices")
    order = np.lexsort((fr, c))
    cs, fs = c[order], fr[order]
    nxt = np.full(c.size, -1, dtype=np.int64)
    ok = (cs[1:] == cs[:-1]) & (fs[1:] == fs[:-1] + 1)
    nxt[order[:-1][ok]] = order[1:][ok]
    return nxt


def copying_from_indices(
    indices: ArrayLike | Sequence[ArrayLike], successor: ArrayLike, fps: float
) -> CopyResult:
    """Verbatim copying from the database indices a sampler chose (design §10.4 "Copying").

    Step ``t − 1 → t`` is verbatim when ``indices[t] = successor[indices[t − 1]] ≠ −1``.

    Args:
        indices: ``(T,)`` int database index of each step, or one such array per clip.
        successor: ``(n,)`` successor of each database example, ``−1`` for none
            (:func:`successor_array`).
        fps: steps per second.

    Returns:
        A :class:`CopyResult`.
    """
    succ = np.asarray(successor).ravel()
    if not np.issubdtype(succ.dtype, np.integer):
        raise ValueError("copying_from_indices: successor must be an integer array")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"copying_from_indices: fps must be positive, got {fps!r}")
    try:
        arr: np.ndarray | None = np.asarray(indices)
    except ValueError:  # ragged: one array per clip
        arr = None
    if arr is not None and arr.dtype != object and arr.ndim == 1:
        parts = [arr]
    elif arr is not None and arr.dtype != object and arr.ndim == 2:
        parts = list(arr)
    else:
        parts = [np.asarray(x).ravel() for x in indices]  # type: ignore[union-attr]
    if not parts or any(p.size < 2 for p in parts):
        raise ValueError("copying_from_indices: every clip needs at least 2 steps")
    for p in parts:
        if not np.issubdtype(p.dtype, np.integer) or p.min() < 0 or p.max() >= succ.size:
            raise ValueError(
                f"copying_from_indices: indices must be integers in 0..{succ.size - 1}"
            )
    return _verbatim(np.concatenate(parts), succ.astype(np.int64), [p.size for p in parts], fps)
