"""Shared building blocks used across subpackages (documented internal namespace).

Not part of the user-facing API; tests and advanced users may import from here.
"""

from ._arrays import (
    load_arrays_json as load_arrays_json,
    save_arrays_json as save_arrays_json,
)

__all__ = [
    "load_arrays_json",
    "save_arrays_json",
]
