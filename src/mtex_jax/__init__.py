"""mtex_jax: Motion Texture (Li, Wang & Shum 2002) and implicit probabilistic motion models
(Sidenbladh, Black & Sigal 2002) in JAX.

Layout, top-down: data and features (``Motion``, readers/writers, ``forward_kinematics``,
``FeatureMap``) → textons → learning → synthesis → implicit model → command line (``mtex``).
"""

from importlib.metadata import PackageNotFoundError, version

from ._bvh import read_bvh, write_bvh
from ._data import example_names, load_example
from ._deepmimic import HUMANOID3D, read_deepmimic
from ._features import FeatureMap, load_feature_map
from ._implicit import ImplicitModel
from ._kinematics import forward_kinematics, forward_kinematics_arrays
from ._lds_refine import RefineReport, exact_log_likelihood_segments, refine_texton
from ._learn import LearnConfig, MotionTexture, bic_select, learn, load_texture
from ._linalg import block_banded_solve
from ._motion import Motion, concatenate_motions
from ._paths import path_cost, path_of_length, random_path, shortest_path
from ._plots import plot_timeline
from ._readers import read_motion
from ._render import render_filmstrip, render_gif
from ._rotation import expmap_to_quat, quat_mul, quat_to_expmap, quat_to_matrix
from ._segment import Segmentation, segment
from ._sequence import Synthesis, choreograph, match_texton, synthesize
from ._skeleton import Skeleton
from ._synthesis import synthesize_texton
from ._texton import (
    DynamicsStats,
    FrameStats,
    SegmentScorer,
    Subspace,
    Texton,
    companion_matrix,
    dynamics_stats,
    exact_log_likelihood,
    fit_texton,
    frame_stats,
    frame_terms,
    init_terms,
    sample_texton,
    segment_log_likelihood,
    segment_scores,
    spectral_radius,
    stack_textons,
    subspace_from_stats,
    texton_from_stats,
)
from ._tracking import Camera, TrackingProblem, TrackResult, make_problem, track

try:
    __version__ = version("mtex_jax")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0+unknown"

__all__ = [
    "HUMANOID3D",
    "Camera",
    "DynamicsStats",
    "FeatureMap",
    "FrameStats",
    "ImplicitModel",
    "LearnConfig",
    "Motion",
    "MotionTexture",
    "RefineReport",
    "SegmentScorer",
    "Segmentation",
    "Skeleton",
    "Subspace",
    "Synthesis",
    "Texton",
    "TrackResult",
    "TrackingProblem",
    "__version__",
    "bic_select",
    "block_banded_solve",
    "choreograph",
    "companion_matrix",
    "concatenate_motions",
    "dynamics_stats",
    "exact_log_likelihood",
    "exact_log_likelihood_segments",
    "example_names",
    "expmap_to_quat",
    "fit_texton",
    "forward_kinematics",
    "forward_kinematics_arrays",
    "frame_stats",
    "frame_terms",
    "init_terms",
    "learn",
    "load_example",
    "load_feature_map",
    "load_texture",
    "make_problem",
    "match_texton",
    "path_cost",
    "path_of_length",
    "plot_timeline",
    "quat_mul",
    "quat_to_expmap",
    "quat_to_matrix",
    "random_path",
    "read_bvh",
    "read_deepmimic",
    "read_motion",
    "refine_texton",
    "render_filmstrip",
    "render_gif",
    "sample_texton",
    "segment",
    "segment_log_likelihood",
    "segment_scores",
    "shortest_path",
    "spectral_radius",
    "stack_textons",
    "subspace_from_stats",
    "synthesize",
    "synthesize_texton",
    "texton_from_stats",
    "track",
    "write_bvh",
]
