"""Synthetic textons and data at the paper's scale, and the numpy semi-Markov Viterbi
baseline, for part (a) of ``bench_learn.py`` (also used by ``bench_forward.py``).
"""

from __future__ import annotations

import time
from typing import Any

import jax.numpy as jnp
import numpy as np

from mtex_jax.texture import fit_texton, stack_textons

# --------------------------------------------------------------------------------------------
# (a) synthetic textons and data at the paper's scale
# --------------------------------------------------------------------------------------------


def random_generators(rng: np.random.Generator, n: int, D: int, k: int) -> list[dict[str, Any]]:
    """``n`` random stable second-order LDS (oscillatory, spectral radius 0.9–0.98)."""
    gens = []
    for _ in range(n):
        C = np.linalg.qr(rng.standard_normal((D, k)))[0]
        A1 = rng.standard_normal((k, k)) / np.sqrt(k)
        A2 = 0.5 * rng.standard_normal((k, k)) / np.sqrt(k)
        F = np.block([[A1, A2], [np.eye(k), np.zeros((k, k))]])
        s = rng.uniform(0.9, 0.98) / np.max(np.abs(np.linalg.eigvals(F)))
        A1, A2 = A1 * s, A2 * s * s  # scales every eigenvalue of F by s
        B = np.tril(0.05 * rng.standard_normal((k, k)), -1) + np.diag(rng.uniform(0.1, 0.3, k))
        gens.append(
            dict(
                mu=0.5 * rng.standard_normal(D),
                C=C,
                A1=A1,
                A2=A2,
                d=0.02 * rng.standard_normal(k),
                B=B,
                sigma=rng.uniform(0.05, 0.15),
            )
        )
    return gens


def sample_lds(rng: np.random.Generator, g: dict[str, Any], length: int) -> np.ndarray:
    k = g["A1"].shape[0]
    X = np.empty((length, k))
    X[0] = 0.5 * rng.standard_normal(k)
    X[1] = 0.5 * rng.standard_normal(k)
    V = rng.standard_normal((length, k)) @ g["B"].T
    for t in range(2, length):
        X[t] = g["A1"] @ X[t - 1] + g["A2"] @ X[t - 2] + g["d"] + V[t]
    W = g["sigma"] * rng.standard_normal((length, g["C"].shape[0]))
    return g["mu"] + X @ g["C"].T + W


def make_problem(
    rng: np.random.Generator, T: int, n: int, D: int, k: int, tmin: int, tmax: int
) -> dict[str, Any]:
    gens = random_generators(rng, n, D, k)
    t0 = time.perf_counter()
    fitted = [
        fit_texton(jnp.asarray(sample_lds(rng, g, tmax)), state_dim=k, sigma2_floor=1e-6)
        for g in gens
    ]
    textons = stack_textons(fitted)
    fit_s = time.perf_counter() - t0
    M = rng.dirichlet(np.full(n, 0.5), size=n)
    M = 0.99 * M + 0.01 / n
    pi = np.full(n, 1.0 / n)
    Ys, labels, lab = [], [], int(rng.integers(n))
    total = 0
    while total < T:
        length = int(rng.integers(tmin, tmax + 1))
        Ys.append(sample_lds(rng, gens[lab], length))
        labels.append(np.full(length, lab))
        total += length
        lab = int(rng.choice(n, p=M[lab]))
    Y = np.concatenate(Ys)[:T]
    truth = np.concatenate(labels)[:T]
    return dict(
        textons=textons,
        log_M=np.log(M),
        log_pi=np.log(pi),
        Y=Y,
        truth=truth,
        fit_seconds=fit_s,
    )


def numpy_viterbi(
    sc: dict[str, np.ndarray],
    log_M: np.ndarray,
    log_pi: np.ndarray,
    tmin: int,
    tmax: int,
) -> tuple[float, list[tuple[int, int, int]]]:
    """Straightforward semi-Markov Viterbi with explicit back-pointers (design §4).

    ``V(e, i) = max_b score_i(b, e) + (b = 0 ? log π_i : H(b − 1, i))`` and
    ``H(e, i) = max_l V(e, l) + log M[l, i]``; segment scores from the prefix sums of a
    :class:`SegmentScorer` (the same formula as ``SegmentScorer.score``). Loops over end frames,
    vectorised over textons and candidate lengths. Returns the score and
    ``[(start, length, label), ...]``.
    """
    init, cd, co = sc["init"], sc["cum_dyn"], sc["cum_obs"]
    doff, ooff = sc["dyn_offset"], sc["obs_offset"]
    N, T = init.shape
    V = np.full((T, N), -np.inf)
    H = np.full((T, N), -np.inf)
    bp_len = np.zeros((T, N), dtype=np.int64)
    bp_prev = np.zeros((T, N), dtype=np.int64)
    lengths_desc = np.arange(tmax, tmin - 1, -1)  # ascending start frame
    rows = np.arange(N)
    for e in range(tmin - 1, T):
        L = lengths_desc[lengths_desc <= e + 1]
        b = e - L + 1
        dyn = (
            cd[:, e + 1, None] - cd[:, np.minimum(b + 2, T)] + (e - b - 1)[None, :] * doff[:, None]
        )
        obs = co[:, e + 1, None] - co[:, b] + (e - b + 1)[None, :] * ooff[:, None]
        prev = np.where(b[None, :] == 0, log_pi[:, None], H[np.maximum(b - 1, 0)].T)
        tot = init[:, b] + dyn + obs + prev  # (N, candidates)
        j = np.argmax(tot, axis=1)
        V[e] = tot[rows, j]
        bp_len[e] = L[j]
        cand = V[e][:, None] + log_M  # (from, to)
        pl = np.argmax(cand, axis=0)
        H[e] = cand[pl, rows]
        bp_prev[e] = pl
    i = int(np.argmax(V[T - 1]))
    score = float(V[T - 1, i])
    segs = []
    e = T - 1
    while True:
        length = int(bp_len[e, i])
        b = e - length + 1
        segs.append((b, length, i))
        if b <= 0:
            break
        i, e = int(bp_prev[b - 1, i]), b - 1
    return score, segs[::-1]
