"""Motion data and its geometry: ``Motion``, ``Skeleton``, rotations, forward kinematics and
the observation features (``FeatureMap``, MT §6.1, SPEC §1).
"""

from ._features import (
    FeatureMap as FeatureMap,
)
from ._features import (
    load_feature_map as load_feature_map,
)
from ._features import (
    raw_features as raw_features,
)
from ._features import (
    unwrap_expmaps as unwrap_expmaps,
)
from ._kinematics import (
    forward_kinematics as forward_kinematics,
)
from ._kinematics import (
    forward_kinematics_arrays as forward_kinematics_arrays,
)
from ._motion import (
    Motion as Motion,
)
from ._motion import (
    concatenate_motions as concatenate_motions,
)
from ._motion import (
    slerp as slerp,
)
from ._rotation import (
    expmap_to_quat as expmap_to_quat,
)
from ._rotation import (
    quat_conj as quat_conj,
)
from ._rotation import (
    quat_from_axis_angle as quat_from_axis_angle,
)
from ._rotation import (
    quat_mul as quat_mul,
)
from ._rotation import (
    quat_normalize as quat_normalize,
)
from ._rotation import (
    quat_rotate as quat_rotate,
)
from ._rotation import (
    quat_to_expmap as quat_to_expmap,
)
from ._rotation import (
    quat_to_matrix as quat_to_matrix,
)
from ._rotation import (
    quat_twist as quat_twist,
)
from ._rotation import (
    yaw_quat as yaw_quat,
)
from ._skeleton import (
    POSITION_CHANNELS as POSITION_CHANNELS,
)
from ._skeleton import (
    ROTATION_CHANNELS as ROTATION_CHANNELS,
)
from ._skeleton import (
    Skeleton as Skeleton,
)

__all__ = [
    "POSITION_CHANNELS",
    "ROTATION_CHANNELS",
    "FeatureMap",
    "Motion",
    "Skeleton",
    "concatenate_motions",
    "expmap_to_quat",
    "forward_kinematics",
    "forward_kinematics_arrays",
    "load_feature_map",
    "quat_conj",
    "quat_from_axis_angle",
    "quat_mul",
    "quat_normalize",
    "quat_rotate",
    "quat_to_expmap",
    "quat_to_matrix",
    "quat_twist",
    "raw_features",
    "slerp",
    "unwrap_expmaps",
    "yaw_quat",
]
