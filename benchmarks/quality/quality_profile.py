"""Where synthesis differs from real motion: quantiles of joint |a| and |j| (bench_quality).

The realism ratios of ``bench_quality`` say *how far* a generated set is from the held-out
clips; this profile says *where*. For each moving joint (of the training clips) the quantiles
``p5, p25, p50, p75, p95, p99`` of ``|a|`` and ``|j|`` are divided by the held-out clips'
median of that joint, then averaged over joints: a real set reads about 1.0 at p50, and a
generated set with too few calm frames reads high at p5, one without bursts low at p99.

The same table holds the W₁ distances to the *training* clips (the data the model was learned
from) beside those to the held-out clips, so that a gap that is not one of generalisation
shows as such.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

import mtex_jax as mj
from mtex_jax import metrics

PCTS = (5, 25, 50, 75, 95, 99)
SEEDS = (1, 2, 3, 4, 5)  # the other seeds of seed_spread (the headline row has its own)


def profile(
    sets: dict[str, Sequence[Any]], train: Sequence[Any], held: Sequence[Any], fps: float
) -> dict[str, dict[str, Any]]:
    """Quantile profile and W₁ to the training and held-out clips of each named set.

    Args:
        sets: name → motions (one skeleton, the training clips').
        train: the training clips.
        held: the held-out clips.
        fps: common frame rate.

    Returns:
        name → ``{"acc": [6 quantile ratios], "jerk": [...], "w1_train": (acc, jerk),
        "w1_held": (acc, jerk)}``; the real sets (training, held out) come first.
    """
    mv = metrics.moving_joints(train)
    _, a_h, j_h = metrics.speed_samples(held, fps)
    med = (np.median(a_h[:, mv], 0), np.median(j_h[:, mv], 0))
    out: dict[str, dict[str, Any]] = {}
    names = _names(train, mv)
    for name, ms in {"real: training clips": train, "real: held-out clips": held, **sets}.items():
        _, a, j = (a_h, a_h, j_h) if ms is held else metrics.speed_samples(ms, fps)
        row: dict[str, Any] = {}
        for q, x, m in (("acc", a[:, mv], med[0]), ("jerk", j[:, mv], med[1])):
            row[q] = [float(np.mean(np.percentile(x, p, axis=0) / m)) for p in PCTS]
        for tag, ref in (("w1_train", train), ("w1_held", held)):
            if ms is ref:  # a set's distance to itself is 0 by definition
                row[tag] = (0.0, 0.0)
                continue
            r = metrics.realism(ms, ref, fps=fps, joints=names)
            row[tag] = (r.acceleration, r.jerk)
        out[name] = row
    return out


def _names(train: Sequence[Any], mv: np.ndarray) -> list[str]:
    sk = train[0].skeleton
    return [sk.names[i] for i in mv]


def lines(prof: dict[str, dict[str, Any]]) -> list[str]:
    """The markdown section of :func:`profile`."""
    pc = " / ".join(f"p{p}" for p in PCTS)
    L = [
        "",
        "## Where the texture's motion differs (quantiles of joint acceleration and jerk)",
        "",
        "Quantiles of each moving joint's acceleration and jerk magnitudes, divided by the",
        "held-out clips' median of that joint and averaged over joints; then the W1",
        "distances (m/s², m/s³) to the training clips and to the held-out clips. The held-out",
        "row's W1 to the training clips is the real-vs-real floor of the table above.",
        "",
        f"| set | acc {pc} | jerk {pc} | W1 acc train / held | W1 jerk train / held |",
        "| --- | --- | --- | ---: | ---: |",
    ]
    for name, r in prof.items():
        qa = " / ".join(f"{x:.2f}" for x in r["acc"])
        qj = " / ".join(f"{x:.2f}" for x in r["jerk"])
        L.append(
            f"| {name} | {qa} | {qj} | {r['w1_train'][0]:.2f} / {r['w1_held'][0]:.2f} "
            f"| {r['w1_train'][1]:.0f} / {r['w1_held'][1]:.0f} |"
        )
    return L


def seed_spread(
    judge: Any, texture: Any, n_frames: int, n_syn: int, seeds: Sequence[int]
) -> dict[str, Any]:
    """The sampling error of the headline row: the default constrained synthesis (``n_syn``
    clips of ``n_frames``) judged again with other keys, ``jax.random.key(seed)`` split
    ``n_syn`` ways for each seed.

    Returns:
        ``{"seeds": [...], "ratios": [[speed, acc, jerk] per seed], "mean": [...],
        "sd": [...]}`` (sample standard deviation over seeds).
    """
    ratios = []
    for seed in seeds:
        keys = jax.random.split(jax.random.key(seed), n_syn)
        r = judge.judge([mj.synthesize(k, texture, n_frames=n_frames).motion for k in keys])
        ratios.append([r["speed_ratio"], r["acceleration_ratio"], r["jerk_ratio"]])
    arr = np.asarray(ratios, dtype=float)
    return dict(
        seeds=list(seeds),
        ratios=arr.tolist(),
        mean=arr.mean(0).tolist(),
        sd=arr.std(0, ddof=1).tolist() if len(seeds) > 1 else [0.0, 0.0, 0.0],
    )


def spread_lines(sp: dict[str, Any], headline_seed: int, row: str) -> list[str]:
    """One paragraph on :func:`seed_spread`."""
    m, s = sp["mean"], sp["sd"]
    per = "; ".join(
        f"{seed}: {r[1]:.2f} / {r[2]:.2f}"
        for seed, r in zip(sp["seeds"], sp["ratios"], strict=True)
    )
    return [
        "",
        f"Sampling error of {row} (seed {headline_seed}): the same synthesis "
        f"with {len(sp['seeds'])} other seeds gives acceleration / jerk ratios {per}; over "
        f"those seeds speed {m[0]:.2f} ± {s[0]:.2f}, acceleration {m[1]:.2f} ± {s[1]:.2f}, "
        f"jerk {m[2]:.2f} ± {s[2]:.2f} (mean ± sample sd).",
    ]
