"""Why Gaussian autoregressive synthesis is too jerky on the salsa clips (issue 16's synthesis
criterion), measured on the fixed split.

A full-covariance Gaussian AR(p) is fitted by least squares to the training clips' observation
vectors (60 Hz, the texture's feature map) and sampled from held-out start frames; the samples
are judged against the held-out clips (speed / acceleration / jerk W1 over the real-vs-real
floor). Rows:

* AR(p), p = 2, 3, 4, 6, Gaussian innovations with the fitted covariance: does the order help?
* AR(2) with a trimmed covariance (frames whose innovation is within 4 or 6 robust standard
  deviations on every channel): is it the heavy tails of the innovations?
* AR(2) driven by blocks of its own training innovations (1, 30, 120 frames; a residual
  bootstrap, not a model): is it their shape in time?

Also the tails: per channel, the innovation variance over its squared robust scale
(1.4826·MAD)², 1 for a Gaussian. Run: ``.venv/bin/python benchmarks/quality_innovations.py``;
writes ``benchmarks/results/innovations.md``.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_quality import HELD, TRAIN, load
from mtex_jax import metrics
from mtex_jax.motion import FeatureMap

OUT = Path(__file__).parent / "results" / "innovations.md"
FPS, N, N_SYN = 60.0, 1200, 8


def lagged(y: np.ndarray, p: int) -> np.ndarray:
    T = len(y)
    return np.concatenate([y[p - j - 1 : T - j - 1] for j in range(p)] + [np.ones((T - p, 1))], 1)


def fit(ys: list[np.ndarray], p: int) -> tuple[np.ndarray, list[np.ndarray]]:
    X = np.concatenate([lagged(y, p) for y in ys])
    Y = np.concatenate([y[p:] for y in ys])
    W = np.linalg.solve(X.T @ X + 1e-6 * np.eye(X.shape[1]), X.T @ Y)
    return W, [y[p:] - lagged(y, p) @ W for y in ys]


def run(W: np.ndarray, p: int, start: np.ndarray, e: np.ndarray) -> np.ndarray:
    Y = np.zeros((N, W.shape[1]))
    Y[:p] = start[:p]
    for t in range(p, N):
        Y[t] = np.concatenate([Y[t - i - 1] for i in range(p)] + [[1.0]]) @ W + e[t]
    if not np.isfinite(Y).all():
        raise FloatingPointError("sample diverged")
    return Y


def main() -> None:
    t0, load0 = time.perf_counter(), os.getloadavg()[0]
    train = [m.resample(FPS) for m in load(TRAIN)]
    held = [m.resample(FPS) for m in load(HELD)]
    fm = FeatureMap.fit(train)
    ty = [np.asarray(fm.encode(m)) for m in train]
    hy = [np.asarray(fm.encode(m)) for m in held]
    D = ty[0].shape[1]
    judge = metrics.MotionJudge(train, held, fps=FPS)
    rows: list[tuple[str, dict]] = []

    def judged(name: str, p: int, W: np.ndarray, noise) -> None:
        ms = []
        for j in range(N_SYN):
            rng = np.random.default_rng(j)
            Y = run(W, p, hy[j % len(hy)], noise(rng))
            ms.append(fm.decode(jnp.asarray(Y), *fm.start_of(held[j % len(held)])))
        rows.append((name, judge.judge(ms, copy=True)))
        print(name, {k: round(v, 3) for k, v in rows[-1][1].items() if "ratio" in k}, flush=True)

    tails = None
    for p in (2, 3, 4, 6):
        W, E = fit(ty, p)
        Ec = np.concatenate(E)
        L = np.linalg.cholesky(Ec.T @ Ec / len(Ec) + 1e-9 * np.eye(D))
        judged(f"AR({p}), Gaussian", p, W, lambda rng, L=L: rng.standard_normal((N, D)) @ L.T)
        if p == 2:
            W2, E2, Ec2 = W, E, Ec
            mad = 1.4826 * np.median(np.abs(Ec - np.median(Ec, 0)), 0)
            tails = np.sort(Ec.var(0) / mad**2)
    assert tails is not None
    z = np.abs(Ec2) / (1.4826 * np.median(np.abs(Ec2 - np.median(Ec2, 0)), 0))
    for thr in (6.0, 4.0):
        keep = (z < thr).all(1)
        S = np.cov(Ec2[keep].T, bias=True)
        L = np.linalg.cholesky(S + 1e-9 * np.eye(D))
        judged(
            f"AR(2), covariance of the {100 * keep.mean():.0f} % of frames within {thr:g} "
            "robust sd",
            2,
            W2,
            lambda rng, L=L: rng.standard_normal((N, D)) @ L.T,
        )
    for blk in (1, 30, 120):

        def boot(rng, blk=blk):
            out, n = [], 0
            while n < N:
                c = int(rng.integers(len(E2)))
                s = int(rng.integers(0, len(E2[c]) - blk))
                out.append(E2[c][s : s + blk])
                n += blk
            return np.concatenate(out)[:N]

        judged(f"AR(2), training innovations in blocks of {blk}", 2, W2, boot)

    lines = [
        "# Gaussian autoregressive synthesis and the innovations of real dance",
        "",
        f"`benchmarks/quality_innovations.py`, one run ({time.perf_counter() - t0:.0f} s, load "
        f"{load0:.1f} → {os.getloadavg()[0]:.1f}); fixed split, {FPS:g} Hz, D = {D}; "
        f"{N_SYN} samples of {N / FPS:g} s from held-out start frames per row, judged against "
        "the held-out clips (ratios: W1 over the real-vs-real floor; copy: share of frames "
        "continuing the previous step's training frame).",
        "",
        "| generator | speed | acc | jerk | skate med / p95 (m/s) | copy / longest (s) |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, r in rows:
        lines.append(
            f"| {name} | {r['speed_ratio']:.2f} | {r['acceleration_ratio']:.2f} "
            f"| {r['jerk_ratio']:.2f} | {r['skating_median']:.2f} / {r['skating_p95']:.2f} "
            f"| {r['copy_fraction']:.2f} / {r['copy_longest_s']:.1f} |"
        )
    lines += [
        "",
        "Tails of the AR(2) innovations, per channel: variance / (1.4826·MAD)² (1 for a "
        f"Gaussian): median {np.median(tails):.1f}, largest five "
        + ", ".join(f"{v:.1f}" for v in tails[::-1][:5])
        + ".",
    ]
    OUT.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
