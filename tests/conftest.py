"""Shared test configuration: float64 everywhere, paths to the project's shared data."""

from __future__ import annotations

import gc
import os
from pathlib import Path

import jax
import pytest

jax.config.update("jax_enable_x64", True)

# The persistent compilation cache (under the user's cache folder, or $MTEX_JAX_CACHE): a
# second run of the suite on the same machine skips most XLA compilations. Results do not
# depend on it; MTEX_NO_CACHE=1 turns it off.
if os.environ.get("MTEX_NO_CACHE", "") not in ("1", "true", "yes"):
    from mtex_jax.core import enable_compilation_cache

    try:
        enable_compilation_cache()
    except (OSError, ValueError, RuntimeError):
        pass  # no writable cache folder: compile as usual

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MTEX_SHARED", REPO.parent / "shared"))
CMU_DIR = SHARED / "data" / "cmu-salsa"
DEEPMIMIC_DIR = SHARED / "data" / "deepmimic"


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_code():
    """Drop JAX's compiled executables after every test module.

    Each XLA:CPU executable keeps a few anonymous memory mappings of JIT code for as long as
    JAX caches it; the whole suite compiles thousands of functions (hypothesis draws many
    shapes), and one process would otherwise run into the kernel's limit on mappings
    (``vm.max_map_count`` = 65530), which XLA reports as an abort or a segfault while
    compiling.
    """
    yield
    jax.clear_caches()
    gc.collect()


def _require(path: Path) -> Path:
    if not path.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"shared data folder {path} is missing in CI")
        pytest.skip(f"shared data folder {path} not available (set MTEX_SHARED)")
    return path


@pytest.fixture(scope="session")
def cmu_dir() -> Path:
    return _require(CMU_DIR)


@pytest.fixture(scope="session")
def cmu_files(cmu_dir: Path) -> list[Path]:
    files = sorted(cmu_dir.glob("*.bvh"))
    assert len(files) == 14, f"expected 14 CMU salsa clips in {cmu_dir}, found {len(files)}"
    return files


@pytest.fixture(scope="session")
def cmu_motions(cmu_files):
    import mtex_jax as mj

    return [mj.read_bvh(f) for f in cmu_files]
