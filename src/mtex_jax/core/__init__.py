"""The lowest layer: building blocks every subpackage may use.

- the model-file format: one ``.npz`` archive of plain arrays plus JSON metadata, never pickled
  (:func:`save_arrays_json`, :func:`load_arrays_json`; re-exported by :mod:`mtex_jax.io`);
- atomic file writes (:func:`atomic_write`): every file the package writes goes through it;
  only regular files are replaced, and temporary files of killed saves are removed;
- the rules of the command line's files (:func:`read_input`: a size cap and regular files only;
  :func:`check_output`: no output over an input, another kind of file only with ``--force``;
  :func:`file_kind`);
- the resource limits of readers, model files, configurations and generators (constants of
  ``core/_limits.py``, re-exported here; :func:`set_limit` raises one) and the PRNG key check
  of public entry points;
- JAX's persistent compilation cache, opt-in (:func:`enable_compilation_cache`);
- shape buckets (:func:`bucket_length`, :func:`pad_frames`): public calls pad lengths to a few
  sizes so that a new length does not compile a new program; :func:`count_compiles` counts
  the compilations of a block of code.
"""

from ._arrays import (
    load_arrays_json as load_arrays_json,
    save_arrays_json as save_arrays_json,
)
from ._atomic import (
    atomic_write as atomic_write,
    check_writable as check_writable,
    remove_stale_temporaries as remove_stale_temporaries,
)
from ._buckets import (
    BUCKET_FRAMES as BUCKET_FRAMES,
    CompileCount as CompileCount,
    as_array as as_array,
    bucket_length as bucket_length,
    count_compiles as count_compiles,
    cut_frames as cut_frames,
    pad_frames as pad_frames,
)
from ._cache import (
    default_cache_dir as default_cache_dir,
    enable_compilation_cache as enable_compilation_cache,
)
from ._files import (
    check_output as check_output,
    describe_kind as describe_kind,
    file_kind as file_kind,
    read_input as read_input,
)
from ._keys import check_key as check_key
from ._limits import (
    MAX_ABS_VALUE as MAX_ABS_VALUE,
    MAX_CANDIDATES as MAX_CANDIDATES,
    MAX_COMPONENTS as MAX_COMPONENTS,
    MAX_DEPTH as MAX_DEPTH,
    MAX_FRAME_TIME as MAX_FRAME_TIME,
    MAX_FRAMES as MAX_FRAMES,
    MAX_GENERATED_FRAMES as MAX_GENERATED_FRAMES,
    MAX_INPUT_BYTES as MAX_INPUT_BYTES,
    MAX_ITERATIONS as MAX_ITERATIONS,
    MAX_JOINTS as MAX_JOINTS,
    MAX_MEMBER_BYTES as MAX_MEMBER_BYTES,
    MAX_MIN_SEGMENTS as MAX_MIN_SEGMENTS,
    MAX_MODEL_BYTES as MAX_MODEL_BYTES,
    MAX_PARTICLES as MAX_PARTICLES,
    MAX_PATH_TEXTONS as MAX_PATH_TEXTONS,
    MAX_SEGMENT_FRAMES as MAX_SEGMENT_FRAMES,
    MAX_STATE_DIM as MAX_STATE_DIM,
    MAX_TEXTONS as MAX_TEXTONS,
    MIN_FRAME_TIME as MIN_FRAME_TIME,
    check_count as check_count,
    check_frame_time as check_frame_time,
    check_json_depth as check_json_depth,
    check_real as check_real,
    check_size as check_size,
    limit as limit,
    set_limit as set_limit,
)
from ._memory import (
    available_memory as available_memory,
    check_memory as check_memory,
    program_bytes as program_bytes,
)
from ._numbers import (
    NUMBER as NUMBER,
    json_value_line as json_value_line,
    load_json as load_json,
    number_problem as number_problem,
    show_token as show_token,
)

__all__ = [
    "BUCKET_FRAMES",
    "MAX_ABS_VALUE",
    "MAX_CANDIDATES",
    "MAX_COMPONENTS",
    "MAX_DEPTH",
    "MAX_FRAMES",
    "MAX_FRAME_TIME",
    "MAX_GENERATED_FRAMES",
    "MAX_INPUT_BYTES",
    "MAX_ITERATIONS",
    "MAX_JOINTS",
    "MAX_MEMBER_BYTES",
    "MAX_MIN_SEGMENTS",
    "MAX_MODEL_BYTES",
    "MAX_PARTICLES",
    "MAX_PATH_TEXTONS",
    "MAX_SEGMENT_FRAMES",
    "MAX_STATE_DIM",
    "MAX_TEXTONS",
    "MIN_FRAME_TIME",
    "NUMBER",
    "CompileCount",
    "as_array",
    "atomic_write",
    "available_memory",
    "bucket_length",
    "check_count",
    "check_frame_time",
    "check_json_depth",
    "check_key",
    "check_memory",
    "check_output",
    "check_real",
    "check_size",
    "check_writable",
    "count_compiles",
    "cut_frames",
    "default_cache_dir",
    "describe_kind",
    "enable_compilation_cache",
    "file_kind",
    "json_value_line",
    "limit",
    "load_arrays_json",
    "load_json",
    "number_problem",
    "pad_frames",
    "program_bytes",
    "read_input",
    "remove_stale_temporaries",
    "save_arrays_json",
    "set_limit",
    "show_token",
]
