"""Tracking: 3-D motion from 2-D joint observations, with either paper's model as the prior
(design §12).

- the observations: :class:`Camera`, :class:`TrackingProblem`, :func:`make_problem` (synthetic
  problems from a clip, with missing joints, outliers and another body's bones);
- the trackers, chosen by passing one to :func:`track`: :class:`ParticleFilter` (the implicit
  model's prior, IP §3 and §6) and :class:`MapSmoother` (the texture's prior, a banded
  Gauss–Newton MAP estimate, batch or fixed-lag);
- the smoother's residual terms, members of :class:`~mtex_jax.edit.ResidualTerm` that a banded
  solve of one's own can take: :class:`Reprojection` (robust, with a :class:`PixelLoss`) and
  :class:`FloorContact`;
- the results: :class:`TrackResult` and the error measures (:func:`joint_errors`).
"""

from ._camera import Camera as Camera
from ._floor import FloorContact as FloorContact
from ._keypoints import (
    COCO17_NAMES as COCO17_NAMES,
    Keypoints as Keypoints,
    coco_joint_map as coco_joint_map,
    problem_from_keypoints as problem_from_keypoints,
    read_camera as read_camera,
    read_keypoints as read_keypoints,
    write_keypoints as write_keypoints,
)
from ._particle import (
    ParticleFilter as ParticleFilter,
    decode_frame as decode_frame,
    systematic as systematic,
)
from ._priors import (
    MotionPrior as MotionPrior,
    SmoothPrior as SmoothPrior,
    TexturePrior as TexturePrior,
)
from ._problem import (
    TrackingProblem as TrackingProblem,
    default_joints as default_joints,
    make_problem as make_problem,
    scaled_skeleton as scaled_skeleton,
)
from ._reprojection import (
    Gaussian as Gaussian,
    Huber as Huber,
    PixelLoss as PixelLoss,
    Reprojection as Reprojection,
    StudentT as StudentT,
)
from ._result import (
    TrackResult as TrackResult,
    joint_errors as joint_errors,
    procrustes_errors as procrustes_errors,
)
from ._smoother import MapSmoother as MapSmoother
from ._track import track as track
from ._tracker import Tracker as Tracker

__all__ = [
    "COCO17_NAMES",
    "Camera",
    "FloorContact",
    "Gaussian",
    "Huber",
    "Keypoints",
    "MapSmoother",
    "MotionPrior",
    "ParticleFilter",
    "PixelLoss",
    "Reprojection",
    "SmoothPrior",
    "StudentT",
    "TexturePrior",
    "TrackResult",
    "Tracker",
    "TrackingProblem",
    "coco_joint_map",
    "decode_frame",
    "default_joints",
    "joint_errors",
    "make_problem",
    "problem_from_keypoints",
    "procrustes_errors",
    "read_camera",
    "read_keypoints",
    "scaled_skeleton",
    "systematic",
    "track",
    "write_keypoints",
]
