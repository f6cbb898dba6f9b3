"""A short human-readable description of a motion texture (the CLI's ``learn`` and ``demo``)."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["texture_summary"]


def texture_summary(tex: Any) -> str:
    """A short human-readable description (used by the CLI)."""
    st = tex.length_stats()
    hist = np.asarray(tex.history)
    lines = [
        f"textons: {tex.n_textons}   segments: {len(np.asarray(tex.segments))}   "
        f"state dim: {tex.config.state_dim}   D: {tex.obs_dim}   threshold: {tex.threshold:.4g}",
        f"observation model: {tex.textons.observation.name}   innovations: "
        + ("Gaussian" if tex.textons.dof is None else f"Student-t, {tex.textons.dof:g} dof"),
        "synthesis innovations: "
        + (
            f"blocks of the {np.shape(tex.residuals.rows)[0]} training residuals"
            if tex.residuals is not None
            else "independent"
            if tex.innovations is None
            else "autocorrelation "
            + ", ".join(f"{r:.2f}" for r in np.asarray(tex.innovations.acf))
            + f"; scale persistence {float(tex.innovations.persistence):.3f}"
        ),
        "training contacts: "
        + (
            "none (learned from observation arrays)"
            if tex.contacts is None
            else f"feet {', '.join(tex.contacts.foot_names)}; floor {tex.contacts.floor:.3f}"
        ),
        f"segment lengths (frames): min {int(st[:, 3][st[:, 0] > 0].min())}  "
        f"mean {np.asarray(tex.segment_lengths).mean():.1f}  max {int(st[:, 4].max())}  "
        f"(tmin {tex.config.tmin}, tmax {tex.config.tmax})",
        "objective per EM iteration (after M-step / after E-step):",
    ]
    lines += [f"  {i:2d}: {a:14.2f} / {b:14.2f}" for i, (a, b) in enumerate(hist)]
    return "\n".join(lines)
