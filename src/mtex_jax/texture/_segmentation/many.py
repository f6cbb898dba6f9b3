"""Many sequences in one call (design §11): the marginal likelihoods and the segmentations of
a list of clips, stacked in one shape bucket and computed by one compiled program, as the
E-step does, rather than one program per clip length."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Float

from ...core import as_array, bucket_length, cut_frames
from .._texton.checks import check_obs
from .._texton.texton import Texton
from .forward import padded_log_likelihood
from .segment import Segmentation, check_dp_inputs, segment

__all__ = ["log_likelihood_many", "segment_many"]


def log_likelihood_many(
    textons: Texton,
    log_M: Float[ArrayLike, "n n"],
    log_pi: Float[ArrayLike, " n"],
    Ys: list[Any],
    tmin: int,
    tmax: int | None = None,
    log_durations: Float[ArrayLike, "n W"] | None = None,
) -> Float[Array, " S"]:
    """:func:`log_likelihood` of each of several sequences, in one call.

    The sequences are padded to the shape bucket of the longest (design §11) and stacked
    (their number to a multiple of 4, with repeats of the first), and one compiled program
    scores them in turn (``lax.map``: the memory of one sequence at a time), so that a test
    set is one program, not one per clip length.

    Args:
        textons: stacked textons.
        log_M: ``(N_t, N_t)`` log transition matrix.
        log_pi: ``(N_t,)`` log initial distribution.
        Ys: a non-empty list of ``(T_s, D)`` observation arrays.
        tmin: shortest segment.
        tmax: longest segment; ``None`` for unbounded (the longest sequence's bucket).
        log_durations: as for :func:`log_likelihood`.

    Returns:
        ``(S,)`` log-likelihoods in nats, in the order of ``Ys``.

    Raises:
        ValueError: an empty list, or any check of :func:`log_likelihood` on a sequence.
    """
    arrays, lengths, Tb = _stack_checks("log_likelihood_many", textons, Ys)
    tmin, tmax, log_M, log_pi = check_dp_inputs(
        textons, log_M, log_pi, Tb, tmin, Tb if tmax is None else tmax
    )
    short = np.flatnonzero(lengths < tmin)
    if short.size:
        s = int(short[0])
        raise ValueError(f"sequence {s} has {lengths[s]} frames, shorter than tmin = {tmin}")
    dur = None
    if log_durations is not None:
        dur = as_array(log_durations)
        if dur.shape != (log_pi.shape[0], tmax - tmin + 1):
            raise ValueError(
                f"log_durations must have shape ({log_pi.shape[0]}, {tmax - tmin + 1}), "
                f"got {dur.shape}"
            )
    batch, nf, S = _stacked(arrays, lengths, Tb)
    out = _padded_log_likelihoods(textons, log_M, log_pi, batch, nf, tmin, tmax, dur)
    return cut_frames(out, S)


@eqx.filter_jit
def _padded_log_likelihoods(
    textons: Texton,
    log_M: Array,
    log_pi: Array,
    Y: Array,
    n_valid: Array,
    tmin: int,
    tmax: int,
    log_durations: Array | None,
) -> Array:
    def one(args: tuple[Array, Array]) -> Array:
        y, n = args
        return padded_log_likelihood(textons, log_M, log_pi, y, n, tmin, tmax, log_durations)

    return lax.map(one, (Y, n_valid))


def segment_many(
    textons: Texton,
    log_M: Float[ArrayLike, "n n"],
    log_pi: Float[ArrayLike, " n"],
    Ys: list[Any],
    tmin: int,
    tmax: int | None = None,
    log_durations: Float[ArrayLike, "n L"] | None = None,
) -> list[Segmentation]:
    """:func:`~mtex_jax.texture.segment` of each of several sequences, in one call.

    The sequences are stacked in the shape bucket of the longest (their number a multiple of
    4) and segmented by the batched E-step's kernel (design §4.2, §11).

    Returns:
        one :class:`Segmentation` per sequence, each with the ``T_s // tmin + 1`` slots of
        its own length.
    """
    arrays, lengths, Tb = _stack_checks("segment_many", textons, Ys)
    if tmax is None:
        tmax = Tb
    batch, nf, S = _stacked(arrays, lengths, Tb)
    seg = segment(
        textons, log_M, log_pi, batch, tmin, tmax, n_frames=nf, log_durations=log_durations
    )
    host = [np.asarray(a) for a in (seg.starts, seg.lengths, seg.labels, seg.n_segments, seg.score)]
    put = jax.device_put
    out = []
    for s in range(S):
        K = int(lengths[s]) // tmin + 1
        st, ln, lb, n, sc = (a[s] for a in host)
        out.append(Segmentation(put(st[:K]), put(ln[:K]), put(lb[:K]), put(n), put(sc)))
    return out


def _stack_checks(name: str, textons: Texton, Ys: Any) -> tuple[list[Any], np.ndarray, int]:
    if not isinstance(Ys, list | tuple) or len(Ys) == 0:
        raise ValueError(f"{name}: Ys must be a non-empty list of (T, D) arrays")
    arrays = []
    for s, Y in enumerate(Ys):
        Y = np.asarray(Y)
        if Y.ndim != 2:
            raise ValueError(f"sequence {s}: Y must have shape (T, D), got {Y.shape}")
        arrays.append(check_obs(f"sequence {s}", Y, textons.obs_dim, min_len=2))
    lengths = np.asarray([a.shape[0] for a in arrays])
    return arrays, lengths, bucket_length(int(lengths.max()))


def _stacked(arrays: list[Any], lengths: np.ndarray, Tb: int) -> tuple[Array, Array, int]:
    """``(S', Tb, D)`` sequences edge-padded to ``Tb`` frames, ``S'`` a multiple of 4 (repeats
    of the first), their lengths, and ``S``."""
    S = len(arrays)
    idx = np.concatenate([np.arange(S), np.zeros(-(-S // 4) * 4 - S, np.int64)])
    dt = np.result_type(*[np.asarray(a).dtype for a in arrays])
    pad = lambda i: np.pad(np.asarray(arrays[i], dt), ((0, int(Tb - lengths[i])), (0, 0)), "edge")
    return jax.device_put(np.stack([pad(i) for i in idx])), jax.device_put(lengths[idx]), S
