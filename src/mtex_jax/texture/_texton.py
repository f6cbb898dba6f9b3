"""Textons: second-order linear dynamic systems (SPEC §2, §3; MT §3.2 and App. B).

A texton ``i`` is the linear dynamic system

.. code-block:: text

    y_t     = mu + C x_t + w_t,                     w_t ~ N(0, sigma2 I_D)     (MT-11)
    x_{t+1} = A1 x_t + A2 x_{t-1} + d + B v_t,      v_t ~ N(0, I_k)            (MT-10)
    [x_1; x_2] ~ N(m0, S0)

with ``C`` a ``(D, k)`` matrix of orthonormal columns and ``Q = B Bᵀ`` (``B`` lower triangular).

This module provides

* :class:`Texton` (a single texton or a stack of ``N_t`` textons along a leading axis) and
  :func:`stack_textons`;
* the closed-form fit from sufficient statistics (:func:`fit_texton`, and the summable
  two-pass path :func:`frame_stats` → :func:`subspace_from_stats` → :func:`dynamics_stats` →
  :func:`texton_from_stats`);
* per-frame log-density terms for all textons at once (:func:`frame_terms`,
  :func:`init_terms`) and the O(1) prefix-sum segment scores (:func:`segment_scores`,
  :class:`SegmentScorer`) used by the segmentation DP;
* the direct per-segment reference :func:`segment_log_likelihood`, the exact marginal
  likelihood of the full LDS by a Kalman filter (:func:`exact_log_likelihood`) and
  noise-driven sampling (:func:`sample_texton`, MT Fig. 4).

Everything is a pure function of arrays; loops are ``lax.scan``/``lax.map``/``vmap``. The
library never changes global JAX configuration: computations run in the floating dtype of the
inputs (use ``jax.config.update("jax_enable_x64", True)`` yourself for float64).
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jax import lax
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float, Int

__all__ = [
    "DynamicsStats",
    "FrameStats",
    "SegmentScorer",
    "Subspace",
    "Texton",
    "companion_matrix",
    "dynamics_stats",
    "exact_log_likelihood",
    "fit_texton",
    "frame_stats",
    "frame_terms",
    "init_terms",
    "sample_texton",
    "segment_log_likelihood",
    "segment_scores",
    "spectral_radius",
    "stack_textons",
    "subspace_from_stats",
    "texton_from_stats",
]

_LOG_2PI = math.log(2.0 * math.pi)


# --------------------------------------------------------------------------------------------
# Texton container
# --------------------------------------------------------------------------------------------


class Texton(eqx.Module):
    """Parameters of one texton, or of a stack of ``N_t`` textons (SPEC §2).

    A single texton has the shapes below with an empty batch shape. A *stack* of ``N_t``
    textons (what the motion texture stores, see :func:`stack_textons`) has every field with
    one extra leading axis of length ``N_t``; ``textons[i]`` returns texton ``i``. All textons
    of a stack share ``D`` and ``k``.

    Attributes:
        mu: ``(*batch, D)`` observation mean ``μ``.
        C: ``(*batch, D, k)`` observation matrix with orthonormal columns.
        A1: ``(*batch, k, k)`` first-order dynamics matrix.
        A2: ``(*batch, k, k)`` second-order dynamics matrix.
        d: ``(*batch, k)`` dynamics offset.
        B: ``(*batch, k, k)`` lower-triangular Cholesky factor of the dynamics noise
            covariance, ``Q = B Bᵀ``.
        sigma2: ``(*batch,)`` observation noise variance ``σ²`` (per dimension).
        m0: ``(*batch, 2k)`` mean of the first two states ``[x_1; x_2]``.
        S0: ``(*batch, 2k, 2k)`` covariance of ``[x_1; x_2]``.
    """

    mu: Float[Array, "*batch D"]
    C: Float[Array, "*batch D k"]
    A1: Float[Array, "*batch k k"]
    A2: Float[Array, "*batch k k"]
    d: Float[Array, "*batch k"]
    B: Float[Array, "*batch k k"]
    sigma2: Float[Array, "*batch"]
    m0: Float[Array, "*batch k2"]
    S0: Float[Array, "*batch k2 k2"]

    def __check_init__(self) -> None:
        shapes = {name: getattr(getattr(self, name), "shape", None) for name in _TEXTON_FIELDS}
        if any(s is None for s in shapes.values()):
            return  # non-array leaves (e.g. jax.eval_shape sentinels): nothing to check
        mu_shape = tuple(shapes["mu"])  # type: ignore[arg-type]
        if len(mu_shape) < 1:
            raise ValueError(f"Texton.mu must have shape (*batch, D), got {mu_shape}")
        batch, D = mu_shape[:-1], mu_shape[-1]
        a1 = tuple(shapes["A1"])  # type: ignore[arg-type]
        if len(a1) != len(batch) + 2:
            raise ValueError(
                f"Texton.A1 must have shape (*batch, k, k) with batch={batch}, got {a1}"
            )
        k = a1[-1]
        expected = {
            "mu": (*batch, D),
            "C": (*batch, D, k),
            "A1": (*batch, k, k),
            "A2": (*batch, k, k),
            "d": (*batch, k),
            "B": (*batch, k, k),
            "sigma2": batch,
            "m0": (*batch, 2 * k),
            "S0": (*batch, 2 * k, 2 * k),
        }
        for name, exp in expected.items():
            got = tuple(shapes[name])  # type: ignore[arg-type]
            if got != tuple(exp):
                raise ValueError(
                    f"Texton.{name} must have shape {tuple(exp)} (batch={batch}, D={D}, "
                    f"k={k}), got {got}"
                )
        if k < 1 or k > D:
            raise ValueError(f"Texton state dimension k={k} must satisfy 1 <= k <= D={D}")

    # -- shape information --------------------------------------------------------------------

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading batch shape: ``()`` for one texton, ``(N_t,)`` for a stack."""
        return tuple(self.mu.shape[:-1])

    @property
    def is_stacked(self) -> bool:
        """Whether this holds a stack of textons (a leading texton axis)."""
        return len(self.batch_shape) > 0

    @property
    def n_textons(self) -> int:
        """Number of textons: ``N_t`` for a stack, ``1`` for a single texton."""
        return int(self.batch_shape[0]) if self.is_stacked else 1

    @property
    def state_dim(self) -> int:
        """State dimension ``k``."""
        return int(self.A1.shape[-1])

    @property
    def obs_dim(self) -> int:
        """Observation dimension ``D``."""
        return int(self.mu.shape[-1])

    # -- derived quantities -------------------------------------------------------------------

    @property
    def Q(self) -> Float[Array, "*batch k k"]:
        """Dynamics noise covariance ``Q = B Bᵀ``, ``(*batch, k, k)``."""
        return self.B @ jnp.swapaxes(self.B, -1, -2)

    def __getitem__(self, index: Any) -> Texton:
        """Index/slice a stack of textons along the leading texton axis."""
        if not self.is_stacked:
            raise TypeError("a single (unstacked) Texton cannot be indexed")
        return jax.tree.map(lambda x: x[index], self)


_TEXTON_FIELDS = ("mu", "C", "A1", "A2", "d", "B", "sigma2", "m0", "S0")


def stack_textons(textons: Sequence[Texton]) -> Texton:
    """Stack single textons into one :class:`Texton` with a leading axis of length ``N_t``.

    Args:
        textons: non-empty sequence of unstacked textons, all with the same ``D`` and ``k``.

    Returns:
        A stacked texton whose fields have shapes ``(N_t, ...)``.

    Raises:
        ValueError: if the sequence is empty, contains stacked textons or shapes differ.
    """
    textons = list(textons)
    if not textons:
        raise ValueError("stack_textons needs at least one texton, got an empty sequence")
    first = textons[0]
    for j, t in enumerate(textons):
        if not isinstance(t, Texton):
            raise ValueError(f"stack_textons: element {j} is {type(t).__name__}, not a Texton")
        if t.is_stacked:
            raise ValueError(
                f"stack_textons: element {j} is already stacked (batch {t.batch_shape})"
            )
        if (t.obs_dim, t.state_dim) != (first.obs_dim, first.state_dim):
            raise ValueError(
                f"stack_textons: element {j} has (D, k) = ({t.obs_dim}, {t.state_dim}), "
                f"element 0 has ({first.obs_dim}, {first.state_dim})"
            )
    return jax.tree.map(lambda *xs: jnp.stack(xs), *textons)


def companion_matrix(texton: Texton) -> Float[Array, "*batch k2 k2"]:
    """Companion matrix ``[[A1, A2], [I, 0]]`` of the second-order dynamics, ``(*batch, 2k, 2k)``.

    The stacked state ``[x_t; x_{t-1}]`` evolves as ``[x_{t+1}; x_t] = F [x_t; x_{t-1}] + ...``.
    """
    return _companion(texton.A1, texton.A2)


def spectral_radius(texton: Texton) -> Float[Array, "*batch"]:
    """Spectral radius of the companion matrix (``< 1`` means stable dynamics)."""
    return jnp.max(jnp.abs(jnp.linalg.eigvals(companion_matrix(texton))), axis=-1)


def _companion(A1: Array, A2: Array) -> Array:
    k = A1.shape[-1]
    batch = A1.shape[:-2]
    eye = jnp.broadcast_to(jnp.eye(k, dtype=A1.dtype), (*batch, k, k))
    zero = jnp.zeros_like(A1)
    top = jnp.concatenate([A1, A2], axis=-1)
    bottom = jnp.concatenate([eye, zero], axis=-1)
    return jnp.concatenate([top, bottom], axis=-2)


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
    """Observation subspace of a texton (SPEC §2 steps 1–2), the result of pass 1.

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


# --------------------------------------------------------------------------------------------
# Input validation (eager, before tracing)
# --------------------------------------------------------------------------------------------


def _float_dtype(*xs: Any) -> Any:
    dtype = jnp.result_type(*xs)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    return dtype


def _as_float_array(name: str, x: Any, ndims: tuple[int, ...], shape_doc: str) -> Array:
    if x is None:
        raise ValueError(f"{name} must be an array of shape {shape_doc}, got None")
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise ValueError(f"{name} must be real, got dtype {x.dtype}")
    if x.ndim not in ndims:
        raise ValueError(f"{name} must have shape {shape_doc}, got shape {tuple(x.shape)}")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(_float_dtype(x))
    return x


def _check_finite(name: str, x: Array) -> None:
    """Eagerly reject NaN/inf when ``x`` is concrete (inside a trace, ``eqx.error_if`` acts)."""
    try:
        xn = np.asarray(x)
    except jax.errors.TracerArrayConversionError:
        return
    finite = np.isfinite(xn)
    if not finite.all():
        bad = tuple(int(i) for i in np.argwhere(~finite)[0])
        raise ValueError(f"{name} (shape {xn.shape}) contains NaN or inf, first at index {bad}")


def _error_if_nonfinite(x: Array, name: str) -> Array:
    return eqx.error_if(x, ~jnp.all(jnp.isfinite(x)), f"{name} contains NaN or inf")


def _check_texton(name: str, texton: Any, stacked: bool | None = None) -> Texton:
    if not isinstance(texton, Texton):
        raise ValueError(f"{name} must be a Texton, got {type(texton).__name__}")
    if stacked is True and not texton.is_stacked:
        raise ValueError(f"{name} must be a stack of textons (leading axis), got a single one")
    if stacked is False and texton.is_stacked:
        raise ValueError(
            f"{name} must be a single texton, got a stack with batch shape {texton.batch_shape}"
            "; index it (textons[i]) or use jax.vmap"
        )
    if len(texton.batch_shape) > 1:
        raise ValueError(
            f"{name} must be a single texton or a 1-D stack, got batch shape {texton.batch_shape}"
        )
    return texton


def _check_obs(name: str, Y: Any, D: int, min_len: int = 1) -> Array:
    Y = _as_float_array(name, Y, (2,), "(T, D)")
    if Y.shape[1] != D:
        raise ValueError(f"{name} has shape {tuple(Y.shape)} but the texton expects D={D} columns")
    if Y.shape[0] < min_len:
        raise ValueError(f"{name} needs at least {min_len} frames, got shape {tuple(Y.shape)}")
    _check_finite(name, Y)
    return Y


def _check_mask(mask: Any, lead_shape: tuple[int, ...]) -> Array:
    if mask is None:
        return jnp.asarray(np.zeros(lead_shape, dtype=np.int32))
    try:  # concrete masks are normalised with numpy (no per-shape XLA compilation)
        mask_np = np.asarray(mask)
    except jax.errors.TracerArrayConversionError:
        mask_np = None
    if mask_np is not None:
        if mask_np.shape != lead_shape:
            raise ValueError(
                f"mask must have shape {lead_shape} (the leading shape of Y), got {mask_np.shape}"
            )
        if mask_np.dtype == np.bool_:
            return jnp.asarray(np.where(mask_np, 0, -1).astype(np.int32))
        if not np.issubdtype(mask_np.dtype, np.integer):
            raise ValueError(
                f"mask must be an integer segment-id array (-1 = unused frame) or boolean, "
                f"got dtype {mask_np.dtype}"
            )
        return jnp.asarray(mask_np.astype(np.int32))
    mask = jnp.asarray(mask)
    if tuple(mask.shape) != lead_shape:
        raise ValueError(
            f"mask must have shape {lead_shape} (the leading shape of Y), got {tuple(mask.shape)}"
        )
    if mask.dtype == jnp.bool_:
        return jnp.where(mask, 0, -1).astype(jnp.int32)
    if not jnp.issubdtype(mask.dtype, jnp.integer):
        raise ValueError(
            f"mask must be an integer segment-id array (-1 = unused frame) or boolean, "
            f"got dtype {mask.dtype}"
        )
    # one dtype for every caller, so that int32/int64 masks do not trigger a recompilation
    return mask.astype(jnp.int32)


def _check_positive(name: str, value: Any, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {bound}, got {value!r}")
    return v


def _check_state_dim(state_dim: Any, D: int, shape: tuple[int, ...]) -> int:
    if isinstance(state_dim, bool) or not isinstance(state_dim, int | np.integer):
        raise ValueError(f"state_dim must be an int, got {state_dim!r}")
    k = int(state_dim)
    if not 1 <= k <= D:
        raise ValueError(
            f"state_dim={k} must satisfy 1 <= state_dim <= D={D} (Y has shape {shape}); "
            "C needs k orthonormal columns in R^D"
        )
    return k


# --------------------------------------------------------------------------------------------
# Linear-algebra helpers
# --------------------------------------------------------------------------------------------


def _sym(M: Array) -> Array:
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def _fix_signs(V: Array) -> Array:
    """Flip eigenvector columns so that each column's largest-magnitude entry is positive."""
    idx = jnp.argmax(jnp.abs(V), axis=0)
    s = jnp.sign(V[idx, jnp.arange(V.shape[1])])
    s = jnp.where(s == 0, 1, s)
    return V * lax.stop_gradient(s)


@jax.custom_jvp
def _eigh_desc(S: Array) -> tuple[Array, Array]:
    """Eigen-decomposition of a symmetric matrix, eigenvalues in descending order.

    Sign convention of :func:`_fix_signs`. The JVP is the usual first-order perturbation
    formula ``dV = V (F ∘ Vᵀ dS V)``, ``F_ij = 1/(λ_j − λ_i)``, except that ``F_ij = 0`` for
    (numerically) equal eigenvalues, where the eigenvectors are not differentiable. This keeps
    gradients finite (e.g. for the discarded, degenerate part of a PCA).
    """
    w, V = jnp.linalg.eigh(S)
    return w[::-1], _fix_signs(V[:, ::-1])


@_eigh_desc.defjvp
def _eigh_desc_jvp(primals: tuple[Array], tangents: tuple[Array]) -> Any:
    (S,) = primals
    (dS,) = tangents
    w, V = _eigh_desc(S)
    M = V.T @ _sym(dS) @ V
    gap = w[None, :] - w[:, None]
    scale = jnp.max(jnp.abs(w))
    tol = 16 * jnp.finfo(S.dtype).eps * S.shape[0] * scale + jnp.finfo(S.dtype).tiny
    safe = jnp.abs(gap) > tol
    F = jnp.where(safe, 1.0 / jnp.where(safe, gap, 1.0), 0.0)
    return (w, V), (jnp.diagonal(M), V @ (F * M))


def _psd_cholesky(M: Array, floor: Array | float) -> Array:
    """Lower Cholesky factor of ``sym(M) + floor·I`` for a covariance estimate ``M``.

    ``M`` is positive semi-definite in exact arithmetic (a covariance estimate), so
    ``sym(M) + floor·I`` is positive definite for ``floor > 0``; if rounding nevertheless makes
    the factorisation fail (NaN), the factor of ``sym(M) + (floor + √eps·mean|diag M|)·I`` is
    returned instead. The extra jitter is far larger than the rounding error of a PSD
    covariance (``O(n·eps·‖M‖)``). If even that fails (heavy cancellation, e.g. float32 sums
    of a short segment), the jitter is raised to the Gershgorin bound
    ``max_i(Σ_{j≠i}|M_ij| − M_ii)``, which makes the matrix strictly diagonally dominant and
    hence positive definite, so the result is always finite (no LAPACK call is needed for it).
    """
    M = _sym(M)
    n = M.shape[-1]
    eye = jnp.eye(n, dtype=M.dtype)
    L = jnp.linalg.cholesky(M + floor * eye)
    finfo = jnp.finfo(M.dtype)
    scale = jnp.maximum(jnp.mean(jnp.abs(jnp.diagonal(M))), finfo.tiny)
    j2 = floor + jnp.sqrt(finfo.eps) * scale
    L2 = jnp.linalg.cholesky(M + j2 * eye)
    diag = jnp.diagonal(M)
    gersh = jnp.max(jnp.sum(jnp.abs(M), axis=-1) - jnp.abs(diag) - diag)
    L3 = jnp.linalg.cholesky(M + (j2 + jnp.maximum(gersh, 0.0) * (1 + 1e-3)) * eye)
    return jnp.where(jnp.all(jnp.isfinite(L)), L, jnp.where(jnp.all(jnp.isfinite(L2)), L2, L3))


def _gauss_logpdf_chol(r: Array, L: Array) -> Array:
    """``log N(r; 0, L Lᵀ)`` for residual vectors ``r (..., n)``."""
    n = L.shape[-1]
    u = jsl.solve_triangular(L, jnp.moveaxis(r, -1, 0).reshape(n, -1), lower=True)
    maha = jnp.sum(u * u, axis=0).reshape(r.shape[:-1])
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(L)))
    return -0.5 * (n * _LOG_2PI + logdet + maha)


# --------------------------------------------------------------------------------------------
# Pass 1: frame statistics and the observation subspace
# --------------------------------------------------------------------------------------------


def frame_stats(Y: ArrayLike, mask: ArrayLike | None = None) -> FrameStats:
    """Pass-1 sums over the frames of a texton (SPEC §2 steps 1–2), summable.

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
    Y, mask = _check_fit_inputs(Y, mask)
    return _frame_stats_jit(Y, mask)


def _check_fit_inputs(Y: Any, mask: Any) -> tuple[Array, Array]:
    Y = _as_float_array("Y", Y, (2, 3), "(T, D) or (S, T, D)")
    if Y.shape[-1] < 1:
        raise ValueError(f"Y must have at least one column (D >= 1), got shape {Y.shape}")
    _check_finite("Y", Y)
    mask = _check_mask(mask, tuple(Y.shape[:-1]))
    return Y, mask


def _frame_stats_impl(Y: Array, mask: Array) -> FrameStats:
    Y = _error_if_nonfinite(Y, "Y")
    D = Y.shape[-1]
    Yf = Y.reshape(-1, D)
    w = (mask.reshape(-1) >= 0).astype(Y.dtype)
    Yw = Yf * w[:, None]
    return FrameStats(count=jnp.sum(w), sum_y=jnp.sum(Yw, axis=0), sum_yy=Yw.T @ Yf)


_frame_stats_jit = eqx.filter_jit(_frame_stats_impl)


def subspace_from_stats(
    stats: FrameStats, *, state_dim: int, sigma2_floor: float = 1e-6
) -> Subspace:
    """Mean, observation matrix and residual variance from pass-1 sums (SPEC §2 steps 1–2).

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
    k = _check_state_dim(state_dim, D, tuple(stats.sum_yy.shape))
    floor = _check_positive("sigma2_floor", sigma2_floor)
    return _subspace_jit(stats, k, floor)


def _subspace_impl(stats: FrameStats, k: int, sigma2_floor: float) -> Subspace:
    D = stats.sum_y.shape[-1]
    n = jnp.maximum(stats.count, 1.0)
    mu = stats.sum_y / n
    S = _sym(stats.sum_yy - n * jnp.outer(mu, mu))
    S = jnp.where(stats.count > 0, S, jnp.zeros_like(S))
    w, V = _eigh_desc(S)
    w = jnp.maximum(w, 0.0)
    C = V[:, :k]
    if k < D:
        resid = jnp.sum(w[k:]) / (n * (D - k))
    else:
        resid = jnp.zeros((), S.dtype)
    sigma2 = jnp.maximum(resid, sigma2_floor)
    return Subspace(mu=mu, C=C, state_var=w[:k] / n, sigma2=sigma2.astype(S.dtype))


_subspace_jit = eqx.filter_jit(_subspace_impl)


# --------------------------------------------------------------------------------------------
# Pass 2: state-space statistics
# --------------------------------------------------------------------------------------------


def dynamics_stats(Y: ArrayLike, mask: ArrayLike | None, subspace: Subspace) -> DynamicsStats:
    """Pass-2 sums in state space for a fixed subspace (SPEC §2 step 3), summable.

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
    Y, mask = _check_fit_inputs(Y, mask)
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


def _dynamics_stats_seq(Y: Array, ids: Array, mu: Array, C: Array) -> DynamicsStats:
    T = Y.shape[0]
    k = C.shape[1]
    dtype = Y.dtype
    pair, triple, start = _valid_terms(ids)
    used = (ids >= 0)[:, None]
    X = jnp.where(used, (Y - mu) @ C, 0.0)
    zero = jnp.zeros((), dtype)
    if T >= 3:
        Z = jnp.concatenate([X[2:], X[1:-1], X[:-2]], axis=1)
        w3 = triple[2:].astype(dtype)
        Zw = Z * w3[:, None]
        n3, sum_z, sum_zz = jnp.sum(w3), jnp.sum(Zw, 0), Zw.T @ Z
    else:
        n3, sum_z, sum_zz = zero, jnp.zeros((3 * k,), dtype), jnp.zeros((3 * k, 3 * k), dtype)
    if T >= 2:
        P = jnp.concatenate([X[:-1], X[1:]], axis=1)  # [x_{t-1}; x_t] for t = 1..T-1
        w2 = pair[1:].astype(dtype)
        Pw = P * w2[:, None]
        ws = start[:-1].astype(dtype)  # s_b = [x_b; x_{b+1}] for b = 0..T-2
        Sw = P * ws[:, None]
        n2, sum_p, sum_pp = jnp.sum(w2), jnp.sum(Pw, 0), Pw.T @ P
        n_s, sum_s, sum_ss = jnp.sum(ws), jnp.sum(Sw, 0), Sw.T @ P
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
    )


def _dynamics_stats_impl(Y: Array, mask: Array, subspace: Subspace) -> DynamicsStats:
    Y = _error_if_nonfinite(Y, "Y")
    mu = subspace.mu.astype(Y.dtype)
    C = subspace.C.astype(Y.dtype)
    if Y.ndim == 2:
        return _dynamics_stats_seq(Y, mask, mu, C)
    per_seq = jax.vmap(_dynamics_stats_seq, in_axes=(0, 0, None, None))(Y, mask, mu, C)
    return jax.tree.map(lambda x: jnp.sum(x, axis=0), per_seq)


_dynamics_stats_jit = eqx.filter_jit(_dynamics_stats_impl)


# --------------------------------------------------------------------------------------------
# Solve: statistics -> texton
# --------------------------------------------------------------------------------------------


def texton_from_stats(
    subspace: Subspace,
    stats: DynamicsStats,
    *,
    ridge: float = 1e-6,
    q_floor: float = 1e-6,
    rho_max: float | None = None,
    init_prior_weight: float = 4.0,
) -> Texton:
    """Closed-form texton from summed statistics (SPEC §2 step 3, corrected regression).

    With ``N`` valid triples, means ``x̄_i = Σ x_{t−i} / N`` and centred scatters
    ``R_ij = Σ x_{t−i} x_{t−j}ᵀ − N x̄_i x̄_jᵀ``, ``P = [[R11, R12], [R21, R22]]``:

    .. code-block:: text

        [A1 A2] = [R01 R02] (P + λ I)⁻¹,   λ = ridge·(tr P / 2k + N·q_floor) + jitter
        d = x̄_0 − A1 x̄_1 − A2 x̄_2                        (= (Q0 − A1 Q1 − A2 Q2) / N)
        Q = E R Eᵀ / N + q_floor I,   E = [I, −A1, −A2]   (residual covariance; equals the
                                                             SPEC formula for the LS [A1 A2])

    ``jitter = 10·eps·(tr P / 2k + N·q_floor)`` keeps the system solvable even for
    ``ridge = 0`` (which otherwise gives plain least squares). With ``rho_max`` set, the
    companion matrix ``[[A1, A2], [I, 0]]`` is projected to spectral radius ``≤ rho_max`` by
    *radial scaling*: ``A1 ← s A1``, ``A2 ← s² A2`` with ``s = min(1, rho_max / ρ)``, which
    multiplies every companion eigenvalue by ``s`` (if ``z`` solves
    ``det(z² I − A1 z − A2) = 0`` then ``s z`` solves it for the scaled pair) while keeping the
    second-order structure; ``d`` and ``Q`` are then re-estimated for the scaled matrices.

    Initial-state Gaussian with shrinkage (``κ = init_prior_weight`` pseudo-observations):
    with ``n_s`` segment starts ``s_b = [x_b; x_{b+1}]`` and the mean/covariance
    ``(m_p, S_p)`` of all consecutive pairs ``[x_{t−1}; x_t]`` of the texton (the empirical
    stationary pair distribution; ``(0, diag(state_var, state_var))`` if there are none),

    .. code-block:: text

        m0 = (Σ s_b + κ m_p) / (n_s + κ)
        S0 = (Σ (s_b − m0)(s_b − m0)ᵀ + κ (S_p + (m_p − m0)(m_p − m0)ᵀ)) / (n_s + κ)
             + q_floor I

    i.e. the start frames pooled with ``κ`` pseudo-samples of the pair distribution; it tends
    to the empirical start distribution when there are many segments and is always PD.

    Args:
        subspace: pass-1 result (``μ``, ``C``, ``σ²``, state variances).
        stats: pass-2 sums computed with that subspace.
        ridge: relative ridge on the regression normal matrix, ``>= 0``.
        q_floor: absolute floor added to ``Q`` and ``S0`` (units of ``x²`` = ``y²``), ``> 0``.
        rho_max: optional bound on the companion spectral radius, ``> 0``.
        init_prior_weight: shrinkage pseudo-count ``κ >= 0`` for ``(m0, S0)``.

    Returns:
        A single :class:`Texton` in the dtype of the statistics.
    """
    if not isinstance(subspace, Subspace):
        raise ValueError(f"subspace must be a Subspace, got {type(subspace).__name__}")
    if not isinstance(stats, DynamicsStats):
        raise ValueError(f"stats must be a DynamicsStats, got {type(stats).__name__}")
    k = int(subspace.C.shape[-1])
    if stats.sum_zz.shape != (3 * k, 3 * k):
        raise ValueError(
            f"stats.sum_zz has shape {stats.sum_zz.shape}, expected {(3 * k, 3 * k)} for k={k}"
        )
    opts = _SolveOptions.make(ridge, q_floor, rho_max, init_prior_weight)
    return _texton_from_stats_jit(subspace, stats, opts)


class _SolveOptions(eqx.Module):
    ridge: float = eqx.field(static=True)
    q_floor: float = eqx.field(static=True)
    rho_max: float | None = eqx.field(static=True)
    init_prior_weight: float = eqx.field(static=True)

    @staticmethod
    def make(ridge: Any, q_floor: Any, rho_max: Any, init_prior_weight: Any) -> _SolveOptions:
        return _SolveOptions(
            ridge=_check_positive("ridge", ridge, allow_zero=True),
            q_floor=_check_positive("q_floor", q_floor),
            rho_max=None if rho_max is None else _check_positive("rho_max", rho_max),
            init_prior_weight=_check_positive(
                "init_prior_weight", init_prior_weight, allow_zero=True
            ),
        )


def _project_radius(A1: Array, A2: Array, rho_max: float) -> tuple[Array, Array]:
    rho = jnp.max(jnp.abs(jnp.linalg.eigvals(_companion(A1, A2))))
    rho = rho.astype(A1.dtype)
    s = jnp.where(rho > rho_max, rho_max / jnp.where(rho > 0, rho, 1.0), 1.0)
    # tiny safety margin so that rounding in the eigenvalues never leaves rho > rho_max
    s = jnp.where(rho > rho_max, s * (1 - 4 * jnp.finfo(A1.dtype).eps), s)
    return s * A1, (s * s) * A2


def _texton_from_stats_impl(
    subspace: Subspace, stats: DynamicsStats, opts: _SolveOptions
) -> Texton:
    dtype = stats.sum_zz.dtype
    k = subspace.C.shape[-1]
    eye_k = jnp.eye(k, dtype=dtype)
    eye_2k = jnp.eye(2 * k, dtype=dtype)
    eps = jnp.finfo(dtype).eps
    q_floor = jnp.asarray(opts.q_floor, dtype)

    # --- dynamics: regression of x_t on [x_{t-1}, x_{t-2}, 1] ---
    N = stats.n3
    Ns = jnp.maximum(N, 1.0)
    mz = stats.sum_z / Ns
    R = _sym(stats.sum_zz - Ns * jnp.outer(mz, mz))
    R = jnp.where(N > 0, R, jnp.zeros_like(R))
    R0p = R[:k, k:]
    Rpp = R[k:, k:]
    scale = jnp.trace(Rpp) / (2 * k) + Ns * q_floor
    lam = opts.ridge * scale + 10 * eps * scale
    Lp = _psd_cholesky(Rpp, lam)
    A = jsl.cho_solve((Lp, True), R0p.T).T  # (k, 2k) = R0p (P + λI)^-1
    A1, A2 = A[:, :k], A[:, k:]
    if opts.rho_max is not None:
        A1, A2 = _project_radius(A1, A2, opts.rho_max)
    d = mz[:k] - A1 @ mz[k : 2 * k] - A2 @ mz[2 * k :]
    E = jnp.concatenate([eye_k, -A1, -A2], axis=1)
    Q = E @ R @ E.T / Ns
    B = _psd_cholesky(Q, q_floor)

    # --- initial two-state Gaussian with shrinkage ---
    kappa = jnp.asarray(opts.init_prior_weight, dtype)
    n2 = stats.n2
    n2s = jnp.maximum(n2, 1.0)
    m_pair = stats.sum_p / n2s
    S_pair = _sym(stats.sum_pp / n2s - jnp.outer(m_pair, m_pair))
    var = jnp.concatenate([subspace.state_var, subspace.state_var]).astype(dtype)
    m_tgt = jnp.where(n2 > 0, m_pair, 0.0)
    S_tgt = jnp.where(n2 > 0, S_pair, jnp.diag(var))
    ns = stats.n_start
    denom = ns + kappa
    denom_s = jnp.where(denom > 0, denom, 1.0)
    m0 = (stats.sum_s + kappa * m_tgt) / denom_s
    scat = (
        stats.sum_ss
        - jnp.outer(stats.sum_s, m0)
        - jnp.outer(m0, stats.sum_s)
        + ns * jnp.outer(m0, m0)
    )
    dm = m_tgt - m0
    S0 = _sym((scat + kappa * (S_tgt + jnp.outer(dm, dm))) / denom_s)
    S0 = jnp.where(denom > 0, S0, jnp.zeros_like(S0)) + q_floor * eye_2k

    return Texton(
        mu=subspace.mu.astype(dtype),
        C=subspace.C.astype(dtype),
        A1=A1,
        A2=A2,
        d=d,
        B=B,
        sigma2=subspace.sigma2.astype(dtype),
        m0=m0,
        S0=S0,
    )


_texton_from_stats_jit = eqx.filter_jit(_texton_from_stats_impl)


# --------------------------------------------------------------------------------------------
# fit_texton
# --------------------------------------------------------------------------------------------


def fit_texton(
    Y: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    state_dim: int,
    ridge: float = 1e-6,
    q_floor: float = 1e-6,
    sigma2_floor: float = 1e-6,
    rho_max: float | None = None,
    init_prior_weight: float = 4.0,
) -> Texton:
    """Closed-form fit of one texton on one or several segments (SPEC §2; MT App. B).

    Equivalent to ``texton_from_stats(sub, dynamics_stats(Y, mask, sub))`` with
    ``sub = subspace_from_stats(frame_stats(Y, mask))``, in one jit-compiled call. Use that
    two-pass path to sum statistics over sequences or devices before solving.

    Segments: ``mask`` holds a non-negative segment id per frame (``-1`` = frame unused). A
    dynamics term at ``t`` is used only if frames ``t−2, t−1, t`` are consecutive frames of one
    sequence with the same id; adjacent segments therefore need different ids. Frames of
    every segment (including segments of one or two frames) enter ``μ``, ``C`` and ``σ²``.

    Args:
        Y: observations ``(T, D)`` or a batch of sequences ``(S, T, D)`` (sequences never
            connect). Must be finite.
        mask: integer segment ids with Y's leading shape, or ``None`` (each sequence is one
            segment); a boolean mask means ``True`` = frame used, one segment per run.
        state_dim: ``k`` with ``1 <= k <= D`` (static).
        ridge: relative ridge of the dynamics regression (see :func:`texton_from_stats`).
        q_floor: absolute floor added to ``Q`` and ``S0`` (units of ``y²``).
        sigma2_floor: absolute floor of ``σ²`` (units of ``y²``).
        rho_max: optional bound on the spectral radius of ``[[A1, A2], [I, 0]]``.
        init_prior_weight: shrinkage pseudo-count of the initial-state Gaussian.

    Returns:
        A single :class:`Texton` in Y's floating dtype. Differentiable w.r.t. ``Y`` (the
        subspace needs distinct top-``k`` eigenvalues for meaningful gradients).

    Raises:
        ValueError: on wrong shapes, NaN/inf in ``Y`` (eagerly when ``Y`` is concrete; under
            an outer ``jit`` an ``eqx.error_if`` runtime error), ``state_dim`` outside
            ``[1, D]`` or invalid floors.
    """
    Y, mask = _check_fit_inputs(Y, mask)
    k = _check_state_dim(state_dim, int(Y.shape[-1]), tuple(Y.shape))
    floor = _check_positive("sigma2_floor", sigma2_floor)
    opts = _SolveOptions.make(ridge, q_floor, rho_max, init_prior_weight)
    return _fit_texton_jit(Y, mask, k, floor, opts)


def _fit_texton_impl(
    Y: Array, mask: Array, k: int, sigma2_floor: float, opts: _SolveOptions
) -> Texton:
    fs = _frame_stats_impl(Y, mask)
    sub = _subspace_impl(fs, k, sigma2_floor)
    ds = _dynamics_stats_impl(Y, mask, sub)
    return _texton_from_stats_impl(sub, ds, opts)


_fit_texton_traced = eqx.debug.assert_max_traces(_fit_texton_impl, max_traces=None)
_fit_texton_jit = eqx.filter_jit(_fit_texton_traced)


# --------------------------------------------------------------------------------------------
# Per-frame terms and prefix-sum segment scores (SPEC §3)
# --------------------------------------------------------------------------------------------


def _terms_single(
    tex: Texton, Yc: Array, yn: Array, ybar: Array, with_dyn_obs: bool, with_init: bool
) -> tuple[Array | None, Array | None, Array | None]:
    """Per-frame terms of one texton on centred frames ``Yc = Y − ȳ`` (``yn = ‖Yc‖²``)."""
    T, D = Yc.shape
    k = tex.C.shape[-1]
    dtype = Yc.dtype
    tex = jax.tree.map(lambda a: a.astype(dtype), tex)
    mc = tex.mu - ybar
    off = mc @ tex.C
    # one GEMM gives the states and the y·μ term: Yc [C | μ − ȳ]
    P = Yc @ jnp.concatenate([tex.C, mc[:, None]], axis=1)
    X = P[:, :k] - off  # x_t = Cᵀ(y_t − μ)
    dyn = obs = init = None
    if with_dyn_obs:
        # whitened dynamics residual w_t = B⁻¹(x_t − A1 x_{t−1} − A2 x_{t−2} − d)
        Binv = jsl.solve_triangular(tex.B, jnp.eye(k, dtype=dtype), lower=True)
        G1 = -(Binv @ tex.A1)
        G2 = -(Binv @ tex.A2)
        logdet_q = 2.0 * jnp.sum(jnp.log(jnp.diagonal(tex.B)))
        if T >= 3:
            W = X[2:] @ Binv.T + X[1:-1] @ G1.T + X[:-2] @ G2.T - Binv @ tex.d
            dyn_t = -0.5 * (k * _LOG_2PI + logdet_q + jnp.sum(W * W, axis=1))
            dyn = jnp.concatenate([jnp.zeros((2,), dtype), dyn_t])
        else:
            dyn = jnp.zeros((T,), dtype)
        # ‖r_t‖² = ‖y_t − μ‖² − ‖x_t‖², clamped at 0 (r outside the subspace)
        r2 = yn - 2.0 * P[:, k] + mc @ mc - jnp.sum(X * X, axis=1)
        r2 = jnp.maximum(r2, 0.0)
        n_res = D - k
        obs = -0.5 * (n_res * (_LOG_2PI + jnp.log(tex.sigma2)) + r2 / tex.sigma2)
        if n_res == 0:
            obs = jnp.zeros_like(obs)
    if with_init:
        L0 = _psd_cholesky(tex.S0, jnp.zeros((), dtype))
        L0inv = jsl.solve_triangular(L0, jnp.eye(2 * k, dtype=dtype), lower=True)
        if T >= 2:
            # L0⁻¹([x_b; x_{b+1}] − m0) without forming the stacked pairs
            U = X[:-1] @ L0inv[:, :k].T + X[1:] @ L0inv[:, k:].T - L0inv @ tex.m0
            logdet0 = 2.0 * jnp.sum(jnp.log(jnp.diagonal(L0)))
            init_b = -0.5 * (2 * k * _LOG_2PI + logdet0 + jnp.sum(U * U, axis=1))
            init = jnp.concatenate([init_b, jnp.full((1,), -jnp.inf, dtype)])
        else:
            init = jnp.full((T,), -jnp.inf, dtype)
    return dyn, obs, init


def _all_terms_impl(
    textons: Texton, Y: Array, with_dyn_obs: bool, with_init: bool, chunk: int
) -> tuple[Array | None, Array | None, Array | None]:
    Y = _error_if_nonfinite(Y, "Y")
    dtype = _float_dtype(Y, textons.mu)
    Y = Y.astype(dtype)
    ybar = jnp.mean(Y, axis=0)
    Yc = Y - ybar
    yn = jnp.sum(Yc * Yc, axis=1)

    def one(tex: Texton) -> tuple[Array | None, Array | None, Array | None]:
        return _terms_single(tex, Yc, yn, ybar, with_dyn_obs, with_init)

    if not textons.is_stacked:
        return one(textons)
    return lax.map(one, textons, batch_size=chunk if chunk > 1 else None)


_all_terms_traced = eqx.debug.assert_max_traces(_all_terms_impl, max_traces=None)
_all_terms_jit = eqx.filter_jit(_all_terms_traced)


def _check_positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"{name} must be a positive int, got {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {value}")
    return int(value)


# Target size of one time block's projections (all textons), in bytes: small enough to stay in
# the (per-core) L2 cache between the projection GEMM and the passes that re-read it.
_BLOCK_BYTES = 2 * 2**20


def _block_frames(block_size: Any, textons: Texton, Y: Array) -> int:
    """Frames per time block of :func:`frame_terms` (``block_size=None``: from the cache size).

    The automatic choice keeps a block's ``(N_t·(k+1), block + 2)`` projections (in the
    promoted dtype of ``Y`` and the stacked ``textons``) near ``_BLOCK_BYTES`` with
    ``block + 2`` a multiple of 16 (GEMM-friendly), between 14 and 1022.
    """
    if block_size is None:
        itemsize = jnp.dtype(_float_dtype(Y, textons.mu)).itemsize
        n, k = textons.n_textons, textons.state_dim
        cols = _BLOCK_BYTES // max(n * (k + 1) * itemsize, 1)
        return min(max(16 * (cols // 16), 16), 1024) - 2
    return _check_positive_int("block_size", block_size)


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
        dyn_const=k * _LOG_2PI + 2.0 * jnp.sum(jnp.log(jnp.abs(jnp.diagonal(tex.B)))),
        obs_const=(D - k) * (_LOG_2PI + jnp.log(tex.sigma2)),
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
    L0 = _psd_cholesky(tex.S0, jnp.zeros((), dt))
    L0inv = jsl.solve_triangular(L0, jnp.eye(2 * k, dtype=dt), lower=True)
    Us = U * s[None, :]
    E = jnp.concatenate([L0inv[:, :k] @ Us, L0inv[k:, k:] @ Us], axis=0)
    return dict(
        E=jnp.concatenate([E, jnp.zeros((3 * k, 1), dt)], axis=1),
        init_c=L0inv @ tex.m0,
        init_const=2 * k * _LOG_2PI + 2.0 * jnp.sum(jnp.log(jnp.diagonal(L0))),
    )


def _frame_terms_impl(
    textons: Texton,
    Y: Array,
    block: int,
    with_init: bool = False,
    out_rows: int | None = None,
    check: bool = True,
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
    of ``Y`` (for callers that checked it eagerly).
    """
    if check:
        Y = _error_if_nonfinite(Y, "Y")
    dtype = _float_dtype(Y, textons.mu)
    Y = Y.astype(dtype)
    textons = jax.tree.map(lambda a: a.astype(dtype), textons)
    T, D = Y.shape
    n, _, k = textons.C.shape
    ybar = jnp.mean(Y, axis=0)
    cw = jax.vmap(_whitened_coords, in_axes=(0, None))(textons, ybar)
    # rows i(k+1) … i(k+1)+k of P are texton i's projection onto [z_t; (y_t − ȳ)·(μ_i − ȳ)]
    P = cw["P"].reshape(n * (k + 1), D + 1)
    F, e, s2 = cw["F"], cw["e"], cw["s2"]
    if with_init:  # [F1; F2; E0; E1[k:]]: one small GEMM per texton for both
        # per texton (lax.map): the Cholesky factors of S0 are not one batched LAPACK call
        ic = lax.map(lambda a: _init_coords(*a), (textons, cw["U"], cw["s"]))
        F = jnp.concatenate([F, ic["E"]], axis=1)
        init_c, init_const = ic["init_c"], ic["init_const"][:, None]
    dyn_const = cw["dyn_const"][:, None]
    obs_const = cw["obs_const"][:, None]
    mcmc = cw["mcmc"][:, None]
    sigma2 = textons.sigma2[:, None]
    W = min(block + 2, T)
    step = max(W - 2, 1)
    n_blocks = -(-max(T - 2, 1) // step)
    ones = jnp.ones((W, 1), dtype)

    def window_terms(w0: Array) -> tuple[Array | None, Array, Array | None]:
        Yw = lax.dynamic_slice_in_dim(Y, w0, W, axis=0) - ybar  # (W, D) centred frames
        # all textons at once: (N_t(k+1), D+1) × (W, D+1)ᵀ
        Z = lax.dot_general(P, jnp.concatenate([Yw, ones], axis=1), (((1,), (1,)), ((), ())))
        Z = Z.reshape(n, k + 1, W)
        # sums over the state index unrolled: each becomes one fused elementwise pass that
        # reads the (shifted) slices of Z and FZ in place, with no reduction copies
        x2: Array | float = 0.0
        for j in range(k):
            x2 = x2 + s2[:, j, None] * Z[:, j] * Z[:, j]
        r2 = jnp.maximum(jnp.sum(Yw * Yw, axis=1) - 2.0 * Z[:, k] + mcmc - x2, 0.0)
        obs = -0.5 * (obs_const + r2 / sigma2) if D > k else jnp.zeros((n, W), dtype)
        if W < 2:
            return None, obs, None
        FZ = jnp.einsum("njm,nmt->njt", F, Z)  # [F1; F2] z_t: one small GEMM per texton
        init = None
        if with_init:  # ‖E0 z_b + E1 z_{b+1} − L0⁻¹m0‖², b = w0 … w0 + W − 2
            u2: Array | float = 0.0
            for j in range(2 * k):  # rows j < k of E1 are zero
                u = FZ[:, 2 * k + j, :-1] - init_c[:, j, None]
                if j >= k:
                    u = u + FZ[:, 3 * k + j, 1:]
                u2 = u2 + u * u
            init = -0.5 * (init_const + jnp.asarray(u2))
        if W < 3:
            return None, obs, init
        w2: Array | float = 0.0
        for j in range(k):
            w = Z[:, j, 2:] + FZ[:, j, 1:-1] + FZ[:, k + j, :-2] - e[:, j, None]
            w2 = w2 + w * w
        return -0.5 * (dyn_const + w2), obs, init

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


_frame_terms_traced = eqx.debug.assert_max_traces(_frame_terms_impl, max_traces=None)
_frame_terms_jit = eqx.filter_jit(_frame_terms_traced)

# below this many texton-frames an eager frame_terms call runs as one execution
_SPLIT_MIN_WORK = 2**20


def _merge_rows(
    first: tuple[Array, Array], rest: Sequence[tuple[Array, Array]], cuts: tuple[int, ...]
) -> tuple[Array, Array]:
    """Write the row blocks ``rest`` into ``first`` (donated: updated in place) at ``cuts``."""
    dyn, obs = first
    for c, (d, o) in zip(cuts, rest, strict=True):
        dyn = lax.dynamic_update_slice_in_dim(dyn, d, c, axis=0)
        obs = lax.dynamic_update_slice_in_dim(obs, o, c, axis=0)
    return dyn, obs


_merge_rows_jit = jax.jit(_merge_rows, static_argnums=2, donate_argnums=0)


def _check_workers(workers: Any) -> int | None:
    return None if workers is None else _check_positive_int("workers", workers)


def _available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _n_parts(workers: int | None, textons: Texton, Y: Array) -> int:
    """Concurrent executions for an eager :func:`frame_terms` call (1 under a trace)."""
    leaves = jax.tree.leaves((textons, Y))
    if any(isinstance(x, Tracer) for x in leaves):
        return 1
    if any(d.platform != "cpu" for d in Y.devices()):
        return 1
    n = textons.n_textons
    if workers is None:
        if n * Y.shape[0] < _SPLIT_MIN_WORK:
            return 1
        workers = _available_cores()
    return max(1, min(workers, n))


def _thread_settings() -> Any:
    """The calling thread's JAX settings that change what a computation is (``enable_x64``,
    ``default_matmul_precision``, ``debug_nans``/``debug_infs``: thread-local when set by
    their context managers), as a function that re-enters them in another thread."""
    # the attributes read each setting's value in this thread (not typed in jax's stubs)
    cfg: Any = jax.config
    x64, precision = cfg.jax_enable_x64, cfg.jax_default_matmul_precision
    nans, infs = cfg.jax_debug_nans, cfg.jax_debug_infs

    def enter(stack: contextlib.ExitStack) -> None:
        stack.enter_context(jax.enable_x64(x64))
        stack.enter_context(jax.default_matmul_precision(precision))
        stack.enter_context(jax.debug_nans(nans))
        stack.enter_context(jax.debug_infs(infs))

    return enter


def _frame_terms_split(textons: Texton, Y: Array, block: int, parts: int) -> tuple[Array, Array]:
    """:func:`_frame_terms_impl` on ``parts`` row blocks of the textons, run concurrently.

    XLA:CPU runs the kernel's per-block batched GEMM and elementwise passes on one core (only
    the projection GEMM is multi-threaded), so one execution leaves the other cores mostly
    idle. Here each block of textons (sizes differing by at most one) is one execution,
    started from its own host thread (executions from different threads run concurrently)
    under the calling thread's JAX settings; the first writes its rows into outputs of the
    full height and the others' rows are copied into them in place. ``Y`` has been checked
    for NaN/inf eagerly.
    """
    n = textons.n_textons
    cuts = [n * i // parts for i in range(parts + 1)]
    pieces = [
        jax.tree.map(lambda a, lo=lo, hi=hi: a[lo:hi], textons)
        for lo, hi in itertools.pairwise(cuts)
    ]
    settings = _thread_settings()

    def run(i: int) -> tuple[Array, Array]:
        with contextlib.ExitStack() as stack:
            settings(stack)
            out = _frame_terms_jit(pieces[i], Y, block, out_rows=n if i == 0 else None, check=False)
            return jax.block_until_ready(out)

    with ThreadPoolExecutor(max_workers=parts - 1) as pool:
        futures = [pool.submit(run, i) for i in range(1, parts)]
        first = run(0)
        rest = [f.result() for f in futures]
    return _merge_rows_jit(first, rest, tuple(cuts[1:-1]))


def frame_terms(
    textons: Texton,
    Y: ArrayLike,
    *,
    block_size: int | None = None,
    chunk_size: int | None = None,
    workers: int | None = None,
) -> tuple[Float[Array, "*n T"], Float[Array, "*n T"]]:
    """Per-frame log-density terms of every texton on every frame (SPEC §3).

    For texton ``i`` with ``x_t = C_iᵀ(y_t − μ_i)``:

    .. code-block:: text

        dyn[i, t] = log N(x_t; A1 x_{t−1} + A2 x_{t−2} + d, Q)      t >= 2   (MT-10)
                  = −½ (k log 2π + log|Q| + ‖B⁻¹(x_t − A1 x_{t−1} − A2 x_{t−2} − d)‖²)
        dyn[i, 0] = dyn[i, 1] = 0
        obs[i, t] = log N(r_t; 0, σ² I_{D−k})                                (MT-11)
                  = −½ ((D−k) log 2πσ² + ‖r_t‖² / σ²),
                    ‖r_t‖² = max(‖y_t − μ‖² − ‖x_t‖², 0)

    (``r_t`` is the residual outside the texton's subspace; ``obs = 0`` when ``k = D``.)

    Implementation (default): each texton's state is used in whitened coordinates
    ``z_t = diag(s)⁻¹ Uᵀ x_t`` from the SVD ``B = U diag(s) Vᵀ``, in which the whitened
    residual is ``z_t + F1 z_{t−1} + F2 z_{t−2} − e`` (``F_j = −diag(s)⁻¹ Uᵀ A_j U diag(s)``,
    ``e = diag(s)⁻¹ Uᵀ d``) and ``‖x_t‖² = ‖diag(s) z_t‖²``: two ``k × k`` products per frame
    instead of three, and a diagonal one for the residual. The frames are processed in time
    blocks of ``block_size`` frames (plus the two preceding ones): one GEMM projects the block
    onto all textons' ``[z_t; y_t·μ]`` at once, ``(N_t(k+1), D+1) × (D+1, block+2)`` (offsets
    folded in through a constant-1 input row), so ``Y`` is read once and the projections stay
    in cache; then one small GEMM per texton gives ``[F1; F2] z`` and fused elementwise passes
    form the shifted sums, squares and the residual term. Exact (no approximation): equal to
    the direct formulas up to rounding.

    Args:
        textons: a stack of ``N_t`` textons (or a single texton).
        Y: observations ``(T, D)``.
        block_size: frames per time block (static); ``None`` chooses it so that one block's
            projections take about 2 MB (62 frames for 246 textons with k = 15 in float64).
            Memory ``O(N_t · k · block_size)`` besides the outputs.
        chunk_size: if given, use instead the per-texton algorithm (``lax.map`` over textons,
            ``chunk_size`` textons per step; each texton projects all frames with one GEMM and
            forms ``B⁻¹(x_t − A1 x_{t−1} − A2 x_{t−2} − d)`` with three ``k × k`` GEMMs).
            Slower; kept as an independent implementation. Not combinable with ``block_size``.
        workers: concurrent executions of an eager call of the blocked kernel on the CPU
            (not used with ``chunk_size``): the textons are split into that many blocks, each
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
            ``block_size``/``chunk_size``/``workers`` is not a positive int (or both
            ``block_size`` and ``chunk_size`` are given).
    """
    textons = _check_texton("textons", textons)
    Y = _check_obs("Y", Y, textons.obs_dim)
    workers = _check_workers(workers)
    if chunk_size is not None:
        if block_size is not None:
            raise ValueError("give at most one of block_size and chunk_size")
        dyn, obs, _ = _all_terms_jit(
            textons, Y, True, False, _check_positive_int("chunk_size", chunk_size)
        )
        assert dyn is not None and obs is not None
        return dyn, obs
    single = not textons.is_stacked
    if single:
        textons = jax.tree.map(lambda a: a[None], textons)
    block = min(_block_frames(block_size, textons, Y), Y.shape[0])
    parts = _n_parts(workers, textons, Y)
    if parts > 1:
        dyn, obs = _frame_terms_split(textons, Y, block, parts)
    else:  # a concrete Y has been checked for NaN/inf eagerly
        dyn, obs = _frame_terms_jit(textons, Y, block, check=isinstance(Y, Tracer))
    if single:
        return dyn[0], obs[0]
    return dyn, obs


def init_terms(textons: Texton, Y: ArrayLike, *, chunk_size: int = 1) -> Float[Array, "*n T"]:
    """Initial-state log-density of a segment starting at each frame (SPEC §3).

    .. code-block:: text

        init[i, b] = log N([x_b; x_{b+1}]; m0_i, S0_i)    for b <= T − 2
        init[i, T−1] = −inf                               (no second frame)

    Args:
        textons: a stack of ``N_t`` textons (or a single texton).
        Y: observations ``(T, D)``.
        chunk_size: textons vectorised per ``lax.map`` step (static).

    Returns:
        ``(N_t, T)`` (``(T,)`` for a single texton).
    """
    textons = _check_texton("textons", textons)
    Y = _check_obs("Y", Y, textons.obs_dim)
    _, _, init = _all_terms_jit(
        textons, Y, False, True, _check_positive_int("chunk_size", chunk_size)
    )
    assert init is not None
    return init


class SegmentScorer(eqx.Module):
    """O(1) segment scores from prefix sums of the per-frame terms (SPEC §3).

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
    textons: Texton, Y: ArrayLike, *, block_size: int | None = None
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

    Returns:
        :class:`SegmentScorer` with arrays ``(N_t, T)`` / ``(N_t, T+1)``.
    """
    textons = _check_texton("textons", textons)
    if not textons.is_stacked:
        textons = jax.tree.map(lambda a: a[None], textons)
    Y = _check_obs("Y", Y, textons.obs_dim, min_len=2)
    block = _block_frames(block_size, textons, Y)
    return _segment_scores_jit(textons, Y, block)


def _segment_scores_impl(textons: Texton, Y: Array, block: int | None = None) -> SegmentScorer:
    # all three terms by the blocked kernel of frame_terms; init_terms(chunk_size=…), the
    # per-texton algorithm, is the independent reference
    if block is None:
        block = _block_frames(None, textons, Y)
    dyn, obs, init = _frame_terms_impl(textons, Y, min(block, Y.shape[0]), with_init=True)
    T = dyn.shape[1]
    dyn_off = jnp.mean(dyn[:, 2:], axis=1) if T > 2 else jnp.zeros(dyn.shape[:1], dyn.dtype)
    obs_off = jnp.mean(obs, axis=1)
    zeros = jnp.zeros((dyn.shape[0], 1), dyn.dtype)
    cum_dyn = jnp.concatenate([zeros, jnp.cumsum(dyn - dyn_off[:, None], axis=1)], axis=1)
    cum_obs = jnp.concatenate([zeros, jnp.cumsum(obs - obs_off[:, None], axis=1)], axis=1)
    return SegmentScorer(
        init=init, cum_dyn=cum_dyn, cum_obs=cum_obs, dyn_offset=dyn_off, obs_offset=obs_off
    )


_segment_scores_jit = eqx.filter_jit(_segment_scores_impl)


# --------------------------------------------------------------------------------------------
# Direct per-segment likelihood (reference) and the exact Kalman likelihood
# --------------------------------------------------------------------------------------------


def segment_log_likelihood(texton: Texton, Y_segment: ArrayLike) -> Float[Array, ""]:
    """Projected-state log-likelihood of one segment, computed directly (SPEC §3).

    .. code-block:: text

        log p(Y_{b:e}) = log N([x_b; x_{b+1}]; m0, S0)
                       + Σ_{t=b+2..e} log N(x_t; A1 x_{t−1} + A2 x_{t−2} + d, Q)
                       + Σ_{t=b..e}   log N(r_t; 0, σ² I_{D−k})

    with ``x_t = Cᵀ(y_t − μ)`` and the explicit residual ``r_t = (y_t − μ) − C x_t``
    (triangular solves with ``B`` and ``chol(S0)``). This is the reference for
    :class:`SegmentScorer`; it handles one texton (``jax.vmap`` it for a stack).

    Args:
        texton: a single texton.
        Y_segment: ``(L, D)`` frames of the segment, ``L >= 2``.

    Returns:
        Scalar log-likelihood.
    """
    texton = _check_texton("texton", texton, stacked=False)
    Y = _check_obs("Y_segment", Y_segment, texton.obs_dim, min_len=2)
    return _segment_ll_jit(texton, Y)


def _segment_ll_impl(tex: Texton, Y: Array) -> Array:
    Y = _error_if_nonfinite(Y, "Y_segment")
    dtype = _float_dtype(Y, tex.mu)
    Y = Y.astype(dtype)
    tex = jax.tree.map(lambda a: a.astype(dtype), tex)
    D, k = tex.C.shape
    Yc = Y - tex.mu
    X = Yc @ tex.C
    Rres = Yc - X @ tex.C.T
    ll_obs = jnp.asarray(0.0, dtype)
    if D > k:
        r2 = jnp.sum(Rres * Rres, axis=1)
        ll_obs = jnp.sum(-0.5 * ((D - k) * (_LOG_2PI + jnp.log(tex.sigma2)) + r2 / tex.sigma2))
    L0 = _psd_cholesky(tex.S0, jnp.zeros((), dtype))
    ll_init = _gauss_logpdf_chol(jnp.concatenate([X[0], X[1]]) - tex.m0, L0)
    ll_dyn = jnp.asarray(0.0, dtype)
    if Y.shape[0] > 2:
        res = X[2:] - X[1:-1] @ tex.A1.T - X[:-2] @ tex.A2.T - tex.d
        ll_dyn = jnp.sum(_gauss_logpdf_chol(res, tex.B))
    return ll_init + ll_dyn + ll_obs


_segment_ll_jit = eqx.filter_jit(_segment_ll_impl)


def exact_log_likelihood(texton: Texton, Y_segment: ArrayLike) -> Float[Array, ""]:
    """Exact marginal log-likelihood ``log p(y_1, …, y_L)`` of the full LDS (SPEC §3).

    Model: ``[x_1; x_2] ~ N(m0, S0)``, ``x_t = A1 x_{t−1} + A2 x_{t−2} + d + B v_t``,
    ``y_t = μ + C x_t + w_t``, ``w_t ~ N(0, σ² I_D)``.

    Because ``C`` has orthonormal columns and ``R = σ² I``, rotate ``y_t − μ`` into
    ``z_t = Cᵀ(y_t − μ) = x_t + Cᵀ w_t`` and the residual ``r_t = (I − C Cᵀ)(y_t − μ)``: the
    two are independent, the rotation has unit Jacobian, and

    .. code-block:: text

        log p(y_{1:L}) = Σ_t log N(r_t; 0, σ² I_{D−k}) + log p(z_{1:L}),
        z_t = x_t + e_t,  e_t ~ N(0, σ² I_k)

    so no ``D × D`` matrix is ever formed (the information/Woodbury reduction of the
    ``D``-dimensional innovation covariance). ``log p(z_{1:L})`` is a Kalman filter in the
    stacked state ``X_t = [x_t; x_{t−1}]``: a joint update of the prior of ``[x_1; x_2]`` with
    ``[z_1; z_2]``, then ``lax.scan`` over ``t = 3..L`` of predict
    (``X⁻ = F X + [d; 0]``, ``P⁻ = F P Fᵀ + diag(Q, 0)``) and update with ``H = [I, 0]``
    (innovation covariance ``S = H P⁻ Hᵀ + σ² I_k`` by Cholesky, Joseph-form covariance
    update). Differentiable in the texton parameters and the data.

    Args:
        texton: a single texton.
        Y_segment: ``(L, D)``, ``L >= 2``.

    Returns:
        Scalar log-likelihood.
    """
    texton = _check_texton("texton", texton, stacked=False)
    Y = _check_obs("Y_segment", Y_segment, texton.obs_dim, min_len=2)
    return _exact_ll_jit(texton, Y)


def _exact_ll_impl(tex: Texton, Y: Array) -> Array:
    Y = _error_if_nonfinite(Y, "Y_segment")
    dtype = _float_dtype(Y, tex.mu)
    Y = Y.astype(dtype)
    tex = jax.tree.map(lambda a: a.astype(dtype), tex)
    D, k = tex.C.shape
    s2 = tex.sigma2
    Yc = Y - tex.mu
    Z = Yc @ tex.C
    ll = jnp.asarray(0.0, dtype)
    if D > k:
        Rres = Yc - Z @ tex.C.T
        r2 = jnp.sum(Rres * Rres)
        ll = ll - 0.5 * (Y.shape[0] * (D - k) * (_LOG_2PI + jnp.log(s2)) + r2 / s2)

    eye_k = jnp.eye(k, dtype=dtype)
    eye_2k = jnp.eye(2 * k, dtype=dtype)

    # joint update of the prior on [x_1; x_2] with [z_1; z_2] (H = I_2k)
    z12 = jnp.concatenate([Z[0], Z[1]])
    S = _sym(tex.S0) + s2 * eye_2k
    Ls = jnp.linalg.cholesky(S)
    v = z12 - tex.m0
    ll = ll + _gauss_logpdf_chol(v, Ls)
    K = jsl.cho_solve((Ls, True), tex.S0).T  # S0 S⁻¹
    m = tex.m0 + K @ v
    IK = eye_2k - K
    P = IK @ tex.S0 @ IK.T + s2 * (K @ K.T)
    # reorder [x_1; x_2] -> stacked state [x_2; x_1]
    perm = jnp.concatenate([jnp.arange(k, 2 * k), jnp.arange(k)])
    m = m[perm]
    P = _sym(P[perm][:, perm])

    F = _companion(tex.A1, tex.A2)
    dvec = jnp.concatenate([tex.d, jnp.zeros((k,), dtype)])
    Qfull = jnp.zeros((2 * k, 2 * k), dtype).at[:k, :k].set(tex.B @ tex.B.T)

    def step(carry: tuple[Array, Array, Array], z: Array) -> tuple[Any, None]:
        m, P, ll = carry
        m = F @ m + dvec
        P = F @ P @ F.T + Qfull
        Sk = _sym(P[:k, :k]) + s2 * eye_k
        Lk = jnp.linalg.cholesky(Sk)
        v = z - m[:k]
        ll = ll + _gauss_logpdf_chol(v, Lk)
        K = jsl.cho_solve((Lk, True), P[:k, :]).T  # P Hᵀ S⁻¹, (2k, k)
        m = m + K @ v
        IKH = eye_2k.at[:, :k].add(-K)
        P = _sym(IKH @ P @ IKH.T + s2 * (K @ K.T))
        return (m, P, ll), None

    (_, _, ll), _ = lax.scan(step, (m, P, ll), Z[2:])
    return ll


_exact_ll_jit = eqx.filter_jit(_exact_ll_impl)


# --------------------------------------------------------------------------------------------
# Sampling (MT Fig. 4)
# --------------------------------------------------------------------------------------------


def sample_texton(
    key: Array,
    texton: Texton,
    length: int,
    x1: ArrayLike | None = None,
    x2: ArrayLike | None = None,
    *,
    observation_noise: bool = True,
) -> tuple[Float[Array, "L k"], Float[Array, "L D"]]:
    """Noise-driven synthesis from one texton (MT Fig. 4).

    ``x_t = A1 x_{t−1} + A2 x_{t−2} + d + B v_t`` with ``v_t ~ N(0, I)`` for ``t = 3..L``
    (``lax.scan``), starting from the two given states; ``y_t = μ + C x_t (+ σ w_t)``.

    Args:
        texton: a single texton.
        key: a JAX PRNG key.
        length: number of frames ``L >= 2`` (static).
        x1, x2: ``(k,)`` first two states (e.g. key poses reprojected, ``Cᵀ(y − μ)``). If both
            are ``None`` they are drawn from ``N(m0, S0)``; give both or neither.
        observation_noise: add ``w_t ~ N(0, σ² I_D)`` to the observations. MT Fig. 4 shows
            the noise-free projection ``μ + C x_t``; ``True`` samples the full generative model.

    Returns:
        ``(states (L, k), observations (L, D))``; ``states[0] = x1``, ``states[1] = x2``.
    """
    texton = _check_texton("texton", texton, stacked=False)
    if isinstance(length, bool) or not isinstance(length, int | np.integer) or length < 2:
        raise ValueError(f"length must be an int >= 2, got {length!r}")
    k = texton.state_dim
    if (x1 is None) != (x2 is None):
        raise ValueError("give both x1 and x2, or neither (then they are sampled from m0, S0)")
    xs: tuple[Array, Array] | None = None
    if x1 is not None and x2 is not None:
        a = _as_float_array("x1", x1, (1,), f"({k},)")
        b = _as_float_array("x2", x2, (1,), f"({k},)")
        for name, v in (("x1", a), ("x2", b)):
            if v.shape != (k,):
                raise ValueError(f"{name} must have shape ({k},), got {tuple(v.shape)}")
            _check_finite(name, v)
        xs = (a, b)
    return _sample_jit(texton, key, int(length), xs, bool(observation_noise))


def _sample_impl(
    tex: Texton,
    key: Array,
    length: int,
    xs: tuple[Array, Array] | None,
    observation_noise: bool,
) -> tuple[Array, Array]:
    dtype = tex.mu.dtype
    k = tex.C.shape[-1]
    D = tex.C.shape[0]
    k_init, k_dyn, k_obs = jax.random.split(key, 3)
    if xs is None:
        L0 = _psd_cholesky(tex.S0, jnp.zeros((), dtype))
        s = tex.m0 + L0 @ jax.random.normal(k_init, (2 * k,), dtype)
        x1, x2 = s[:k], s[k:]
    else:
        x1, x2 = xs[0].astype(dtype), xs[1].astype(dtype)
    V = jax.random.normal(k_dyn, (length - 2, k), dtype)

    def step(carry: tuple[Array, Array], v: Array) -> tuple[tuple[Array, Array], Array]:
        xm1, xm2 = carry
        x = tex.A1 @ xm1 + tex.A2 @ xm2 + tex.d + tex.B @ v
        return (x, xm1), x

    _, rest = lax.scan(step, (x2, x1), V)
    states = jnp.concatenate([x1[None], x2[None], rest], axis=0)
    obs = tex.mu + states @ tex.C.T
    if observation_noise:
        obs = obs + jnp.sqrt(tex.sigma2) * jax.random.normal(k_obs, (length, D), dtype)
    return states, obs


_sample_jit = eqx.filter_jit(_sample_impl)
