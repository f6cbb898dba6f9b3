"""Whether a dotted ``mtex_jax.…`` name names a module or an attribute that exists (for the
layout and documentation tests)."""

from __future__ import annotations

import importlib


def resolves(dotted: str) -> bool:
    """``True`` when the longest importable prefix of ``dotted`` has the remaining attributes."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False
