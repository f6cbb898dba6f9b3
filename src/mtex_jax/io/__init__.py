"""Reading and writing motion: BVH, DeepMimic JSON, the embedded example clips (the CMU salsa
default data and the DeepMimic clips), and the array + JSON model-file format.
"""

from ._bvh import (
    euler_to_quat as euler_to_quat,
    parse_bvh as parse_bvh,
    quat_to_euler as quat_to_euler,
    read_bvh as read_bvh,
    write_bvh as write_bvh,
    write_bvh_chunks as write_bvh_chunks,
)
from ._data import (
    example_names as example_names,
    example_path as example_path,
    load_example as load_example,
)
from ._deepmimic import (
    HUMANOID3D as HUMANOID3D,
    parse_deepmimic as parse_deepmimic,
    read_deepmimic as read_deepmimic,
)
from ._readers import (
    read_motion as read_motion,
)
from ._salsa import (
    load_salsa as load_salsa,
    salsa_credit as salsa_credit,
    salsa_names as salsa_names,
    salsa_split as salsa_split,
)

__all__ = [
    "HUMANOID3D",
    "euler_to_quat",
    "example_names",
    "example_path",
    "load_example",
    "load_salsa",
    "parse_bvh",
    "parse_deepmimic",
    "quat_to_euler",
    "read_bvh",
    "read_deepmimic",
    "read_motion",
    "salsa_credit",
    "salsa_names",
    "salsa_split",
    "write_bvh",
    "write_bvh_chunks",
]
