"""The package layout rules of ARCHITECTURE.md, checked on the source tree.

- no source file over 500 lines;
- no private name (``_x``) imported from another subpackage;
- no module imports from a subpackage of a higher layer (nor from a sibling of its layer);
- the top level re-exports at most 30 names; ``MotionTexture`` lives outside the trainer.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

import mtex_jax

SRC = Path(mtex_jax.__file__).resolve().parent

# lower number = lower layer; a module may import only from its own subpackage or a lower layer
LAYERS = {
    "core": 0,
    "internal": 7,
    "motion": 1,
    "io": 2,
    "texture": 3,
    "implicit": 3,
    "metrics": 4,
    "edit": 5,
    "viz": 5,
    "cli": 6,
    "data": 0,
}


def _modules() -> list[Path]:
    return sorted(p for p in SRC.rglob("*.py"))


def _subpackage(path: Path) -> str | None:
    rel = path.relative_to(SRC).parts
    return rel[0] if len(rel) > 1 else None


def _imports(path: Path) -> list[tuple[str, list[str], int]]:
    return _imports_of(path.read_text(), path.relative_to(SRC).parts)


def _imports_of(text: str, rel: tuple[str, ...]) -> list[tuple[str, list[str], int]]:
    """``(target subpackage, imported names, line)`` of every package-internal import of a
    module at ``src/mtex_jax/<rel>``."""
    tree = ast.parse(text)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level == 0:
                mod = node.module or ""
                if not mod.startswith("mtex_jax"):
                    continue
                parts = mod.split(".")[1:]
            else:
                base = list(rel[:-1])
                up = node.level - 1
                base = base[: len(base) - up] if up else base
                parts = base + (node.module.split(".") if node.module else [])
            target = parts[0] if parts else ""
            names = [a.name for a in node.names]
            # "from .. import _x" imports a module of the target package
            if node.module is None and node.level > 1 and not parts:
                target = names[0]
            out.append((target, names + parts[1:], node.lineno))
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("mtex_jax."):
                    parts = a.name.split(".")[1:]
                    out.append((parts[0], parts[1:], node.lineno))
    return out


def test_every_subpackage_has_a_layer():
    subs = {p.name for p in SRC.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert subs <= set(LAYERS), f"add {subs - set(LAYERS)} to LAYERS and ARCHITECTURE.md"


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(SRC)))
def test_no_file_over_500_lines(path):
    n = len(path.read_text().splitlines())
    assert n <= 500, f"{path.relative_to(SRC)} has {n} lines"


def test_no_private_names_across_subpackages_and_no_upward_imports():
    problems = []
    for path in _modules():
        own = _subpackage(path)
        if own is None:  # top-level modules re-export the API
            continue
        for target, names, line in _imports(path):
            if target in ("", own) or target not in LAYERS:
                continue
            where = f"{path.relative_to(SRC)}:{line}"
            private = [n for n in names if n.startswith("_") and n != "__version__"]
            if private:
                problems.append(f"{where} imports private {private} from {target}")
            if own != "cli" and LAYERS[target] >= LAYERS[own]:
                problems.append(f"{where}: {own} (layer {LAYERS[own]}) imports {target}")
    assert not problems, "\n".join(problems)


def test_checker_sees_violations():
    """The import walker finds private and upward imports (so the rule test can fail)."""
    src = (
        "from ..motion._features import raw_features\n"
        "from ..motion import _helper\n"
        "from mtex_jax.viz import render_gif\n"
        "from . import _fit\n"
    )
    found = _imports_of(src, ("texture", "_probe.py"))
    assert ("motion", ["raw_features", "_features"], 1) in found
    assert ("motion", ["_helper"], 2) in found
    assert ("viz", ["render_gif"], 3) in found
    assert ("texture", ["_fit"], 4) in found


def test_small_top_level():
    assert len(mtex_jax.__all__) <= 30
    importlib.import_module("mtex_jax.texture")
    importlib.import_module("mtex_jax.implicit")
    assert mtex_jax.texture.MotionTexture.__module__ == "mtex_jax.texture._model"
    assert mtex_jax.implicit.ImplicitModel is mtex_jax.ImplicitModel
    for name in mtex_jax.__all__:
        assert hasattr(mtex_jax, name)
