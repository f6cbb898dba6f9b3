"""Implicit probabilistic motion model (Sidenbladh, Black & Sigal 2002): the PCA-tree motion
database and probabilistic tree search (the particle-filter tracker that uses it as a prior is
:mod:`mtex_jax.tracking`).
"""

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
from ._tree import (
    sign_codes as sign_codes,
    tree_sample_indices as tree_sample_indices,
)
from ._windows import (
    channel_importance as channel_importance,
    joint_reach as joint_reach,
    pose_vectors as pose_vectors,
    velocity_channels as velocity_channels,
)

__all__ = [
    "ImplicitModel",
    "MotionDatabase",
    "SynthesisConfig",
    "channel_importance",
    "fade_weight",
    "joint_reach",
    "learn",
    "pose_vectors",
    "sign_codes",
    "synthesize",
    "synthesize_poses",
    "tree_sample_indices",
    "velocity_channels",
]
