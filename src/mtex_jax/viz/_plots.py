"""Static figures: texton timelines (MT Fig. 2)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..core import atomic_write

__all__ = ["plot_timeline"]


def plot_timeline(
    rows: Sequence[Sequence[Sequence[int]]] | Sequence[Sequence[int]],
    path: str | os.PathLike[str],
    *,
    fps: float,
    n_textons: int | None = None,
    names: Sequence[str] | None = None,
    title: str | None = None,
) -> Path:
    """Draw texton labels over time as coloured bars, one row per sequence (MT Fig. 2).

    Args:
        rows: per sequence, its segments ``(start, length, label)``; or one sequence's list.
        path: output image (PNG).
        fps: frames per second (the x axis is in seconds).
        n_textons: number of textons (for the colour map); default the largest label + 1.
        names: optional sequence names for the y axis.
        title: optional title.

    Returns:
        the path written.
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError('plotting needs matplotlib: pip install "mtex_jax[plot]"') from e
    seqs: list[Any] = list(rows)
    if seqs and len(seqs[0]) and np.ndim(seqs[0][0]) == 0:
        seqs = [seqs]  # a single sequence's list of (start, length, label)
    if not seqs:
        raise ValueError("plot_timeline: no sequences")
    if not fps > 0:
        raise ValueError(f"plot_timeline: fps must be positive, got {fps!r}")
    p = Path(path)
    if not p.parent.exists():
        raise ValueError(f"plot_timeline: folder {p.parent} does not exist")
    labels = [int(r[2]) for seq in seqs for r in seq]
    n_t = n_textons if n_textons is not None else (max(labels) + 1 if labels else 1)
    import matplotlib

    cmap = matplotlib.colormaps["tab20"]
    height = 0.6 + 0.35 * len(seqs)
    fig = Figure(figsize=(10, height), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    t_end = 0.0
    for y, seq in enumerate(seqs):
        for start, length, lab in seq:
            b, L = start / fps, length / fps
            ax.barh(y, L, left=b, height=0.8, color=cmap(int(lab) % 20), edgecolor="white", lw=0.5)
            if L > 0.02 * max(t_end, 1.0) and n_t <= 400:
                ax.text(b + L / 2, y, str(int(lab)), ha="center", va="center", fontsize=6)
            t_end = max(t_end, b + L)
    ax.set_yticks(range(len(seqs)))
    ax.set_yticklabels(list(names) if names is not None else [str(i) for i in range(len(seqs))])
    ax.invert_yaxis()
    ax.set_xlim(0, t_end)
    ax.set_xlabel("time (s)")
    ax.set_title(title or f"texton labels over time ({n_t} textons)")
    fig.tight_layout()
    with atomic_write(p, "wb") as fh:
        fig.savefig(fh, format=p.suffix.lstrip(".").lower() or "png")
    return p
