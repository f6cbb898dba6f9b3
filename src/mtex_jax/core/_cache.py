"""JAX's persistent compilation cache, opt-in for the library (a library must not change
global configuration behind its user's back) and on by default for the ``mtex`` command.

XLA compiles every jitted program once per process; the persistent cache keeps the compiled
executables on disk, keyed by the program, its shapes, the compiler version and the device, so
that a new process skips the compilation of a program seen before. Results never depend on it:
a missing, stale or unreadable entry is compiled again. Programs with host callbacks are not
cached by JAX.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

__all__ = ["default_cache_dir", "enable_compilation_cache"]


def default_cache_dir() -> Path:
    """``$MTEX_JAX_CACHE``, else ``$XDG_CACHE_HOME/mtex_jax/jax`` (``~/.cache/mtex_jax/jax``)."""
    env = os.environ.get("MTEX_JAX_CACHE")
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "mtex_jax" / "jax"


def enable_compilation_cache(path: str | os.PathLike[str] | None = None) -> Path:
    """Turn on JAX's persistent compilation cache in ``path`` (default
    :func:`default_cache_dir`), for every program that takes at least 0.1 s to compile.

    This changes JAX's global configuration for the whole process, which is why the library
    never calls it by itself.

    Args:
        path: the cache folder; created if missing.

    Returns:
        The cache folder.

    Raises:
        ValueError: if ``path`` exists and is not a folder.
    """
    folder = Path(path).expanduser() if path is not None else default_cache_dir()
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"enable_compilation_cache: {folder} exists and is not a folder")
    folder.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.1)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder
