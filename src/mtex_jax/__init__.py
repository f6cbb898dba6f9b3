"""mtex_jax: Motion Texture (Li, Wang & Shum 2002) and implicit probabilistic motion models
(Sidenbladh, Black & Sigal 2002) in JAX.

The top level holds what a user reaches for first. Everything else lives in one subpackage per
concern, each with its own API:

- :mod:`mtex_jax.motion`: ``Motion``, ``Skeleton``, rotations, forward kinematics, ``FeatureMap``;
- :mod:`mtex_jax.io`: BVH, DeepMimic, the embedded clips, the model-file format;
- :mod:`mtex_jax.texture`: Motion Texture (textons, learning, segmentation, synthesis);
- :mod:`mtex_jax.implicit`: the implicit model and the particle-filter tracker;
- :mod:`mtex_jax.viz`: rendering and plots;
- :mod:`mtex_jax.cli`: the ``mtex`` command.
"""

from importlib.metadata import PackageNotFoundError, version

from .implicit import ImplicitModel as ImplicitModel
from .implicit import track as track
from .io import example_names as example_names
from .io import load_example as load_example
from .io import read_bvh as read_bvh
from .io import read_deepmimic as read_deepmimic
from .io import read_motion as read_motion
from .io import write_bvh as write_bvh
from .motion import FeatureMap as FeatureMap
from .motion import Motion as Motion
from .motion import Skeleton as Skeleton
from .motion import forward_kinematics as forward_kinematics
from .motion import load_feature_map as load_feature_map
from .texture import LearnConfig as LearnConfig
from .texture import MotionTexture as MotionTexture
from .texture import choreograph as choreograph
from .texture import learn as learn
from .texture import load_texture as load_texture
from .texture import synthesize as synthesize
from .viz import plot_timeline as plot_timeline
from .viz import render_filmstrip as render_filmstrip
from .viz import render_gif as render_gif

try:
    __version__ = version("mtex_jax")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0+unknown"

__all__ = [
    "FeatureMap",
    "ImplicitModel",
    "LearnConfig",
    "Motion",
    "MotionTexture",
    "Skeleton",
    "__version__",
    "choreograph",
    "example_names",
    "forward_kinematics",
    "learn",
    "load_example",
    "load_feature_map",
    "load_texture",
    "plot_timeline",
    "read_bvh",
    "read_deepmimic",
    "read_motion",
    "render_filmstrip",
    "render_gif",
    "synthesize",
    "track",
    "write_bvh",
]
