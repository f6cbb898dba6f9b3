"""The temporal structure of the textons' innovations, for synthesis.

The density model (design §2) treats the whitened innovations ``u_j = B⁻¹(x_j − A1 x_{j−1} −
A2 x_{j−2} − d)`` of a texton as independent from frame to frame: ``N(0, I_k)``, or
``t_ν(0, I_k)`` as the scale mixture ``u_j = z_j / √g_j``, ``g_j ~ Gamma(ν/2, rate ν/2)``.
Measured on the training residuals of real dance they are not (the 10 training clips of the
quality split, 60 Hz, the default texture):

* their autocorrelation, pooled over dimensions, is ``r_1 … r_4 = 0.15, −0.45, −0.11, 0.05``:
  the power sits around a quarter of the frame rate and little of it at the Nyquist frequency,
  where white noise puts as much as anywhere (jerk, a third difference, weighs exactly that);
* their scale persists: ``log ‖u_j‖²`` keeps an autocorrelation of 0.55 at a lag of 5 frames
  and 0.31 at 15. Calm stretches and bursts last, where independent scales
  average out within a few frames.

Synthesis from white innovations is therefore too jerky and too uniformly busy (design §10.8;
the documentation's results page has the figures). An :class:`InnovationProcess` keeps the
per-frame law of the innovations and adds the two measured dependences:

.. code-block:: text

    g_j = b_j g_{j−1} + c_j,   b_j ~ Beta(aρ, a(1−ρ)),  c_j ~ Gamma(a(1−ρ), rate a),  a = ν/2
    w_j = z_j / √g_j,          z_j ~ N(0, I_k)
    v_j = Σ_{i=1}^p φ_i v_{j−i} + s w_j,   φ = R_p⁻¹ r,   s² = 1 − φ·r

The scale chain is the beta–gamma autoregression (its stationary law is ``Gamma(a, rate a)``
and ``corr(g_j, g_{j−1}) = ρ``), so each ``w_j`` is still ``t_ν``; the AR(p) filter with the
Yule–Walker coefficients of ``r`` (``R_p`` the Toeplitz matrix of ``1, r_1 … r_{p−1}``) gives
``v`` exactly the autocorrelation ``r_1 … r_p`` and the variance of ``w`` (``s`` is its
innovation scale). The filter starts in its stationary state. Gaussian textons use ``w = z``.

Both statistics are estimated in closed form after learning (:func:`fit_innovation_process`),
on the training residuals of the final segmentation; nothing is tuned.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float

from .._texton.texton import Texton
from .draws import standard_normal

__all__ = [
    "InnovationProcess",
    "draw_innovations",
    "fit_innovation_process",
    "innovation_statistics",
    "process_from_statistics",
    "segment_innovations",
]

ORDER = 4  # AR order of the colour filter
_LAGS = (5, 15)  # lags whose autocorrelations give the scale persistence
_RHO_MAX = 0.999


class InnovationProcess(eqx.Module):
    """Autocorrelation and scale persistence of a texture's whitened innovations.

    Attributes:
        acf: ``(p,)`` autocorrelations ``r_1 … r_p`` of the innovations, pooled over
            dimensions; the Toeplitz matrix of ``1, r_1 … r_p`` must be positive definite.
            Zeros: white innovations.
        persistence: ``ρ ∈ [0, 1)``, the lag-1 correlation of the Student-t scale chain
            (0: independent scales; unused by Gaussian textons).
    """

    acf: Float[Array, " p"]
    persistence: Float[Array, ""]

    def __check_init__(self) -> None:
        r = np.asarray(self.acf)
        if r.ndim != 1 or r.size < 1:
            raise ValueError(f"InnovationProcess.acf must have shape (p,), got {r.shape}")
        if np.shape(self.persistence) != ():
            raise ValueError("InnovationProcess.persistence must be a scalar")
        if isinstance(self.acf, Tracer) or isinstance(self.persistence, Tracer):
            return
        if not np.isfinite(r).all() or not _positive_definite(r):
            raise ValueError(
                "InnovationProcess.acf must be finite autocorrelations whose Toeplitz matrix "
                f"is positive definite, got {r.tolist()}"
            )
        rho = float(np.asarray(self.persistence))
        if not 0.0 <= rho < 1.0:
            raise ValueError(f"InnovationProcess.persistence must be in [0, 1), got {rho}")

    @property
    def order(self) -> int:
        return int(np.shape(self.acf)[0])


def _positive_definite(r: np.ndarray) -> bool:
    from scipy.linalg import toeplitz

    return bool(np.linalg.eigvalsh(toeplitz(np.concatenate([[1.0], r]))).min() > 1e-9)


def innovation_statistics(
    innovations: Sequence[Float[ArrayLike, "n k"]], order: int = ORDER
) -> np.ndarray:
    """Additive sufficient statistics of :func:`fit_innovation_process` (numpy, float64).

    Sums over segments, so the statistics of disjoint sets of segments (the clips of the
    processes of a distributed learn) add up: ``Σ‖u_j‖²`` and ``Σ u_j·u_{j−h}`` for
    ``h = 1 … p``; for ``ℓ_j = log ‖u_j‖²`` the count, ``Σℓ``, ``Σℓ²`` and, for each lag ``h``
    of :data:`_LAGS`, ``Σ ℓ_j ℓ_{j−h}``, ``Σ ℓ_j``, ``Σ ℓ_{j−h}`` and the number of pairs.
    Lags never cross a segment boundary.

    Raises:
        ValueError: inconsistent ``k``, NaN values or ``order < 1``.
    """
    if isinstance(order, bool) or not isinstance(order, int) or order < 1:
        raise ValueError(f"order must be a positive integer, got {order!r}")
    u = [np.asarray(x, dtype=np.float64) for x in innovations]
    if any(x.ndim != 2 or x.shape[1] != u[0].shape[1] for x in u):
        raise ValueError("fit_innovation_process: innovations must be (n_s, k) with one k")
    if not all(np.isfinite(x).all() for x in u):
        raise ValueError("fit_innovation_process: innovations contain NaN or inf")
    u = [x for x in u if x.shape[0]]
    out = [sum(float(np.sum(x * x)) for x in u)]
    out += [
        sum(float(np.sum(x[h:] * x[:-h])) for x in u if len(x) > h) for h in range(1, order + 1)
    ]
    logs = [np.log(np.sum(x * x, axis=1) + np.finfo(float).tiny) for x in u]
    out += [sum(float(ell.size) for ell in logs)]
    out += [sum(float(ell.sum()) for ell in logs), sum(float(ell @ ell) for ell in logs)]
    for h in _LAGS:
        pairs = [ell for ell in logs if ell.size > h]
        out += [
            sum(float(ell[h:] @ ell[:-h]) for ell in pairs),
            sum(float(ell[h:].sum()) for ell in pairs),
            sum(float(ell[:-h].sum()) for ell in pairs),
            sum(float(ell.size - h) for ell in pairs),
        ]
    return np.asarray(out)


def process_from_statistics(stats: ArrayLike, order: int = ORDER) -> InnovationProcess:
    """The :class:`InnovationProcess` of summed :func:`innovation_statistics`.

    * ``acf``: ``r_h = Σ u_j·u_{j−h} / Σ ‖u_j‖²`` (the biased, positive-definite estimator);
      white (zeros) if the Toeplitz matrix is not positive definite.
    * ``persistence``: with ``c_h`` the autocorrelation of ``ℓ_j = log ‖u_j‖²`` (centred at
      its mean), ``ρ = (c_15 / c_5)^(1/10)``: the decay rate of the scale's autocorrelation,
      read at lags long enough for the colour (lags ≤ 4) not to enter. 0 when either is not
      positive or no segment is longer than 15 frames; at most 0.999.

    Raises:
        ValueError: statistics of the wrong length or without any frame.
    """
    st = np.asarray(stats, dtype=np.float64)
    if st.shape != (1 + order + 3 + 4 * len(_LAGS),) or not np.isfinite(st).all():
        raise ValueError(f"innovation statistics for order {order} have the wrong shape {st.shape}")
    den, num = st[0], st[1 : 1 + order]
    n, s1, s2 = st[1 + order : 4 + order]
    if not (den > 0 and n > 0):
        raise ValueError("fit_innovation_process: no innovations")
    r = num / den
    if not _positive_definite(r):
        r = np.zeros(order)
    m = s1 / n
    var = s2 / n - m * m
    c = []
    for i in range(len(_LAGS)):
        prod, left, right, pairs = st[4 + order + 4 * i : 8 + order + 4 * i]
        cov = (prod - m * (left + right) + m * m * pairs) / n  # biased, like the variance
        c.append(cov / var if var > 0 and pairs > 0 else 0.0)
    rho = 0.0
    if c[0] > 0 and c[1] > 0:
        rho = float(min((c[1] / c[0]) ** (1.0 / (_LAGS[1] - _LAGS[0])), _RHO_MAX))
    return InnovationProcess(acf=jnp.asarray(r), persistence=jnp.asarray(rho))


def fit_innovation_process(
    innovations: Sequence[Float[ArrayLike, "n k"]], order: int = ORDER
) -> InnovationProcess:
    """Estimate an :class:`InnovationProcess` from whitened innovations, segment by segment:
    :func:`process_from_statistics` of :func:`innovation_statistics`.

    Args:
        innovations: ``(n_s, k)`` whitened innovations ``B⁻¹ e`` of each training segment.
        order: ``p``, the number of autocorrelations kept (the AR order of the filter).

    Returns:
        The process.

    Raises:
        ValueError: no innovations, inconsistent ``k``, NaN values or ``order < 1``.
    """
    return process_from_statistics(innovation_statistics(innovations, order), order)


def segment_innovations(
    textons: Texton, ys: Sequence[np.ndarray], segments: np.ndarray
) -> list[np.ndarray]:
    """Whitened innovations ``B⁻¹(x_j − A1 x_{j−1} − A2 x_{j−2} − d)``, ``x = Cᵀ(y − μ)``, of
    every segment ``(seq, start, length, label)`` under its texton (numpy, float64):
    ``(length − 2, k)`` each."""
    names = ("mu", "C", "A1", "A2", "d", "B")
    leaves = {f: np.asarray(getattr(textons, f), dtype=np.float64) for f in names}
    out = []
    for s, a, n, i in np.asarray(segments, dtype=np.int64):
        t = {f: v[i] for f, v in leaves.items()}
        x = (np.asarray(ys[s][a : a + n], dtype=np.float64) - t["mu"]) @ t["C"]
        e = x[2:] - x[1:-1] @ t["A1"].T - x[:-2] @ t["A2"].T - t["d"]
        out.append(np.linalg.solve(t["B"], e.T).T)
    return out


def _filter(process: InnovationProcess, dtype: jnp.dtype) -> tuple[Array, Array, Array]:
    """``(φ (p,), s, L (p, p))``: Yule–Walker coefficients, innovation scale and the Cholesky
    factor of the stationary covariance ``R_p`` of ``(v_{j−1} … v_{j−p})``."""
    r = process.acf.astype(dtype)
    p = r.shape[0]
    full = jnp.concatenate([jnp.ones((1,), dtype), r])
    idx = jnp.abs(jnp.arange(p)[:, None] - jnp.arange(p)[None, :])
    R = full[idx]
    phi = jnp.linalg.solve(R, r)
    s = jnp.sqrt(jnp.maximum(1.0 - phi @ r, 0.0))
    return phi, s, jnp.linalg.cholesky(R)


def _draw_innovations(
    key: Array, process: InnovationProcess, shape: tuple[int, ...], dtype, dof: float | None
) -> Array:
    """Innovations ``v`` of shape ``(…, n, k)`` (time on axis −2) from ``process``.

    Each leading index is an independent stretch; along time the scale chain and the AR filter
    of the module docstring run from their stationary laws. ``dof=None``: Gaussian textons
    (``w = z``, no scale chain).

    The stationary start ``(v_{−1} … v_{−p})`` is Gaussian with the covariance
    ``var(w) R_p``; for ``ν ≤ 2`` (infinite variance) ``var(w)`` is taken as 1.

    Raises:
        TypeError: ``process`` is not an :class:`InnovationProcess`.
        ValueError: ``shape`` has fewer than two axes or an empty one; ``dof`` not positive.
    """
    if not isinstance(process, InnovationProcess):
        raise TypeError(
            f"draw_innovations: process must be an InnovationProcess, got {type(process).__name__}"
        )
    shape = tuple(int(s) for s in shape)
    if len(shape) < 2 or min(shape) < 1:
        raise ValueError(
            f"draw_innovations: shape must be (..., n, k) with every axis ≥ 1, got {shape}"
        )
    if dof is not None and not float(dof) > 0:
        raise ValueError(f"draw_innovations: dof must be positive or None, got {dof}")
    n, batch = shape[-2], shape[:-2]
    k_z, k_0, k_g = jax.random.split(key, 3)
    z = standard_normal(k_z, shape, dtype)
    if dof is not None:
        g = _scale_chain(k_g, dof / 2, process.persistence.astype(dtype), (n, *batch), dtype)
        z = z / jnp.sqrt(jnp.moveaxis(g, 0, -1))[..., None]
    phi, s, L = _filter(process, dtype)
    p = phi.shape[0]
    # stationary start: (v_{−1} … v_{−p}) ~ N(0, var(w) R_p) per column
    z0 = standard_normal(k_0, (p, *batch, shape[-1]), dtype)
    var_w = 1.0 if dof is None else (dof / (dof - 2) if dof > 2 else 1.0)
    c0 = jnp.tensordot(L, z0, axes=1) * float(np.sqrt(var_w))

    def step(carry: Array, w: Array) -> tuple[Array, Array]:
        v = s * w + jnp.tensordot(phi, carry, axes=1)
        return jnp.concatenate([v[None], carry[:-1]]), v

    _, v = lax.scan(step, c0, jnp.moveaxis(z, -2, 0))
    return jnp.moveaxis(v, 0, -2)


draw_innovations = eqx.filter_jit(_draw_innovations)


def _scale_chain(key: Array, a: float, rho: Array, shape: tuple[int, ...], dtype) -> Array:
    """``g`` ``(n, …)``: the beta–gamma AR(1) chain along axis 0 with ``Gamma(a, rate a)``
    marginals and lag-1 correlation ``ρ`` (independent draws when ``ρ = 0``).

    All gamma variates come from one :func:`jax.random.loggamma` call (one sampler to
    compile, not five): ``log X ~ logGamma(aρ)``, ``log Y, log c ~ logGamma(a(1 − ρ))`` and
    ``log(a g_0) ~ logGamma(a)``; ``b = X / (X + Y)`` is formed in log space, which stays
    finite where ``X`` and ``Y`` underflow (shape parameters near 0). ``ρ = 0`` sets ``b = 0``,
    so that ``g_j = c_j ~ Gamma(a, rate a)``.
    """
    n_b = int(np.prod(shape[1:]))
    size = shape[0] * n_b
    on = rho > 0
    r = jnp.where(on, jnp.clip(rho, 1e-6, _RHO_MAX), 0.0).astype(dtype)
    alpha = jnp.concatenate(
        [
            jnp.full((size,), a * jnp.maximum(r, 1e-6), dtype),  # X
            jnp.full((2 * size,), a * (1 - r), dtype),  # Y, c
            jnp.full((n_b,), a, dtype),  # g_0
        ]
    )
    lg = jax.random.loggamma(key, alpha, dtype=dtype)
    lx, ly, lc = lg[:size], lg[size : 2 * size], lg[2 * size : 3 * size]
    b = jnp.where(on, jnp.exp(lx - jnp.logaddexp(lx, ly)), 0.0).reshape(shape)
    c = (jnp.exp(lc) / a).reshape(shape)
    g0 = (jnp.exp(lg[3 * size :]) / a).reshape(shape[1:])

    def step(g: Array, bc: tuple[Array, Array]) -> tuple[Array, Array]:
        g = bc[0] * g + bc[1]
        return g, g

    _, chain = lax.scan(step, g0, (b, c))
    return chain
