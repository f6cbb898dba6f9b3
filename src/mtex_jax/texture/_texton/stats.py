"""Summable sufficient statistics of textons (design §2): frame moments, the observation subspace,
and the second-order dynamics statistics, each computable per clip and added across clips."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from .checks import (
    as_float_array,
    check_finite,
    check_mask,
    check_positive,
    check_state_dim,
    eigh_desc,
    error_if_nonfinite,
    sym,
)

# --------------------------------------------------------------------------------------------
# Sufficient statistics
# --------------------------------------------------------------------------------------------


class _Summable(eqx.Module):
    """Mixin: statistics add field by field (``a + b``, ``sum([...])``, ``lax.psum``)."""

    def __add__(self, other: Any) -> Any:
        if not isinstance(other, type(self)):
            return NotImplemented
        return jax.tree.map(jnp.add, self, other)

    def __radd__(self, other: Any) -> Any:
        if isinstance(other, int | float) and other == 0:  # support builtin sum()
            return self
        return NotImplemented


class FrameStats(_Summable):
    """Pass-1 sufficient statistics: sums over the frames used by a texton.

    They determine ``μ``, ``C`` and ``σ²`` (:func:`subspace_from_stats`) and add across
    segments, sequences and devices (``stats_a + stats_b`` or ``jax.lax.psum``). The sums are
    uncentred, so the scatter ``Σ y yᵀ − n μ μᵀ`` loses precision when ``|μ|`` is large
    compared with the spread of the frames; in float32 centre the features first (the package's
    feature map z-scores them).

    Attributes:
        count: ``()`` number of frames ``n``.
        sum_y: ``(D,)`` ``Σ y_t``.
        sum_yy: ``(D, D)`` ``Σ y_t y_tᵀ``.
    """

    count: Float[Array, ""]
    sum_y: Float[Array, " D"]
    sum_yy: Float[Array, "D D"]


class Subspace(eqx.Module):
    """Observation subspace of a texton (design §2 steps 1–2), the result of pass 1.

    Attributes:
        mu: ``(D,)`` mean of the frames.
        C: ``(D, k)`` top-``k`` eigenvectors of the scatter matrix (orthonormal columns;
            sign convention: the entry of largest magnitude of every column is positive).
        state_var: ``(k,)`` variances of the states ``x = Cᵀ(y − μ)`` (eigenvalues / n).
        sigma2: ``()`` mean discarded eigenvalue per dimension (floored), the residual
            variance ``σ²``.
    """

    mu: Float[Array, " D"]
    C: Float[Array, "D k"]
    state_var: Float[Array, " k"]
    sigma2: Float[Array, ""]


class DynamicsStats(_Summable):
    """Pass-2 sufficient statistics in state space ``x_t = Cᵀ(y_t − μ)`` (``C``, ``μ`` fixed).

    Sums run over *valid* terms: a triple is valid at ``t`` if frames ``t−2, t−1, t`` carry
    the same non-negative segment id (and are consecutive frames of one sequence); a pair is
    valid at ``t`` if ``t−1, t`` are; a segment start is the first frame ``b`` of a run of
    equal non-negative ids that has at least two frames. All fields add across segments,
    sequences and devices.

    Attributes:
        n3: ``()`` number of valid triples ``N``.
        sum_z: ``(3k,)`` ``Σ z_t`` with ``z_t = [x_t; x_{t−1}; x_{t−2}]``.
        sum_zz: ``(3k, 3k)`` ``Σ z_t z_tᵀ``.
        n2: ``()`` number of valid consecutive pairs.
        sum_p: ``(2k,)`` ``Σ p_t`` with ``p_t = [x_{t−1}; x_t]``.
        sum_pp: ``(2k, 2k)`` ``Σ p_t p_tᵀ``.
        n_start: ``()`` number of segment starts.
        sum_s: ``(2k,)`` ``Σ s_b`` with ``s_b = [x_b; x_{b+1}]`` at segment starts.
        sum_ss: ``(2k, 2k)`` ``Σ s_b s_bᵀ``.
        sum_uu: ``(3, 3)`` lag Gram of the centred frames ``u_t = y_t − μ`` over the valid
            triples, ``sum_uu[a, b] = Σ u_{t−a}·u_{t−b}``; with the traces of the ``sum_zz``
            blocks it gives the residual's lag Gram (the ``"residual"`` observation model).
    """

    n3: Float[Array, ""]
    sum_z: Float[Array, " k3"]
    sum_zz: Float[Array, "k3 k3"]
    n2: Float[Array, ""]
    sum_p: Float[Array, " k2"]
    sum_pp: Float[Array, "k2 k2"]
    n_start: Float[Array, ""]
    sum_s: Float[Array, " k2"]
    sum_ss: Float[Array, "k2 k2"]
    sum_uu: Float[Array, "3 3"]


# --------------------------------------------------------------------------------------------
# Pass 1: frame statistics and the observation subspace
# --------------------------------------------------------------------------------------------


def frame_stats(Y: ArrayLike, mask: ArrayLike | None = None) -> FrameStats:
    """Pass-1 sums over the frames of a texton (design §2 steps 1–2), summable.

    Args:
        Y: observations ``(T, D)`` or a batch of sequences ``(S, T, D)``.
        mask: segment ids with Y's leading shape (``(T,)`` or ``(S, T)``), ``-1`` for frames
            not used; a boolean mask means ``True`` = used. ``None`` uses every frame.

    Returns:
        :class:`FrameStats` with ``count = Σ w_t``, ``sum_y = Σ w_t y_t``,
        ``sum_yy = Σ w_t y_t y_tᵀ`` where ``w_t = [mask_t >= 0]``.

    Raises:
        ValueError: on wrong shapes/dtypes or NaN/inf in ``Y``.
    """
    Y, mask = check_fit_inputs(Y, mask)
    return _frame_stats_jit(Y, mask)


def check_fit_inputs(Y: Any, mask: Any) -> tuple[Array, Array]:
    Y = as_float_array("Y", Y, (2, 3), "(T, D) or (S, T, D)")
    if Y.shape[-1] < 1:
        raise ValueError(f"Y must have at least one column (D >= 1), got shape {Y.shape}")
    check_finite("Y", Y)
    mask = check_mask(mask, tuple(Y.shape[:-1]))
    return Y, mask


def frame_stats_impl(Y: Array, mask: Array, check: bool = True) -> FrameStats:
    if check:  # an in-program check is a host callback: uncacheable (see fit_all)
        Y = error_if_nonfinite(Y, "Y")
    D = Y.shape[-1]
    Yf = Y.reshape(-1, D)
    w = (mask.reshape(-1) >= 0).astype(Y.dtype)
    Yw = Yf * w[:, None]
    return FrameStats(count=jnp.sum(w), sum_y=jnp.sum(Yw, axis=0), sum_yy=Yw.T @ Yf)


_frame_stats_jit = eqx.filter_jit(frame_stats_impl)


def subspace_from_stats(
    stats: FrameStats, *, state_dim: int, sigma2_floor: float = 1e-6
) -> Subspace:
    """Mean, observation matrix and residual variance from pass-1 sums (design §2 steps 1–2).

    ``μ = Σy / n``; scatter ``S = Σ y yᵀ − n μ μᵀ`` with eigenvalues ``λ_1 ≥ … ≥ λ_D``;
    ``C`` = top-``k`` eigenvectors (the left singular vectors of the centred frames);
    ``σ² = max(Σ_{j>k} λ_j / (n (D − k)), sigma2_floor)`` (``sigma2_floor`` when ``k = D``).
    With ``n = 0`` the result is finite (``μ = 0``, ``C`` = ``k`` unit vectors).

    Args:
        stats: pass-1 sums (possibly summed over sequences/devices).
        state_dim: ``k``, ``1 <= k <= D``.
        sigma2_floor: absolute floor on ``σ²`` (units of ``y²``), ``> 0``.

    Returns:
        :class:`Subspace`.
    """
    D = int(stats.sum_y.shape[-1])
    k = check_state_dim(state_dim, D, tuple(stats.sum_yy.shape))
    floor = check_positive("sigma2_floor", sigma2_floor)
    return _subspace_jit(stats, k, floor)


def subspace_impl(stats: FrameStats, k: int, sigma2_floor: float) -> Subspace:
    D = stats.sum_y.shape[-1]
    n = jnp.maximum(stats.count, 1.0)
    mu = stats.sum_y / n
    S = sym(stats.sum_yy - n * jnp.outer(mu, mu))
    S = jnp.where(stats.count > 0, S, jnp.zeros_like(S))
    w, V = eigh_desc(S)
    w = jnp.maximum(w, 0.0)
    C = V[:, :k]
    if k < D:
        resid = jnp.sum(w[k:]) / (n * (D - k))
    else:
        resid = jnp.zeros((), S.dtype)
    sigma2 = jnp.maximum(resid, sigma2_floor)
    return Subspace(mu=mu, C=C, state_var=w[:k] / n, sigma2=sigma2.astype(S.dtype))


_subspace_jit = eqx.filter_jit(subspace_impl)


# --------------------------------------------------------------------------------------------
# Pass 2: state-space statistics
# --------------------------------------------------------------------------------------------


def dynamics_stats(Y: ArrayLike, mask: ArrayLike | None, subspace: Subspace) -> DynamicsStats:
    """Pass-2 sums in state space for a fixed subspace (design §2 step 3), summable.

    The states are ``x_t = Cᵀ(y_t − μ)``. Terms whose frames are not all inside one segment
    (same non-negative id, consecutive frames of one sequence) are dropped; the sequences of a
    batched ``(S, T, D)`` input never connect.

    Args:
        Y: ``(T, D)`` or ``(S, T, D)`` observations.
        mask: segment ids with Y's leading shape, ``-1`` = unused; ``None`` = each sequence is
            one segment.
        subspace: ``μ``, ``C`` (from :func:`subspace_from_stats` on the summed pass-1 stats).

    Returns:
        :class:`DynamicsStats`.
    """
    Y, mask = check_fit_inputs(Y, mask)
    if not isinstance(subspace, Subspace):
        raise ValueError(f"subspace must be a Subspace, got {type(subspace).__name__}")
    if subspace.mu.shape != (Y.shape[-1],):
        raise ValueError(
            f"subspace.mu has shape {subspace.mu.shape} but Y has D={Y.shape[-1]} columns"
        )
    return _dynamics_stats_jit(Y, mask, subspace)


def _valid_terms(ids: Int[Array, " T"]) -> tuple[Array, Array, Array]:
    """Masks of valid pairs (at t), triples (at t) and segment starts (at b), each ``(T,)``."""
    T = ids.shape[0]
    used = ids >= 0
    same_prev = jnp.concatenate([jnp.zeros((1,), bool), ids[1:] == ids[:-1]])
    pair = used & same_prev  # frames t-1, t in one segment
    triple = pair & jnp.concatenate([jnp.zeros((1,), bool), pair[:-1]])
    pair_next = jnp.concatenate([pair[1:], jnp.zeros((1,), bool)]) if T > 0 else pair
    start = used & ~same_prev & pair_next
    return pair, triple, start


def _dynamics_stats_seq(
    Y: Array,
    ids: Array,
    mu: Array,
    C: Array,
    max_starts: int | None = None,
    weights: Array | None = None,
) -> DynamicsStats:
    """Pass-2 sums of one sequence. The pair sums follow from the triple and start sums: the
    pairs ``(t−1, t)`` of a segment ``[b, e]`` are its triples' (``t >= b + 2``) and its start
    pair ``(b, b+1)``, so ``Σ p pᵀ = R (Σ z zᵀ)[:2k, :2k] Rᵀ + Σ s sᵀ`` with ``R`` swapping the
    two ``k``-blocks (one ``(2k)²`` GEMM over the frames fewer). ``max_starts`` (static): at
    most that many segments start in ``Y``; the start sums then use only those rows (another
    GEMM over the frames fewer). ``weights (T,)``: the triple at ``t`` counts ``weights[t]``
    times (``n3`` becomes ``Σ w``; the Student-t M-step), the starts once."""
    T = Y.shape[0]
    k = C.shape[1]
    dtype = Y.dtype
    _, triple, start = _valid_terms(ids)
    used = (ids >= 0)[:, None]
    U = jnp.where(used, Y - mu, 0.0)
    X = U @ C
    zero = jnp.zeros((), dtype)
    if T >= 3:
        Z = jnp.concatenate([X[2:], X[1:-1], X[:-2]], axis=1)
        w3 = triple[2:].astype(dtype)
        if weights is not None:
            w3 = w3 * weights[2:].astype(dtype)
        Zw = Z * w3[:, None]
        n3, sum_z, sum_zz = jnp.sum(w3), jnp.sum(Zw, 0), Zw.T @ Z
        lags = (U[2:], U[1:-1], U[:-2])
        sum_uu = jnp.stack(
            [jnp.stack([jnp.sum(w3 * jnp.sum(a * b, axis=1)) for b in lags]) for a in lags]
        )
    else:
        n3, sum_z, sum_zz = zero, jnp.zeros((3 * k,), dtype), jnp.zeros((3 * k, 3 * k), dtype)
        sum_uu = jnp.zeros((3, 3), dtype)
    if T >= 2:
        P = jnp.concatenate([X[:-1], X[1:]], axis=1)  # [x_{t-1}; x_t] for t = 1..T-1
        ws = start[:-1].astype(dtype)  # s_b = [x_b; x_{b+1}] for b = 0..T-2
        if max_starts is not None and max_starts < T - 1:
            (b,) = jnp.nonzero(start[:-1], size=max_starts, fill_value=0)
            Ps, wsb = P[b], ws[b] * (jnp.arange(max_starts) < jnp.sum(start[:-1]))
        else:
            Ps, wsb = P, ws
        Sw = Ps * wsb[:, None]
        n_s, sum_s, sum_ss = jnp.sum(wsb), jnp.sum(Sw, 0), Sw.T @ Ps
        if T >= 3:  # the pairs: the triples' last two frames (swapped) and the starts
            swap = jnp.concatenate([jnp.arange(k, 2 * k), jnp.arange(k)])
            n2 = n3 + n_s
            sum_p = sum_z[: 2 * k][swap] + sum_s
            sum_pp = sum_zz[: 2 * k, : 2 * k][swap][:, swap] + sum_ss
        else:
            n2, sum_p, sum_pp = n_s, sum_s, sum_ss
    else:
        n2, sum_p, sum_pp = zero, jnp.zeros((2 * k,), dtype), jnp.zeros((2 * k, 2 * k), dtype)
        n_s, sum_s, sum_ss = n2, sum_p, sum_pp
    return DynamicsStats(
        n3=n3,
        sum_z=sum_z,
        sum_zz=sum_zz,
        n2=n2,
        sum_p=sum_p,
        sum_pp=sum_pp,
        n_start=n_s,
        sum_s=sum_s,
        sum_ss=sum_ss,
        sum_uu=sum_uu,
    )


def dynamics_stats_impl(
    Y: Array,
    mask: Array,
    subspace: Subspace,
    max_starts: int | None = None,
    weights: Array | None = None,
    check: bool = True,
) -> DynamicsStats:
    if check:
        Y = error_if_nonfinite(Y, "Y")
    mu = subspace.mu.astype(Y.dtype)
    C = subspace.C.astype(Y.dtype)
    if Y.ndim == 2:
        return _dynamics_stats_seq(Y, mask, mu, C, max_starts, weights)
    per_seq = jax.vmap(_dynamics_stats_seq, in_axes=(0, 0, None, None, None, 0))(
        Y, mask, mu, C, None, weights
    )
    return jax.tree.map(lambda x: jnp.sum(x, axis=0), per_seq)


_dynamics_stats_jit = eqx.filter_jit(dynamics_stats_impl)
