"""The notebooks run as shipped: executed top to bottom with nbclient, from the installed package
and its shipped salsa clips (no path outside the repository).

Slow: each notebook learns a model on the 14 clips. Needs the ``notebooks`` extra
(``pip install -e ".[notebooks]"``); skipped without it. The kernels start with the test
process's persistent compilation cache (set through the environment, not in the notebooks).
"""

import json
import shutil
from pathlib import Path

import pytest

from jax_cache import cache_env

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))


def test_notebooks_found():
    assert {p.name for p in NOTEBOOKS} >= {"motion_texture.ipynb", "implicit_model.ipynb"}


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_reads_shipped_data(path):
    """No cell reads files from outside the repository (the shared data folder)."""
    cells = json.loads(path.read_text(encoding="utf-8"))["cells"]
    code = "\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "code")
    for outside in ("MTEX_SHARED", "shared", "read_bvh("):
        assert outside not in code, f"{path.name} reads {outside!r}: use mtex_jax.io.load_salsa"
    assert "load_salsa" in code


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_executes(path, tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    # run in a copy so that the figures it writes do not replace the committed ones
    work = tmp_path / path.name
    shutil.copy(path, work)
    nb = nbformat.read(work, as_version=4)
    for name, value in cache_env().items():  # the kernel inherits this environment
        monkeypatch.setenv(name, value)
    client = nbclient.NotebookClient(
        nb,
        timeout=3600,
        kernel_name="python3",
        resources={"metadata": {"path": str(tmp_path)}},
    )
    client.execute()
    errors = [
        o
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
        if o.get("output_type") == "error"
    ]
    assert not errors
    assert any((tmp_path / "figures").glob("*.png"))
