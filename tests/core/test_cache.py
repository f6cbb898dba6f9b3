"""The persistent compilation cache switch (``mtex_jax.enable_compilation_cache``)."""

from __future__ import annotations

import jax
import pytest

from mtex_jax.core import default_cache_dir, enable_compilation_cache


def test_default_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("MTEX_JAX_CACHE", str(tmp_path / "c"))
    assert default_cache_dir() == tmp_path / "c"
    monkeypatch.delenv("MTEX_JAX_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "mtex_jax" / "jax"


def test_enable_sets_the_folder_and_refuses_a_file(tmp_path):
    before = jax.config.jax_compilation_cache_dir
    try:
        folder = enable_compilation_cache(tmp_path / "cache")
        assert folder.is_dir()
        assert jax.config.jax_compilation_cache_dir == str(folder)
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
    f = tmp_path / "a_file"
    f.write_text("x")
    with pytest.raises(ValueError, match="not a folder"):
        enable_compilation_cache(f)
