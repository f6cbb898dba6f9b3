"""Texton paths on a learned transition matrix (design §5; MT §5.2–5.3).

A path is a sequence of texton labels ``ℓ_1 … ℓ_n``; its probability under the motion texture
is ``Π_m M[ℓ_m, ℓ_{m+1}]``, so the lowest-cost path between two textons minimises
``Σ_m −log M[ℓ_m, ℓ_{m+1}]``. Three planners:

* :func:`random_path`: a random walk on ``M`` (first texton from ``π`` or given), ``lax.scan``;
* :func:`shortest_path`: Dijkstra on the edge weights ``−log M_ij`` (``i ≠ j``, edges with
  ``M_ij = 0`` absent), then — if a key is given — each texton on the path repeated according
  to its self-transition probability: draw the successor from its row of ``M`` and repeat while
  the draw is the texton itself, so the number of extra repeats is geometric,
  ``P(r) = M_ii^r (1 − M_ii)``;
* :func:`path_of_length`: the most probable path of exactly ``L`` textons from ``u`` to ``v``
  (self-transitions allowed), by the max-product recursion
  ``V_{m+1}(j) = max_i V_m(i) + log M_ij`` over ``L − 1`` steps (``lax.scan``, ``O(L·N_t²)``).

The planners take either a :class:`~mtex_jax.texture.MotionTexture` or a bare ``(N_t, N_t)``
row-stochastic matrix, and return numpy ``int`` arrays (paths are host-side plans that
decide static shapes of the synthesis that follows).
"""

from __future__ import annotations

import heapq
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float

from ...core import (
    MAX_GENERATED_FRAMES,
    as_array,
    bucket_length,
    check_count,
    check_key,
    check_size,
)
from .._model import MotionTexture

__all__ = ["path_cost", "path_of_length", "random_path", "shortest_path"]


def _transition_matrix(texture: MotionTexture) -> np.ndarray:
    """``M`` as a float64 numpy array, validated (square, finite, non-negative, rows sum to 1)."""
    M = getattr(texture, "M", texture)
    try:
        M = np.asarray(M, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise TypeError(f"expected a MotionTexture or a transition matrix, got {type(M)}") from e
    if M.ndim != 2 or M.shape[0] != M.shape[1] or M.shape[0] < 1:
        raise ValueError(f"transition matrix must be square (N_t, N_t), got shape {M.shape}")
    if not np.isfinite(M).all() or (M < 0).any():
        raise ValueError("transition matrix has negative or non-finite entries")
    rows = M.sum(axis=1)
    if not np.allclose(rows, 1.0, atol=1e-6):
        bad = int(np.argmax(np.abs(rows - 1.0)))
        raise ValueError(f"transition matrix row {bad} sums to {rows[bad]:.6g}, not 1")
    return M


def _label(name: str, x: Any, n: int) -> int:
    if isinstance(x, bool) or not isinstance(x, int | np.integer):
        try:
            arr = np.asarray(x)
        except Exception as e:  # pragma: no cover - exotic objects
            raise TypeError(f"{name} must be a texton index, got {x!r}") from e
        if arr.shape != () or not np.issubdtype(arr.dtype, np.integer):
            raise TypeError(f"{name} must be a texton index (int), got {x!r}")
        x = int(arr)
    if not 0 <= int(x) < n:
        raise ValueError(f"{name} = {int(x)} is not a texton index in [0, {n})")
    return int(x)


def path_cost(texture: MotionTexture, path: Any) -> float:
    """Cost ``Σ_m −log M[ℓ_m, ℓ_{m+1}]`` of a path (``inf`` if it uses an absent edge)."""
    M = _transition_matrix(texture)
    p = np.asarray(path, dtype=np.int64)
    if p.ndim != 1 or p.size < 1 or (p < 0).any() or (p >= M.shape[0]).any():
        raise ValueError(f"path must be a non-empty 1-D array of texton indices < {M.shape[0]}")
    with np.errstate(divide="ignore"):
        return float(-np.log(M[p[:-1], p[1:]]).sum())


# --------------------------------------------------------------------------------------------
# random walk
# --------------------------------------------------------------------------------------------


def _walk(log_M: Array, first: Array, key: Array, n: int) -> Array:
    def step(cur: Array, k: Array) -> tuple[Array, Array]:
        nxt = jax.random.categorical(k, log_M[cur]).astype(cur.dtype)
        return nxt, nxt

    _, rest = lax.scan(step, first, jax.random.split(key, n - 1))
    return jnp.concatenate([first[None], rest])


_walk_jit = jax.jit(_walk, static_argnums=3)
_WALK_BUCKET = 128


def random_path(
    key: Array, texture: MotionTexture, n_textons: int, *, start: int | None = None
) -> np.ndarray:
    """A random walk of ``n_textons`` labels on the transition matrix (MT §5.2).

    ``ℓ_1 ~ π`` (uniform if ``texture`` is a bare matrix) unless ``start`` is given, then
    ``ℓ_{m+1} ~ M[ℓ_m, ·]``.

    Args:
        texture: a :class:`~mtex_jax.texture.MotionTexture` or an ``(N_t, N_t)`` matrix.
        key: JAX PRNG key.
        n_textons: path length (static).
        start: first texton, or ``None`` to draw it from ``π``.

    Returns:
        ``(n_textons,)`` int64 labels.
    """
    check_key(key, "random_path")
    M = _transition_matrix(texture)
    n = M.shape[0]
    check_count(n_textons, "n_textons", MAX_GENERATED_FRAMES)
    with np.errstate(divide="ignore"):
        log_M = np.log(M)
    k_first, k_walk = jax.random.split(key)
    if start is None:
        pi = np.asarray(getattr(texture, "pi", np.full(n, 1.0 / n)), dtype=np.float64)
        with np.errstate(divide="ignore"):
            first = jax.random.categorical(k_first, jnp.asarray(np.log(pi)))
    else:
        first = jnp.asarray(_label("start", start, n))
    if n_textons == 1:
        return np.asarray([int(first)], dtype=np.int64)
    # drawn for a bucket of lengths (the walk's keys are prefix-stable), so that walks of
    # other lengths do not compile again (design §11)
    n_b = bucket_length(int(n_textons), _WALK_BUCKET)
    out = _walk_jit(jnp.asarray(log_M), first.astype(jnp.int32), k_walk, n_b)
    return np.asarray(out, dtype=np.int64)[: int(n_textons)]


# --------------------------------------------------------------------------------------------
# Dijkstra
# --------------------------------------------------------------------------------------------


def _dijkstra(W: np.ndarray, u: int) -> tuple[np.ndarray, np.ndarray]:
    """Single-source shortest paths on a dense non-negative weight matrix (``inf`` = no edge).

    Returns ``(dist (N,), pred (N,))`` with ``pred = −1`` for the source and unreachable nodes.
    """
    n = W.shape[0]
    dist = np.full(n, np.inf)
    pred = np.full(n, -1, dtype=np.int64)
    done = np.zeros(n, dtype=bool)
    dist[u] = 0.0
    heap: list[tuple[float, int]] = [(0.0, u)]
    while heap:
        d, i = heapq.heappop(heap)
        if done[i]:
            continue
        done[i] = True
        cand = d + W[i]
        better = (cand < dist) & ~done
        better[i] = False
        for j in np.flatnonzero(better):
            dist[j] = cand[j]
            pred[j] = i
            heapq.heappush(heap, (float(cand[j]), int(j)))
    return dist, pred


MAX_SELF_REPEATS = (
    1000  # a texton that (almost) always follows itself is repeated at most this often
)


def _repeat_self(M: np.ndarray, path: np.ndarray, key: Array) -> np.ndarray:
    """Repeat each texton ``r ~ Geometric`` extra times: ``P(r) = M_ii^r (1 − M_ii)``,
    truncated at :data:`MAX_SELF_REPEATS` (``M_ii = 1`` would repeat forever)."""
    stay = np.clip(M[path, path], 0.0, 1.0 - 1e-12)
    # inverse-CDF sample of the number of failures before the first success (p = 1 − M_ii)
    u = np.asarray(jax.random.uniform(key, (path.size,), dtype=jnp.float32), dtype=np.float64)
    u = np.clip(u, 1e-12, 1.0)
    with np.errstate(divide="ignore"):
        reps = np.where(stay > 0, np.floor(np.log(u) / np.log(np.maximum(stay, 1e-300))), 0)
    reps = np.minimum(reps, MAX_SELF_REPEATS)
    return np.repeat(path, 1 + reps.astype(np.int64))


def shortest_path(
    texture: MotionTexture, u: int, v: int, *, key: Array | None = None
) -> np.ndarray:
    """Lowest-cost texton path from ``u`` to ``v`` (MT §5.2; design §5).

    Dijkstra on the weights ``W_ij = −log M_ij`` for ``i ≠ j`` (``M_ij = 0``: no edge); the
    result has no repeated texton. With ``key`` given, every texton on it is then repeated
    according to its self-transition probability (successors are drawn from ``M[i, ·]`` until
    one differs from ``i``; equivalently ``r`` extra copies with ``P(r) = M_ii^r(1 − M_ii)``).

    Args:
        texture: a :class:`~mtex_jax.texture.MotionTexture` or an ``(N_t, N_t)`` matrix.
        u: first texton.
        v: last texton.
        key: PRNG key for the self-repeats, or ``None`` for none.

    Returns:
        int64 labels starting with ``u`` and ending with ``v`` (``[u]`` if ``u == v`` and no
        key).

    Raises:
        ValueError: ``v`` is unreachable from ``u``, or bad indices / matrix.
    """
    check_key(key, "shortest_path", allow_none=True)
    M = _transition_matrix(texture)
    n = M.shape[0]
    u, v = _label("u", u, n), _label("v", v, n)
    with np.errstate(divide="ignore"):
        W = -np.log(M)
    np.fill_diagonal(W, np.inf)
    _, pred = _dijkstra(W, u)
    if u != v and pred[v] < 0:
        raise ValueError(f"texton {v} is not reachable from texton {u} (M has no such path)")
    rev = [v]
    while rev[-1] != u:
        rev.append(int(pred[rev[-1]]))
    path = np.asarray(rev[::-1], dtype=np.int64)
    if key is not None:
        path = _repeat_self(M, path, key)
    return path


# --------------------------------------------------------------------------------------------
# path of a given length
# --------------------------------------------------------------------------------------------


def _length_dp(
    log_M: Float[Array, "n n"], u: Array, n_steps: Array, size: int
) -> tuple[Array, Array]:
    """Max-product DP: ``V (n,)`` after ``n_steps`` steps and back-pointers ``(size, n)``.

    The scan runs ``size ≥ n_steps`` steps (a shape bucket, design §11) and ``V`` stops
    changing after ``n_steps``; back-pointers past it are unused."""
    n = log_M.shape[0]
    V0 = jnp.where(jnp.arange(n) == u, 0.0, -jnp.inf).astype(log_M.dtype)

    def step(V: Array, i: Array) -> tuple[Array, Array]:
        cand = V[:, None] + log_M  # cand[i, j] = V(i) + log M_ij
        return jnp.where(i < n_steps, jnp.max(cand, axis=0), V), jnp.argmax(cand, axis=0)

    V, back = lax.scan(step, V0, jnp.arange(size))
    return V, back


_length_dp_jit = jax.jit(_length_dp, static_argnums=3)
_PATH_STEPS = 64  # path lengths are padded to a multiple of this


def path_of_length(texture: MotionTexture, u: int, v: int, L: int) -> tuple[np.ndarray, float]:
    """Most probable path of exactly ``L`` textons from ``u`` to ``v`` (MT §5.3; design §5).

    Maximises ``Σ_{m=1}^{L−1} log M[ℓ_m, ℓ_{m+1}]`` subject to ``ℓ_1 = u``, ``ℓ_L = v`` (self
    transitions allowed) by ``V_1 = 0·[i = u] − ∞·[i ≠ u]``,
    ``V_{m+1}(j) = max_i V_m(i) + log M_ij``, then back-tracking: ``O(L·N_t²)``.

    Args:
        texture: a :class:`~mtex_jax.texture.MotionTexture` or an ``(N_t, N_t)`` matrix.
        u: first texton.
        v: last texton.
        L: number of textons on the path (``≥ 1``; ``L = 1`` needs ``u == v``).

    Returns:
        ``(labels (L,) int64, log_probability)``.

    Raises:
        ValueError: no path of that length exists, or bad arguments (``L`` more than the limit
            ``MAX_PATH_TEXTONS`` of :mod:`mtex_jax.core`, or ``L·N_t`` more than
            ``MAX_GENERATED_FRAMES``).
    """
    M = _transition_matrix(texture)
    n = M.shape[0]
    u, v = _label("u", u, n), _label("v", v, n)
    if isinstance(L, bool) or not isinstance(L, int | np.integer):
        raise TypeError(f"L must be an int, got {L!r}")
    if L < 1:
        raise ValueError(f"L must be >= 1, got {L}")
    check_size(L, "path_of_length: L", "MAX_PATH_TEXTONS")
    check_size(L * n, "path_of_length: L × N_t back-pointers", "MAX_GENERATED_FRAMES")
    if L == 1:
        if u != v:
            raise ValueError(f"a path of 1 texton cannot go from {u} to {v}")
        return np.asarray([u], dtype=np.int64), 0.0
    with np.errstate(divide="ignore"):
        log_M = jnp.asarray(np.log(M))
    size = bucket_length(L - 1, _PATH_STEPS)
    V, back = _length_dp_jit(log_M, jnp.asarray(u), as_array(np.int32(L - 1)), size)
    score = float(np.asarray(V)[v])
    if not np.isfinite(score):
        raise ValueError(f"no path of exactly {L} textons from {u} to {v}")
    back_np = np.asarray(back)[: L - 1]
    path = [v]
    for m in range(L - 2, -1, -1):  # host back-tracking over L labels (not frames)
        path.append(int(back_np[m, path[-1]]))
    return np.asarray(path[::-1], dtype=np.int64), score
