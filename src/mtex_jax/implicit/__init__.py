"""Implicit probabilistic motion model (Sidenbladh, Black & Sigal 2002): the PCA-tree motion
database, probabilistic tree search and the particle-filter tracker.
"""

from ._camera import (
    Camera as Camera,
    decode_frame as decode_frame,
    default_joints as default_joints,
)
from ._learn import (
    learn as learn,
)
from ._model import (
    ImplicitModel as ImplicitModel,
)
from ._tracking import (
    TrackingProblem as TrackingProblem,
    TrackResult as TrackResult,
    make_problem as make_problem,
    track as track,
)
from ._tree import (
    sign_codes as sign_codes,
)
from ._windows import (
    pose_vectors as pose_vectors,
    velocity_channels as velocity_channels,
)

__all__ = [
    "Camera",
    "ImplicitModel",
    "TrackResult",
    "TrackingProblem",
    "decode_frame",
    "default_joints",
    "learn",
    "make_problem",
    "pose_vectors",
    "sign_codes",
    "track",
    "velocity_channels",
]
