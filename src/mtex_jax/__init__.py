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
from ._kinematics import forward_kinematics, forward_kinematics_arrays
from ._motion import Motion, concatenate_motions
from ._readers import read_motion
from ._render import render_filmstrip, render_gif
from ._rotation import expmap_to_quat, quat_mul, quat_to_expmap, quat_to_matrix
from ._skeleton import Skeleton

try:
    __version__ = version("mtex_jax")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0+unknown"

__all__ = [
    "HUMANOID3D",
    "FeatureMap",
    "Motion",
    "Skeleton",
    "__version__",
    "concatenate_motions",
    "example_names",
    "expmap_to_quat",
    "forward_kinematics",
    "forward_kinematics_arrays",
    "load_example",
    "load_feature_map",
    "quat_mul",
    "quat_to_expmap",
    "quat_to_matrix",
    "read_bvh",
    "read_deepmimic",
    "read_motion",
    "render_filmstrip",
    "render_gif",
    "write_bvh",
]
