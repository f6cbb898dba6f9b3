"""The interface of an observation model: how a texton scores the part of ``y`` outside its
state subspace (design §2.2, §10.3).

A texton ``i`` explains ``y_t`` by its state ``x_t = C_iᵀ(y_t − μ_i)`` and the residual
``r_t = (I − C_i C_iᵀ)(y_t − μ_i)``. The dynamics of the state are common to every model; the
observation model says what the residual costs, what its M-step is, and how many free
parameters that adds. Each model is one module of this folder: an ``equinox.Module`` subclass
of :class:`ObservationModel` that owns its parameters (a stack of textons holds its member
with one leading axis on every parameter, as it holds its own fields). ``Texton.observation``
holds the member; its registry name is what the CLI and a model file's JSON spell.

A member built without its parameters (``ResidualObservation()``) is a *choice* of model: what
a learn or a fit is given. Its M-step (:meth:`ObservationModel.fit`) returns the member with
its parameters, which is what a fitted texton holds.

Every hook keeps the segment scores' prefix-sum form (design §3.2): a model changes the
per-frame terms ``dyn`` (frames ``t ≥ b + 2``) and ``obs``, never the recursion of the
Viterbi or forward algorithms.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._texton.checks import check_dof

if TYPE_CHECKING:
    from .._texton.stats import DynamicsStats, Subspace

__all__ = ["MEMBER_FIELDS", "FitOptions", "ObservationModel", "ResidualArrays"]

#: the texton class a member's M-step builds (the texton module imports the members, so they
#: are handed its constructor rather than importing it)
T = TypeVar("T")


class FitOptions(Protocol):
    """What a member's M-step reads of the texton fit's options
    (the texton fit's options are one)."""

    @property
    def ridge(self) -> float: ...

    @property
    def q_floor(self) -> float: ...

    @property
    def rho_max(self) -> float | None: ...

    @property
    def sigma2_floor(self) -> float: ...

    @property
    def dof(self) -> float | None: ...


#: The arrays of a member in a model file: every texton's residual AR(2) ``res_a (*batch, 2)``
#: and its innovation variance ``res_s2 (*batch,)``; a white residual is ``a = 0``,
#: ``s_r² = σ²`` (design §10.3).
ResidualArrays = dict[str, Any]

#: The names of :data:`ResidualArrays` (``texton.res_a``, ``texton.res_s2`` in a file).
MEMBER_FIELDS = ("res_a", "res_s2")


class ObservationModel(eqx.Module):
    """One observation model of textons (the protocol; subclasses are the members).

    Class attributes:
        name: the registry name, spelled by the CLI and in model files.
        student_t: whether the textons may have Student-t dynamics innovations
            (``Texton.dof``).
        kalman: whether :func:`~mtex_jax.texture.exact_log_likelihood` (the Kalman
            likelihood of the paper's model) applies.
    """

    name: ClassVar[str]
    student_t: ClassVar[bool] = False
    kalman: ClassVar[bool] = True

    # -- parameters ---------------------------------------------------------------------------

    @property
    def fitted(self) -> bool:
        """Whether the member holds its parameters (a member without parameters always
        does)."""
        return True

    def check_shapes(self, batch: tuple[int, ...], D: int, k: int) -> None:
        """Raise ``ValueError`` unless the member's parameters fit a texton (stack) of batch
        shape ``batch`` with ``D``, ``k`` (called by ``Texton.__check_init__``)."""

    def fit(
        self, stats: DynamicsStats, k: int, D: int, sigma2: Array, opts: FitOptions
    ) -> ObservationModel:
        """The M-step of one texton: the member with its parameters from the texton's
        dynamics statistics (traced). Default: no parameters beyond ``σ²``."""
        return self

    def to_arrays(self, sigma2: Array) -> ResidualArrays:
        """The member's arrays in a model file (:data:`ResidualArrays`); ``sigma2`` the
        textons' ``σ²``. Default: the white residual."""
        s2 = jnp.asarray(sigma2)
        return {"res_a": jnp.zeros((*s2.shape, 2), s2.dtype), "res_s2": s2}

    def from_arrays(self, arrays: ResidualArrays) -> ObservationModel:
        """This member with the parameters read from a model file's arrays. Default: none to
        read."""
        return self

    # -- shapes and counts ----------------------------------------------------------------

    def fixed_state_dim(self, D: int) -> int | None:
        """The state dimension the model requires for ``D``-dimensional observations, or
        ``None`` when ``k`` is free (chosen by BIC or given)."""
        return None

    def check_state_dim(self, D: int, k: int) -> None:
        """Raise ``ValueError`` if a texton with ``D``, ``k`` cannot have this model."""
        fixed = self.fixed_state_dim(D)
        if fixed is not None and k != fixed:
            raise ValueError(f"observation={self.name!r} needs state_dim = D = {D}, got k={k}")

    def check_dof(self, dof: Any, where: str = "dof") -> float | None:
        """``dof`` checked (:func:`check_dof`) and allowed for this model."""
        dof = check_dof(dof, where=where)
        if dof is not None and not self.student_t:
            from . import OBSERVATION_MODELS

            takes = [n for n, m in OBSERVATION_MODELS.items() if m.student_t]
            raise ValueError(
                f"Student-t innovations ({where}={dof:g}) need an observation model that "
                f"takes them ({', '.join(takes)}), got {self.name!r}"
            )
        return dof

    def n_params(self, n_t: int, D: int, k: int, frames: Any = None, starts: Any = None) -> float:
        """Free parameters of ``n_t`` textons (for BIC, design §4.7): per texton ``μ`` D,
        ``C`` Dk − k(k+1)/2, ``A1, A2`` 2k², ``d`` k, ``Q`` k(k+1)/2, ``σ²`` 1, ``m0`` 2k,
        ``S0`` k(2k+1), plus :meth:`extra_params`. ``frames`` and ``starts`` (each texton's
        dynamics terms and segments) are for models whose estimates are shrunk, whose
        effective number of parameters depends on them; unshrunk models ignore them."""
        per = D + (D * k - k * (k + 1) // 2) + 2 * k * k + k + k * (k + 1) // 2 + 1 + 2 * k
        per += k * (2 * k + 1)
        return n_t * (per + self.extra_params(D, k))

    def extra_params(self, D: int, k: int) -> int:
        """Free parameters per texton of the residual model (0: none beyond ``σ²``)."""
        return 0

    # -- M-step of a stack ----------------------------------------------------------------

    def solve(
        self,
        fit_one: Callable[[Subspace, DynamicsStats], T],
        make: Callable[..., T],
        sub: Subspace,
        ds: DynamicsStats,
        opts: FitOptions,
    ) -> T:
        """The M-step's closed form for a stack of textons from their summed statistics
        (traced; design §2.4–§2.6). ``fit_one`` is the closed form of one texton
        (``texton_from_stats`` with the learn's options ``opts``); ``make`` the texton class,
        for a model that builds the stack itself. Default: each texton on its own
        statistics, one at a time (``lax.map``: batched LAPACK calls can deadlock jaxlib's
        CPU thread pool on 2 cores). A model that ties parameters across textons overrides
        this."""
        del make
        return jax.lax.map(lambda a: fit_one(a[0], a[1]), (sub, ds))

    # -- frame terms (prefix-sum form) ------------------------------------------------------

    def window_dyn_terms(
        self, Yw: Array, Z: Array, s2: Array, mcmc: Array, obs: Array, k: int
    ) -> Array | None:
        """What the model adds to ``dyn`` on frames ``2 … W−1`` of a window of the blocked
        kernel (``(N_t, W − 2)``; the member is the stack's), or ``None``. ``Yw``: the
        window's centred frames; ``Z``: every texton's whitened states and ``y·μ`` row;
        ``s2``: the whitening scales; ``mcmc``: ``‖μ − ȳ‖²`` per texton; ``obs``: the white
        residual terms of the window."""
        return None

    def residual_terms(self, C: Array, U: Array, sigma2: Array) -> Array | None:
        """What the model adds to ``dyn`` on frames ``2 … L−1`` of one texton's frames
        ``U = y − μ`` ``(L, D)`` (the member is one texton's; ``C`` its subspace, ``sigma2``
        its ``σ²``), by the direct formula, or ``None``: the per-texton reference kernel
        and the per-segment reference both sum it."""
        return None

    def predict_residual(self, r1: Array, r2: Array) -> Array | None:
        """The one-step prediction of the residual from the two before, ``(n, D)`` each (the
        member holds one texton per row), or ``None`` for a white residual."""
        return None

    # -- choosing k ---------------------------------------------------------------------------

    def residual_loglik(
        self, w: np.ndarray, V: np.ndarray, S: np.ndarray, n: int, N: int, k: int
    ) -> float:
        """Maximised log-likelihood of the residual outside the top-``k`` principal
        subspace, for :func:`~mtex_jax.texture.choose_state_dim` (float64 numpy).

        Args:
            w: eigenvalues of the frames' scatter, descending; ``V`` its eigenvectors.
            S: the scatter of the lagged frames ``[u_t, u_{t−1}, u_{t−2}]`` ``(3D, 3D)``.
            n: frames; ``N``: frames with two predecessors; ``k``: the state dimension.
        """
        raise ValueError(f"observation={self.name!r} has no state dimension to choose")
