"""Baseline densities on observation vectors (design §10.4): a single full-covariance AR(2),
constant velocity and hold-last-frame, each a Gaussian one-step predictor, fitted in closed
form on training sequences.

Every baseline is the same model with different coefficients:

.. code-block:: text

    (y_0, y_1) ~ N(m0, S0)                                     (the first two frames)
    y_t = A1 y_{t−1} + A2 y_{t−2} + c + e_t,   e_t ~ N(0, Σ)    (t ≥ 2)

- AR(2): ``[A1 A2 c]`` by ridge-regularised least squares of ``y_t`` on
  ``[y_{t−1}, y_{t−2}, 1]`` over every ``t`` of every training sequence, ``Σ`` the residual
  covariance (maximum likelihood, floored);
- constant velocity: ``A1 = 2I``, ``A2 = −I``, ``c = 0``;
- hold last frame: ``A1 = I``, ``A2 = 0``, ``c = 0``;

and ``Σ``, ``m0``, ``S0`` fitted on the training residuals and first-pair statistics in each
case. Log-densities are exact: ``log p(y_0:T−1) = log N((y_0, y_1); m0, S0) + Σ_t log N(e_t;
0, Σ)``, so the figures are comparable with the marginal likelihood of a motion texture on the
same observation vectors (every frame scored).

The kernels run in shape buckets (design §11): a sequence is padded (last frame repeated) to
:func:`~mtex_jax.core.bucket_length` frames, every output row depends on its own frame and
the two before it, and the rows of the padding are cut on the host, so one program serves
every length of a bucket and the rows are those of the unpadded computation.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, overload

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..core import as_array, bucket_length, cut_frames, pad_frames

__all__ = ["GaussianAR2", "constant_velocity", "fit_ar2", "hold_last", "prediction_error"]

_KINDS = ("ar2", "constant_velocity", "hold_last")


class GaussianAR2(eqx.Module):
    """A second-order Gaussian one-step predictor on observation vectors (see module doc).

    Attributes:
        A1, A2: ``(D, D)`` coefficients on ``y_{t−1}`` and ``y_{t−2}``.
        c: ``(D,)`` intercept.
        chol: ``(D, D)`` lower Cholesky factor of the innovation covariance ``Σ``.
        m0: ``(2D,)`` mean of the first two frames ``[y_0; y_1]``.
        chol0: ``(2D, 2D)`` lower Cholesky factor of their covariance ``S0``.
        kind: ``"ar2"``, ``"constant_velocity"`` or ``"hold_last"`` (static).
    """

    A1: Float[Array, "D D"]
    A2: Float[Array, "D D"]
    c: Float[Array, " D"]
    chol: Float[Array, "D D"]
    m0: Float[Array, " D2"]
    chol0: Float[Array, "D2 D2"]
    kind: str = eqx.field(static=True)

    def __check_init__(self) -> None:
        D = np.shape(self.c)[0]
        for name, shape in (
            ("A1", (D, D)),
            ("A2", (D, D)),
            ("chol", (D, D)),
            ("m0", (2 * D,)),
            ("chol0", (2 * D, 2 * D)),
        ):
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(
                    f"GaussianAR2.{name} has shape {np.shape(getattr(self, name))}, "
                    f"expected {shape}"
                )
        if self.kind not in _KINDS:
            raise ValueError(f"GaussianAR2.kind must be one of {_KINDS}, got {self.kind!r}")

    @property
    def obs_dim(self) -> int:
        return int(np.shape(self.c)[0])

    def predict(self, Y: Float[ArrayLike, "T D"]) -> Float[Array, "T2 D"]:
        """One-step predictive means ``ŷ_t = A1 y_{t−1} + A2 y_{t−2} + c`` for ``t = 2…T−1``
        (computed in a shape bucket, design §11)."""
        y = _check_seq(Y, self.obs_dim, "Y")
        return cut_frames(_predict(self, _bucketed(y)), y.shape[0] - 2)

    def frame_log_density(self, Y: Float[ArrayLike, "T D"]) -> Float[Array, " T1"]:
        """Per-step log-densities: ``log p(y_0, y_1)`` first, then ``log p(y_t | y_{t−1},
        y_{t−2})`` for ``t = 2…T−1`` (``T − 1`` numbers that sum to ``log p(Y)``; computed
        in a shape bucket, design §11)."""
        y = _check_seq(Y, self.obs_dim, "Y")
        return cut_frames(_frame_log_density(self, _bucketed(y)), y.shape[0] - 1)

    @overload
    def log_likelihood(
        self, Y: Float[ArrayLike, "T D"], *, mean: bool = ..., per_frame: Literal[False] = ...
    ) -> float: ...

    @overload
    def log_likelihood(
        self, Y: Float[ArrayLike, "T D"], *, mean: bool = ..., per_frame: Literal[True]
    ) -> np.ndarray: ...

    def log_likelihood(
        self, Y: Float[ArrayLike, "T D"], *, mean: bool = False, per_frame: bool = False
    ) -> float | np.ndarray:
        """``log p(Y)`` in nats (design §10.4).

        ``mean=True`` divides it by the number of frames ``T``. ``per_frame=True`` returns its
        exact decomposition by the chain rule, ``(T,)`` values summing to ``log p(Y)``:
        ``log p(y_0)`` and ``log p(y_1 | y_0)`` (the first-pair density ``N(m0, S0)`` split
        through its Cholesky factor), then ``log p(y_t | y_{t−1}, y_{t−2})`` for ``t ≥ 2``.
        """
        if mean and per_frame:
            raise ValueError("mean=True and per_frame=True exclude each other")
        y = _check_seq(Y, self.obs_dim, "Y")
        T = y.shape[0]
        if per_frame:
            return np.asarray(_chain_log_density(self, _bucketed(y)), np.float64)[:T]
        # the frames' terms in a shape bucket (design §11), summed on the host
        ll = float(np.sum(np.asarray(_frame_log_density(self, _bucketed(y)))[: T - 1]))
        return ll / (T if mean else 1)


def _bucketed(y: Array) -> Array:
    """``y`` padded to its shape bucket (last frame repeated, design §11)."""
    return pad_frames(y, bucket_length(y.shape[0]), axis=0)


@eqx.filter_jit
def _predict(model: GaussianAR2, Y: Array) -> Array:
    return Y[1:-1] @ model.A1.T + Y[:-2] @ model.A2.T + model.c


def _gauss_logpdf(r: Array, chol: Array) -> Array:
    """``log N(r; 0, L Lᵀ)`` for rows ``r (n, d)``."""
    z = jax.scipy.linalg.solve_triangular(chol, r.T, lower=True)
    d = r.shape[-1]
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diag(chol)))
    return -0.5 * (d * jnp.log(2.0 * jnp.pi) + logdet + jnp.sum(z * z, axis=0))


@eqx.filter_jit
def _frame_log_density(model: GaussianAR2, Y: Array) -> Array:
    first = _gauss_logpdf(jnp.concatenate([Y[0], Y[1]])[None] - model.m0, model.chol0)
    rest = _gauss_logpdf(Y[2:] - _predict(model, Y), model.chol)
    return jnp.concatenate([first, rest])


@eqx.filter_jit
def _chain_log_density(model: GaussianAR2, Y: Array) -> Array:
    """``log p(y_0)``, ``log p(y_1 | y_0)``, then the one-step terms: with ``S0 = L Lᵀ`` and
    ``z = L⁻¹([y_0; y_1] − m0)``, the first ``D`` entries of ``z`` whiten ``y_0`` under its
    marginal and the last ``D`` whiten ``y_1`` given ``y_0`` (``L`` is block lower
    triangular)."""
    D = Y.shape[1]
    z = jax.scipy.linalg.solve_triangular(
        model.chol0, jnp.concatenate([Y[0], Y[1]]) - model.m0, lower=True
    )
    logd = jnp.log(jnp.diag(model.chol0))
    c = 0.5 * D * jnp.log(2.0 * jnp.pi)
    first = -c - jnp.sum(logd[:D]) - 0.5 * jnp.sum(z[:D] ** 2)
    second = -c - jnp.sum(logd[D:]) - 0.5 * jnp.sum(z[D:] ** 2)
    rest = _gauss_logpdf(Y[2:] - _predict(model, Y), model.chol)
    return jnp.concatenate([jnp.stack([first, second]), rest])


def _check_seq(Y: ArrayLike, D: int | None, name: str) -> Array:
    # checked on the host: an eager jnp operation would compile a program per length
    y = as_array(Y)
    if y.ndim != 2 or (D is not None and y.shape[1] != D):
        want = "(T, D)" if D is None else f"(T, {D})"
        raise ValueError(f"{name} must have shape {want}, got {tuple(y.shape)}")
    if y.shape[0] < 3:
        raise ValueError(f"{name} has {y.shape[0]} frames; a second-order model needs >= 3")
    if not jnp.issubdtype(y.dtype, jnp.floating):
        y = as_array(np.asarray(y).astype(jnp.result_type(float)))
    if not np.isfinite(np.asarray(y)).all():
        raise ValueError(f"{name} contains NaN or inf")
    return y


def _check_list(Ys: Sequence[ArrayLike] | ArrayLike) -> list[Array]:
    if isinstance(Ys, np.ndarray | jax.Array) and np.ndim(Ys) == 2:
        Ys = [Ys]
    if not isinstance(Ys, Sequence | np.ndarray | jax.Array) or len(Ys) == 0:
        raise ValueError("need a non-empty list of (T, D) training sequences")
    out = [_check_seq(y, None, f"sequence {i}") for i, y in enumerate(Ys)]
    D = out[0].shape[1]
    for i, y in enumerate(out):
        if y.shape[1] != D:
            raise ValueError(f"sequence {i} has dimension {y.shape[1]}, sequence 0 has {D}")
    return out


def _chol_floor(S: np.ndarray, floor: float) -> np.ndarray:
    S = 0.5 * (S + S.T) + floor * np.eye(S.shape[0])
    return np.linalg.cholesky(S)


def finish(
    Ys: list[Array], A1: np.ndarray, A2: np.ndarray, c: np.ndarray, kind: str, floor: float
) -> GaussianAR2:
    dtype = Ys[0].dtype
    Yn = [np.asarray(y, np.float64) for y in Ys]
    R = np.concatenate([y[2:] - y[1:-1] @ A1.T - y[:-2] @ A2.T - c for y in Yn])
    Sigma = R.T @ R / R.shape[0]
    # the first pair of a clip may be any pair of the motion: its density is fitted on all
    pairs = np.concatenate([np.concatenate([y[:-1], y[1:]], axis=1) for y in Yn])
    m0 = pairs.mean(axis=0)
    S0 = np.cov(pairs, rowvar=False, bias=True)

    def arr(a):
        return jnp.asarray(a, dtype)

    return GaussianAR2(
        A1=arr(A1),
        A2=arr(A2),
        c=arr(c),
        chol=arr(_chol_floor(Sigma, floor)),
        m0=arr(m0),
        chol0=arr(_chol_floor(S0, floor)),
        kind=kind,
    )


def fit_ar2(
    Ys: Sequence[ArrayLike] | ArrayLike, *, ridge: float = 1e-4, floor: float = 1e-6
) -> GaussianAR2:
    """Fit a full-covariance AR(2) ``y_t = A1 y_{t−1} + A2 y_{t−2} + c + e_t`` in closed form.

    ``[A1 A2 c] = (Zᵀ Z + λ N I')⁻¹ Zᵀ Y`` with ``Z = [y_{t−1}, y_{t−2}, 1]`` over every
    ``t ≥ 2`` of every sequence, ``N`` the number of such ``t`` and ``I'`` the identity without
    the intercept (the ridge ``λ`` is relative, so it does not depend on the amount of data);
    ``Σ`` is the mean outer product of the residuals plus ``floor · I``.

    Args:
        Ys: training sequences ``(T_i, D)`` (or one ``(T, D)`` array), ``T_i ≥ 3``.
        ridge: relative ridge ``λ ≥ 0`` on the coefficients.
        floor: added to the diagonal of the covariances.

    Returns:
        a :class:`GaussianAR2` of kind ``"ar2"`` (dtype of the first sequence).
    """
    if not (np.isfinite(ridge) and ridge >= 0) or not (np.isfinite(floor) and floor > 0):
        raise ValueError(f"ridge must be >= 0 and floor > 0, got ridge={ridge}, floor={floor}")
    Ys = _check_list(Ys)
    Yn = [np.asarray(y, np.float64) for y in Ys]
    D = Yn[0].shape[1]
    Z = np.concatenate(
        [np.concatenate([y[1:-1], y[:-2], np.ones((len(y) - 2, 1))], axis=1) for y in Yn]
    )
    T = np.concatenate([y[2:] for y in Yn])
    reg = ridge * Z.shape[0] * np.diag(np.r_[np.ones(2 * D), 0.0])
    W = np.linalg.solve(Z.T @ Z + reg, Z.T @ T)  # (2D + 1, D)
    return finish(Ys, W[:D].T, W[D : 2 * D].T, W[2 * D], "ar2", floor)


def constant_velocity(Ys: Sequence[ArrayLike] | ArrayLike, *, floor: float = 1e-6) -> GaussianAR2:
    """The constant-velocity predictor ``ŷ_t = 2 y_{t−1} − y_{t−2}`` with its innovation
    covariance fitted on ``Ys``."""
    Ys = _check_list(Ys)
    D = Ys[0].shape[1]
    return finish(Ys, 2.0 * np.eye(D), -np.eye(D), np.zeros(D), "constant_velocity", floor)


def hold_last(Ys: Sequence[ArrayLike] | ArrayLike, *, floor: float = 1e-6) -> GaussianAR2:
    """The hold-last-frame predictor ``ŷ_t = y_{t−1}`` with its innovation covariance fitted on
    ``Ys``."""
    Ys = _check_list(Ys)
    D = Ys[0].shape[1]
    return finish(Ys, np.eye(D), np.zeros((D, D)), np.zeros(D), "hold_last", floor)


def prediction_error(predicted: Float[ArrayLike, "n D"], actual: Float[ArrayLike, "n D"]) -> float:
    """Mean squared one-step prediction error per dimension, ``mean_{t,d} (ŷ_td − y_td)²``
    (in the units of the observation vectors: z-units for a feature map's)."""
    p, a = np.asarray(predicted, np.float64), np.asarray(actual, np.float64)
    if p.shape != a.shape or p.ndim != 2:
        raise ValueError(f"predicted {p.shape} and actual {a.shape} must be equal (n, D) shapes")
    return float(np.mean((p - a) ** 2))
