"""``track``: one entry point for every tracker and prior (design §12)."""

from __future__ import annotations

from typing import Any

import numpy as np
from jaxtyping import PRNGKeyArray

from ..core import check_key
from ..implicit import ImplicitModel
from ..texture import MotionTexture
from ._particle import ParticleFilter
from ._problem import TrackingProblem, feature_map_of
from ._result import TrackResult
from ._smoother import MapSmoother
from ._tracker import Tracker, check_problem

__all__ = ["track"]


def track(
    key: PRNGKeyArray,
    prior: MotionTexture | ImplicitModel,
    problem: TrackingProblem,
    method: Tracker | None = None,
    **options: Any,
) -> TrackResult:
    """Estimate the 3-D motion behind 2-D joint observations, with a motion model as the prior.

    The method is an object (:class:`ParticleFilter`, :class:`MapSmoother`); without one, a
    texture is tracked by its MAP smoother (design §12.2) and an implicit model by the
    paper's particle filter (IP §3, §6), built from ``options``:
    ``track(key, model, problem, n_particles=100)`` is
    ``track(key, model, problem, ParticleFilter(n_particles=100))``.

    Args:
        key: PRNG key (a particle filter's sampling; a smoother is deterministic).
        prior: a :class:`~mtex_jax.texture.MotionTexture` or an
            :class:`~mtex_jax.implicit.ImplicitModel`.
        problem: the observations (:func:`make_problem`, :func:`problem_from_keypoints`).
        method: the tracker and its options.
        **options: the default tracker's options, when ``method`` is not given.

    Returns:
        a :class:`TrackResult`; its errors are set when the problem has a ground truth.

    Raises:
        TypeError: a prior, problem or method of the wrong kind.
        ValueError: bad observations (non-finite pixels that are not declared missing,
            confidences outside ``[0, 1]``), a bad camera, or a problem made for another model.
    """
    check_key(key, "track")
    if method is None:
        if isinstance(prior, ImplicitModel):
            method = ParticleFilter(**options)
        elif isinstance(prior, MotionTexture):
            method = MapSmoother(**options)
        else:
            raise TypeError(
                "track: the prior must be a MotionTexture or an ImplicitModel, got "
                f"{type(prior).__name__}"
            )
    elif options:
        raise TypeError(
            f"track: options {sorted(options)} are given beside a method object; set them on "
            "the method"
        )
    if not isinstance(method, Tracker):
        raise TypeError(f"track: method must be a Tracker, got {type(method).__name__}")
    problem = check_problem(problem)
    if problem.bone_scale is not None:
        J = feature_map_of(prior).skeleton.n_joints
        if np.shape(problem.bone_scale) != (J,):
            raise ValueError(
                f"track: the problem's bone_scale has shape {np.shape(problem.bone_scale)}; the "
                f"prior's skeleton has {J} joints"
            )
    return method.run(key, prior, problem)
