"""Textons: second-order linear dynamic systems (design §2, §3; MT §3.2 and App. B).

A texton ``i`` is the linear dynamic system

.. code-block:: text

    y_t     = mu + C x_t + w_t,                     w_t ~ N(0, sigma2 I_D)     (MT-11)
    x_{t+1} = A1 x_t + A2 x_{t-1} + d + B v_t,      v_t ~ N(0, I_k)            (MT-10)
    [x_1; x_2] ~ N(m0, S0)

with ``C`` a ``(D, k)`` matrix of orthonormal columns and ``Q = B Bᵀ`` (``B`` lower triangular).

The *observation model* (:attr:`Texton.observation`: a member, which owns its
parameters) says how the part of
``y`` outside the state subspace, the residual ``r_t = (I − C Cᵀ)(y_t − μ)``, is scored:

* :class:`PaperObservation` (MT-11): white noise, ``r_t ~ N(0, σ² I_{D−k})`` on every frame;
* :class:`ResidualObservation`: the first two frames of a segment as in the paper, then an
  isotropic AR(2) on the residual, ``r_t = a₁ r_{t−1} + a₂ r_{t−2} + e_t``,
  ``e_t ~ N(0, s_r² I_{D−k})`` in the residual subspace (the member's ``a = (a₁, a₂)`` and
  ``s2 = s_r²``). The residual of smooth motion is smooth, so its one-step prediction error is
  far smaller than its variance;
* :class:`FullObservation`: ``k = D`` (no residual): the texton is a full-covariance AR(2) on
  ``y`` and the texture an autoregressive hidden semi-Markov model;
* :class:`TiedObservation` (the default of :class:`~mtex_jax.texture.LearnConfig`): full
  textons whose dynamics are shared by the vocabulary, each with its own offset and shrunk
  covariance (design §10.10). One texton is scored as a full one; only the vocabulary's
  M-step differs.

A full (or tied) texton may have Student-t dynamics innovations (static :attr:`Texton.dof` ``= ν``):
``x_{t+1} = A1 x_t + A2 x_{t−1} + d + ε_t``, ``ε_t ~ t_ν(0, B Bᵀ)``. Real capture has rare
large innovations (glitches, sudden contacts); a Gaussian fitted to them inflates ``Q`` for
every frame, a t down-weights them (its M-step is iteratively reweighted least squares).

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

from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, Float

from .._observation import ObservationModel, PaperObservation, check_observation
from .checks import check_dof, companion_blocks

# --------------------------------------------------------------------------------------------
# Texton container
# --------------------------------------------------------------------------------------------


def _dof(dof: Any) -> float | None:
    return check_dof(dof, where="Texton.dof")


class Texton(eqx.Module):
    """Parameters of one texton, or of a stack of ``N_t`` textons (design §2).

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
        observation: the observation model, a member that owns its parameters (each with
            the texton's batch shape in front; see the module doc). Default: the paper's.
        dof: degrees of freedom ``ν`` of Student-t dynamics innovations (static; only for
            an observation model that takes them, ``student_t``):
            ``x_t = A1 x_{t−1} + A2 x_{t−2} + d + ε_t`` with ``ε_t ~ t_ν(0, Q)``, a scale
            mixture ``ε_t = B v_t / √g_t``, ``v_t ~ N(0, I)``,
            ``g_t ~ Gamma(ν/2, rate ν/2)``. ``None``: Gaussian innovations ``N(0, Q)``.
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
    observation: ObservationModel = PaperObservation()
    dof: float | None = eqx.field(static=True, default=None, converter=_dof)

    def __check_init__(self) -> None:
        check_observation(self.observation, "Texton.observation")
        self.observation.check_dof(self.dof, where="Texton.dof")
        shapes = {name: getattr(getattr(self, name), "shape", None) for name in TEXTON_FIELDS}
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
        try:
            self.observation.check_state_dim(D, k)
            self.observation.check_shapes(batch, D, k)
        except ValueError as e:
            raise ValueError(f"Texton.{e}") from None

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
        """Index/slice a stack of textons along the leading texton axis.

        An integer (or a concrete array of integers) outside ``[-N_t, N_t)`` is an
        ``IndexError``, as for a list (JAX would clamp it to the last texton); a traced index
        (under ``jit``) cannot be checked and is clamped.
        """
        if not self.is_stacked:
            raise TypeError("a single (unstacked) Texton cannot be indexed")
        check_index(index, self.n_textons, "texton")
        return jax.tree.map(lambda x: x[index], self)


#: The dynamics core's array fields (the observation member holds its own).
TEXTON_FIELDS = ("mu", "C", "A1", "A2", "d", "B", "sigma2", "m0", "S0")


def check_index(index: Any, n: int, what: str) -> None:
    """``IndexError`` if a concrete integer ``index`` (or array of them) lies outside
    ``[-n, n)``; slices, booleans masks of length ``n`` and traced indices pass unchecked."""
    if isinstance(index, slice | Tracer) or index is None or index is Ellipsis:
        return
    if isinstance(index, tuple):
        if index:
            check_index(index[0], n, what)
        return
    a = np.asarray(index)
    if a.dtype == bool:
        if a.shape[:1] != (n,):
            raise IndexError(f"a boolean {what} mask must have length {n}, got shape {a.shape}")
        return
    if a.dtype.kind not in "iu":
        raise IndexError(f"{what} index must be an integer or a slice, got {index!r}")
    if a.size and (a.min() < -n or a.max() >= n):
        bad = int(a.max()) if a.max() >= n else int(a.min())
        raise IndexError(f"{what} index {bad} is out of range for {n} {what}s")


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
        if t.dof != first.dof:
            raise ValueError(
                f"stack_textons: element {j} has dof {t.dof}, element 0 has {first.dof}"
            )
        if type(t.observation) is not type(first.observation):
            raise ValueError(
                f"stack_textons: element {j} has observation model {t.observation.name!r}, "
                f"element 0 has {first.observation.name!r}"
            )
        if (t.obs_dim, t.state_dim) != (first.obs_dim, first.state_dim):
            raise ValueError(
                f"stack_textons: element {j} has (D, k) = ({t.obs_dim}, {t.state_dim}), "
                f"element 0 has ({first.obs_dim}, {first.state_dim})"
            )
    return jax.tree.map(_stack_leaves, *textons)


def _stack_leaves(*xs: Array) -> Array:
    """``jnp.stack(xs)``; concrete leaves are stacked on the host (an eager ``jnp.stack``, or
    ``jnp.asarray`` of a NumPy array, compiles once per number of textons)."""
    if any(isinstance(x, Tracer) for x in xs):
        return jnp.stack(xs)
    return jax.device_put(np.stack([np.asarray(x) for x in xs]))


def companion_matrix(texton: Texton) -> Float[Array, "*batch k2 k2"]:
    """Companion matrix ``[[A1, A2], [I, 0]]`` of the second-order dynamics, ``(*batch, 2k, 2k)``.

    The stacked state ``[x_t; x_{t-1}]`` evolves as ``[x_{t+1}; x_t] = F [x_t; x_{t-1}] + ...``.
    """
    return companion_blocks(texton.A1, texton.A2)


def spectral_radius(texton: Texton) -> Float[Array, "*batch"]:
    """Spectral radius of the companion matrix (``< 1`` means stable dynamics)."""
    return jnp.max(jnp.abs(jnp.linalg.eigvals(companion_matrix(texton))), axis=-1)


def check_texton(name: str, texton: Any, stacked: bool | None = None) -> Texton:
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
