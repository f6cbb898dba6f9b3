"""Implicit probabilistic motion model (Sidenbladh, Black & Sigal 2002): the PCA-tree motion
database, probabilistic tree search and the particle-filter tracker.
"""

from ._model import (
    ImplicitModel as ImplicitModel,
)
from ._model import (
    pose_vectors as pose_vectors,
)
from ._model import (
    sign_codes as sign_codes,
)
from ._model import (
    velocity_channels as velocity_channels,
)
from ._tracking import (
    Camera as Camera,
)
from ._tracking import (
    TrackingProblem as TrackingProblem,
)
from ._tracking import (
    TrackResult as TrackResult,
)
from ._tracking import (
    decode_frame as decode_frame,
)
from ._tracking import (
    default_joints as default_joints,
)
from ._tracking import (
    make_problem as make_problem,
)
from ._tracking import (
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
