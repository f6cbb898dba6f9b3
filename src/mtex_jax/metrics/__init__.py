"""Motion quality, measured: held-out likelihood and prediction against baselines, realism of
joint speed/acceleration/jerk distributions, foot contacts, skating and floor penetration,
transitions, novelty, and a classifier two-sample test (design §10.4).
"""

# --- likelihood baselines and prediction (baselines module) ---
from ._baselines import (
    GaussianAR2 as GaussianAR2,
    constant_velocity as constant_velocity,
    fit_ar2 as fit_ar2,
    hold_last as hold_last,
    prediction_error as prediction_error,
)

# --- motion metrics (realism, contacts, transitions, novelty) ---
from ._kinematics import (
    derivatives as derivatives,
    joint_speeds as joint_speeds,
    moving_joints as moving_joints,
)
from ._novelty import (
    CopyResult as CopyResult,
    NoveltyResult as NoveltyResult,
    copying as copying,
    copying_from_indices as copying_from_indices,
    novelty as novelty,
    successor_array as successor_array,
)
from ._prediction import texture_predict as texture_predict
from ._realism import (
    RealismResult as RealismResult,
    realism as realism,
    speed_samples as speed_samples,
    wasserstein_1d as wasserstein_1d,
)
from ._report import MotionJudge as MotionJudge, density_report as density_report
from ._transitions import (
    TransitionResult as TransitionResult,
    boundary_jumps as boundary_jumps,
    joint_jumps as joint_jumps,
    jump_p99 as jump_p99,
    transitions as transitions,
)
from ._two_sample import (
    TwoSampleResult as TwoSampleResult,
    two_sample_auc as two_sample_auc,
    window_features as window_features,
)

__all__ = [
    "CopyResult",
    "GaussianAR2",
    "MotionJudge",
    "NoveltyResult",
    "RealismResult",
    "TransitionResult",
    "TwoSampleResult",
    "boundary_jumps",
    "constant_velocity",
    "copying",
    "copying_from_indices",
    "density_report",
    "derivatives",
    "fit_ar2",
    "hold_last",
    "joint_jumps",
    "joint_speeds",
    "jump_p99",
    "moving_joints",
    "novelty",
    "prediction_error",
    "realism",
    "speed_samples",
    "successor_array",
    "texture_predict",
    "transitions",
    "two_sample_auc",
    "wasserstein_1d",
    "window_features",
]
