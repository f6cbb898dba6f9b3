"""The full-dimensional observation model (design §2.2, §10.3): ``k = D``, so there is no
residual; the texton is a full-covariance AR(2) on ``y`` and the texture an autoregressive
hidden semi-Markov model. The only model whose textons may have Student-t innovations
(design §10.7). Its frame terms come from the stacked-lag kernel (``k = D``)."""

from __future__ import annotations

from typing import ClassVar

from .base import ObservationModel

__all__ = ["FullObservation"]


class FullObservation(ObservationModel):
    """No residual (``k = D``); Student-t innovations allowed."""

    name: ClassVar[str] = "full"
    student_t: ClassVar[bool] = True

    def fixed_state_dim(self, D: int) -> int | None:
        return D
