"""Marginal likelihood of a sequence under a motion texture: the semi-Markov forward algorithm
(design §10.1).

With segment scores ``s_i(b, e)`` (design §3), an optional duration term ``log p_i(L)`` (zero
for the paper's flat durations), transition log-probabilities ``log M[l, i]`` and initial
log-probabilities ``log π[i]``:

.. code-block:: text

    α(e, i) = logsumexp_b [ s_i(b, e) + log p_i(e − b + 1)
                            + (b = 0 ? log π_i : logsumexp_l α(b − 1, l) + log M[l, i]) ]
    log p(y_0:T−1) = logsumexp_i α(T − 1, i)

summed over every segmentation with ``tmin ≤ e − b + 1 ≤ tmax`` and every labelling. It is the
Viterbi recursion of :func:`viterbi_segments` with logsumexp in place of max, over the log
semiring: one recursion (``recursion.py``) with the same split ``s_i(b, e) = A_i(e) + B⁰_i(b)``,
the same ring buffer of ``B``, the same ``lax.scan`` over blocks of ``tmin`` ends. Inside a
block, the window of candidate starts of every end is
gathered (in chunks of starts, with a running maximum, so the memory stays bounded even for
``tmax = None``) and reduced by a logsumexp that is exact (no underflow of the window's largest
term) and has finite gradients where a window holds no feasible start. The transition step
``logsumexp_l α(e, l) + log M[l, i]`` is one matrix product in linear space, ``exp(α − max) ·
exp(log M − column max)``, with the ``(P, N, N)`` logsumexp as the exact fallback if a column's
terms all underflow.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float, Int

from ...core import as_array, bucket_length, pad_frames
from .._scoring.scores import SegmentScorer, segment_scores
from .._texton.checks import check_obs
from .._texton.texton import Texton
from .recursion import LogSumExp, safe_logsumexp, semi_markov_values
from .segment import check_dp_inputs

__all__ = ["forward_log_likelihood", "log_likelihood", "padded_log_likelihood"]


@eqx.filter_jit
def forward_log_likelihood(
    scorer: SegmentScorer,
    log_M: Float[Array, "n n"],
    log_pi: Float[Array, " n"],
    n_valid: Int[Array, ""],
    tmin: int,
    tmax: int,
    log_durations: Float[Array, "n W"] | None = None,
) -> Float[Array, ""]:
    """``log p(y_0:n_valid−1)`` summed over all segmentations and labels (design §10.1).

    Args:
        scorer: prefix sums of the textons' per-frame terms over ``T`` (padded) frames.
        log_M: ``(N_t, N_t)`` log transition matrix, ``log_M[l, i] = log P(i | l)``.
        log_pi: ``(N_t,)`` log initial distribution.
        n_valid: number of real frames ``T_s ≤ T`` (the rest is padding and ignored).
        tmin: shortest segment length (static), ``3 ≤ tmin ≤ tmax``.
        tmax: longest segment length (static).
        log_durations: ``(N_t, tmax − tmin + 1)`` log-probability of each segment length
            ``L = tmin … tmax`` per texton; ``None`` for flat durations (the paper's).

    Returns:
        the scalar log-likelihood (``−inf`` if no segmentation fits).
    """
    n_t, _ = scorer.init.shape
    dtype = scorer.cum_dyn.dtype
    log_M = jnp.asarray(log_M, dtype)
    log_pi = jnp.asarray(log_pi, dtype)
    sr = LogSumExp(log_M, log_durations, tmin, tmax, n_t, dtype)
    _, V = semi_markov_values(scorer, log_pi, sr)
    return safe_logsumexp(V[jnp.asarray(n_valid) - 1], axis=0)


def log_likelihood(
    textons: Texton,
    log_M: Float[ArrayLike, "n n"],
    log_pi: Float[ArrayLike, " n"],
    Y: Float[ArrayLike, "T D"],
    tmin: int,
    tmax: int | None = None,
    *,
    log_durations: Float[ArrayLike, "n W"] | None = None,
) -> Float[Array, ""]:
    """Marginal log-likelihood ``log p(Y)`` of one sequence under textons and transitions.

    The sum over every segmentation (``tmin ≤`` length ``≤ tmax``) and every labelling of the
    textons' segment likelihoods (design §3) times transition and duration probabilities
    (design §10.1); it is ``≥`` the score of the best segmentation (:func:`segment`), with
    equality when one path carries all the mass. Differentiable in ``Y`` and the parameters.

    Args:
        textons: stacked textons (``N_t`` on the leading axis).
        log_M: ``(N_t, N_t)`` log transition matrix (rows: from, columns: to).
        log_pi: ``(N_t,)`` log initial distribution.
        Y: ``(T, D)`` observations, ``T ≥ tmin``.
        tmin: shortest segment (frames, ``≥ 3``).
        tmax: longest segment; ``None`` for unbounded.
        log_durations: ``(N_t, tmax − tmin + 1)`` log-probabilities of the lengths
            ``tmin … tmax`` per texton, or ``None`` for flat durations.

    Returns:
        the scalar ``log p(Y)`` in nats (``−inf`` if no segmentation fits).

    Raises:
        ValueError: bad shapes, ``tmin < 3``, ``tmax < tmin``, a sequence shorter than
            ``tmin``, non-finite ``Y``.
    """
    Y = as_array(Y)
    if Y.ndim != 2:
        raise ValueError(f"Y must have shape (T, D), got {Y.shape}")
    T = Y.shape[0]
    # padded to a shape bucket (design §11): one program per bucket, not per length
    Tb = bucket_length(T)
    tmin, tmax, log_M, log_pi = check_dp_inputs(
        textons, log_M, log_pi, T, tmin, Tb if tmax is None else tmax
    )
    if T < tmin:
        raise ValueError(f"sequence has {T} frames, shorter than tmin = {tmin}")
    n_t = log_pi.shape[0]
    dur = None
    if log_durations is not None:
        dur = jnp.asarray(log_durations)
        if dur.shape != (n_t, tmax - tmin + 1):
            raise ValueError(
                f"log_durations must have shape ({n_t}, {tmax - tmin + 1}) "
                f"(lengths {tmin}..{tmax}), got {dur.shape}"
            )
    check_obs("Y", Y, textons.obs_dim, min_len=2)
    # a concrete Y was checked above: no in-program check (a host callback, which would keep
    # the program out of the persistent compilation cache)
    traced = isinstance(Y, Tracer)
    n_valid = jax.device_put(np.asarray(T))
    return padded_log_likelihood(
        textons, log_M, log_pi, pad_frames(Y, Tb), n_valid, tmin, tmax, dur, traced
    )


@eqx.filter_jit
def padded_log_likelihood(
    textons: Texton,
    log_M: Array,
    log_pi: Array,
    Y: Array,
    n_valid: Array,
    tmin: int,
    tmax: int,
    log_durations: Array | None,
    check: bool = False,
) -> Array:
    """:func:`forward_log_likelihood` of the first ``n_valid`` frames of ``Y``, the frame terms
    and the recursion as one program per shape bucket (design §11); ``check``: NaN/inf check
    of ``Y`` inside the program."""
    scorer = segment_scores(textons, Y, check=check)
    return forward_log_likelihood(scorer, log_M, log_pi, n_valid, tmin, tmax, log_durations)
