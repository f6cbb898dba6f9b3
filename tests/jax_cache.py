"""The environment of a child process (the README tour, the notebooks' kernels, the workers of
the multi-process tests) with JAX's persistent compilation cache set as in this test process
(tests/conftest.py turns it on): a child skips the compilations that an earlier run on the
same machine stored. Results never depend on the cache; with ``MTEX_NO_CACHE=1`` it stays off
in the children too."""

from __future__ import annotations

import os

import jax


def cache_env() -> dict[str, str]:
    """The ``JAX_…`` variables that give a new Python process this process's persistent
    compilation cache (JAX reads its configuration from them when it starts); empty when the
    cache is off here."""
    folder = jax.config.jax_compilation_cache_dir
    if not folder:
        return {}
    return {
        "JAX_COMPILATION_CACHE_DIR": str(folder),
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": str(
            jax.config.jax_persistent_cache_min_compile_time_secs
        ),
        "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": str(
            jax.config.jax_persistent_cache_min_entry_size_bytes
        ),
    }


def child_env(**extra: str) -> dict[str, str]:
    """``os.environ`` with :func:`cache_env` and ``extra`` on top."""
    return {**os.environ, **cache_env(), **extra}
