"""How much of the synthesis gap is the innovations' and how much the dynamics' (bench_quality).

Each training clip is run again through the texture's own dynamics along its own training
segmentation, noise-driven from its first two frames,

    x_t = A1 x_{t−1} + A2 x_{t−2} + d + B v_t,   y_t = μ + C x_t   (the texton of frame t),

with the state carried across segment boundaries. Only the innovations ``v`` differ between
the rows:

* **aligned**: the clip's own whitened residuals ``v_t = B⁻¹(x_t − A1 x_{t−1} − A2 x_{t−2} −
  d)``. With ``k = D`` this gives the clip back exactly: the row checks the replay itself.
* **shuffled**: each segment takes the residuals of another training segment of the same
  texton (a random one, its frames in their order, repeated if it is shorter). These are
  real innovations with every property of real ones (law, autocorrelation, calm stretches,
  bursts, cross-channel structure); only their alignment to the state is lost.
* **fitted process**: draws from the texture's :class:`~mtex_jax.texture.InnovationProcess`
  (what synthesis uses).
* **independent**: independent Student-t (or Gaussian) draws, re-derived in numpy.

The W₁ distances of ``|v|, |a|, |j|`` to the training clips themselves (in-sample: nothing is
held out, so no generalisation gap enters) are reported beside the real-vs-real floor. If the
shuffled row is no closer than the fitted process, no model of the innovations alone can
close the gap: it lies in how the linear dynamics and the innovations fit together.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

from mtex_jax import metrics
from mtex_jax.texture import draw_innovations

_FIELDS = ("mu", "C", "A1", "A2", "d", "B")


def _labels(segments: np.ndarray, clip: int, n: int) -> np.ndarray:
    lab = np.full(n, -1, np.int64)
    for s, a, m, i in segments:
        if s == clip:
            lab[a : a + m] = i
    if (lab < 0).any():
        raise ValueError(f"the segmentation does not cover clip {clip}")
    return lab


def _residuals(t: dict[str, np.ndarray], y: np.ndarray, lab: np.ndarray) -> np.ndarray:
    """``(n, k)`` whitened residuals of every frame under its texton (rows 0, 1 zero).

    Deliberately not :func:`mtex_jax.texture.segment_innovations`: the replay needs the
    residuals of a whole clip, the two frames after each segment boundary included (there
    the texton's recursion reaches back into the previous segment), which the package does
    not compute; it is also an independent numpy re-derivation of the same formula."""
    v = np.zeros((len(y), t["A1"].shape[-1]))
    for i in np.unique(lab[2:]):
        j = np.flatnonzero(lab == i)
        j = j[j >= 2]
        x = [(y[j - s] - t["mu"][i]) @ t["C"][i] for s in (0, 1, 2)]
        e = x[0] - x[1] @ t["A1"][i].T - x[2] @ t["A2"][i].T - t["d"][i]
        v[j] = np.linalg.solve(t["B"][i], e.T).T
    return v


def _run(t: dict[str, np.ndarray], y01: np.ndarray, lab: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Noise-driven recursion along ``lab`` from the frames ``y01``; observations ``(n, D)``."""
    n = len(lab)
    out = np.zeros((n, y01.shape[1]))
    out[:2] = y01
    for j in range(2, n):
        i = lab[j]
        x1 = (out[j - 1] - t["mu"][i]) @ t["C"][i]
        x0 = (out[j - 2] - t["mu"][i]) @ t["C"][i]
        x = t["A1"][i] @ x1 + t["A2"][i] @ x0 + t["d"][i] + t["B"][i] @ v[j]
        out[j] = t["mu"][i] + t["C"][i] @ x
    return out


def _shuffled(
    rng: np.random.Generator, segments: np.ndarray, res: list[np.ndarray], clip: int, n: int
) -> np.ndarray:
    v = np.zeros((n, res[0].shape[1]))
    for s, a, m, i in segments:
        if s != clip:
            continue
        donors = [(s2, a2, m2) for s2, a2, m2, i2 in segments if i2 == i and (s2, a2) != (s, a)]
        if not donors:
            donors = [(s, a, m)]
        s2, a2, m2 = donors[rng.integers(len(donors))]
        block = res[s2][max(a2, 2) : a2 + m2]
        v[a : a + m] = np.resize(block, (m, block.shape[1]))
    return v


def replay(
    texture: Any, train: Sequence[Any], fps: float, seed: int, floor: Any
) -> dict[str, dict[str, float]]:
    """The four replays of the training clips (module docstring); W₁ and ratios to the floor.

    Args:
        texture: the learned :class:`~mtex_jax.MotionTexture` (with a feature map).
        train: its training clips (the motions it was learned from, in order).
        fps: their frame rate.
        seed: seeds the shuffling and the draws.
        floor: the real-vs-real :class:`~mtex_jax.metrics.RealismResult` (held out vs train).

    Returns:
        row name → ``{"speed", "acceleration", "jerk"}`` W₁ to the training clips and
        ``"*_ratio"`` over ``floor``.
    """
    fm = texture.feature_map
    t = {f: np.asarray(getattr(texture.textons, f), dtype=np.float64) for f in _FIELDS}
    segs = np.asarray(texture.segments, dtype=np.int64)
    ys = [np.asarray(fm.encode(m), dtype=np.float64) for m in train]
    labs = [_labels(segs, c, len(y)) for c, y in enumerate(ys)]
    res = [_residuals(t, y, lab) for y, lab in zip(ys, labs, strict=True)]
    rng = np.random.default_rng(seed)
    keys = jax.random.split(jax.random.key(seed), len(ys))
    k = t["A1"].shape[-1]
    dof = texture.textons.dof
    rows: dict[str, list[np.ndarray]] = {k_: [] for k_ in _ROWS}
    for c, (y, lab) in enumerate(zip(ys, labs, strict=True)):
        n = len(y)
        if texture.innovations is None:
            fitted = None
        else:
            draw = draw_innovations(keys[c], texture.innovations, (1, n, k), np.float64, dof)
            fitted = np.asarray(draw)[0]
        z = rng.standard_normal((n, k))
        g = 1.0 if dof is None else rng.gamma(dof / 2, 2 / dof, (n, 1))
        vs = {
            _ROWS[0]: res[c],
            _ROWS[1]: _shuffled(rng, segs, res, c, n),
            _ROWS[2]: fitted,
            _ROWS[3]: z / np.sqrt(g),
        }
        for name, v in vs.items():
            if v is not None:
                rows[name].append(fm.decode(_run(t, y[:2], lab, v)))
    out = {}
    for name, ms in rows.items():
        if ms:
            r = metrics.realism(ms, train, fps=fps, floor=floor)
            out[name] = dict(
                speed=r.speed,
                acceleration=r.acceleration,
                jerk=r.jerk,
                speed_ratio=r.speed_ratio,
                acceleration_ratio=r.acceleration_ratio,
                jerk_ratio=r.jerk_ratio,
            )
    return out


_ROWS = (
    "aligned: the clips' own residuals",
    "shuffled: another segment's real residuals, same texton",
    "fitted innovation process (synthesis)",
    "independent innovations",
)


def lines(rows: dict[str, dict[str, float]]) -> list[str]:
    """Markdown section of :func:`replay`'s rows."""
    L = [
        "",
        "## Innovations or dynamics? (training clips replayed through the texture)",
        "",
        "Each training clip is run again through the texture's dynamics along its own",
        "training segmentation, noise-driven from its first two frames; the rows differ",
        "only in the innovations (`benchmarks/quality/quality_replay.py`). W1 to the",
        "training clips themselves (in-sample) and the ratio over the real-vs-real floor:",
        "",
        "| innovations | W1 speed | W1 acc | W1 jerk | speed / acc / jerk ratio |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for name, r in rows.items():
        L.append(
            f"| {name} | {r['speed']:.3f} | {r['acceleration']:.2f} | {r['jerk']:.0f} "
            f"| {r['speed_ratio']:.2f} / {r['acceleration_ratio']:.2f} / "
            f"{r['jerk_ratio']:.2f} |"
        )
    return L
