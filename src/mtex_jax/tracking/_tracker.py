"""The tracker protocol (design §12): a tracker is an object with the options of one method, and
:func:`~mtex_jax.tracking.track` runs whichever it is given, as dynamax's emission members are
chosen by passing one."""

from __future__ import annotations

import abc
from typing import Any

import equinox as eqx
import numpy as np
from jaxtyping import PRNGKeyArray

from ._problem import TrackingProblem
from ._result import TrackResult

__all__ = ["Tracker", "check_problem"]


class Tracker(eqx.Module):
    """One tracking method and its options (a member of the family of trackers)."""

    @abc.abstractmethod
    def run(self, key: PRNGKeyArray, prior: Any, problem: TrackingProblem) -> TrackResult:
        """Track ``problem`` with ``prior`` (checked by :func:`~mtex_jax.tracking.track`)."""


def check_problem(problem: Any, caller: str = "track") -> TrackingProblem:
    """The checks every tracker needs: finite observations wherever they count, confidences in
    ``[0, 1]``, a camera with a positive focal length; observations declared missing
    (confidence 0) may hold anything, NaN included, and are set to 0."""
    if not isinstance(problem, TrackingProblem):
        raise TypeError(
            f"{caller}: problem must be a TrackingProblem, got {type(problem).__name__}"
        )
    cam = problem.camera
    f = float(np.asarray(cam.focal))
    if not (np.isfinite(f) and f > 0):
        raise ValueError(f"{caller}: the camera's focal length must be positive, got {f}")
    for name in ("rotation", "translation", "center"):
        if not np.all(np.isfinite(np.asarray(getattr(cam, name)))):
            raise ValueError(f"{caller}: the camera's {name} is not finite")
    rot = np.asarray(cam.rotation, dtype=np.float64)
    if np.max(np.abs(rot @ rot.T - np.eye(3))) > 1e-6 or np.linalg.det(rot) < 0:
        raise ValueError(f"{caller}: the camera's rotation is not a rotation matrix")
    conf = np.asarray(problem.confidence)
    if not np.all(np.isfinite(conf)) or np.any(conf < 0) or np.any(conf > 1):
        raise ValueError(f"{caller}: confidences must be finite and in [0, 1]")
    obs = np.asarray(problem.observations)
    bad = ~np.isfinite(obs).all(axis=-1) & (conf > 0)
    if bad.any():
        t, k = (int(v) for v in np.argwhere(bad)[0])
        raise ValueError(
            f"{caller}: the pixel of joint {problem.joints[k]} at frame {t} is not finite but "
            f"not declared missing (give it confidence 0); {int(bad.sum())} such pixels"
        )
    if not np.isfinite(obs).all():
        obs = np.where(np.isfinite(obs), obs, 0.0)
        problem = eqx.tree_at(lambda p: p.observations, problem, np.asarray(obs, obs.dtype))
    if problem.truth is not None:
        xc = np.asarray(problem.truth) @ rot.T + np.asarray(cam.translation)
        if np.any(xc[..., 2] <= 0):
            raise ValueError(
                f"{caller}: the camera is behind the subject (a joint at depth "
                f"{float(xc[..., 2].min()):.3g} m); every joint must be in front of it"
            )
    return problem
