"""The lowest layer: building blocks every subpackage may use.

- the model-file format: one ``.npz`` archive of plain arrays plus JSON metadata, never pickled
  (:func:`save_arrays_json`, :func:`load_arrays_json`; re-exported by :mod:`mtex_jax.io`);
- atomic file writes (:func:`atomic_write`): every file the package writes goes through it;
- the resource limits of readers, model files and generators (constants of
  ``core/_limits.py``, re-exported here) and the PRNG key check of public entry points;
- JAX's persistent compilation cache, opt-in (:func:`enable_compilation_cache`).
"""

from ._arrays import (
    load_arrays_json as load_arrays_json,
    save_arrays_json as save_arrays_json,
)
from ._atomic import atomic_write as atomic_write
from ._cache import (
    default_cache_dir as default_cache_dir,
    enable_compilation_cache as enable_compilation_cache,
)
from ._keys import check_key as check_key
from ._limits import (
    MAX_ABS_VALUE as MAX_ABS_VALUE,
    MAX_DEPTH as MAX_DEPTH,
    MAX_FRAME_TIME as MAX_FRAME_TIME,
    MAX_FRAMES as MAX_FRAMES,
    MAX_GENERATED_FRAMES as MAX_GENERATED_FRAMES,
    MAX_JOINTS as MAX_JOINTS,
    MAX_MEMBER_BYTES as MAX_MEMBER_BYTES,
    MAX_MODEL_BYTES as MAX_MODEL_BYTES,
    MAX_PARTICLES as MAX_PARTICLES,
    MIN_FRAME_TIME as MIN_FRAME_TIME,
    check_count as check_count,
    check_frame_time as check_frame_time,
    check_json_depth as check_json_depth,
)

__all__ = [
    "MAX_ABS_VALUE",
    "MAX_DEPTH",
    "MAX_FRAMES",
    "MAX_FRAME_TIME",
    "MAX_GENERATED_FRAMES",
    "MAX_JOINTS",
    "MAX_MEMBER_BYTES",
    "MAX_MODEL_BYTES",
    "MAX_PARTICLES",
    "MIN_FRAME_TIME",
    "atomic_write",
    "check_count",
    "check_frame_time",
    "check_json_depth",
    "check_key",
    "default_cache_dir",
    "enable_compilation_cache",
    "load_arrays_json",
    "save_arrays_json",
]
