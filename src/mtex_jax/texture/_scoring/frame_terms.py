"""Per-frame log-density terms of every texton on every frame (design §3): the blocked kernel
used by learning (the per-texton reference kernel is in ``_frame_terms_ref``)."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jax import lax
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float

from .._texton.checks import (
    LOG_2PI,
    UNROLL_MAX_K,
    check_obs,
    check_positive_int,
    error_if_nonfinite,
    float_dtype,
    psd_cholesky,
)
from .._texton.texton import Texton, check_texton
from .frame_terms_full import full_block_frames, full_terms
from .workers import check_workers, n_parts, run_row_blocks

# --------------------------------------------------------------------------------------------
# Per-frame terms and prefix-sum segment scores (design §3)
# --------------------------------------------------------------------------------------------


# Target size of one time block's projections (all textons), in bytes: small enough to stay in
# the (per-core) L2 cache between the projection GEMM and the passes that re-read it.
_BLOCK_BYTES = 2 * 2**20
# The same for k > UNROLL_MAX_K: the sums over the state index are then vectorised passes
# over (N_t, k, block) arrays, and per-block overhead, not the cache, sets the pace. With
# k = D = 54 on 49,708 frames (2 cores), segment scores of 32 / 64 / 305 textons took 2.04 /
# 4.31 / 26.7 s with the 2 MiB blocks (142 / 62 / 14 frames) and 1.29 / 2.48 / 18.3 s with
# blocks of 1022 / 510 / 126 frames, which this budget gives.
_BLOCK_BYTES_WIDE = 16 * 2**20
# Largest state dimension whose sums over the state index are unrolled in the kernel.


def block_frames(block_size: Any, textons: Texton, Y: Array) -> int:
    """Frames per time block of :func:`frame_terms` (``block_size=None``: from the cache size).

    The automatic choice keeps a block's ``(N_t·(k+1), block + 2)`` projections (in the
    promoted dtype of ``Y`` and the stacked ``textons``) near ``_BLOCK_BYTES`` (for
    ``k > UNROLL_MAX_K``: ``_BLOCK_BYTES_WIDE``) with ``block + 2`` a multiple of 16
    (GEMM-friendly), between 14 and 1022. Full-dimensional textons (``k = D``):
    :func:`~._frame_terms_full.full_block_frames`.
    """
    if block_size is None:
        itemsize = jnp.dtype(float_dtype(Y, textons.mu)).itemsize
        n, k = textons.n_textons, textons.state_dim
        if k == textons.obs_dim:  # full-dimensional textons: the kernel of _frame_terms_full
            return full_block_frames(n, k, itemsize)
        budget = _BLOCK_BYTES if k <= UNROLL_MAX_K else _BLOCK_BYTES_WIDE
        cols = budget // max(n * (k + 1) * itemsize, 1)
        return min(max(16 * (cols // 16), 16), 1024) - 2
    return check_positive_int("block_size", block_size)


def _whitened_coords(tex: Texton, ybar: Array) -> dict[str, Array]:
    """Per-texton constants of the whitened-state form of the frame terms (one texton).

    With the SVD ``B = U diag(s) Vᵀ`` (so ``Q = B Bᵀ = U diag(s²) Uᵀ``) and the state
    coordinates ``z_t = diag(s)⁻¹ Uᵀ x_t = Ctᵀ (y_t − μ)``, ``Ct = C U diag(s)⁻¹``:

    .. code-block:: text

        ‖B⁻¹(x_t − A1 x_{t−1} − A2 x_{t−2} − d)‖² = ‖z_t + F1 z_{t−1} + F2 z_{t−2} − e‖²
        F_j = −diag(s)⁻¹ Uᵀ A_j U diag(s),   e = diag(s)⁻¹ Uᵀ d
        ‖x_t‖² = ‖diag(s) z_t‖²

    (``B⁻¹ = V diag(s)⁻¹ Uᵀ`` and ``V`` is orthogonal, so it drops out of the norm).

    Args:
        tex: one texton (already in the working dtype).
        ybar: ``(D,)`` mean frame ``ȳ`` the frames are centred with.

    Returns:
        Dict with ``P (k+1, D+1)``: rows ``0…k−1`` are ``[Ctᵀ | −Ctᵀ(μ − ȳ)]`` and row ``k`` is
        ``[(μ − ȳ)ᵀ | 0]``, so that ``P [y_t − ȳ; 1] = [z_t; (y_t − ȳ)·(μ − ȳ)]``;
        ``F (2k, k+1)`` ``= [F1; F2]`` with a zero last column (it multiplies the ``y·μ``
        row); ``e (k,)``; ``s2 (k,)`` ``= s²``; and the scalars ``mcmc = ‖μ − ȳ‖²``,
        ``dyn_const = k log 2π + log|Q|`` and ``obs_const = (D−k) log 2πσ²``; ``U``, ``s``
        (for :func:`_init_coords`).
    """
    D, k = tex.C.shape
    U, s, _ = jnp.linalg.svd(tex.B)
    Ct = (tex.C @ U) / s
    mc = tex.mu - ybar
    ratio = s[None, :] / s[:, None]
    F = jnp.concatenate([-(U.T @ tex.A1 @ U) * ratio, -(U.T @ tex.A2 @ U) * ratio], axis=0)
    zero = jnp.zeros((1,), mc.dtype)
    return dict(
        P=jnp.concatenate(
            [
                jnp.concatenate([Ct.T, -(mc @ Ct)[:, None]], axis=1),
                jnp.concatenate([mc, zero])[None, :],
            ],
            axis=0,
        ),
        F=jnp.concatenate([F, jnp.zeros((2 * k, 1), F.dtype)], axis=1),
        e=(U.T @ tex.d) / s,
        s2=s * s,
        mcmc=mc @ mc,
        dyn_const=k * LOG_2PI + 2.0 * jnp.sum(jnp.log(jnp.abs(jnp.diagonal(tex.B)))),
        obs_const=(D - k) * (LOG_2PI + jnp.log(tex.sigma2)),
        U=U,
        s=s,
    )


def _init_coords(tex: Texton, U: Array, s: Array) -> dict[str, Array]:
    """Constants of the initial-state term in whitened coordinates (one texton).

    With ``S0 = L0 L0ᵀ`` and ``x = U diag(s) z``:
    ``L0⁻¹([x_b; x_{b+1}] − m0) = E0 z_b + E1 z_{b+1} − L0⁻¹ m0`` with
    ``E_i = L0⁻¹[:, ik:(i+1)k] U diag(s)``.

    ``L0⁻¹`` is lower triangular, so the first ``k`` rows of ``E1`` are zero: only its last
    ``k`` rows are kept.

    Returns:
        ``E (3k, k+1)`` ``= [E0; E1[k:]]`` with a zero last column, ``init_c (2k,)``
        ``= L0⁻¹ m0`` and ``init_const = 2k log 2π + log|S0|``.
    """
    k = tex.C.shape[-1]
    dt = tex.mu.dtype
    L0 = psd_cholesky(tex.S0, jnp.zeros((), dt))
    L0inv = jsl.solve_triangular(L0, jnp.eye(2 * k, dtype=dt), lower=True)
    Us = U * s[None, :]
    E = jnp.concatenate([L0inv[:, :k] @ Us, L0inv[k:, k:] @ Us], axis=0)
    return dict(
        E=jnp.concatenate([E, jnp.zeros((3 * k, 1), dt)], axis=1),
        init_c=L0inv @ tex.m0,
        init_const=2 * k * LOG_2PI + 2.0 * jnp.sum(jnp.log(jnp.diagonal(L0))),
    )


def frame_coefs(
    textons: Texton, ybar: Array, with_init: bool
) -> tuple[Array, dict[str, Array], dict[str, Array] | None]:
    """``(ȳ, cw, ic)``: the per-texton constants of :func:`_whitened_coords` and (with
    ``with_init``) :func:`_init_coords` for frames centred by ``ybar (D,)``, stacked along the
    texton axis; computed once for several calls of :func:`frame_terms_impl` (``coefs``) on
    the same textons (any ``ȳ`` gives the same terms; one near the frames' mean keeps the
    rounding small)."""
    dtype = float_dtype(ybar, textons.mu)
    ybar = ybar.astype(dtype)
    textons = jax.tree.map(lambda a: a.astype(dtype), textons)
    cw = jax.vmap(_whitened_coords, in_axes=(0, None))(textons, ybar)
    ic = None
    if with_init:  # per texton (lax.map): the Cholesky factors of S0 are not one batched call
        ic = lax.map(lambda a: _init_coords(*a), (textons, cw["U"], cw["s"]))
    return ybar, cw, ic


def has_residual(textons: Texton, Y: Array) -> bool:
    """Whether the textons' state is smaller than the observation (``k < D``): then ``obs``
    holds the residual's terms; full-dimensional textons (``k = D``) have none, and their
    kernel (``full_terms``) returns ``obs ≡ 0``."""
    return textons.C.shape[-1] < Y.shape[-1]


def frame_terms_impl(
    textons: Texton,
    Y: Array,
    block: int,
    with_init: bool = False,
    out_rows: int | None = None,
    check: bool = True,
    coefs: tuple[Array, dict[str, Array], dict[str, Array] | None] | None = None,
    n_active: Array | None = None,
) -> tuple[Array, ...]:
    """Time-blocked per-frame terms of a stack of textons, ``(N_t, T)`` each (see frame_terms).

    Block ``i`` is the window of frames ``w_i … w_i + W − 1`` (``W = min(block + 2, T)``,
    ``w_i = min(i·(W − 2), T − W)``, so the last window may overlap the previous one): it gives
    ``obs`` on the whole window and ``dyn`` on its last ``W − 2`` frames (the first two are the
    lags). The windows cover every frame; overlapping frames are written twice with the same
    values. Memory besides the outputs: ``O(N_t · k · W)`` per block.

    ``with_init``: also the initial-state terms ``init (N_t, T)`` of :func:`init_terms`
    (``init[:, b]`` on the window's first ``W − 1`` frames, ``−inf`` at the last frame), from
    the same projections: ``[E0; E1[k:]]`` is stacked under ``[F1; F2]`` in the per-texton
    GEMM.

    ``out_rows`` (not with ``with_init``): ``dyn`` and ``obs`` get ``out_rows >= N_t`` rows, of
    which the first ``N_t`` are computed and the others are 0 (the rest of a stack, to be
    filled in place by :func:`_merge_rows`). ``check=False`` skips the in-trace NaN/inf check
    of ``Y`` (for callers that checked it eagerly). ``coefs``: :func:`frame_coefs` of
    ``textons`` (with the same ``with_init``), computed by the caller once for many calls.
    ``n_active`` (traced, full-dimensional textons only): only the first ``n_active`` rows are
    needed (see :func:`~._frame_terms_full.full_terms`).
    """
    if check:
        Y = error_if_nonfinite(Y, "Y")
    dtype = float_dtype(Y, textons.mu)
    Y = Y.astype(dtype)
    textons = jax.tree.map(lambda a: a.astype(dtype), textons)
    T, D = Y.shape
    n, _, k = textons.C.shape
    if coefs is None:
        coefs = frame_coefs(textons, jnp.mean(Y, axis=0), with_init)
    ybar, cw, ic = coefs
    # rows i(k+1) … i(k+1)+k of P are texton i's projection onto [z_t; (y_t − ȳ)·(μ_i − ȳ)]
    P = cw["P"].reshape(n * (k + 1), D + 1)
    F, e, s2 = cw["F"], cw["e"], cw["s2"]
    if with_init:  # [F1; F2; E0; E1[k:]]: one small GEMM per texton for both
        assert ic is not None
        F = jnp.concatenate([F, ic["E"]], axis=1)
        init_c, init_const = ic["init_c"], ic["init_const"][:, None]
    if not has_residual(textons, Y):  # the stacked-lag kernel
        return full_terms(cw, ic, Y - ybar, block, out_rows, n_active, textons.dof)
    dyn_const = cw["dyn_const"][:, None]
    obs_const = cw["obs_const"][:, None]
    mcmc = cw["mcmc"][:, None]
    sigma2 = textons.sigma2[:, None]
    model = textons.observation
    W = min(block + 2, T)
    step = max(W - 2, 1)
    n_blocks = -(-max(T - 2, 1) // step)
    ones = jnp.ones((W, 1), dtype)

    def window_terms(w0: Array) -> tuple[Array | None, Array, Array | None]:
        Yw = lax.dynamic_slice_in_dim(Y, w0, W, axis=0) - ybar  # (W, D) centred frames
        # all textons at once: (N_t(k+1), D+1) × (W, D+1)ᵀ
        Z = lax.dot_general(P, jnp.concatenate([Yw, ones], axis=1), (((1,), (1,)), ((), ())))
        Z = Z.reshape(n, k + 1, W)
        # sums over the state index unrolled (k <= UNROLL_MAX_K): each becomes one fused
        # elementwise pass that reads the (shifted) slices of Z and FZ in place, with no
        # reduction copies; for larger k one vectorised reduction each (the unrolled program
        # would take minutes to compile)
        unroll = k <= UNROLL_MAX_K
        x2: Array | float = 0.0
        if unroll:
            for j in range(k):
                x2 = x2 + s2[:, j, None] * Z[:, j] * Z[:, j]
        else:
            x2 = jnp.einsum("nj,njt->nt", s2, Z[:, :k] * Z[:, :k])
        r2 = jnp.maximum(jnp.sum(Yw * Yw, axis=1) - 2.0 * Z[:, k] + mcmc - x2, 0.0)
        obs = -0.5 * (obs_const + r2 / sigma2) if D > k else jnp.zeros((n, W), dtype)
        if W < 2:
            return None, obs, None
        FZ = jnp.einsum("njm,nmt->njt", F, Z)  # [F1; F2] z_t: one small GEMM per texton
        init = None
        if with_init:  # ‖E0 z_b + E1 z_{b+1} − L0⁻¹m0‖², b = w0 … w0 + W − 2
            u2: Array | float = 0.0
            if unroll:
                for j in range(2 * k):  # rows j < k of E1 are zero
                    u = FZ[:, 2 * k + j, :-1] - init_c[:, j, None]
                    if j >= k:
                        u = u + FZ[:, 3 * k + j, 1:]
                    u2 = u2 + u * u
            else:
                u = FZ[:, 2 * k : 4 * k, :-1] - init_c[:, :, None]
                u = u.at[:, k:].add(FZ[:, 4 * k : 5 * k, 1:])
                u2 = jnp.sum(u * u, axis=1)
            init = -0.5 * (init_const + jnp.asarray(u2))
        if W < 3:
            return None, obs, init
        w2: Array | float = 0.0
        if unroll:
            for j in range(k):
                w = Z[:, j, 2:] + FZ[:, j, 1:-1] + FZ[:, k + j, :-2] - e[:, j, None]
                w2 = w2 + w * w
        else:
            w = Z[:, :k, 2:] + FZ[:, :k, 1:-1] + FZ[:, k : 2 * k, :-2] - e[:, :, None]
            w2 = jnp.sum(w * w, axis=1)
        dyn_w = -0.5 * (dyn_const + w2)
        extra = model.window_dyn_terms(Yw, Z, s2, mcmc, obs, k)
        if extra is not None:  # the observation model's own terms (design §10.3)
            dyn_w = dyn_w + extra
        return dyn_w, obs, init

    def body(i: Array, carry: tuple[Array, ...]) -> tuple[Array, ...]:
        dyn, obs, *init = carry
        w0 = jnp.minimum(i * step, T - W)
        dyn_w, obs_w, init_w = window_terms(w0)
        if dyn_w is not None:
            dyn = lax.dynamic_update_slice_in_dim(dyn, dyn_w, w0 + 2, axis=1)
        obs = lax.dynamic_update_slice_in_dim(obs, obs_w, w0, axis=1)
        if init_w is not None:
            init = [lax.dynamic_update_slice_in_dim(init[0], init_w, w0, axis=1)]
        return dyn, obs, *init

    zeros = jnp.zeros((n if out_rows is None else out_rows, T), dtype)  # dyn[:, :2] stays 0
    carry: tuple[Array, ...] = (zeros, zeros)
    if with_init:  # init[:, T−1] stays −inf (no segment starts at the last frame)
        carry = (*carry, jnp.full((n, T), -jnp.inf, dtype))
    return lax.fori_loop(0, n_blocks, body, carry)


frame_terms_jit = eqx.filter_jit(frame_terms_impl)


def frame_terms(
    textons: Texton,
    Y: ArrayLike,
    *,
    block_size: int | None = None,
    workers: int | None = None,
) -> tuple[Float[Array, "*n T"], Float[Array, "*n T"]]:
    """Per-frame log-density terms of every texton on every frame (design §3).

    For texton ``i`` with ``x_t = C_iᵀ(y_t − μ_i)``:

    .. code-block:: text

        dyn[i, t] = log N(x_t; A1 x_{t−1} + A2 x_{t−2} + d, Q)      t >= 2   (MT-10)
                  = −½ (k log 2π + log|Q| + ‖B⁻¹(x_t − A1 x_{t−1} − A2 x_{t−2} − d)‖²)
        dyn[i, 0] = dyn[i, 1] = 0
        obs[i, t] = log N(r_t; 0, σ² I_{D−k})                                (MT-11)
                  = −½ ((D−k) log 2πσ² + ‖r_t‖² / σ²),
                    ‖r_t‖² = max(‖y_t − μ‖² − ‖x_t‖², 0)

    (``r_t`` is the residual outside the texton's subspace; ``obs = 0`` when ``k = D``.)
    For a texton with the residual AR(2) (``ResidualObservation``) the residual of frames
    ``t >= b + 2`` is scored by its AR(2) instead of white noise, and the difference goes into
    ``dyn``:

    .. code-block:: text

        dyn[i, t] += log N(e_t; 0, s_r² I_{D−k}) − obs[i, t],   e_t = r_t − a₁ r_{t−1} − a₂ r_{t−2}

    so that a segment's score ``init(b) + Σ_{b+2..e} dyn + Σ_{b..e} obs`` keeps its prefix-sum
    form: white noise on its first two frames, the AR(2) on the others.

    Implementation (default): each texton's state is used in whitened coordinates
    ``z_t = diag(s)⁻¹ Uᵀ x_t`` from the SVD ``B = U diag(s) Vᵀ``, in which the whitened
    residual is ``z_t + F1 z_{t−1} + F2 z_{t−2} − e`` (``F_j = −diag(s)⁻¹ Uᵀ A_j U diag(s)``,
    ``e = diag(s)⁻¹ Uᵀ d``) and ``‖x_t‖² = ‖diag(s) z_t‖²``: two ``k × k`` products per frame
    instead of three, and a diagonal one for the residual. The frames are processed in time
    blocks of ``block_size`` frames (plus the two preceding ones): one GEMM projects the block
    onto all textons' ``[z_t; y_t·μ]`` at once, ``(N_t(k+1), D+1) × (D+1, block+2)`` (offsets
    folded in through a constant-1 input row), so ``Y`` is read once and the projections stay
    in cache; then one small GEMM per texton gives ``[F1; F2] z`` and fused elementwise passes
    form the shifted sums, squares and the residual term. Full-dimensional textons
    (``k = D``, no residual) use three GEMMs per block of all textons' stacked rows with the
    block's lagged frames instead (``_frame_terms_full``). Exact (no approximation): equal to
    the direct formulas up to rounding.

    Args:
        textons: a stack of ``N_t`` textons (or a single texton).
        Y: observations ``(T, D)``.
        block_size: frames per time block (static); ``None`` chooses it so that one block's
            projections take about 2 MB (62 frames for 246 textons with k = 15 in float64).
            Memory ``O(N_t · k · block_size)`` besides the outputs.
        workers: concurrent executions of an eager call of the blocked kernel on the CPU: the
            textons are split into that many blocks, each
            computed by one execution started from its own host thread, and the rows are
            assembled in place (XLA:CPU runs the small GEMMs and elementwise passes of one
            execution on one core). ``None``: the number of cores available to the process
            when the call has at least 2²⁰ texton-frames, else 1. Under a trace (inside
            ``jit``/``grad``/``vmap``) the call is always one computation. Results equal those
            of ``workers=1`` up to rounding; the blocks' own outputs need ``(1 − 1/workers)``
            times the outputs' memory on top, until assembled.

    Returns:
        ``(dyn, obs)``, each ``(N_t, T)`` (``(T,)`` for a single texton), in the promoted
        floating dtype of ``Y`` and the textons.

    Raises:
        ValueError: if ``Y`` is not ``(T, D)`` with the textons' ``D``, or contains NaN/inf
            (checked eagerly when ``Y`` is concrete, by ``eqx.error_if`` under a trace), or if
            ``block_size``/``workers`` is not a positive int. (The per-texton algorithm of
            ``_scoring/frame_terms_ref.py`` is an independent implementation of the same
            terms, the tests' reference.)
    """
    textons = check_texton("textons", textons)
    Y = check_obs("Y", Y, textons.obs_dim)
    workers = check_workers(workers)
    single = not textons.is_stacked
    if single:
        textons = jax.tree.map(lambda a: a[None], textons)
    block = min(block_frames(block_size, textons, Y), Y.shape[0])
    parts = n_parts(workers, textons, Y)
    if parts > 1:
        dyn, obs = run_row_blocks(
            lambda piece, rows: frame_terms_jit(piece, Y, block, out_rows=rows, check=False),
            textons,
            parts,
        )
    else:  # a concrete Y has been checked for NaN/inf eagerly
        dyn, obs = frame_terms_jit(textons, Y, block, check=isinstance(Y, Tracer))
    if single:
        return dyn[0], obs[0]
    return dyn, obs
