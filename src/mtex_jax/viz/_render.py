"""Stick-figure rendering of a :class:`Motion`: animated GIFs and key-frame filmstrips.

Drawing uses matplotlib's object API on an Agg canvas (no ``pyplot``, no global backend
change) and Pillow writes the files; both are optional dependencies, imported only when a
function here is called (``pip install "mtex_jax[plot]"``).

The skeleton's up axis becomes the vertical axis of the plot through a proper rotation, so the
figure is never mirrored: z up is drawn as is, y up as ``(x, -z, y)``, x up as ``(y, z, x)``.
Bones on the figure's left are blue, on its right red (from the joint names: ``left…``,
``l_…``, ``lShldr``, ``…_l``), the rest dark grey.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..core import atomic_write
from ..motion import Motion

if TYPE_CHECKING:
    pass
from ._panel import (
    PLOT_EXTRA,
    Box,
    Panel,
    bone_segments,
    dot_joints,
    ground_height,
    is_int,
    new_figure,
    nice_step,
    plot_positions,
    trajectory_points,
)

#: GIF players (browsers in particular) slow down frames shorter than 20 ms.
MAX_GIF_FPS = 50.0


# ---------------------------------------------------------------------------------------------
# Checks and preparation (no matplotlib needed)
# ---------------------------------------------------------------------------------------------
def require_plotting(fn: str) -> None:
    """Raise a helpful ImportError when matplotlib or Pillow is missing."""
    missing = []
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        missing.append("matplotlib")
    try:
        import PIL  # noqa: F401
    except ImportError:
        missing.append("Pillow")
    if missing:
        raise ImportError(f"{fn} needs {' and '.join(missing)}; {PLOT_EXTRA}")


def check_motion(motion: Any, fn: str) -> Motion:
    if not isinstance(motion, Motion):
        raise TypeError(f"{fn} expects a Motion, got {type(motion).__name__}")
    if motion.n_frames == 0:
        raise ValueError(f"{fn}: the motion has no frames")
    return motion


def check_path(path: str | os.PathLike[str], fn: str) -> Path:
    p = Path(path)
    if p.exists() and p.is_dir():
        raise ValueError(f"{fn}: {p} is a directory, expected a file name")
    parent = p.parent
    if not parent.is_dir():
        raise ValueError(f"{fn}: folder {parent} does not exist (create it first)")
    return p


def positive_float(x: Any, name: str, fn: str) -> float:
    if isinstance(x, bool) or not isinstance(x, int | float | np.integer | np.floating):
        raise ValueError(f"{fn}: {name} must be a positive number, got {x!r}")
    v = float(x)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{fn}: {name} must be positive and finite, got {x!r}")
    return v


# ---------------------------------------------------------------------------------------------
# GIF
# ---------------------------------------------------------------------------------------------
def _gif_frame_indices(start: int, stop: int, motion_fps: float, fps: float) -> np.ndarray:
    """Motion frames shown at ``fps``: the nearest frame to each output time ``k / fps``."""
    ratio = motion_fps / fps
    n_out = math.floor((stop - 1 - start) / ratio + 1e-9) + 1
    idx = start + np.rint(np.arange(n_out) * ratio).astype(np.int64)
    return np.minimum(idx, stop - 1)


def _gif_durations(n: int, fps: float) -> list[int]:
    """Per-frame durations in ms, multiples of 10 ms (the GIF unit) averaging ``1000 / fps``.

    Frame ``k`` ends at ``round((k + 1) · 100 / fps)`` centiseconds, so rounding errors do not
    accumulate: at 30 fps the durations run 30, 40, 30, 30, 40, 30, … ms.
    """
    ends = np.rint(np.arange(1, n + 1) * 100.0 / fps).astype(np.int64)
    cs = np.diff(ends, prepend=0)
    return [int(10 * max(c, 1)) for c in cs]


def save_gif(out: Any, frames: Sequence[int], draw: Any, rate: float) -> None:
    """Draw ``frames`` with ``draw(i) -> PIL image`` and write them as a looping GIF at
    ``rate`` frames per second, atomically, with one palette taken from the last frame (no
    flicker; the background kept pure white)."""
    from PIL import Image

    palette = draw(frames[-1]).quantize(colors=255, method=Image.Quantize.FASTOCTREE)
    entries = np.asarray(palette.getpalette() or [], dtype=np.int64).reshape(-1, 3)
    entries[(entries >= 250).all(axis=1)] = 255  # keep the background pure white
    palette.putpalette(entries.astype(np.uint8).ravel().tolist())
    images = [draw(i).quantize(palette=palette, dither=Image.Dither.NONE) for i in frames]
    with atomic_write(out, "wb") as fh:  # a failed render leaves an older file intact
        images[0].save(
            fh,
            format="GIF",
            save_all=True,
            append_images=images[1:],
            duration=_gif_durations(len(images), rate),
            loop=0,
            disposal=1,
            optimize=False,
        )


def render_gif(
    motion: Motion,
    path: str | os.PathLike[str],
    *,
    fps: float | None = None,
    trajectories: str | int | Sequence[str | int] | None = None,
    end_sites: bool = True,
    frame_range: tuple[int, int] | None = None,
    size: tuple[float, float] = (5.0, 5.0),
    dpi: float = 80,
    elev: float = 15.0,
    azim: float = -60.0,
    title: str | None = None,
) -> Path:
    """Write a looping animated GIF of the motion as a 3-D stick figure.

    Bones are parent→child segments (left side blue, right side red); the skeleton's up axis is
    drawn vertical. The axes are fixed over the rendered frames: a cube around the figure's
    whole trajectory with equal aspect, so the figure is never rescaled between frames. A light
    ground square with a 1-2-5 grid is drawn at the lowest point the figure reaches (joints and
    end sites). The frame number and time are shown in the top-left corner.

    Args:
        motion: the clip to draw.
        path: output file (written as GIF whatever its suffix); its folder must exist.
        fps: playback rate. Frames are picked from the motion at this rate (the nearest frame to
            each time ``k / fps``), so the animation plays in real time. Default
            ``min(motion.fps, 30)``; must be at most ``motion.fps`` and at most 50 (GIF frame
            durations are multiples of 10 ms, and players slow down frames under 20 ms). Frame
            durations alternate between neighbouring multiples of 10 ms so that they average
            exactly ``1000 / fps`` ms.
        trajectories: joint names (or point indices: ``0..J-1`` joints, ``J..J+E-1`` end sites
            in ``skeleton.end_sites`` order) whose paths are drawn as lines, up to the current
            frame (as in the Motion Texture paper's figures).
        end_sites: draw the end-site segments (head top, hands, toes, …).
        frame_range: ``(start, stop)`` motion frames to render, ``stop`` exclusive; default the
            whole clip. The axes and the ground are fitted to this range.
        size: figure size in inches ``(width, height)``.
        dpi: pixels per inch (80 with the default size gives 400 × 400 pixels).
        elev: camera elevation in degrees above the ground plane.
        azim: camera azimuth in degrees (matplotlib's convention, in plot coordinates).
        title: optional text at the top.

    Returns:
        The path written.

    Raises:
        TypeError: ``motion`` is not a :class:`Motion`.
        ValueError: empty motion, bad ``fps`` / ``frame_range`` / ``size`` / ``dpi``, unknown
            trajectory joints, missing output folder, or non-finite joint positions (naming the
            first bad frame).
        ImportError: matplotlib or Pillow is not installed.
    """
    fn = "render_gif"
    motion = check_motion(motion, fn)
    out = check_path(path, fn)
    t_all = motion.n_frames
    if frame_range is None:
        start, stop = 0, t_all
    else:
        if (
            not isinstance(frame_range, Sequence)
            or len(frame_range) != 2
            or not all(is_int(v) for v in frame_range)
        ):
            raise ValueError(
                f"{fn}: frame_range must be (start, stop) integers, got {frame_range!r}"
            )
        start, stop = int(frame_range[0]), int(frame_range[1])
        if not 0 <= start < stop <= t_all:
            raise ValueError(
                f"{fn}: frame_range {frame_range!r} must satisfy 0 <= start < stop <= {t_all}"
            )
    if fps is None:
        rate = min(float(motion.fps), 30.0)
    else:
        rate = positive_float(fps, "fps", fn)
        if rate > float(motion.fps) * (1 + 1e-9):
            raise ValueError(
                f"{fn}: fps={fps!r} exceeds the motion's frame rate {motion.fps}; frames are "
                "only skipped, never repeated (resample the motion first)"
            )
        if rate > MAX_GIF_FPS:
            raise ValueError(
                f"{fn}: fps={fps!r} is above {MAX_GIF_FPS:g}; GIF frame durations are multiples "
                "of 10 ms and players slow down frames shorter than 20 ms"
            )
    if not isinstance(size, Sequence) or len(size) != 2:
        raise ValueError(f"{fn}: size must be (width, height) in inches, got {size!r}")
    width = positive_float(size[0], "size[0]", fn)
    height = positive_float(size[1], "size[1]", fn)
    dpi = positive_float(dpi, "dpi", fn)
    traj = trajectory_points(trajectories, motion, fn)
    require_plotting(fn)
    from PIL import Image

    pos = plot_positions(motion[start:stop], fn)
    ground = ground_height(pos)
    lo = pos.reshape(-1, 3).min(axis=0)
    hi = pos.reshape(-1, 3).max(axis=0)
    span = float(max((hi - lo).max(), motion.skeleton.size * 0.5, 1e-9))
    half = 0.55 * span
    mid = (lo + hi) / 2
    box = Box((float(mid[0]), float(mid[1]), float(mid[2])), half)
    step = nice_step(2 * half)
    bones, colours = bone_segments(motion, end_sites)

    fig, canvas = new_figure((width, height), dpi)
    panel = Panel(
        fig,
        (0.0, 0.0, 1.0, 1.0),
        box=box,
        ground=ground,
        step=step,
        bones=bones,
        colours=colours,
        joints=dot_joints(motion),
        trajectories=traj,
        elev=float(elev),
        azim=float(azim),
        linewidth=2.4,
    )
    if traj:
        panel.ax.legend(loc="upper right", fontsize=7, frameon=False, handlelength=1.2)
    width_digits = len(str(t_all - 1))
    # the frame counter takes the top-left corner; with a title (which spans the top, and may
    # be long) it moves to the bottom-left, so that the two never overlap
    counter = fig.text(
        0.02,
        0.02 if title else 0.98,
        "",
        ha="left",
        va="bottom" if title else "top",
        fontsize=8,
        family="monospace",
    )
    if title:
        fig.text(
            0.5, 0.98 if not traj else 0.93, title, ha="center", va="top", fontsize=10, wrap=True
        )
    fig.text(0.98, 0.02, f"grid {step:g}", ha="right", va="bottom", fontsize=7, color="#808080")

    shown = _gif_frame_indices(start, stop, float(motion.fps), rate)

    def draw(i: int) -> Image.Image:
        k = i - start
        panel.show(pos[k], [pos[: k + 1, p] for p, _ in traj], clip=False)
        counter.set_text(f"frame {i:>{width_digits}d}/{t_all - 1}  t={i / motion.fps:6.2f} s")
        canvas.draw()
        rgba = np.asarray(canvas.buffer_rgba())
        return Image.fromarray(np.ascontiguousarray(rgba[..., :3]))

    # One palette for every frame (no flicker): taken from the last frame, which shows the
    # complete trajectories and so every colour used.
    save_gif(out, [int(i) for i in shown], draw, rate)
    return out


# ---------------------------------------------------------------------------------------------
# Filmstrip
# ---------------------------------------------------------------------------------------------
def render_filmstrip(
    motion: Motion,
    path: str | os.PathLike[str],
    *,
    n_frames: int = 8,
    frames: Sequence[int] | None = None,
    trajectories: str | int | Sequence[str | int] | None = None,
    end_sites: bool = True,
    height: float = 3.0,
    dpi: float = 100,
    elev: float = 15.0,
    azim: float = -60.0,
    title: str | None = None,
) -> Path:
    """Write a PNG of key frames side by side, one square 3-D panel per frame.

    All panels share one scale and one vertical range (the cube side fits the largest pose
    among the chosen frames); each panel is centred horizontally on its own pose, and the
    ground grid is fixed in the world, so travel shows as the grid shifting under the figure.
    The frame number and time are written under each panel.

    Args:
        motion: the clip to draw.
        path: output file (written as PNG whatever its suffix); its folder must exist.
        n_frames: number of evenly spaced frames from first to last (ignored with ``frames``);
            a clip with fewer frames shows all of them.
        frames: explicit frame indices (``0 <= i < motion.n_frames``), in the order shown.
        trajectories: joint names or point indices (see :func:`render_gif`) whose paths from
            the first frame up to each panel's frame are drawn (clipped to the panel).
        end_sites: draw the end-site segments.
        height: panel height (and width) in inches.
        dpi: pixels per inch.
        elev: camera elevation in degrees.
        azim: camera azimuth in degrees.
        title: optional text above the strip.

    Returns:
        The path written.

    Raises:
        TypeError: ``motion`` is not a :class:`Motion`.
        ValueError: empty motion, bad ``n_frames`` / ``frames`` / ``height`` / ``dpi``, unknown
            trajectory joints, missing output folder, or non-finite joint positions.
        ImportError: matplotlib or Pillow is not installed.
    """
    fn = "render_filmstrip"
    motion = check_motion(motion, fn)
    out = check_path(path, fn)
    t_all = motion.n_frames
    if frames is None:
        if not is_int(n_frames) or n_frames < 1:
            raise ValueError(f"{fn}: n_frames must be a positive integer, got {n_frames!r}")
        chosen = np.rint(np.linspace(0, t_all - 1, min(int(n_frames), t_all))).astype(np.int64)
    else:
        if isinstance(frames, str) or not isinstance(frames, Sequence | np.ndarray):
            raise ValueError(f"{fn}: frames must be a sequence of frame indices, got {frames!r}")
        if len(frames) == 0:
            raise ValueError(f"{fn}: frames is empty")
        for f in frames:
            if not is_int(f) or not 0 <= int(f) < t_all:
                raise ValueError(f"{fn}: frame index {f!r} is not an integer in 0..{t_all - 1}")
        chosen = np.asarray([int(f) for f in frames], dtype=np.int64)
    height = positive_float(height, "height", fn)
    dpi = positive_float(dpi, "dpi", fn)
    traj = trajectory_points(trajectories, motion, fn)
    require_plotting(fn)

    pos = plot_positions(motion, fn)
    ground = ground_height(pos)
    sel = pos[chosen]  # (N, P, 3)
    lo = sel.min(axis=1)
    hi = sel.max(axis=1)
    extents = np.concatenate([(hi - lo)[:, :2], (hi[:, 2] - ground)[:, None]], axis=1)
    span = float(max(extents.max(), motion.skeleton.size * 0.5, 1e-9))
    half = 0.55 * span
    z_centre = ground + span / 2
    step = nice_step(2 * half)
    bones, colours = bone_segments(motion, end_sites)

    n = len(chosen)
    label_h = 0.3
    title_h = 0.4 if title else 0.0
    fig_h = height + label_h + title_h
    fig, _ = new_figure((n * height, fig_h), dpi)
    bottom = label_h / fig_h
    panel_h = height / fig_h
    for k, i in enumerate(chosen):
        centre = ((lo[k, 0] + hi[k, 0]) / 2, (lo[k, 1] + hi[k, 1]) / 2, z_centre)
        panel = Panel(
            fig,
            (k / n, bottom, 1.0 / n, panel_h),
            box=Box((float(centre[0]), float(centre[1]), float(centre[2])), half),
            ground=ground,
            step=step,
            bones=bones,
            colours=colours,
            joints=dot_joints(motion),
            trajectories=traj,
            elev=float(elev),
            azim=float(azim),
            linewidth=2.0,
        )
        panel.show(pos[i], [pos[: i + 1, p] for p, _ in traj], clip=True)
        fig.text(
            (k + 0.5) / n,
            0.5 * label_h / fig_h,
            f"frame {i}  ·  {i / motion.fps:.2f} s",
            ha="center",
            va="center",
            fontsize=9,
        )
        if traj and k == n - 1:
            panel.ax.legend(loc="upper right", fontsize=7, frameon=False, handlelength=1.2)
    if title:
        fig.text(0.5, 1.0 - 0.5 * title_h / fig_h, title, ha="center", va="center", fontsize=11)
    fig.text(
        0.002,
        0.5 * label_h / fig_h,
        f"grid {step:g}",
        ha="left",
        va="center",
        fontsize=7,
        color="#808080",
    )
    with atomic_write(out, "wb") as fh:
        fig.savefig(fh, format="png", dpi=dpi, facecolor="white")
    return out
