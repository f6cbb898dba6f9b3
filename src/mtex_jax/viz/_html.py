"""A self-contained HTML page with a 3-D stick-figure player (``mtex view``).

The page is one file that opens from disk without a network or a server: the player
(``_player.js``, a perspective camera of its own on a 2-D canvas), its styles and the data are
inlined. Joint positions are stored as little-endian ``int16`` in base64, in units of about a
millimetre (0.1 % of the figure's size), at the player's frame rate (30 Hz by default), so a
20 s clip of a 57-point figure takes about 300 kB.

Coordinates: the skeleton's up axis becomes ``z`` (the same proper rotation as the GIF
renderer), every motion stands on its own floor (its lowest point over the clip at height 0)
and several motions are placed side by side along ``x``. Foot contacts are those of
:func:`mtex_jax.motion.fit_contacts` fitted on the motion itself (a foot is marked while it
is low and slow).
"""

from __future__ import annotations

import base64
import html
import json
import math
import os
from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ..core import atomic_write
from ..motion import Motion, fit_contacts, forward_kinematics_arrays
from ..texture import MotionTexture, synthesize
from ._panel import TO_PLOT, bone_segments, dot_joints

__all__ = ["write_html"]

#: at most this many textons get a small player in the gallery (the most used ones)
MAX_GALLERY = 60
#: frames per forward-kinematics call: one compiled program for every clip length
FK_BLOCK = 512
#: successors of a texton shown when hovering it: the most probable, if at least 1 %
N_SUCCESSORS = 3


# ---------------------------------------------------------------------------------------------
# one figure: positions, bones, contacts
# ---------------------------------------------------------------------------------------------
def _frame_indices(n: int, fps: float, out_fps: float) -> np.ndarray:
    """Source frames shown at ``out_fps``: the nearest frame to each output time."""
    n_out = math.floor((n - 1) * out_fps / fps + 1e-9) + 1
    return np.minimum(np.rint(np.arange(n_out) * fps / out_fps).astype(np.int64), n - 1)


def _positions(motion: Motion, idx: np.ndarray, fn: str) -> np.ndarray:
    """World positions of joints then end sites at frames ``idx``, ``(T, J + E, 3)``, with the
    up axis turned to ``z``; computed in blocks of :data:`FK_BLOCK` frames around the origin
    (the root path added in float64), so clips of any length share one compiled program."""
    sk = motion.skeleton
    q = np.asarray(motion.rotations, dtype=np.float64)[idx]
    lp = motion.local_positions
    lp = None if lp is None else np.asarray(lp, dtype=np.float64)[idx]
    n = len(idx)
    out = np.empty((n, sk.n_joints + len(sk.end_sites), 3))
    for s in range(0, n, FK_BLOCK):
        e = min(s + FK_BLOCK, n)
        qb = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (FK_BLOCK, sk.n_joints, 1))
        qb[: e - s] = q[s:e]
        lb = None
        if lp is not None:
            lb = np.zeros((FK_BLOCK, sk.n_joints, 3))
            lb[: e - s] = lp[s:e]
        pb = forward_kinematics_arrays(sk, np.zeros((FK_BLOCK, 3)), qb, lb, end_sites=True)
        out[s:e] = np.asarray(pb, dtype=np.float64)[: e - s]
    out += np.asarray(motion.root_positions, dtype=np.float64)[idx][:, None, :]
    bad = ~np.isfinite(out).all(axis=(1, 2))
    if bad.any():
        raise ValueError(f"{fn}: non-finite joint positions, first at frame {int(idx[bad][0])}")
    return out @ TO_PLOT[sk.up_axis].T


def _kept_points(motion: Motion, feet: Sequence[int]) -> np.ndarray:
    """Points drawn: the joints carrying a sizeable chain (and the root and feet), and below
    each of them that has no such child the start of its longest remaining chain, so a hand
    ends in one bone instead of a fan of fingers (points: joints, then end sites)."""
    sk = motion.skeleton
    parent = [*sk.parents, *(p for p, _ in sk.end_sites)]
    ends = [float(np.linalg.norm(o)) for _, o in sk.end_sites]
    length = np.concatenate([np.linalg.norm(sk.offsets_array, axis=1), np.asarray(ends)])
    reach = np.zeros(len(parent))  # the longest chain below each point
    for k in range(len(parent) - 1, 0, -1):  # children come after their parents
        reach[parent[k]] = max(reach[parent[k]], reach[k] + length[k])
    big = set(dot_joints(motion).tolist()) | {0, *feet}
    keep = set(big)
    for j in big:
        children = [k for k in range(1, len(parent)) if parent[k] == j]
        if children and not big & set(children):
            keep.add(max(children, key=lambda k: reach[k] + length[k]))
    return np.asarray(sorted(keep), dtype=np.int64)


def _contacts(motion: Motion) -> tuple[list[int], np.ndarray | None]:
    """Foot joints and per-frame contact flags ``(T, F)`` (``None`` for too short a clip)."""
    if motion.n_frames < 3:
        return [], None
    model = fit_contacts(motion)
    steps = model.labels(motion)  # (T - 1, F): low at both ends of the step, and slow
    flags = np.zeros((motion.n_frames, len(model.feet)), dtype=bool)
    flags[:-1] |= steps
    flags[1:] |= steps
    return list(model.feet), flags


def _encode(a: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(a).astype(dtype).tobytes()).decode("ascii")


def _figure(
    motion: Motion, label: str, out_fps: float, contacts: bool, fn: str
) -> tuple[dict[str, Any], np.ndarray]:
    """The figure's data (points in its own frame: floor at 0, centred horizontally) and its
    positions ``(T_out, P, 3)``."""
    idx = _frame_indices(motion.n_frames, motion.fps, out_fps)
    feet, flags = _contacts(motion) if contacts else ([], None)
    keep = _kept_points(motion, feet)
    new_index = {int(k): i for i, k in enumerate(keep)}
    pairs, colours = bone_segments(motion, end_sites=True)
    bones = [
        (new_index[int(a)], new_index[int(b)], c)
        for (a, b), c in zip(pairs, colours, strict=True)
        if int(a) in new_index and int(b) in new_index
    ]
    p = _positions(motion, idx, fn)[:, keep]
    p[..., 2] -= p[..., 2].min()  # the figure stands on the floor
    centre = 0.5 * (p[..., :2].min(axis=(0, 1)) + p[..., :2].max(axis=(0, 1)))
    p[..., :2] -= centre
    fig: dict[str, Any] = {
        "label": label,
        "n": len(idx),
        "P": len(keep),
        "points": [int(k) for k in keep],  # joints, then end sites from n_joints on
        "bones": [[a, b] for a, b, _ in bones],
        "colours": [c for _, _, c in bones],
        "dots": [new_index[int(j)] for j in dot_joints(motion) if int(j) in new_index],
        "feet": [new_index[f] for f in feet],
        "contact": _encode(flags[idx], "u1") if flags is not None else "",
        "timeline": None,
    }
    return fig, p


def _pack(fig: dict[str, Any], p: np.ndarray, size: float) -> dict[str, Any]:
    """Store the positions as ``int16`` steps of ``unit`` (0.1 % of ``size``, coarser only if
    the clip reaches farther than 32 000 steps from its centre)."""
    lo, hi = p.min(axis=(0, 1)), p.max(axis=(0, 1))
    origin = 0.5 * (lo + hi)
    reach = float(np.abs(p - origin).max())
    unit = max(1e-3 * size, reach / 32000.0, 1e-9)
    q = np.rint((p - origin) / unit)
    fig.update(origin=[float(v) for v in origin], unit=unit, pos=_encode(q, "<i2"))
    return fig


# ---------------------------------------------------------------------------------------------
# textures: timelines, texton statistics, the gallery
# ---------------------------------------------------------------------------------------------
def timeline_rows(segments: Any, n_frames: int, fps: float, out_fps: float) -> list[list[int]]:
    """Texton segments ``(start, length, label)`` in a motion's frames, converted to the
    player's frames.

    Args:
        segments: a :class:`~mtex_jax.texture.Synthesis` (its path, starts and lengths) or an
            ``(n, 3)`` array of ``(start, length, label)`` rows.
        n_frames: frames of the motion the segments belong to.
        fps: the motion's frame rate.
        out_fps: the player's frame rate.

    Returns:
        rows ``[start, length, label]`` in player frames (every length at least 1).
    """
    if all(hasattr(segments, a) for a in ("starts", "lengths", "path")):
        rows = np.stack(
            [np.asarray(segments.starts), np.asarray(segments.lengths), np.asarray(segments.path)],
            axis=1,
        )
    else:
        rows = np.asarray(segments)
    if rows.ndim != 2 or rows.shape[1] != 3 or not np.issubdtype(rows.dtype, np.integer):
        raise ValueError(
            f"write_html: a timeline must be a Synthesis or (n, 3) integer rows (start, length, "
            f"label), got shape {rows.shape} of {rows.dtype}"
        )
    start, length, label = rows.T
    if (start < 0).any() or (length < 1).any() or (label < 0).any():
        raise ValueError("write_html: timeline rows need start >= 0, length >= 1, label >= 0")
    if (start + length > n_frames).any():
        raise ValueError(
            f"write_html: a timeline segment ends after the motion's {n_frames} frames"
        )
    ratio = out_fps / fps
    first = np.rint(start * ratio).astype(np.int64)
    end = np.maximum(np.rint((start + length) * ratio).astype(np.int64), first + 1)
    return [[int(a), int(b - a), int(c)] for a, b, c in zip(first, end, label, strict=True)]


def _texture_fps(texture: MotionTexture) -> float | None:
    fm = texture.feature_map
    if fm is not None:
        return float(fm.fps)
    return None if texture.config.fps is None else float(texture.config.fps)


def texton_stats(texture: MotionTexture) -> dict[str, Any]:
    """Per texton: its training segments (``count``), their mean duration (``mean``, in
    ``unit``: seconds, or frames if the texture's frame rate is unknown) and its most probable
    successors under ``M`` (``succ``: up to 3 ``[texton, probability]`` pairs of at least 1 %).
    """
    stats = texture.length_stats()
    fps = _texture_fps(texture)
    M = np.asarray(texture.M, dtype=np.float64)
    succ = []
    for row in M:
        order = np.argsort(-row, kind="stable")[:N_SUCCESSORS]
        succ.append([[int(j), round(float(row[j]), 3)] for j in order if row[j] >= 0.01])
    return {
        "count": [int(c) for c in stats[:, 0]],
        "mean": [round(float(m) / (fps or 1.0), 3) for m in stats[:, 1]],
        "unit": "frames" if fps is None else "s",
        "succ": succ,
    }


def _gallery_textons(texture: MotionTexture) -> list[int]:
    """Textons shown in the gallery: all with training segments, or the most used ones."""
    counts = texture.length_stats()[:, 0]
    used = np.flatnonzero(counts > 0)
    if used.size > MAX_GALLERY:
        used = np.sort(used[np.argsort(-counts[used], kind="stable")[:MAX_GALLERY]])
    return [int(i) for i in used]


def _gallery_samples(texture: MotionTexture) -> list[tuple[int, Motion, str]]:
    """One deterministic sample (zero noise) of every texton at its median training length,
    decoded to a motion.

    All samples come from one :func:`~mtex_jax.texture.synthesize` call (one compilation)
    along the path ``i₁, s(i₁), i₂, s(i₂), …`` with ``s(i)`` the most probable successor of
    ``i``: each texton ends at its successor's key poses, as a one-texton synthesis would, and
    the successors' frames are dropped.
    """
    if texture.feature_map is None:
        raise ValueError("write_html: the texture was learned from arrays; it has no skeleton")
    shown = _gallery_textons(texture)
    M = np.asarray(texture.M, dtype=np.float64)
    counts = texture.length_stats()[:, 0]
    succ = [int(np.argmax(np.where(counts > 0, M[i], -1.0))) for i in shown]
    path = np.ravel(np.column_stack([shown, succ]))
    lens = np.array([_median_length(texture, int(j)) for j in path])
    syn = synthesize(None, texture, path=path, lengths=lens)
    assert syn.motion is not None  # the texture has a feature map
    motion = syn.motion.numpy()
    starts = np.asarray(syn.starts)
    out = []
    for k, i in enumerate(shown):
        a = int(starts[2 * k])
        sample = motion[a : a + int(lens[2 * k])]
        out.append((i, sample, f"sample (zero noise), {sample.duration:.2f} s"))
    return out


def _median_length(texture: MotionTexture, i: int) -> int:
    """The median length of texton ``i``'s training segments (at least 4 frames)."""
    lengths = np.asarray(texture.segment_lengths)[np.asarray(texture.key_pose_labels) == i]
    return max(4, round(float(np.median(lengths))))


def _gallery_instances(
    texture: MotionTexture, clips: Sequence[Motion]
) -> list[tuple[int, Motion, str]]:
    """Every texton's training segment of median length, cut from the training clips."""
    segs = np.asarray(texture.segments)
    if segs.size and int(segs[:, 0].max()) >= len(clips):
        raise ValueError(
            f"write_html: the texture's segments refer to {int(segs[:, 0].max()) + 1} training "
            f"clips, but gallery holds {len(clips)}"
        )
    tex_fps = _texture_fps(texture)
    out = []
    for i in _gallery_textons(texture):
        mine = segs[segs[:, 3] == i]
        pick = mine[np.argmin(np.abs(mine[:, 2] - np.median(mine[:, 2])))]
        seq, start, length = (int(v) for v in pick[:3])
        clip = clips[seq]
        r = 1.0 if tex_fps is None else clip.fps / tex_fps
        a = min(round(start * r), clip.n_frames - 1)
        b = min(max(round((start + length) * r), a + 1), clip.n_frames)
        note = f"training clip {seq}, frames {a}–{b - 1}"
        out.append((i, clip[a:b].numpy(), note))
    return out


# ---------------------------------------------------------------------------------------------
# the page
# ---------------------------------------------------------------------------------------------
def _asset(name: str) -> str:
    return resources.files("mtex_jax.viz").joinpath(name).read_text(encoding="utf-8")


def _as_motion(item: Any, i: int) -> tuple[Motion, Any]:
    """A motion entry: a :class:`Motion`, or a Synthesis (its motion, and its timeline)."""
    if isinstance(item, Motion):
        return item, None
    motion = getattr(item, "motion", None)
    if isinstance(motion, Motion) and hasattr(item, "path"):
        return motion, item
    raise TypeError(
        f"write_html: motions[{i}] must be a Motion or a Synthesis with a decoded motion, "
        f"got {type(item).__name__}"
    )


def write_html(
    path: str | os.PathLike[str],
    motions: Any,
    *,
    labels: Sequence[str] | None = None,
    title: str | None = None,
    timelines: Sequence[Any] | None = None,
    texture: MotionTexture | None = None,
    gallery: bool | Sequence[Motion] = True,
    fps: float = 30.0,
    contacts: bool = True,
) -> Path:
    """Write one self-contained HTML page with a 3-D player of one or more motions.

    The page needs no network and no server. It shows the motions side by side on a floor
    grid (orbit, zoom and pan with the mouse), with play/pause, a frame slider, a speed
    control and a frame counter (element id ``frame-counter``); feet in contact with the floor
    are marked. A motion with segments gets a texton timeline under the player (a click on a
    segment seeks to its first frame; hovering shows the texton's statistics). With a
    ``texture`` the page also has a gallery of the vocabulary: one small looping player per
    texton.

    Args:
        path: the output file (``.html``).
        motions: a :class:`~mtex_jax.motion.Motion`, a
            :class:`~mtex_jax.texture.Synthesis` (its motion, with its texton timeline), or a
            sequence of them.
        labels: a name per motion (default ``motion 1``, ``motion 2``, …).
        title: the page title (default from the labels).
        timelines: per motion ``None`` or its segments (a Synthesis or ``(n, 3)`` rows
            ``(start, length, label)`` in the motion's frames), overriding a Synthesis's own.
        texture: the :class:`~mtex_jax.texture.MotionTexture` the textons belong to: hovering
            a segment shows its training count, mean duration and top successors under ``M``.
        gallery: with a texture: ``True`` for a zero-noise sample of every texton at its
            median training length (one :func:`~mtex_jax.texture.synthesize` call), the
            texture's training clips (in training order) for a training segment of every
            texton, ``False`` for no gallery. At most :data:`MAX_GALLERY` textons are shown
            (the most used).
        fps: the player's frame rate (motions are subsampled to at most this rate).
        contacts: mark foot contacts (:func:`~mtex_jax.motion.fit_contacts` on each motion).

    Returns:
        the path written.
    """
    fn = "write_html"
    items = [motions] if isinstance(motions, Motion) or hasattr(motions, "path") else motions
    if not isinstance(items, Sequence) or isinstance(items, str) or not items:
        raise TypeError(f"{fn}: motions must be a Motion, a Synthesis or a non-empty sequence")
    pairs = [_as_motion(m, i) for i, m in enumerate(items)]
    ms = [m for m, _ in pairs]
    for i, m in enumerate(ms):
        if m.n_frames == 0:
            raise ValueError(f"{fn}: motions[{i}] has no frames")
    names = [f"motion {i + 1}" for i in range(len(ms))] if labels is None else list(labels)
    if len(names) != len(ms) or not all(isinstance(s, str) for s in names):
        raise ValueError(f"{fn}: labels must be {len(ms)} strings, got {labels!r}")
    segs = [s for _, s in pairs] if timelines is None else list(timelines)
    if len(segs) != len(ms):
        raise ValueError(f"{fn}: timelines must have one entry per motion ({len(ms)})")
    real = int | float | np.integer | np.floating
    if isinstance(fps, bool) or not (isinstance(fps, real) and math.isfinite(fps) and fps > 0):
        raise ValueError(f"{fn}: fps must be a positive number, got {fps!r}")
    p = Path(path)
    if p.is_dir() or not p.parent.is_dir():
        raise ValueError(f"{fn}: cannot write {p} (a folder, or its folder does not exist)")
    if texture is not None and not isinstance(texture, MotionTexture):
        raise TypeError(f"{fn}: texture must be a MotionTexture, got {type(texture).__name__}")

    out_fps = min(float(fps), max(m.fps for m in ms))
    size = max(float(m.skeleton.size) for m in ms)
    figs, placed = [], []
    x = 0.0
    for m, name, seg in zip(ms, names, segs, strict=True):
        fig, pos = _figure(m, name, out_fps, contacts, fn)
        half = float(np.abs(pos[..., 0]).max())
        if figs:
            x += half + 0.5 * size
        pos[..., 0] += x
        x += half
        if seg is not None:
            fig["timeline"] = timeline_rows(seg, m.n_frames, m.fps, out_fps)
            if texture is not None and max(r[2] for r in fig["timeline"]) >= texture.n_textons:
                raise ValueError(f"{fn}: a timeline label is beyond the texture's textons")
        figs.append(fig)
        placed.append(pos)
    shift = x / 2  # centre the row of figures on the origin
    for pos in placed:
        pos[..., 0] -= shift
    data: dict[str, Any] = {
        "fps": out_fps,
        "n_frames": max(f["n"] for f in figs),
        "size": size,
        "grid": _grid_step(size),
        "motions": [_pack(f, pos, size) for f, pos in zip(figs, placed, strict=True)],
        "textons": None if texture is None else texton_stats(texture),
        "gallery": [],
    }
    if texture is not None and gallery is not False:
        entries = (
            _gallery_samples(texture)
            if gallery is True
            else _gallery_instances(texture, _clips(gallery, fn))
        )
        for i, m, note in entries:
            g, pos = _figure(m, f"texton {i}", out_fps, contacts, fn)
            data["gallery"].append({"texton": i, "note": note, "figure": _pack(g, pos, size)})
    page_title = title if title is not None else "mtex view: " + " · ".join(names)
    text = _page(page_title, data)
    with atomic_write(p, "w", encoding="utf-8") as fh:
        fh.write(text)
    return p


def _clips(gallery: Any, fn: str) -> list[Motion]:
    if not isinstance(gallery, Sequence) or not all(isinstance(m, Motion) for m in gallery):
        raise TypeError(f"{fn}: gallery must be True, False or the texture's training motions")
    return list(gallery)


def _grid_step(size: float) -> float:
    """Floor grid spacing: 0.5 m for a figure of about 1 m (a 1-2-5 step near half its size)."""
    raw = max(size, 1e-9) / 2
    base = 10.0 ** math.floor(math.log10(raw))
    return min((m * base for m in (1.0, 2.0, 5.0, 10.0)), key=lambda s: abs(math.log(s / raw)))


def _page(title: str, data: dict[str, Any]) -> str:
    """The HTML text: template, styles, player and data (JSON with ``<`` escaped, so no
    string in it can close the script element)."""
    blob = json.dumps(data, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c")
    page = _asset("_player.html")
    page = page.replace("@@TITLE@@", html.escape(title))
    page = page.replace("@@CSS@@", _asset("_player.css"))
    page = page.replace("@@JS@@", _asset("_player.js"))
    return page.replace("@@DATA@@", blob)  # last: the data is never searched for markers
