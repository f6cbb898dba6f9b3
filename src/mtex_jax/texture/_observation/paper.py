"""The paper's observation model (MT eq. (11), design §2.2): the residual outside the state
subspace is white noise, ``r_t ~ N(0, σ² I_{D−k})`` on every frame."""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from .._texton.checks import LOG_2PI
from .base import ObservationModel

__all__ = ["PaperObservation"]


class PaperObservation(ObservationModel):
    """White residual noise (MT-11): nothing beyond ``σ²``, and the exact Kalman likelihood
    of the paper's LDS applies."""

    name: ClassVar[str] = "paper"

    def residual_loglik(
        self, w: np.ndarray, V: np.ndarray, S: np.ndarray, n: int, N: int, k: int
    ) -> float:
        D = w.shape[0]
        s2 = max(float(w[k:].sum()) / (n * (D - k)), 1e-12)
        return -0.5 * n * (D - k) * (math.log(s2) + LOG_2PI + 1)
