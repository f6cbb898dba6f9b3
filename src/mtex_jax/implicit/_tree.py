"""The PCA sign tree and its sampling kernels (IP §4, Eq. 3 and 7-8; design §7): sign codes, the
probabilistic tree descent and exact sampling over all windows, on a :class:`MotionDatabase`."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.scipy.special import log_ndtr, ndtr
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from ._database import MotionDatabase


# --------------------------------------------------------------------------- pure kernels
@jax.jit
def _right_svd_jit(x: Array) -> tuple[Array, Array]:
    if x.shape[0] > x.shape[1]:
        # X = Q R and R = U S Vᵀ give X = (Q U) S Vᵀ: the same S and V, from a square SVD
        x = jnp.linalg.qr(x, mode="r")
    _, s, vt = jnp.linalg.svd(x, full_matrices=False)
    return s, vt


def right_svd(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Singular values and right singular vectors of ``x`` (``n × W``), in JAX."""
    s, vt = _right_svd_jit(jnp.asarray(x))
    return np.asarray(s, dtype=np.float64), np.asarray(vt, dtype=np.float64)


def codes_np(coeffs: np.ndarray) -> np.ndarray:
    b = coeffs.shape[1]
    weights = (1 << np.arange(b - 1, -1, -1)).astype(np.int64)
    return ((coeffs > 0).astype(np.int64) @ weights).astype(np.int32)


def sign_codes(coeffs: Float[ArrayLike, "*batch b"]) -> Int[Array, "*batch"]:
    """``b``-bit sign codes (bit ``b−1−l`` = ``[c_l > 0]``) of coefficient vectors (int32)."""
    coeffs = jnp.asarray(coeffs)
    b = coeffs.shape[-1]
    weights = jnp.left_shift(jnp.int32(1), jnp.arange(b - 1, -1, -1, dtype=jnp.int32))
    return jnp.sum(jnp.where(coeffs > 0, weights, 0), axis=-1).astype(jnp.int32)


def descend(
    sorted_codes: Int[Array, " n"], z: Float[Array, " b"], u: Float[Array, " b"]
) -> tuple[Array, Array, Array]:
    """Walk the sign tree (IP Eq. 7–8) for one probe with ``z_l = c_{t,l} / (√β σ_l)``.

    At level ``l`` go right iff ``u_l < Φ_N(z_l)``; an empty child forces the other branch.

    Returns:
        the leaf's sorted-order range ``[lo, hi)`` (never empty) and the log-probability of
        the path taken (forced moves count as probability 1).
    """
    b = z.shape[0]
    n = sorted_codes.shape[0]
    p_right = ndtr(z)
    log_r, log_l = log_ndtr(z), log_ndtr(-z)

    def level(lev, carry):
        lo, hi, prefix, logq = carry
        split = jnp.left_shift(2 * prefix + 1, b - 1 - lev)  # smallest code of right child
        mid = jnp.searchsorted(sorted_codes, split, side="left").astype(jnp.int32)
        forced = (mid >= hi) | (mid <= lo)
        right = jnp.where(mid >= hi, False, jnp.where(mid <= lo, True, u[lev] < p_right[lev]))
        logq = logq + jnp.where(forced, 0.0, jnp.where(right, log_r[lev], log_l[lev]))
        lo = jnp.where(right, mid, lo)
        hi = jnp.where(right, hi, mid)
        return lo, hi, 2 * prefix + right.astype(jnp.int32), logq

    init = (jnp.int32(0), jnp.int32(n), jnp.int32(0), jnp.zeros((), z.dtype))
    lo, hi, _, logq = lax.fori_loop(0, b, level, init)
    return lo, hi, logq


def _tree_one(
    db: MotionDatabase, key: PRNGKeyArray, c: Float[Array, " b"], beta: Array, leaf: str
) -> tuple[Int[Array, ""], Float[Array, ""]]:
    """One tree sample for coefficient vector ``c`` → (example index, log proposal prob.)."""
    k_walk, k_leaf = jax.random.split(key)
    b = db.n_components
    scale = jnp.sqrt(beta) * db.sigma.astype(c.dtype)
    u = jax.random.uniform(k_walk, (b,), dtype=c.dtype)
    lo, hi, logq = descend(db.sorted_codes, c / scale, u)
    if leaf == "uniform":
        v = jax.random.uniform(k_leaf, (), dtype=c.dtype)
        size = (hi - lo).astype(c.dtype)
        pos = jnp.minimum(lo + jnp.floor(v * size).astype(jnp.int32), hi - 1)
        logq = logq - jnp.log(size)
    else:
        cand = lo + jnp.arange(db.leaf_max, dtype=jnp.int32)
        valid = cand < hi
        safe = jnp.minimum(cand, db.n_examples - 1)
        zz = (db.sorted_coeffs[safe].astype(c.dtype) - c) / scale
        logw = jnp.where(valid, -0.5 * jnp.sum(zz * zz, axis=-1), -jnp.inf)
        pick = jax.random.categorical(k_leaf, logw)
        pos = cand[pick]
        logq = logq + logw[pick] - jax.nn.logsumexp(logw)
    return db.order[pos], logq


def tree_sample_indices(
    db: MotionDatabase,
    key: PRNGKeyArray,
    probes: Float[Array, "N W"],
    beta: Array,
    leaf: str,
    candidates: int = 1,
) -> Int[Array, " N"]:
    """Traceable core of :meth:`ImplicitModel.sample` (no checks; usable inside ``jit``).

    With ``candidates = K > 1``: ``K`` independent walks per probe, then one of them chosen
    with probability ``∝ p(i_k | Φ_t) / q(i_k)`` (exact kernel of IP Eq. 3 over the walk's
    proposal probability) — sampling-importance-resampling, ``O(K (b log n + W))``.
    """
    c = db.coefficients(probes)
    n = probes.shape[0]
    one = lambda k, ci: _tree_one(db, k, ci, beta, leaf)
    if candidates == 1:
        return jax.vmap(one)(jax.random.split(key, n), c)[0]
    k_walk, k_pick = jax.random.split(key)
    keys = jax.random.split(k_walk, (n, candidates))
    idx, logq = jax.vmap(jax.vmap(one, in_axes=(0, None)))(keys, c)  # (N, K)
    diff = db.windows[idx].astype(probes.dtype) - probes[:, None, :]
    logp = -0.5 * jnp.sum(diff * diff, axis=-1) / beta
    pick = jax.random.categorical(k_pick, logp - logq, axis=-1)
    return jnp.take_along_axis(idx, pick[:, None], axis=1)[:, 0]


def exact_sample_indices(
    db: MotionDatabase, key: PRNGKeyArray, probes: Float[Array, "N W"], beta: Array
) -> Int[Array, " N"]:
    """Traceable core of :meth:`ImplicitModel.sample_exact`: ``O(n·W)`` per probe."""
    w = db.windows.astype(probes.dtype)
    d2 = (
        jnp.sum(probes * probes, axis=-1, keepdims=True)
        + jnp.sum(w * w, axis=-1)[None, :]
        - 2.0 * probes @ w.T
    )
    logits = -0.5 * jnp.maximum(d2, 0.0) / beta
    return jax.random.categorical(key, logits, axis=-1).astype(jnp.int32)


sample_tree_jit = eqx.filter_jit(tree_sample_indices)
sample_exact_jit = eqx.filter_jit(exact_sample_indices)
