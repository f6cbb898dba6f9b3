"""mtex_jax: Motion Texture (Li, Wang & Shum 2002) and implicit probabilistic motion models
(Sidenbladh, Black & Sigal 2002) in JAX.

The top level holds what a user reaches for first. Everything else lives in one subpackage per
concern, each with its own API:

- :mod:`mtex_jax.motion`: ``Motion``, ``Skeleton``, rotations, forward kinematics, ``FeatureMap``;
- :mod:`mtex_jax.io`: BVH, DeepMimic, the embedded clips, the model-file format;
- :mod:`mtex_jax.texture`: Motion Texture (textons, learning, segmentation, synthesis);
- :mod:`mtex_jax.implicit`: the implicit model (PCA tree, tree search, synthesis);
- :mod:`mtex_jax.edit`: pose edits and cleaning (foot contacts, the floor) by optimisation;
- :mod:`mtex_jax.tracking`: 3-D motion from 2-D keypoints with either model as the prior;
- :mod:`mtex_jax.viz`: rendering and plots;
- :mod:`mtex_jax.cli`: the ``mtex`` command.
"""

from importlib.metadata import PackageNotFoundError, version

from .core import enable_compilation_cache as enable_compilation_cache
from .edit import synthesize as synthesize
from .implicit import ImplicitModel as ImplicitModel
from .io import (
    example_names as example_names,
    load_example as load_example,
    read_bvh as read_bvh,
    read_deepmimic as read_deepmimic,
    read_motion as read_motion,
    write_bvh as write_bvh,
)
from .motion import (
    FeatureMap as FeatureMap,
    Motion as Motion,
    Skeleton as Skeleton,
    forward_kinematics as forward_kinematics,
    load_feature_map as load_feature_map,
)
from .texture import (
    LearnConfig as LearnConfig,
    MotionTexture as MotionTexture,
    choreograph as choreograph,
    learn as learn,
    load_texture as load_texture,
)
from .tracking import track as track
from .viz import (
    plot_timeline as plot_timeline,
    render_filmstrip as render_filmstrip,
    render_gif as render_gif,
)

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
    "enable_compilation_cache",
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
