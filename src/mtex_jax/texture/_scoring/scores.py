"""O(1) segment scores from prefix sums of the frame terms (design §3): :class:`SegmentScorer`
and :func:`segment_scores`, used by the segmentation DP."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._texton.checks import check_obs
from .._texton.texton import Texton, check_texton
from .frame_terms import block_frames, frame_terms_impl, has_residual


class SegmentScorer(eqx.Module):
    """O(1) segment scores from prefix sums of the per-frame terms (design §3).

    ``score_i(b, e) = init_i(b) + Σ_{t=b+2..e} dyn_i(t) + Σ_{t=b..e} obs_i(t)`` for
    ``0 <= b < e <= T−1`` (0-based, inclusive; a segment has at least two frames).

    To keep the prefix sums accurate for long sequences they are taken of the terms minus a
    per-texton constant (their mean), added back analytically:

    .. code-block:: text

        cum_dyn[i, t] = Σ_{s<t} (dyn[i, s] − dyn_offset[i])        (N_t, T+1)
        Σ_{t=b+2..e} dyn_i(t) = cum_dyn[i, e+1] − cum_dyn[i, b+2] + (e − b − 1) dyn_offset[i]

    and likewise for ``obs`` with ``cum_obs[i, e+1] − cum_obs[i, b]`` and ``(e − b + 1)``.

    Attributes:
        init: ``(N_t, T)`` :func:`init_terms`.
        cum_dyn: ``(N_t, T+1)`` centred prefix sums of ``dyn``.
        cum_obs: ``(N_t, T+1)`` centred prefix sums of ``obs``.
        dyn_offset: ``(N_t,)`` constant subtracted from ``dyn`` before summing.
        obs_offset: ``(N_t,)`` constant subtracted from ``obs`` before summing.
    """

    init: Float[Array, "n T"]
    cum_dyn: Float[Array, "n T1"]
    cum_obs: Float[Array, "n T1"]
    dyn_offset: Float[Array, " n"]
    obs_offset: Float[Array, " n"]

    @property
    def n_textons(self) -> int:
        """Number of textons ``N_t``."""
        return int(self.init.shape[0])

    @property
    def n_frames(self) -> int:
        """Number of frames ``T``."""
        return int(self.init.shape[1])

    def score(self, b: ArrayLike, e: ArrayLike, i: ArrayLike) -> Float[Array, ...]:
        """Score of segment ``[b, e]`` (inclusive, 0-based) under texton ``i``.

        ``b``, ``e``, ``i`` are integer arrays broadcast against each other (e.g.
        ``i = arange(N_t)[:, None]`` with ``b`` of shape ``(L,)`` scores every texton for ``L``
        candidate starts). Invalid combinations (``b < 0``, ``e > T−1``, ``e < b + 1``, ``i``
        out of range) give ``−inf``. Pure ``jnp`` indexing: jit/vmap friendly.

        Returns:
            Array of the broadcast shape of ``b, e, i``.
        """
        return _score_jit(self, jnp.asarray(b), jnp.asarray(e), jnp.asarray(i))

    def _score(self, b: Array, e: Array, i: Array) -> Array:
        b, e, i = jnp.broadcast_arrays(b, e, i)
        T = self.init.shape[1]
        n = self.init.shape[0]
        valid = (b >= 0) & (e <= T - 1) & (e >= b + 1) & (i >= 0) & (i < n)
        bc = jnp.clip(b, 0, T - 1)
        ec = jnp.clip(e, 0, T - 1)
        ic = jnp.clip(i, 0, n - 1)
        dyn = (
            self.cum_dyn[ic, ec + 1]
            - self.cum_dyn[ic, jnp.minimum(bc + 2, T)]
            + (ec - bc - 1).astype(self.cum_dyn.dtype) * self.dyn_offset[ic]
        )
        obs = (
            self.cum_obs[ic, ec + 1]
            - self.cum_obs[ic, bc]
            + (ec - bc + 1).astype(self.cum_obs.dtype) * self.obs_offset[ic]
        )
        val = self.init[ic, bc] + dyn + obs
        return jnp.where(valid, val, -jnp.inf)

    def scores_ending_at(self, e: ArrayLike, lengths: ArrayLike) -> Float[Array, "n L"]:
        """Scores of every texton for segments ``[e − L + 1, e]``, ``L`` in ``lengths``.

        Args:
            e: scalar end frame.
            lengths: ``(L,)`` segment lengths (>= 2 for a finite score).

        Returns:
            ``(N_t, L)`` scores (``−inf`` where the segment does not fit).
        """
        lengths = jnp.asarray(lengths)
        e = jnp.asarray(e)
        b = e - lengths + 1
        i = jnp.arange(self.init.shape[0])[:, None]
        return self.score(b[None, :], e, i)


_score_jit = eqx.filter_jit(SegmentScorer._score)


def segment_scores(
    textons: Texton, Y: ArrayLike, *, block_size: int | None = None, check: bool = True
) -> SegmentScorer:
    """Per-frame terms of all textons and their prefix sums, for O(1) segment scores.

    Computes ``init``, ``dyn`` and ``obs`` (see :func:`frame_terms`, :func:`init_terms`), all
    three by the blocked kernel of :func:`frame_terms` (the initial-state term from the same
    whitened projections), and returns a :class:`SegmentScorer`.

    Args:
        textons: a stack of ``N_t`` textons (a single texton is treated as ``N_t = 1``).
        Y: observations ``(T, D)``, ``T >= 2``.
        block_size: frames per time block of the kernel (static); ``None`` chooses it from
            the cache size, as in :func:`frame_terms`.
        check: check a traced ``Y`` for NaN/inf inside the program (``eqx.error_if``, a host
            callback, which keeps the program out of JAX's persistent compilation cache);
            ``False`` for a caller that checked it eagerly. A concrete ``Y`` is always checked.

    Returns:
        :class:`SegmentScorer` with arrays ``(N_t, T)`` / ``(N_t, T+1)``.
    """
    textons = check_texton("textons", textons)
    if not textons.is_stacked:
        textons = jax.tree.map(lambda a: a[None], textons)
    Y = check_obs("Y", Y, textons.obs_dim, min_len=2)
    block = block_frames(block_size, textons, Y)
    return _segment_scores_jit(textons, Y, block, check)


def _segment_scores_impl(
    textons: Texton, Y: Array, block: int | None = None, check: bool = True
) -> SegmentScorer:
    # all three terms by the blocked kernel of frame_terms; init_terms (per texton), the
    # per-texton algorithm, is the independent reference
    if block is None:
        block = block_frames(None, textons, Y)
    dyn, obs, init = frame_terms_impl(
        textons, Y, min(block, Y.shape[0]), with_init=True, check=check
    )
    return scorer_from_terms(dyn, obs if has_residual(textons, Y) else None, init)


def scorer_from_terms(dyn: Array, obs: Array | None, init: Array) -> SegmentScorer:
    """Centred prefix sums of ``(N_t, T)`` frame terms (``dyn`` of frames 0, 1 unused).
    ``obs=None``: ``obs ≡ 0`` (k = D); zeros, not the cumsum of a constant, which XLA would
    constant-fold at every compile (seconds for (4, 16, 2048), issue 57)."""
    T = dyn.shape[1]
    dyn_off = jnp.mean(dyn[:, 2:], axis=1) if T > 2 else jnp.zeros(dyn.shape[:1], dyn.dtype)
    zeros = jnp.zeros((dyn.shape[0], 1), dyn.dtype)
    cum_dyn = jnp.concatenate([zeros, jnp.cumsum(dyn - dyn_off[:, None], axis=1)], axis=1)
    if obs is None:
        obs_off = jnp.zeros(dyn.shape[:1], dyn.dtype)
        cum_obs = jnp.zeros((dyn.shape[0], T + 1), dyn.dtype)
    else:
        obs_off = jnp.mean(obs, axis=1)
        cum_obs = jnp.concatenate([zeros, jnp.cumsum(obs - obs_off[:, None], axis=1)], axis=1)
    return SegmentScorer(
        init=init, cum_dyn=cum_dyn, cum_obs=cum_obs, dyn_offset=dyn_off, obs_offset=obs_off
    )


def batch_scores_impl(textons: Texton, Y: Array, check: bool = True) -> SegmentScorer:
    """The :class:`SegmentScorer` of every sequence of ``Y (S, T, D)`` (arrays with a leading
    ``S`` axis), equal to ``vmap(segment_scores)`` to rounding.

    The frame terms are computed once on the ``S·T`` frames laid end to end, so the blocked
    kernel runs on full blocks (under ``vmap`` every block holds ``S`` sequences' frames and
    falls out of cache: about twice slower on the 14 salsa clips). Terms that would reach
    across two sequences (``dyn`` at frames 0 and 1, ``init`` at frame ``T − 1``) are never
    part of a segment score; they are set to the values the per-sequence kernel gives them
    (0 and ``−inf``) before the prefix sums, which are taken per sequence. ``check=False``
    leaves out the in-program NaN/inf check of ``Y`` (a host callback, which keeps the program
    out of the persistent compilation cache) for callers that checked it eagerly.
    """
    S, T, D = Y.shape
    flat = Y.reshape(S * T, D)
    block = block_frames(None, textons, flat)
    dyn, obs, init = frame_terms_impl(textons, flat, min(block, S * T), with_init=True, check=check)

    def per_seq(a: Array) -> Array:  # (N, S·T) -> (S, N, T)
        return jnp.moveaxis(a.reshape(a.shape[0], S, T), 1, 0)

    dyn, obs, init = per_seq(dyn), per_seq(obs), per_seq(init)
    dyn = dyn.at[:, :, : min(2, T)].set(0.0)
    init = init.at[:, :, T - 1].set(-jnp.inf)
    return jax.vmap(scorer_from_terms)(dyn, obs if has_residual(textons, Y) else None, init)


_segment_scores_jit = eqx.filter_jit(_segment_scores_impl)
