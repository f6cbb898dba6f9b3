"""The ``mtex`` command line: one module per command family, shared argument validators."""

from ._main import main as main

__all__ = ["main"]
