"""The interface of an observation model: how a texton scores the part of ``y`` outside its
state subspace (design §2.2, §10.3).

A texton ``i`` explains ``y_t`` by its state ``x_t = C_iᵀ(y_t − μ_i)`` and the residual
``r_t = (I − C_i C_iᵀ)(y_t − μ_i)``. The dynamics of the state are common to every model; the
observation model says what the residual costs, what its M-step is, and how many free
parameters that adds. Each model is one module of this folder implementing
:class:`ObservationModel`, registered by name in ``__init__.py`` (``Texton.observation`` holds
the name, so a model file stays plain arrays + JSON).

Every hook keeps the segment scores' prefix-sum form (design §3.2): a model changes the
per-frame terms ``dyn`` (frames ``t ≥ b + 2``) and ``obs``, never the recursion of the
Viterbi or forward algorithms.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, TypeVar

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._texton.checks import check_dof

if TYPE_CHECKING:
    from .._texton.options import SolveOptions
    from .._texton.stats import DynamicsStats, Subspace

__all__ = ["ObservationModel", "TextonView"]

#: the texton class a member's M-step builds (the texton module imports the members, so they
#: are handed its constructor rather than importing it)
T = TypeVar("T")


class TextonView(Protocol):
    """What a member reads of a :class:`~mtex_jax.texture.Texton` (one, or a stack)."""

    @property
    def C(self) -> Array: ...

    @property
    def sigma2(self) -> Array: ...

    @property
    def res_a(self) -> Array: ...

    @property
    def res_s2(self) -> Array: ...


class ObservationModel:
    """One observation model of textons (the protocol; subclasses are the members).

    Class attributes:
        name: the registry name, stored in ``Texton.observation`` and in model files.
        student_t: whether the textons may have Student-t dynamics innovations
            (``Texton.dof``).
        kalman: whether :func:`~mtex_jax.texture.exact_log_likelihood` (the Kalman
            likelihood of the paper's model) applies.
    """

    name: ClassVar[str]
    student_t: ClassVar[bool] = False
    kalman: ClassVar[bool] = True

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

    # -- M-step -----------------------------------------------------------------------------

    def fit_residual(
        self, stats: DynamicsStats, k: int, D: int, sigma2: Array, opts: SolveOptions
    ) -> tuple[Array, Array]:
        """``(res_a (2,), res_s2 ())`` of one texton from its dynamics statistics (traced).
        Default: the paper's white residual, ``a = 0`` and ``s_r² = σ²``."""
        dtype = stats.sum_zz.dtype
        return jnp.zeros((2,), dtype), sigma2.astype(dtype)

    def solve(
        self,
        fit_one: Callable[[Subspace, DynamicsStats], T],
        make: Callable[..., T],
        sub: Subspace,
        ds: DynamicsStats,
        opts: SolveOptions,
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
        self, Yw: Array, Z: Array, s2: Array, mcmc: Array, textons: TextonView, obs: Array, k: int
    ) -> Array | None:
        """What the model adds to ``dyn`` on frames ``2 … W−1`` of a window of the blocked
        kernel (``(N_t, W − 2)``), or ``None``. ``Yw``: the window's centred frames;
        ``Z``: every texton's whitened states and ``y·μ`` row; ``s2``: the whitening
        scales; ``mcmc``: ``‖μ − ȳ‖²`` per texton; ``obs``: the white residual terms of the
        window."""
        return None

    def reference_dyn_terms(self, tex: TextonView, U: Array, obs: Array) -> Array | None:
        """The same for one texton on a whole sequence (``(T − 2,)``, frames ``2 … T−1``), by
        the direct formula: the per-texton reference kernel. ``U``: the frames minus the
        texton's mean, ``y_t − μ``; ``obs``: the white residual terms."""
        return None

    def segment_dyn_term(self, tex: TextonView, Rres: Array) -> Array | None:
        """The same summed over one segment from its residuals ``Rres (L, D)``: the direct
        per-segment reference."""
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

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"
