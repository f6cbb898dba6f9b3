"""Implicit probabilistic motion model (Sidenbladh, Black & Sigal 2002): the PCA-tree motion
database, probabilistic tree search and the particle-filter tracker.
"""

from ._camera import (
    Camera as Camera,
    decode_frame as decode_frame,
    default_joints as default_joints,
)
from ._database import (
    MotionDatabase as MotionDatabase,
)
from ._learn import (
    learn as learn,
)
from ._model import (
    ImplicitModel as ImplicitModel,
)
from ._synthesis import (
    SynthesisConfig as SynthesisConfig,
    fade_weight as fade_weight,
)
from ._synthesis_api import (
    synthesize as synthesize,
    synthesize_poses as synthesize_poses,
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
    channel_importance as channel_importance,
    joint_reach as joint_reach,
    pose_vectors as pose_vectors,
    velocity_channels as velocity_channels,
)

__all__ = [
    "Camera",
    "ImplicitModel",
    "MotionDatabase",
    "SynthesisConfig",
    "TrackResult",
    "TrackingProblem",
    "channel_importance",
    "decode_frame",
    "default_joints",
    "fade_weight",
    "joint_reach",
    "learn",
    "make_problem",
    "pose_vectors",
    "sign_codes",
    "synthesize",
    "synthesize_poses",
    "track",
    "velocity_channels",
]
