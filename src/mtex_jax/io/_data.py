"""Embedded example data: the DeepMimic humanoid3d clips (zlib licence, see NOTICE)."""

from __future__ import annotations

from importlib import resources

from ..motion import Motion
from ._deepmimic import parse_deepmimic
from ._salsa import load_salsa

__all__ = ["example_names", "example_path", "load_example"]

_PACKAGE = "mtex_jax.data.deepmimic"
_PREFIX = "humanoid3d_"


def example_names() -> list[str]:
    """Names of the embedded example clips, e.g. ``["backflip", "cartwheel", ...]``."""
    folder = resources.files(_PACKAGE)
    names = [
        f.name[len(_PREFIX) : -len(".txt")]
        for f in folder.iterdir()
        if f.name.startswith(_PREFIX) and f.name.endswith(".txt")
    ]
    return sorted(names)


def example_path(name: str) -> str:
    """A readable description of where an example lives (for messages)."""
    return f"{_PACKAGE}/{_PREFIX}{name}.txt"


def load_example(name: str) -> Motion:
    """Load an embedded DeepMimic humanoid3d clip by name (see :func:`example_names`), or a
    shipped CMU salsa clip as ``salsa/NAME`` (e.g. ``salsa/60_01``, see :func:`load_salsa`).

    The clips ship inside the package (they work from an installed wheel); their zlib licence
    notice is in ``mtex_jax.data.deepmimic/LICENSE-zlib.txt``.

    Raises:
        ValueError: unknown name (the message lists the available ones).
    """
    if name.startswith("salsa/"):
        return load_salsa(name[len("salsa/") :])
    names = example_names()
    if name not in names:
        raise ValueError(
            f"unknown example {name!r}; available: {', '.join(names)}, or salsa/NAME "
            "(NAME one of the CMU salsa clips 60_01 ... 60_15, see 'mtex examples')"
        )
    res = resources.files(_PACKAGE).joinpath(f"{_PREFIX}{name}.txt")
    return parse_deepmimic(res.read_text(encoding="utf-8"), example_path(name))
