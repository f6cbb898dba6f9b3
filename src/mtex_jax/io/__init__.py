"""Reading and writing motion: BVH, DeepMimic JSON, the embedded example clips, and the
array + JSON model-file format.
"""

from ._bvh import (
    euler_to_quat as euler_to_quat,
)
from ._bvh import (
    parse_bvh as parse_bvh,
)
from ._bvh import (
    quat_to_euler as quat_to_euler,
)
from ._bvh import (
    read_bvh as read_bvh,
)
from ._bvh import (
    write_bvh as write_bvh,
)
from ._data import (
    example_names as example_names,
)
from ._data import (
    example_path as example_path,
)
from ._data import (
    load_example as load_example,
)
from ._deepmimic import (
    HUMANOID3D as HUMANOID3D,
)
from ._deepmimic import (
    parse_deepmimic as parse_deepmimic,
)
from ._deepmimic import (
    read_deepmimic as read_deepmimic,
)
from ._readers import (
    read_motion as read_motion,
)

__all__ = [
    "HUMANOID3D",
    "euler_to_quat",
    "example_names",
    "example_path",
    "load_example",
    "parse_bvh",
    "parse_deepmimic",
    "quat_to_euler",
    "read_bvh",
    "read_deepmimic",
    "read_motion",
    "write_bvh",
]
