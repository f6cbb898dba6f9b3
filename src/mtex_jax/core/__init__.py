"""The lowest layer: building blocks every subpackage may use.

- the model-file format: one ``.npz`` archive of plain arrays plus JSON metadata, never pickled
  (:func:`save_arrays_json`, :func:`load_arrays_json`; re-exported by :mod:`mtex_jax.io`).
"""

from ._arrays import (
    load_arrays_json as load_arrays_json,
    save_arrays_json as save_arrays_json,
)

__all__ = [
    "load_arrays_json",
    "save_arrays_json",
]
