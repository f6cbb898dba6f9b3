"""Quality figures: the distributions of joint speed, acceleration and jerk of real and
generated motion, side by side (the quantities behind :func:`mtex_jax.metrics.realism`)."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from ..core import atomic_write
from ..metrics import speed_samples
from ..motion import Motion

__all__ = ["plot_speed_distributions"]

_LABELS = ("speed |v| (m/s)", "acceleration |a| (m/s²)", "jerk |j| (m/s³)")


def plot_speed_distributions(
    sets: dict[str, Sequence[Motion]],
    path: str | os.PathLike[str],
    *,
    fps: float,
    title: str | None = None,
) -> None:
    """Histograms (log-spaced bins, pooled over every joint and frame) of ``|v|``, ``|a|`` and
    ``|j|`` of several named sets of clips, one panel per quantity, written to a PNG.

    Args:
        sets: name → clips, e.g. ``{"real (held out)": test, "synthesised": synth}``.
        path: output ``.png``.
        fps: the common frame rate the derivatives are taken at.
        title: figure title.
    """
    if not sets:
        raise ValueError("plot_speed_distributions: give at least one set of clips")
    if os.path.splitext(os.fspath(path))[1].lower() != ".png":
        raise ValueError(f"plot_speed_distributions: {os.fspath(path)!r} must end in .png")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    samples = {name: speed_samples(list(clips), fps) for name, clips in sets.items()}
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for q, ax in enumerate(axes):
        pooled = {n: np.concatenate([np.ravel(x) for x in s[q]]) for n, s in samples.items()}
        pos = np.concatenate([v[v > 0] for v in pooled.values()])
        lo, hi = np.quantile(pos, [0.001, 0.999]) if pos.size else (1e-3, 1.0)
        bins = np.geomspace(max(lo, 1e-6), max(hi, 2 * max(lo, 1e-6)), 60)
        for name, v in pooled.items():
            ax.hist(v, bins=bins, density=True, histtype="step", lw=1.6, label=name)
        ax.set_xscale("log")
        ax.set_xlabel(_LABELS[q])
        ax.set_yticks([])
    axes[0].legend(fontsize=8, loc="upper left")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    try:
        with atomic_write(path, "wb") as fh:
            fig.savefig(fh, format="png", dpi=90)
    finally:
        plt.close(fig)
