"""Input checks and small numerical helpers shared by the texture modules (dtype, finiteness,
shapes, symmetric eigendecomposition and PSD Cholesky with floors)."""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jax import lax
from jaxtyping import Array

from ...core import as_array
from ...linalg import sym as sym

LOG_2PI = math.log(2.0 * math.pi)

#: Largest state dimension whose sums over the state index the blocked frame-term kernel
#: unrolls (larger ones are one vectorised reduction: an unrolled program compiles slowly).
UNROLL_MAX_K = 16


# --------------------------------------------------------------------------------------------
# Input validation (eager, before tracing)
# --------------------------------------------------------------------------------------------


def float_dtype(*xs: Any) -> Any:
    dtype = jnp.result_type(*xs)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    return dtype


def as_float_array(name: str, x: Any, ndims: tuple[int, ...], shape_doc: str) -> Array:
    if x is None:
        raise ValueError(f"{name} must be an array of shape {shape_doc}, got None")
    x = as_array(x)
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise ValueError(f"{name} must be real, got dtype {x.dtype}")
    if x.ndim not in ndims:
        raise ValueError(f"{name} must have shape {shape_doc}, got shape {tuple(x.shape)}")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(float_dtype(x))
    return x


def check_finite(name: str, x: Array) -> None:
    """Eagerly reject NaN/inf when ``x`` is concrete (inside a trace, ``eqx.error_if`` acts)."""
    try:
        xn = np.asarray(x)
    except jax.errors.TracerArrayConversionError:
        return
    finite = np.isfinite(xn)
    if not finite.all():
        bad = tuple(int(i) for i in np.argwhere(~finite)[0])
        raise ValueError(f"{name} (shape {xn.shape}) contains NaN or inf, first at index {bad}")


def error_if_nonfinite(x: Array, name: str) -> Array:
    return eqx.error_if(x, ~jnp.all(jnp.isfinite(x)), f"{name} contains NaN or inf")


def check_obs(name: str, Y: Any, D: int, min_len: int = 1) -> Array:
    Y = as_float_array(name, Y, (2,), "(T, D)")
    if Y.shape[1] != D:
        raise ValueError(f"{name} has shape {tuple(Y.shape)} but the texton expects D={D} columns")
    if Y.shape[0] < min_len:
        raise ValueError(f"{name} needs at least {min_len} frames, got shape {tuple(Y.shape)}")
    check_finite(name, Y)
    return Y


def check_mask(mask: Any, lead_shape: tuple[int, ...]) -> Array:
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


def check_positive(name: str, value: Any, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {bound}, got {value!r}")
    return v


def check_state_dim(state_dim: Any, D: int, shape: tuple[int, ...]) -> int:
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


def _fix_signs(V: Array) -> Array:
    """Flip eigenvector columns so that each column's largest-magnitude entry is positive."""
    idx = jnp.argmax(jnp.abs(V), axis=0)
    s = jnp.sign(V[idx, jnp.arange(V.shape[1])])
    s = jnp.where(s == 0, 1, s)
    return V * lax.stop_gradient(s)


@jax.custom_jvp
def eigh_desc(S: Array) -> tuple[Array, Array]:
    """Eigen-decomposition of a symmetric matrix, eigenvalues in descending order.

    Sign convention of :func:`_fix_signs`. The JVP is the usual first-order perturbation
    formula ``dV = V (F ∘ Vᵀ dS V)``, ``F_ij = 1/(λ_j − λ_i)``, except that ``F_ij = 0`` for
    (numerically) equal eigenvalues, where the eigenvectors are not differentiable. This keeps
    gradients finite (e.g. for the discarded, degenerate part of a PCA).
    """
    w, V = jnp.linalg.eigh(S)
    return w[::-1], _fix_signs(V[:, ::-1])


@eigh_desc.defjvp
def _eigh_desc_jvp(primals: tuple[Array], tangents: tuple[Array]) -> Any:
    (S,) = primals
    (dS,) = tangents
    w, V = eigh_desc(S)
    M = V.T @ sym(dS) @ V
    gap = w[None, :] - w[:, None]
    scale = jnp.max(jnp.abs(w))
    tol = 16 * jnp.finfo(S.dtype).eps * S.shape[0] * scale + jnp.finfo(S.dtype).tiny
    safe = jnp.abs(gap) > tol
    F = jnp.where(safe, 1.0 / jnp.where(safe, gap, 1.0), 0.0)
    return (w, V), (jnp.diagonal(M), V @ (F * M))


def psd_cholesky(M: Array, floor: Array | float) -> Array:
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
    M = sym(M)
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


def gauss_logpdf_chol(r: Array, L: Array, dof: float | None = None) -> Array:
    """``log N(r; 0, L Lᵀ)`` for residual vectors ``r (..., n)``; with ``dof``, the
    Student-t density of :func:`innovation_logpdf` with scale matrix ``L Lᵀ``."""
    n = L.shape[-1]
    u = jsl.solve_triangular(L, jnp.moveaxis(r, -1, 0).reshape(n, -1), lower=True)
    maha = jnp.sum(u * u, axis=0).reshape(r.shape[:-1])
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(L)))
    return innovation_logpdf(maha, logdet, n, dof)


def innovation_logpdf(maha: Array, logdet: Array, n: int, dof: float | None) -> Array:
    """Log-density of an ``n``-dimensional innovation from its squared Mahalanobis norm
    ``q = rᵀ Q⁻¹ r`` and ``log|Q|``.

    .. code-block:: text

        Gaussian (dof None):  −½ (n log 2π + log|Q| + q)
        Student-t (dof ν):    log Γ((ν+n)/2) − log Γ(ν/2) − (n/2) log(νπ) − ½ log|Q|
                              − ((ν+n)/2) log(1 + q/ν)

    (``Q`` is the t's scale matrix; its covariance is ``ν/(ν−2) Q`` for ``ν > 2``.)
    """
    if dof is None:
        return -0.5 * (n * LOG_2PI + logdet + maha)
    nu = float(dof)
    const = math.lgamma((nu + n) / 2) - math.lgamma(nu / 2) - 0.5 * n * math.log(nu * math.pi)
    return const - 0.5 * logdet - 0.5 * (nu + n) * jnp.log1p(maha / nu)


def student_weights(maha: Array, n: int, dof: float) -> Array:
    """IRLS / EM weights ``w = (ν + n) / (ν + q)`` of Student-t innovations: the posterior
    mean of each innovation's precision scale (the E-step of the t as a scale mixture of
    Gaussians)."""
    return (dof + n) / (dof + maha)


def check_dof(dof: Any, where: str = "dof") -> float | None:
    """``None`` (Gaussian innovations) or a degrees-of-freedom ``ν > 0`` as a float. (Which
    observation models allow Student-t innovations: :meth:`ObservationModel.check_dof`.)"""
    if dof is None:
        return None
    if isinstance(dof, bool) or not isinstance(dof, int | float | np.integer | np.floating):
        raise ValueError(f"{where} must be None or a number > 0, got {dof!r}")
    if not math.isfinite(float(dof)) or float(dof) <= 0:
        raise ValueError(f"{where} must be None or a finite number > 0, got {dof!r}")
    return float(dof)


def check_positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"{name} must be a positive int, got {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {value}")
    return int(value)


def companion_blocks(A1: Array, A2: Array) -> Array:
    k = A1.shape[-1]
    batch = A1.shape[:-2]
    eye = jnp.broadcast_to(jnp.eye(k, dtype=A1.dtype), (*batch, k, k))
    zero = jnp.zeros_like(A1)
    top = jnp.concatenate([A1, A2], axis=-1)
    bottom = jnp.concatenate([eye, zero], axis=-1)
    return jnp.concatenate([top, bottom], axis=-2)


def project_radius(A1: Array, A2: Array, rho_max: float) -> tuple[Array, Array]:
    """``(A1, A2)`` scaled so that the companion spectral radius is at most ``rho_max``
    (design §2.7): ``A_j ← s^j A_j`` scales every eigenvalue by ``s``."""
    rho = jnp.max(jnp.abs(jnp.linalg.eigvals(companion_blocks(A1, A2))))
    rho = rho.astype(A1.dtype)
    s = jnp.where(rho > rho_max, rho_max / jnp.where(rho > 0, rho, 1.0), 1.0)
    # tiny safety margin so that rounding in the eigenvalues never leaves rho > rho_max
    s = jnp.where(rho > rho_max, s * (1 - 4 * jnp.finfo(A1.dtype).eps), s)
    return s * A1, (s * s) * A2
