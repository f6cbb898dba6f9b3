"""The options of the closed-form texton fit (design §2): a static bundle of floors, bounds
and the observation model's member, shared by the single fit and the EM's M-step.

:meth:`SolveOptions.make` checks each value's domain; whether the member takes Student-t
innovations (``dof``) is the member's to say, and its callers ask it
(``ObservationModel.check_dof``) before making the options."""

from __future__ import annotations

from typing import Any

import equinox as eqx

from .._observation import ObservationModel, PaperObservation, check_observation
from .checks import check_dof, check_positive, check_positive_int

__all__ = ["SolveOptions"]


class SolveOptions(eqx.Module):
    """The options of one texton fit (static: a new value compiles a new M-step).

    Attributes:
        ridge: ridge on the dynamics' normal equations (relative to their scale), ``≥ 0``.
        q_floor: absolute floor added to ``Q`` and ``S0``, ``> 0``.
        rho_max: optional bound on the companion spectral radius.
        init_prior_weight: shrinkage pseudo-count of ``(m0, S0)``, ``≥ 0``.
        observation: the observation model's member (without parameters: the choice).
        sigma2_floor: floor of the observation noise variances.
        dof: Student-t degrees of freedom of the innovations (``None``: Gaussian).
        irls_steps: reweighting steps of a Student-t fit.
    """

    ridge: float = eqx.field(static=True)
    q_floor: float = eqx.field(static=True)
    rho_max: float | None = eqx.field(static=True)
    init_prior_weight: float = eqx.field(static=True)
    observation: ObservationModel = eqx.field(static=True, default=PaperObservation())
    sigma2_floor: float = eqx.field(static=True, default=1e-6)
    dof: float | None = eqx.field(static=True, default=None)
    irls_steps: int = eqx.field(static=True, default=10)

    @staticmethod
    def make(
        ridge: Any,
        q_floor: Any,
        rho_max: Any,
        init_prior_weight: Any,
        observation: Any = PaperObservation(),
        sigma2_floor: Any = 1e-6,
        dof: Any = None,
        irls_steps: Any = 10,
    ) -> SolveOptions:
        return SolveOptions(
            ridge=check_positive("ridge", ridge, allow_zero=True),
            q_floor=check_positive("q_floor", q_floor),
            rho_max=None if rho_max is None else check_positive("rho_max", rho_max),
            init_prior_weight=check_positive(
                "init_prior_weight", init_prior_weight, allow_zero=True
            ),
            observation=check_observation(observation),
            sigma2_floor=check_positive("sigma2_floor", sigma2_floor),
            dof=check_dof(dof),
            irls_steps=check_positive_int("irls_steps", irls_steps),
        )
