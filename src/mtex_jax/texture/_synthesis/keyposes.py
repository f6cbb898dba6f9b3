"""Key poses of whole-sequence synthesis (MT §5.1): the segments that may follow one another,
their boundary jumps, and the training instances a texton path draws its key poses from."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ...core import bucket_length
from .._model import MotionTexture


def _uniform_impl(key: Array, n: int) -> Array:
    return jax.random.uniform(key, (n,))


_uniform = jax.jit(_uniform_impl, static_argnums=1)


def next_segments(texture: MotionTexture) -> np.ndarray:
    """Index of the training segment directly after each segment (``-1`` at a clip end)."""
    segs = np.asarray(texture.segments)
    nxt = np.full(segs.shape[0], -1, dtype=np.int64)
    if segs.shape[0] > 1:
        follows = (segs[1:, 0] == segs[:-1, 0]) & (segs[1:, 1] == segs[:-1, 1] + segs[:-1, 2])
        nxt[:-1] = np.where(follows, np.arange(1, segs.shape[0]), -1)
    return nxt


def _chain_costs(kp: np.ndarray, nxt: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(|a|, |b|)`` cost of key-pose instance ``b`` following instance ``a``.

    Texton ``ℓ_m`` is synthesised from the key poses of its instance ``a`` (a training
    segment) to the key poses of the next instance ``b`` in ``len(a)`` frames. In the training
    clip, segment ``a`` led to the two frames after it, ``K_next(a)``; the cost is the squared
    distance ``‖K_next(a) − K_b‖²`` of those frames to the key poses asked for (0 when ``b`` is
    the segment that really followed ``a``: the texton repeats a transition it was trained
    on). Where ``a`` ends a clip, nothing is known and the cost is the largest of the others.

    ``kp``: ``(n_seg, 2D)`` key poses, centred (the expanded squared distance below then
    cancels less); ``nxt``: :func:`next_segments`.
    """
    nxt = nxt[a]
    has = nxt >= 0
    cost = np.zeros((a.size, b.size))
    if has.any():
        x, y = kp[nxt[has]], kp[b]
        d2 = (x * x).sum(1)[:, None] + (y * y).sum(1)[None, :] - 2.0 * (x @ y.T)
        d2 = np.maximum(d2, 0.0)
        d2[nxt[has][:, None] == b[None, :]] = 0.0  # exact zero for the true successor
        cost[has] = d2
        cost[~has] = d2.max()
    return cost


def key_pair_jumps(texture: MotionTexture) -> np.ndarray:
    """``(n_seg,)`` jump inside every key-pose pair: the largest displacement of a joint between
    its two frames (decoded with the texture's feature map), or ``‖K[1] − K[0]‖`` in
    observation space for a texture learned from raw arrays."""
    kp = np.asarray(texture.key_poses, dtype=np.float64)
    fm = texture.feature_map
    if fm is None:
        return np.linalg.norm(kp[:, 1] - kp[:, 0], axis=1)
    # decoding all pairs as one sequence leaves every within-pair jump as it is: the root's
    # integrated heading and position only move a pair rigidly about the up axis
    P = np.asarray(fm.joint_positions(kp.reshape(-1, kp.shape[-1])))
    P = P.reshape(kp.shape[0], 2, -1, P.shape[-1])
    return np.linalg.norm(P[:, 1] - P[:, 0], axis=-1).max(axis=1)


def usable_key_poses(texture: MotionTexture) -> np.ndarray:
    """``(n_seg,)`` bool: key-pose pairs that are not outliers of the within-pair jump.

    A pair whose jump is beyond Tukey's fence ``q3 + 1.5 (q3 − q1)`` of all pairs' jumps (the
    usual box-plot outlier rule) and beyond twice their median is a capture glitch or a cut at
    an abrupt event; held as a constraint, it would put that jump into the synthesised motion
    at the boundary. (The second bound keeps the moving pairs of a texture whose pairs mostly
    do not move; with a median of 0 nothing is an outlier.) A pair with a non-finite jump is
    never usable. The fence is the texture's, not the texton's: the fast starts of a texton
    count as outliers when they are far faster than the texture's typical pair.
    """
    jumps = key_pair_jumps(texture)
    finite = np.isfinite(jumps)
    if not finite.any():
        return finite
    q1, med, q3 = np.percentile(jumps[finite], [25.0, 50.0, 75.0])
    if med <= 0.0:
        return finite
    return finite & (jumps <= max(q3 + 1.5 * (q3 - q1), 2.0 * med))


def key_pose_instances(texture: MotionTexture, key: Array | None, path: np.ndarray) -> np.ndarray:
    """One training segment of texton ``path[m]`` for every ``m`` (index into key_poses).

    The instances are chosen together, as the chain of minimum total cost
    ``Σ_m cost(a_m, a_{m+1})`` (:func:`_chain_costs`) by dynamic programming (Viterbi over
    the path positions, O(Σ_m |cand_m|·|cand_{m+1}|)): wherever the training clips contain a
    segment of ``ℓ_m`` directly followed by one of ``ℓ_{m+1}``, the chain can use that pair,
    and texton ``m`` then goes from its key poses to the next ones in the number of frames it
    took in the training data. Exact ties (several chains of equal cost) are broken towards
    segments of median length without a key and at random with one. Candidates are the
    texton's usable key poses (:func:`usable_key_poses`), all of them if it has none.
    """
    lab = np.asarray(texture.key_pose_labels)
    lengths = np.asarray(texture.segment_lengths, dtype=np.float64)
    usable = usable_key_poses(texture)
    cands = [np.flatnonzero(lab == p) for p in path]
    # outlier key poses only where the texton has nothing else
    cands = [c[usable[c]] if usable[c].any() else c for c in cands]
    if key is None:
        tie = [np.abs(lengths[c] - np.median(lengths[c])) for c in cands]
    else:
        # uniform draws are prefix-stable in their flat index: drawn for a bucket of sizes
        # (no program per path length, design §11) and cut to the (n, c) block
        shape = (path.size, max(c.size for c in cands))
        n = shape[0] * shape[1]
        u = np.asarray(_uniform(key, bucket_length(n, 1 << 16)))[:n].reshape(shape)
        tie = [u[m, : c.size] for m, c in enumerate(cands)]
    kp = np.asarray(texture.key_poses, dtype=np.float64)
    kp = kp.reshape(kp.shape[0], -1)
    kp = kp - kp.mean(axis=0)
    nxt = next_segments(texture)
    # Viterbi on (total cost, total tie-break) compared lexicographically
    acc, acc_tie = np.zeros(cands[0].size), tie[0].astype(np.float64)
    back = []
    for m in range(path.size - 1):  # host loop over path positions (textons, not frames)
        tot = acc[:, None] + _chain_costs(kp, nxt, cands[m], cands[m + 1])
        arg = np.lexsort((np.broadcast_to(acc_tie[:, None], tot.shape).T, tot.T))[:, 0]
        back.append(arg)
        acc = tot[arg, np.arange(tot.shape[1])]
        acc_tie = acc_tie[arg] + tie[m + 1]
    out = np.empty(path.size, dtype=np.int64)
    j = int(np.lexsort((acc_tie, acc))[0])
    out[-1] = cands[-1][j]
    for m in range(path.size - 2, -1, -1):
        j = int(back[m][j])
        out[m] = cands[m][j]
    return out


def next_texton(texture: MotionTexture, key: Array | None, label: int) -> int:
    """A texton drawn from ``M[label, ·]`` (the most probable one without a key)."""
    row = np.asarray(texture.M, dtype=np.float64)[label]
    if key is None:
        return int(np.argmax(row))
    with np.errstate(divide="ignore"):
        return int(jax.random.categorical(key, jnp.asarray(np.log(row))))
