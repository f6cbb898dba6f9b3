"""The gallery of a texture's vocabulary: one row per texton, a few of its instances as small
side-view filmstrips (in the manner of syllable movies), with the texton's figures beside
them (MT §3: the textons and their distribution)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..core import atomic_write
from ..motion import Motion
from ._panel import bone_segments, plot_positions
from ._render import check_path, require_plotting

if TYPE_CHECKING:
    from ..texture import MotionTexture

__all__ = ["render_gallery", "render_texton_gallery", "texton_instances", "texton_labels"]

_FN = "render_gallery"


def _strip(ax, motion: Motion, n_poses: int) -> None:
    """``n_poses`` evenly spaced poses of ``motion`` seen from the side (plot x against up),
    each shifted right by a figure's width, on a ground line; earlier poses lighter."""
    T = motion.n_frames
    idx = np.linspace(0, T - 1, n_poses).round().astype(int)
    # only the poses shown, always n_poses of them: one forward-kinematics program for all
    pos = plot_positions(motion[idx], _FN)
    pairs, colours = bone_segments(motion, end_sites=False)
    ground = float(pos[..., 2].min())
    width = 0.9 * float(motion.skeleton.size)
    from matplotlib.collections import LineCollection
    from matplotlib.colors import to_rgba

    lines, rgba = [], []
    for n in range(len(idx)):
        p = pos[n] - np.array([pos[n, 0, 0] - n * width, 0.0, ground])
        alpha = 0.35 + 0.65 * (n + 1) / len(idx)
        lines.append(np.stack([p[pairs[:, 0]][:, [0, 2]], p[pairs[:, 1]][:, [0, 2]]], axis=1))
        rgba += [to_rgba(c, alpha) for c in colours]
    ax.add_collection(LineCollection(list(np.concatenate(lines)), colors=rgba, linewidths=1.0))
    ax.axhline(0.0, color="#b4b4b4", lw=0.8)
    ax.set_xlim(-0.6 * width, (len(idx) - 0.4) * width)
    ax.set_ylim(-0.05 * width, 2.2 * width)
    ax.set_aspect("equal")
    ax.set_axis_off()


def render_gallery(
    instances: Sequence[Sequence[Motion]],
    labels: Sequence[str],
    path: str | os.PathLike[str],
    *,
    n_poses: int = 5,
    title: str | None = None,
    dpi: float = 80,
) -> Path:
    """Write a PNG with one row per texton: its label, then its instances as filmstrips.

    Args:
        instances: per texton, the motions to show (e.g. a few of its training segments);
            a texton with none shows its label only.
        labels: per texton, the text beside its row (count, duration, successors).
        path: output PNG; its folder must exist.
        n_poses: poses per instance.
        title: a title over the gallery.
        dpi: resolution.

    Returns:
        The path written.

    Raises:
        ValueError: no textons, ``labels`` of another length, a motion with no frames.
        TypeError: an instance that is not a :class:`Motion`.
    """
    require_plotting(_FN)
    rows = [list(r) for r in instances]
    if not rows:
        raise ValueError(f"{_FN}: no textons to draw")
    if len(labels) != len(rows):
        raise ValueError(f"{_FN}: {len(labels)} labels for {len(rows)} textons")
    if isinstance(n_poses, bool) or not isinstance(n_poses, int) or n_poses < 1:
        raise ValueError(f"{_FN}: n_poses must be a positive integer, got {n_poses!r}")
    for r in rows:
        for m in r:
            if not isinstance(m, Motion):
                raise TypeError(f"{_FN}: instances must be Motions, got {type(m).__name__}")
            if m.n_frames == 0:
                raise ValueError(f"{_FN}: an instance has no frames")
    p = check_path(path, _FN)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n_cols = max(1, max(len(r) for r in rows))
    strip_w = 0.45 * n_poses + 0.3
    fig = Figure(figsize=(2.6 + n_cols * strip_w, 0.3 + 1.05 * len(rows)), dpi=dpi)
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(len(rows), n_cols + 1, width_ratios=[2.6] + [strip_w] * n_cols)
    for i, (r, text) in enumerate(zip(rows, labels, strict=True)):
        ax = fig.add_subplot(grid[i, 0])
        ax.set_axis_off()
        ax.text(0.0, 0.5, text, ha="left", va="center", fontsize=7, transform=ax.transAxes)
        for j, m in enumerate(r):
            _strip(fig.add_subplot(grid[i, j + 1]), m, n_poses)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.subplots_adjust(left=0.01, right=0.99, top=0.97 if title else 0.995, bottom=0.005)
    with atomic_write(p, "wb") as fh:
        fig.savefig(fh, format="png")
    return p


def texton_labels(tex: MotionTexture) -> list[str]:
    """Per texton the gallery's text: its segments (and share), mean duration, how often it
    repeats itself and its most likely successors (``tex.summary()``)."""
    voc = tex.summary()
    out = []
    for r in voc.rows():
        dur = f"{r['mean_seconds']:.2f} s" if r["mean_seconds"] is not None else "frames"
        if r["mean_seconds"] is None:
            dur = f"{r['mean_length']:.0f} frames"
        succ = ", ".join(f"{j} ({p:.2f})" for j, p in r["successors"][:3]) or "none"
        out.append(
            f"texton {r['texton']}\n{r['segments']} segments ({100 * r['share']:.0f} %)\n"
            f"mean {dur}, stays {r['self']:.2f}\nnext: {succ}"
        )
    return out


def texton_instances(
    tex: MotionTexture, clips: Sequence[Motion] | None, per_texton: int = 3, seed: int = 0
) -> tuple[list[list[Motion]], str]:
    """A few instances of every texton: with ``clips`` (the training clips, in the order they
    were given to :func:`~mtex_jax.texture.learn`) its training segments, evenly spread over
    its list of segments; else samples of its dynamics from its training key poses
    (:func:`~mtex_jax.texture.synthesize_texton`, the texture's innovations, each as long as
    the mean training segment). Returns the
    instances and what they are (``"training segments"`` or ``"samples"``)."""
    import jax

    from ..texture import synthesize_texton

    fm = tex.feature_map
    if fm is None:
        raise ValueError(f"{_FN}: the texture was learned from arrays; there is no motion to draw")
    if isinstance(per_texton, bool) or not isinstance(per_texton, int) or per_texton < 1:
        raise ValueError(f"{_FN}: per_texton must be a positive integer, got {per_texton!r}")
    segs = np.asarray(tex.segments, dtype=np.int64).reshape(-1, 4)
    rows: list[list[Motion]] = []
    if clips is not None:
        clips = [c if c.fps == fm.fps else c.resample(fm.fps) for c in clips]
        n_need = int(segs[:, 0].max()) + 1 if len(segs) else 0
        if len(clips) < n_need:
            raise ValueError(
                f"{_FN}: the texture's segments come from {n_need} clips, got {len(clips)}; "
                "give the training clips in the order they were learned from"
            )
        for i in range(tex.n_textons):
            mine = segs[segs[:, 3] == i]
            pick = np.unique(np.linspace(0, len(mine) - 1, min(per_texton, len(mine))).round())
            inst = []
            for s, b, n, _ in mine[pick.astype(int)] if len(mine) else []:
                if b + n > clips[s].n_frames:
                    raise ValueError(
                        f"{_FN}: segment ({s}, {b}, {n}) lies beyond clip {s} "
                        f"({clips[s].n_frames} frames): these are not the training clips"
                    )
                inst.append(clips[s][int(b) : int(b + n)])
            rows.append(inst)
        return rows, "training segments"
    kp = np.asarray(tex.key_poses)
    lab = np.asarray(tex.key_pose_labels)
    # one length for every sample (the mean training segment): one program for all
    n = round(float(np.asarray(tex.segment_lengths).mean()))
    key = jax.random.key(seed)
    for i in range(tex.n_textons):
        inst = []
        for j in np.flatnonzero(lab == i)[:per_texton]:
            key, sub = jax.random.split(key)
            Y = synthesize_texton(sub, tex.textons[i], n, kp[j], innovations=tex.innovations)
            inst.append(fm.decode(Y))
        rows.append(inst)
    return rows, "samples"


def render_texton_gallery(
    tex: MotionTexture,
    path: str | os.PathLike[str],
    clips: Sequence[Motion] | None = None,
    *,
    per_texton: int = 3,
    n_poses: int = 5,
    dpi: float = 80,
) -> Path:
    """The gallery of a texture's vocabulary (MT §3): one row per texton with its figures and
    ``per_texton`` instances (training segments of ``clips``, or samples of its dynamics
    without them; see :func:`texton_instances`).

    Returns:
        The path written.
    """
    inst, what = texton_instances(tex, clips, per_texton)
    title = f"{tex.n_textons} textons; each row: its figures and {what}"
    return render_gallery(inst, texton_labels(tex), path, n_poses=n_poses, title=title, dpi=dpi)
