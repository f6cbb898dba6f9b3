"""Motion data and its geometry: ``Motion``, ``Skeleton``, rotations, forward kinematics, the
observation features (``FeatureMap``, MT §6.1, design §1), and the feet: which joints they are
and when they touch the floor (``ContactModel``, design §10.4).
"""

from ._channels import (
    raw_features as raw_features,
    unwrap_expmaps as unwrap_expmaps,
)
from ._contacts import (
    ContactModel as ContactModel,
    PenetrationResult as PenetrationResult,
    SkatingResult as SkatingResult,
    fit_contacts as fit_contacts,
)
from ._features import (
    FeatureMap as FeatureMap,
    load_feature_map as load_feature_map,
)
from ._feet import foot_joints as foot_joints
from ._kinematics import (
    as_motion_list as as_motion_list,
    forward_kinematics as forward_kinematics,
    forward_kinematics_arrays as forward_kinematics_arrays,
    joint_positions as joint_positions,
)
from ._motion import (
    Motion as Motion,
    concatenate_motions as concatenate_motions,
    slerp as slerp,
    slerp_frames as slerp_frames,
)
from ._rotation import (
    expmap_to_quat as expmap_to_quat,
    quat_conj as quat_conj,
    quat_from_axis_angle as quat_from_axis_angle,
    quat_mul as quat_mul,
    quat_normalize as quat_normalize,
    quat_rotate as quat_rotate,
    quat_to_expmap as quat_to_expmap,
    quat_to_matrix as quat_to_matrix,
    quat_twist as quat_twist,
    yaw_quat as yaw_quat,
)
from ._skeleton import (
    POSITION_CHANNELS as POSITION_CHANNELS,
    ROTATION_CHANNELS as ROTATION_CHANNELS,
    Skeleton as Skeleton,
    ground_axes as ground_axes,
    sub_skeleton as sub_skeleton,
)

__all__ = [
    "POSITION_CHANNELS",
    "ROTATION_CHANNELS",
    "ContactModel",
    "FeatureMap",
    "Motion",
    "PenetrationResult",
    "SkatingResult",
    "Skeleton",
    "as_motion_list",
    "concatenate_motions",
    "expmap_to_quat",
    "fit_contacts",
    "foot_joints",
    "forward_kinematics",
    "forward_kinematics_arrays",
    "ground_axes",
    "joint_positions",
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
    "slerp_frames",
    "sub_skeleton",
    "unwrap_expmaps",
    "yaw_quat",
]
