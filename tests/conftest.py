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


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` with the longest test files first (tests/xdist_order.py)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist_order import LongestFirst

    return LongestFirst(config, log)


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


# the implicit-model test modules (test_implicit, test_tracking) share these, built once per
# test process: the CMU salsa clips at 30 Hz, the database's equal-length training chunks and
# the default implicit model on them (test_tracking's default database is test_implicit's
# model: the same chunks and window)
_SALSA30_HELD_OUT = 2  # 60_03 is held out of the database: probes and the tracked clip
_SALSA30_CHUNK = 128  # equal-length training chunks: one jit compilation of the features
_SALSA30_WINDOW = 10  # frames of the default model's windows


@pytest.fixture(scope="session")
def salsa30_held_out() -> int:
    """The index of the clip that :func:`salsa30_chunks` leaves out."""
    return _SALSA30_HELD_OUT


@pytest.fixture(scope="session")
def salsa30(cmu_motions):
    """The 14 CMU salsa clips at 30 Hz."""
    return [m.resample(30.0) for m in cmu_motions]


@pytest.fixture(scope="session")
def salsa30_chunks(salsa30):
    """``128``-frame chunks of every clip but the held-out one."""
    train = [m for i, m in enumerate(salsa30) if i != _SALSA30_HELD_OUT]
    n = _SALSA30_CHUNK
    return [m[i : i + n] for m in train for i in range(0, m.n_frames - n + 1, n)]


@pytest.fixture(scope="session")
def salsa30_model(salsa30_chunks):
    """The default implicit model (10-frame windows) of :func:`salsa30_chunks`."""
    import mtex_jax as mj

    return mj.implicit.learn(salsa30_chunks, _SALSA30_WINDOW)
