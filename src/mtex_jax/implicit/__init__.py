"""Implicit probabilistic motion model (Sidenbladh, Black & Sigal 2002): the PCA-tree motion
database, probabilistic tree search and the particle-filter tracker.
"""

from ._model import (
    ImplicitModel as ImplicitModel,
    pose_vectors as pose_vectors,
    sign_codes as sign_codes,
    velocity_channels as velocity_channels,
)
from ._tracking import (
    Camera as Camera,
    TrackResult as TrackResult,
    TrackingProblem as TrackingProblem,
    decode_frame as decode_frame,
    default_joints as default_joints,
    make_problem as make_problem,
    track as track,
)

__all__ = [
    "Camera",
    "ImplicitModel",
    "TrackResult",
    "TrackingProblem",
    "decode_frame",
    "default_joints",
    "make_problem",
    "pose_vectors",
    "sign_codes",
    "track",
    "velocity_channels",
]
