"""Two motions side by side in one animated GIF, with the same camera and the same scale (a
synthesised motion beside a real clip)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..motion import Motion
from ._panel import (
    Box,
    Panel,
    bone_segments,
    dot_joints,
    ground_height,
    new_figure,
    nice_step,
    plot_positions,
    trajectory_points,
)
from ._render import (
    MAX_GIF_FPS,
    check_motion,
    check_path,
    positive_float,
    require_plotting,
    save_gif,
)

__all__ = ["render_gif_pair"]


def render_gif_pair(
    left: Motion,
    right: Motion,
    path: str | os.PathLike[str],
    *,
    titles: tuple[str, str] = ("", ""),
    seconds: float | None = None,
    fps: float = 15.0,
    trajectories: str | int | Sequence[str | int] | None = None,
    panel_size: float = 4.0,
    dpi: float = 90,
    elev: float = 15.0,
    azim: float = -60.0,
    title: str | None = None,
) -> Path:
    """Write a looping GIF of two motions side by side: same camera, same scale.

    Both panels use the same camera angles and a cube of the same side (the larger of the two
    motions' extents over the frames shown), each centred on its own motion; each has its own
    ground (the lowest point of its motion) with a grid of the same spacing. The animation
    lasts ``seconds`` (default: the left motion's duration); a shorter right motion loops. The
    motions may have different frame rates and skeletons; frames are picked at ``fps`` (the
    nearest frame to each time ``k / fps``), so both play in real time.

    Args:
        left: the motion on the left (e.g. a synthesised dance).
        right: the motion on the right (e.g. a real clip).
        path: output GIF; its folder must exist.
        titles: a caption above each panel.
        seconds: length of the animation in seconds.
        fps: playback rate (at most each motion's frame rate and at most 50).
        trajectories: joint names (present in both skeletons) whose paths are drawn.
        panel_size: inches per panel (square); ``dpi`` pixels per inch.
        elev: camera elevation in degrees (as in :func:`render_gif`).
        azim: camera azimuth in degrees (as in :func:`render_gif`).
        title: optional text at the top.

    Returns:
        The path written.

    Raises:
        TypeError / ValueError / ImportError: as :func:`render_gif`.
    """
    fn = "render_gif_pair"
    motions = (check_motion(left, fn), check_motion(right, fn))
    out = check_path(path, fn)
    rate = positive_float(fps, "fps", fn)
    if rate > MAX_GIF_FPS or any(rate > float(m.fps) * (1 + 1e-9) for m in motions):
        raise ValueError(
            f"{fn}: fps={fps!r} must be at most {MAX_GIF_FPS:g} and at most both motions' "
            "frame rates"
        )
    length = left.duration if seconds is None else positive_float(seconds, "seconds", fn)
    size = positive_float(panel_size, "panel_size", fn)
    dpi = positive_float(dpi, "dpi", fn)
    if len(titles) != 2:
        raise ValueError(f"{fn}: titles must be two strings, got {titles!r}")
    traj = [trajectory_points(trajectories, m, fn) for m in motions]
    require_plotting(fn)
    from PIL import Image

    n_out = int(np.floor(length * rate + 1e-9)) + 1
    times = np.arange(n_out) / rate
    shown = []
    for m in motions:
        idx = np.rint(times * m.fps).astype(np.int64)
        shown.append(idx % m.n_frames if m.n_frames > 1 else np.zeros_like(idx))
    pos = [plot_positions(m, fn) for m in motions]
    spans = []
    for p, s in zip(pos, shown, strict=True):
        q = p[np.unique(s)]
        spans.append(float((q.reshape(-1, 3).max(axis=0) - q.reshape(-1, 3).min(axis=0)).max()))
    span = max(*spans, *(0.5 * m.skeleton.size for m in motions), 1e-9)
    half = 0.55 * span
    step = nice_step(2 * half)

    fig, canvas = new_figure((2 * size, size + (0.35 if title else 0.0)), dpi)
    top = size / (size + (0.35 if title else 0.0))
    panels = []
    for k, (m, p, s) in enumerate(zip(motions, pos, shown, strict=True)):
        q = p[np.unique(s)].reshape(-1, 3)
        mid = (q.min(axis=0) + q.max(axis=0)) / 2
        bones, colours = bone_segments(m, True)
        panel = Panel(
            fig,
            (k / 2, 0.0, 0.5, top * 0.94),
            box=Box((float(mid[0]), float(mid[1]), float(mid[2])), half),
            ground=ground_height(p[np.unique(s)]),
            step=step,
            bones=bones,
            colours=colours,
            joints=dot_joints(m),
            trajectories=traj[k],
            elev=float(elev),
            azim=float(azim),
            linewidth=2.2,
        )
        panels.append(panel)
        fig.text((k + 0.5) / 2, top * 0.97, titles[k], ha="center", va="top", fontsize=10)
    counters = [
        fig.text(k / 2 + 0.01, 0.01, "", ha="left", va="bottom", fontsize=8, family="monospace")
        for k in range(2)
    ]
    if title:
        fig.text(0.5, 0.995, title, ha="center", va="top", fontsize=11)
    fig.text(0.995, 0.01, f"grid {step:g}", ha="right", va="bottom", fontsize=7, color="#808080")

    def draw(i: int) -> Image.Image:
        for k in range(2):
            f = int(shown[k][i])
            start = f - int(np.rint(min(times[i], 2.0) * motions[k].fps))  # last 2 s of path
            paths = [pos[k][max(start, 0) : f + 1, pt] for pt, _ in traj[k]]
            panels[k].show(pos[k][f], paths, clip=False)
            counters[k].set_text(f"t={f / motions[k].fps:6.2f} s")
        canvas.draw()
        rgba = np.asarray(canvas.buffer_rgba())
        return Image.fromarray(np.ascontiguousarray(rgba[..., :3]))

    save_gif(out, list(range(n_out)), draw, rate)
    return out
