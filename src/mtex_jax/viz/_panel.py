"""One stick-figure panel of the renderers: the bones and joints of a pose, the ground grid,
trajectories of chosen joints, and a fixed camera box over the whole clip."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeGuard

import numpy as np

from ..motion import Motion, forward_kinematics

if TYPE_CHECKING:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.axes3d import Axes3D

PLOT_EXTRA = 'install them with: pip install "mtex_jax[plot]"'

#: World → plot coordinates (rows: plot x, y, z), a rotation taking ``up_axis`` to plot z.
TO_PLOT = {
    0: np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
    1: np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
    2: np.eye(3),
}

_LEFT_COLOUR = "#1f5fbf"
_RIGHT_COLOUR = "#d62728"
_CENTRE_COLOUR = "#3a3a3a"
_TRAJECTORY_COLOURS = ("#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf")
_GROUND_FACE = "#e6e6e6"
_GROUND_GRID = "#b4b4b4"


def plot_positions(motion: Motion, fn: str) -> np.ndarray:
    """World positions of joints then end sites, ``(T, J + E, 3)``, in plot coordinates."""
    pos = np.asarray(forward_kinematics(motion, end_sites=True), dtype=np.float64)
    bad = ~np.isfinite(pos).all(axis=(1, 2))
    if bad.any():
        t = int(np.argmax(bad))
        j = int(np.argmax(~np.isfinite(pos[t]).all(axis=1)))
        raise ValueError(
            f"{fn}: non-finite joint positions, first at frame {t} (point {_point_name(motion, j)})"
        )
    return pos @ TO_PLOT[motion.skeleton.up_axis].T


def _point_name(motion: Motion, i: int) -> str:
    sk = motion.skeleton
    if i < sk.n_joints:
        return repr(sk.names[i])
    return f"end site of {sk.names[sk.end_sites[i - sk.n_joints][0]]!r}"


def _side(name: str) -> int:
    """-1 for a joint on the figure's left, +1 on its right, 0 otherwise (from its name)."""
    low = name.lower()
    for sign, word, letter in ((-1, "left", "l"), (1, "right", "r")):
        if low.startswith(word) or low.startswith((f"{letter}_", f"{letter}.", f"{letter}-")):
            return sign
        if len(name) > 1 and name[0].lower() == letter and name[1].isupper():
            return sign
        if low.endswith((f"_{letter}", f".{letter}", f"-{letter}")):
            return sign
    return 0


def dot_joints(motion: Motion) -> np.ndarray:
    """Joints marked with a dot: those carrying a chain of at least 8 % of the figure's size.

    This leaves out fingers, toes and eyes, whose dots would blot out the hands and head.
    """
    sk = motion.skeleton
    lengths = np.linalg.norm(sk.offsets_array, axis=1)
    reach = np.zeros(sk.n_joints)  # longest chain below each joint
    for p, off in sk.end_sites:
        reach[p] = max(reach[p], float(np.linalg.norm(off)))
    for j in range(sk.n_joints - 1, 0, -1):
        p = sk.parents[j]
        reach[p] = max(reach[p], reach[j] + lengths[j])
    return np.nonzero(reach >= 0.08 * sk.size)[0]


def bone_segments(motion: Motion, end_sites: bool) -> tuple[np.ndarray, list[str]]:
    """Parent/child point index pairs ``(B, 2)`` and a colour per bone."""
    sk = motion.skeleton
    pairs: list[tuple[int, int]] = []
    sides: list[int] = []
    for j, p in enumerate(sk.parents):
        if p >= 0:
            pairs.append((p, j))
            sides.append(_side(sk.names[j]) or _side(sk.names[p]))
    if end_sites:
        for e, (p, _) in enumerate(sk.end_sites):
            pairs.append((p, sk.n_joints + e))
            sides.append(_side(sk.names[p]))
    colours = [{-1: _LEFT_COLOUR, 1: _RIGHT_COLOUR, 0: _CENTRE_COLOUR}[s] for s in sides]
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2), colours


def trajectory_points(
    trajectories: str | int | Sequence[str | int] | None, motion: Motion, fn: str
) -> list[tuple[int, str]]:
    """Resolve joint names / point indices to ``(point index, label)`` pairs (deduplicated)."""
    if trajectories is None:
        return []
    sk = motion.skeleton
    n_points = sk.n_joints + len(sk.end_sites)
    items: list[object]
    if isinstance(trajectories, str) or is_int(trajectories):
        items = [trajectories]
    elif isinstance(trajectories, Sequence | np.ndarray):
        items = list(trajectories)
    else:
        raise ValueError(f"{fn}: trajectories must be joint names or indices, got {trajectories!r}")
    out: list[tuple[int, str]] = []
    for item in items:
        if isinstance(item, str):
            if item not in sk.names:
                raise ValueError(
                    f"{fn}: unknown joint {item!r} in trajectories; valid names: "
                    f"{', '.join(sk.names)}"
                )
            idx = sk.names.index(item)
        elif is_int(item):
            idx = int(item)
            if not 0 <= idx < n_points:
                raise ValueError(
                    f"{fn}: trajectory index {idx} is out of range; use 0..{sk.n_joints - 1} for "
                    f"joints or {sk.n_joints}..{n_points - 1} for end sites"
                    if n_points > sk.n_joints
                    else f"{fn}: trajectory index {idx} is out of range 0..{n_points - 1}"
                )
        else:
            raise ValueError(
                f"{fn}: trajectories must hold joint names or integer indices, got {item!r}"
            )
        if idx not in [i for i, _ in out]:
            label = sk.names[idx] if idx < sk.n_joints else f"{_point_name(motion, idx)[1:-1]}·end"
            out.append((idx, label))
    return out


def nice_step(span: float) -> float:
    """A 1-2-5 × 10^k grid spacing giving about six cells over ``span``."""
    raw = max(span, 1e-12) / 6.0
    base = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 5.0, 10.0):
        if raw <= m * base * 1.0001:
            return m * base
    return 10.0 * base  # pragma: no cover - the loop always returns


@dataclass(frozen=True)
class Box:
    """An axis-aligned cube in plot coordinates: centre and half side."""

    centre: tuple[float, float, float]
    half: float

    @property
    def lo(self) -> np.ndarray:
        return np.asarray(self.centre) - self.half

    @property
    def hi(self) -> np.ndarray:
        return np.asarray(self.centre) + self.half


def _with_nan_outside(path: np.ndarray, box: Box) -> np.ndarray:
    """Copy of a ``(K, 3)`` path with points outside the box replaced by NaN (a line break)."""
    out = path.copy()
    outside = ((path < box.lo - 1e-9) | (path > box.hi + 1e-9)).any(axis=1)
    out[outside] = np.nan
    return out


# ---------------------------------------------------------------------------------------------
# One 3-D panel: axes, ground, bones, joints, trajectories — updated in place per frame
# ---------------------------------------------------------------------------------------------
class Panel:
    def __init__(
        self,
        fig: Figure,
        rect: tuple[float, float, float, float],
        *,
        box: Box,
        ground: float,
        step: float,
        bones: np.ndarray,
        colours: list[str],
        joints: np.ndarray,
        trajectories: list[tuple[int, str]],
        elev: float,
        azim: float,
        linewidth: float,
    ) -> None:
        from mpl_toolkits.mplot3d.art3d import Line3D, Line3DCollection, Poly3DCollection
        from mpl_toolkits.mplot3d.axes3d import Axes3D

        ax = fig.add_axes(rect, projection="3d")
        assert isinstance(ax, Axes3D)
        self.ax: Axes3D = ax
        self.box = box
        lo, hi = box.lo, box.hi
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(lo[2], hi[2])
        # (matplotlib's stub types `zoom` as int; any positive float works)
        ax.set_box_aspect((1.0, 1.0, 1.0), zoom=1.15)  # pyright: ignore[reportArgumentType]
        ax.view_init(elev=elev, azim=azim)
        ax.set_axis_off()
        ax.computed_zorder = False  # ground below, then trajectories, bones, joints
        ax.patch.set_alpha(0.0)

        # Ground: a light square at the ground height and a grid on world multiples of `step`.
        x0, y0, x1, y1 = lo[0], lo[1], hi[0], hi[1]
        square = [[(x0, y0, ground), (x1, y0, ground), (x1, y1, ground), (x0, y1, ground)]]
        ax.add_collection3d(
            Poly3DCollection(square, facecolors=_GROUND_FACE, edgecolors="none", zorder=0)
        )
        segs = []
        for x in np.arange(math.ceil(x0 / step), math.floor(x1 / step) + 1) * step:
            segs.append([(x, y0, ground), (x, y1, ground)])
        for y in np.arange(math.ceil(y0 / step), math.floor(y1 / step) + 1) * step:
            segs.append([(x0, y, ground), (x1, y, ground)])
        ax.add_collection3d(Line3DCollection(segs, colors=_GROUND_GRID, linewidths=0.6, zorder=1))

        self.trajectories = trajectories
        self.traj_lines: list[Line3D] = []
        for k, (_, label) in enumerate(trajectories):
            (line,) = ax.plot(
                [],
                [],
                [],
                color=_TRAJECTORY_COLOURS[k % len(_TRAJECTORY_COLOURS)],
                linewidth=0.9 * linewidth,
                alpha=0.9,
                label=label,
                zorder=2,
            )
            assert isinstance(line, Line3D)
            self.traj_lines.append(line)
        self.bones = bones
        self.bone_lines = Line3DCollection(
            np.zeros((len(bones), 2, 3)),
            colors=colours,
            linewidths=linewidth,
            capstyle="round",
            zorder=3,
        )
        ax.add_collection3d(self.bone_lines)
        self.joints = joints
        (dots,) = ax.plot(
            [],
            [],
            [],
            linestyle="none",
            marker="o",
            markersize=1.1 * linewidth,
            color="#111111",
            zorder=4,
        )
        assert isinstance(dots, Line3D)
        self.dots = dots

    def show(self, frame: np.ndarray, paths: Sequence[np.ndarray], clip: bool) -> None:
        """Pose the figure: ``frame`` is ``(P, 3)``, ``paths`` one ``(K, 3)`` array a trajectory."""
        self.bone_lines.set_segments(list(frame[self.bones]))
        j = frame[self.joints]
        self.dots.set_data_3d(j[:, 0], j[:, 1], j[:, 2])
        for line, path in zip(self.traj_lines, paths, strict=True):
            if clip:
                path = _with_nan_outside(path, self.box)
            line.set_data_3d(path[:, 0], path[:, 1], path[:, 2])


def new_figure(size: tuple[float, float], dpi: float) -> tuple[Figure, FigureCanvasAgg]:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=dpi, facecolor="white")
    canvas = FigureCanvasAgg(fig)
    return fig, canvas


def ground_height(pos: np.ndarray) -> float:
    """Ground height: the lowest point reached by any joint or end site."""
    return float(pos[..., 2].min())


def is_int(x: object) -> TypeGuard[int | np.integer]:
    return isinstance(x, int | np.integer) and not isinstance(x, bool | np.bool_)
