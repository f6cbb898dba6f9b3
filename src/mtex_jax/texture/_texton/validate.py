"""Value checks of a loaded motion texture (the door of :func:`load_texture`), and the finite
output check of noise-driven synthesis."""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from jax.core import Tracer

from .texton import Texton, spectral_radius

__all__ = ["TEXTURE_MEMBERS", "check_finite_output", "check_texture_arrays"]

#: The members a motion-texture file may hold besides the required ones (fnmatch patterns);
#: any other member is rejected before it is decompressed.
TEXTURE_MEMBERS = (
    "texton.*",
    "feature_map.offset",
    "feature_map.scale",
    "log_durations",
    "innovations.acf",
    "innovations.persistence",
    "residuals.rows",
    "residuals.starts",
    "residuals.lengths",
    "residuals.labels",
)

_STOCHASTIC_TOL = 1e-6


def check_texture_arrays(path: str | os.PathLike[str], arrays: dict[str, np.ndarray]) -> None:
    """Raise ``ValueError`` naming ``path`` unless the arrays of a texture file hold sane values.

    Every floating array finite; the transition matrix ``M`` square with non-negative rows
    summing to 1 and ``pi`` a non-negative vector summing to 1; texton noise variances
    ``sigma2`` positive; key-pose labels within ``[0, N_t)``; segment lengths positive.
    """

    def fail(msg: str) -> ValueError:
        return ValueError(f"{path}: invalid motion texture file: {msg}")

    for k, a in arrays.items():
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise fail(f"array {k!r} contains NaN or inf")
    m = arrays.get("M")
    pi = arrays.get("pi")
    if m is None or pi is None:
        return  # reported as missing arrays by the caller
    if m.ndim != 2 or m.shape[0] != m.shape[1] or pi.shape != (m.shape[0],):
        raise fail(f"M has shape {m.shape} and pi {pi.shape}; expected (n, n) and (n,)")
    for name, a, rows in (("M", m, m), ("pi", pi, pi[None])):
        if (a < 0).any():
            raise fail(f"{name} has negative entries (minimum {float(a.min()):.3g})")
        err = np.abs(rows.sum(axis=-1) - 1.0)
        if a.size and err.max() > _STOCHASTIC_TOL:
            i = int(np.argmax(err))
            what = f"row {i} of M sums" if name == "M" else "pi sums"
            raise fail(f"{what} to {float(rows[i].sum()):.6g}, not 1 (not stochastic)")
    scale = arrays.get("feature_map.scale")
    if scale is not None and (scale <= 0).any():
        raise fail("feature_map.scale must be positive")
    s2 = arrays.get("texton.sigma2")
    if s2 is not None and (s2 <= 0).any():
        raise fail("texton.sigma2 (observation noise variance) must be positive")
    labels = arrays.get("key_pose_labels")
    if labels is not None and labels.size and (labels.min() < 0 or labels.max() >= m.shape[0]):
        raise fail(f"key_pose_labels outside [0, {m.shape[0]})")
    lengths = arrays.get("segment_lengths")
    if lengths is not None and lengths.size and lengths.min() < 1:
        raise fail("segment_lengths must be positive")


def check_finite_output(out: Any, texton: Texton, where: str) -> None:
    """Raise ``ValueError`` if a concrete synthesis result holds NaN or inf (finite input).

    Noise-driven synthesis of a texton whose dynamics have spectral radius ``ρ > 1`` grows
    like ``ρ^t`` and overflows after some hundred frames; the error names ``ρ`` and the cure.
    Traced results (under ``jit``/``vmap``) are not checked.
    """
    if isinstance(out, Tracer) or np.isfinite(np.asarray(out)).all():
        return
    rho = np.asarray(spectral_radius(texton))
    rho_s = ", ".join(f"{float(r):.3g}" for r in np.atleast_1d(rho)[:5])
    raise ValueError(
        f"{where}: the result overflows (NaN/inf): the texton's dynamics are unstable "
        f"(spectral radius {rho_s} > 1) and grow without bound over {np.shape(out)[-2]} frames; "
        "hold the end (end=...), synthesise fewer frames, or learn with "
        "LearnConfig(rho_max=0.999) (the default)"
    )
