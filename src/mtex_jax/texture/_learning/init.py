"""Greedy initialisation of textons (MT §4.2): grow textons from windows the current bank
predicts worst."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._config import LearnConfig
from .._texton.fit import fit_texton
from .._texton.texton import Texton

# ---------------------------------------------------------------------------------------------
# Segment lists: numpy arrays (seq, start, length, label), one row per segment, in time order
# ---------------------------------------------------------------------------------------------
Segs = np.ndarray  # (n, 4) int64


def feasible(n: int, tmin: int, tmax: int) -> bool:
    """Whether ``n`` frames split into pieces of lengths in ``[tmin, tmax]`` (0 is fine)."""
    if n == 0:
        return True
    k = -(-n // tmax)  # fewest pieces
    return k * tmin <= n


# ---------------------------------------------------------------------------------------------
# Greedy initialisation
# ---------------------------------------------------------------------------------------------
def _err_leaves(mu: np.ndarray, C: np.ndarray, A1: np.ndarray, A2: np.ndarray, d: np.ndarray):
    """One texton's arrays for :func:`_bank_errors` (numpy, host): ``μ (D,)``,
    ``Cm = [C; −μᵀC] (D+1, k)``, ``W = [C A1ᵀ; C A2ᵀ; dᵀ − μᵀC(A1 + A2)ᵀ] (2D+1, k)`` and
    ``‖μ‖²``, so that ``x_t = [y_t, 1] Cm`` and ``p_t = [y_{t−1}, y_{t−2}, 1] W``."""
    muC = mu @ C
    Cm = np.concatenate([C, -muC[None]], axis=0)
    W = np.concatenate([C @ A1.T, C @ A2.T, (d - muC @ A1.T - muC @ A2.T)[None]], axis=0)
    return mu, Cm, W, np.asarray(mu @ mu)


@jax.jit
def _bank_errors(leaves: tuple[Array, ...], Y: Array) -> Array:
    """Per-frame one-step prediction errors ``‖y_t − μ − C(A1 x_{t−1} + A2 x_{t−2} + d)‖² / D``
    of a stack of textons given by their :func:`_err_leaves` (leading axis ``n``) on the
    frames ``Y (L, D)``, ``(n, L)`` (frames 0 and 1 get 0).

    ``C`` has orthonormal columns (an eigenbasis, as :func:`fit_texton` makes it), so with
    ``x_t = Cᵀ(y_t − μ)`` and the prediction ``p_t = A1 x_{t−1} + A2 x_{t−2} + d``:
    ``‖y_t − μ − C p_t‖² = ‖y_t − μ‖² − 2 x_t·p_t + ‖p_t‖²``, and ``x`` and ``p`` of every
    texton come from two GEMMs of the frames with the stacked ``Cm`` and ``W``, instead of
    small products per texton. (A plain ``jax.jit`` of arrays: its dispatch costs far less
    than a filtered call on a Module, over the hundreds of calls of one greedy pass.)
    """
    mu, Cm, W, mm = leaves
    n, D1, k = Cm.shape
    D, L = D1 - 1, Y.shape[0]
    one = jnp.ones((L, 1), Y.dtype)
    X = jnp.concatenate([Y, one], axis=1) @ jnp.moveaxis(Cm, 0, 1).reshape(D1, n * k)
    lag = jnp.concatenate([Y[1:-1], Y[:-2], one[2:]], axis=1)
    P = lag @ jnp.moveaxis(W, 0, 1).reshape(2 * D + 1, n * k)
    X, P = X[2:].reshape(L - 2, n, k), P.reshape(L - 2, n, k)
    yy = jnp.sum(Y[2:] ** 2, axis=1)[:, None] - 2.0 * Y[2:] @ mu.T + mm
    e = jnp.maximum(yy - 2.0 * jnp.sum(X * P, axis=-1) + jnp.sum(P * P, axis=-1), 0.0) / D
    return jnp.concatenate([jnp.zeros((n, 2), Y.dtype), e.T], axis=1)


# Smallest capacity of the bank: each capacity compiles _bank_errors once (about 0.1 s), and
# 32 textons cost little more to score than 1.
_BANK_MIN_CAP = 32


class _Bank:
    """Textons found so far: the fields that predict, stacked on the host with a doubling
    capacity (few recompilations; adding a texton writes one slot instead of restacking)."""

    def __init__(self) -> None:
        self.items: list[Texton] = []
        self._host: list[np.ndarray] = []
        self._stack: tuple[Array, ...] | None = None

    def add(self, t: Texton) -> int:
        n = len(self.items)
        leaves = _err_leaves(*(np.asarray(getattr(t, f)) for f in ("mu", "C", "A1", "A2", "d")))
        if not self._host or n == self._host[0].shape[0]:  # grow: double the capacity
            cap = max(_BANK_MIN_CAP, 2 * n)
            grown = [np.repeat(a[None], cap, axis=0) for a in leaves]
            for g, h in zip(grown, self._host, strict=False):  # (no _host yet: n = 0)
                g[:n] = h
            self._host = grown
        for h, a in zip(self._host, leaves, strict=True):
            h[n:] = a  # this slot, and the padding slots after it (copies of the last)
        self.items.append(t)
        self._stack = None
        return n

    def one(self, i: int) -> tuple[Array, ...]:
        """Texton ``i``'s :func:`_err_leaves`, each ``(1, …)``, on the device."""
        return jax.device_put(tuple(h[i : i + 1] for h in self._host))

    def stacked(self) -> tuple[Array, ...]:
        """The :func:`_err_leaves` of the bank, ``(capacity, …)`` each, on the device."""
        stack = self._stack
        if stack is None:
            stack = self._stack = jax.device_put(tuple(self._host))
        return stack


# Greedy init fits a texton on one window of tmin frames; more state dimensions than the
# paper's 12–15 would only fit that window's noise. EM refits every texton at the full k.
_INIT_STATE_DIM_MAX = 15


def greedy_init(
    ys: Sequence[np.ndarray], config: LearnConfig, threshold: float, *, smooth: int = 3
) -> tuple[Segs, int]:
    """Greedy segmentation of MT §4.

    For each sequence, from frame ``b``: test every texton found so far on the next ``tmin``
    frames and take the one with the lowest mean prediction error if that is at most
    ``threshold``; otherwise fit a new texton on those frames. Then extend the segment frame by
    frame while that texton's prediction error (averaged over the last ``smooth`` frames) stays
    at most ``threshold`` (never beyond ``tmax``, and never leaving a remainder that cannot be
    segmented). The error of frame ``t`` is ``‖y_t − μ − C(A1 x_{t−1} + A2 x_{t−2} + d)‖² / D``.
    The textons of this stage are the paper's with ``k = min(state_dim, 15)``: one window of
    ``tmin`` frames supports no more; EM refits every texton at the full ``state_dim``.

    Returns:
        ``(segments, n_textons)``; segments as rows ``(seq, start, length, label)``.
    """
    tmin = config.tmin
    k_state = config.state_dim if config.state_dim is not None else _INIT_STATE_DIM_MAX
    rows: list[tuple[int, int, int, int]] = []
    bank = _Bank()
    for s, y in enumerate(ys):
        T = y.shape[0]
        tmax = T if config.tmax is None else config.tmax
        b = 0
        while b < T:
            win = jax.device_put(y[b : b + tmin])  # sliced on the host: no compile per length
            label = -1
            if bank.items:
                err = np.asarray(_bank_errors(bank.stacked(), win))[: len(bank.items)]
                mean_err = err[:, 2:].mean(axis=1)
                best = int(np.argmin(mean_err))
                if mean_err[best] <= threshold:
                    label = best
            if label < 0:
                label = bank.add(
                    fit_texton(
                        win,
                        state_dim=min(_INIT_STATE_DIM_MAX, k_state),
                        ridge=config.ridge,
                        q_floor=config.q_floor,
                        sigma2_floor=config.sigma2_floor,
                        rho_max=config.rho_max,
                        init_prior_weight=config.init_prior_weight,
                    )
                )
            # extend while the running mean error stays below the threshold
            hi = min(b + tmax, T)
            span = np.zeros((tmax, y.shape[1]), y.dtype)
            span[: hi - b] = y[b:hi]
            e_t = np.asarray(_bank_errors(bank.one(label), jax.device_put(span)))[0]
            e_t = e_t[: hi - b]
            # local error: mean over the last `smooth` frames (robust to a single noisy frame,
            # but sharp at a change of dynamics, unlike a running mean over the whole segment)
            loc = np.convolve(e_t, np.ones(smooth) / smooth, mode="full")[: hi - b]
            length = tmin
            while length < hi - b and loc[length] <= threshold:
                length += 1
            # keep the rest segmentable
            if not feasible(T - b - length, tmin, tmax):
                cands = [L for L in range(tmin, hi - b + 1) if feasible(T - b - L, tmin, tmax)]
                length = min(cands, key=lambda L: (abs(L - length), L))
            rows.append((s, b, length, label))
            b += length
    return np.asarray(rows, dtype=np.int64).reshape(-1, 4), len(bank.items)


def threshold_for_textons(
    ys: Sequence[np.ndarray], config: LearnConfig, n_textons: int, *, iters: int = 18
) -> tuple[float, Segs, int]:
    """Bisection on the (log) threshold for a greedy initialisation with ``n_textons`` textons.

    Returns the threshold, its segmentation and the number of textons it gives (the closest
    to the request that the search found; ties prefer more textons).
    """
    lo, hi = math.log(1e-5), math.log(1e3)
    best: tuple[int, float, Segs, int] | None = None
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        segs, n = greedy_init(ys, config, math.exp(mid))
        score = abs(n - n_textons)
        if best is None or score < best[0] or (score == best[0] and n > best[3]):
            best = (score, math.exp(mid), segs, n)
        if n == n_textons:
            break
        if n > n_textons:
            lo = mid
        else:
            hi = mid
    assert best is not None
    return best[1], best[2], best[3]


#: Chunks per initial texton of ``init="chunks"`` without ``n_textons``: the initial
#: vocabulary grows with the data, and the selection (design §10.10) then removes the textons
#: that do not pay.
CHUNKS_PER_TEXTON = 4

#: At most this many initial textons (the first E-steps' cost grows with them; 64 is one per
#: 4 chunks of 20,480 frames).
MAX_INITIAL_TEXTONS = 64


def initial_textons(ys: Sequence[np.ndarray], chunk: int) -> int:
    """The initial number of textons of ``init="chunks"``: one per ``CHUNKS_PER_TEXTON``
    chunks of ``chunk`` frames, at least 1 and at most ``MAX_INITIAL_TEXTONS``."""
    n_chunks = sum(max(y.shape[0] // chunk, 1) for y in ys)
    return min(MAX_INITIAL_TEXTONS, max(1, round(n_chunks / CHUNKS_PER_TEXTON)))


def chunk_init(
    ys: Sequence[np.ndarray], config: LearnConfig, n_textons: int, chunk: int, seed: int = 0
) -> Segs:
    """Initial segments from clustered chunks (design §10.10): every clip cut into chunks of
    ``chunk`` frames (the remainder joins the last chunk, which stays within ``[tmin,
    tmax]``), the chunks labelled by k-means on their mean frames (k-means++ seeding, the
    best of 10 restarts). EM then refits the textons and prunes the rare ones.

    Args:
        ys: observation sequences ``(T_s, D)``, each at least ``tmin`` frames.
        config: the configuration (``tmin``, ``tmax``).
        n_textons: the number of clusters (at most the number of chunks).
        chunk: the chunk length in frames, within ``[tmin, tmax]``.
        seed: the seed of the k-means restarts.

    Returns:
        Segment rows ``(clip, start, length, label)``.
    """
    tmax = config.tmax if config.tmax is not None else max(y.shape[0] for y in ys)
    if not config.tmin <= chunk <= tmax:
        raise ValueError(f"chunk length {chunk} must lie in [tmin, tmax] = [{config.tmin}, {tmax}]")
    rows, feats = [], []
    for s, y in enumerate(ys):
        T = y.shape[0]
        n = max(T // chunk, 1)
        bounds = [i * chunk for i in range(n)] + [T]
        for b, e in itertools.pairwise(bounds):
            if e - b > tmax:  # a long remainder: split it in two
                mid = b + (e - b) // 2
                rows += [(s, b, mid - b), (s, mid, e - mid)]
                feats += [y[b:mid].mean(axis=0), y[mid:e].mean(axis=0)]
            else:
                rows.append((s, b, e - b))
                feats.append(y[b:e].mean(axis=0))
    X = np.asarray(feats)
    k = min(int(n_textons), len(X))
    labels = _kmeans(X, k, np.random.default_rng(seed))
    # relabel by first appearance, so that texton ids read in the order of the clips
    order = {int(lab): i for i, lab in enumerate(dict.fromkeys(labels.tolist()))}
    return np.asarray(
        [(s, b, n, order[int(lab)]) for (s, b, n), lab in zip(rows, labels, strict=True)],
        dtype=np.int64,
    )


def _kmeans(X: np.ndarray, k: int, rng: np.random.Generator, restarts: int = 10) -> np.ndarray:
    """Labels of the lowest-inertia k-means of ``X`` over ``restarts`` k-means++ starts."""
    best, best_inertia = None, np.inf
    for _ in range(restarts):
        centres = [X[rng.integers(len(X))]]
        for _ in range(1, k):
            d2 = np.min(((X[:, None, :] - np.asarray(centres)[None]) ** 2).sum(-1), axis=1)
            p = d2 / d2.sum() if d2.sum() > 0 else np.full(len(X), 1.0 / len(X))
            centres.append(X[rng.choice(len(X), p=p)])
        C = np.asarray(centres)
        for _ in range(100):
            lab = np.argmin(((X[:, None, :] - C[None]) ** 2).sum(-1), axis=1)
            newC = np.asarray([X[lab == j].mean(0) if np.any(lab == j) else C[j] for j in range(k)])
            if np.allclose(newC, C):
                break
            C = newC
        lab = np.argmin(((X[:, None, :] - C[None]) ** 2).sum(-1), axis=1)
        inertia = float(((X - C[lab]) ** 2).sum())
        if inertia < best_inertia:
            best, best_inertia = lab, inertia
    assert best is not None
    return best
