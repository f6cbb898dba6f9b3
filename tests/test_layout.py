"""The package layout rules of ARCHITECTURE.md, checked on the source tree.

- no source file over 500 lines;
- no private name (``_x``) imported from another subpackage, except by ``internal`` (the one
  white-box namespace, which re-exports private building blocks under public names);
- no module imports from a subpackage of a higher layer (nor from a sibling of its layer);
- ``internal`` is the top layer: nothing in the package imports it (not even the top level);
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


def _rule_problems(
    own: str | None, imports: list[tuple[str, list[str], int]], where: str
) -> list[str]:
    """The layout rules broken by the ``imports`` of one module of subpackage ``own`` (``None``
    for a top-level module)."""
    problems = []
    for target, names, line in imports:
        if target in ("", own) or target not in LAYERS:
            continue
        at = f"{where}:{line}"
        if target == "internal":
            problems.append(f"{at} imports the white-box namespace internal")
            continue
        if own is None:  # top-level modules re-export the subpackages' public API
            continue
        private = [n for n in names if n.startswith("_") and n != "__version__"]
        if private and own != "internal":
            problems.append(f"{at} imports private {private} from {target}")
        if own != "cli" and LAYERS[target] >= LAYERS[own]:
            problems.append(f"{at}: {own} (layer {LAYERS[own]}) imports {target}")
    return problems


def test_no_private_names_across_subpackages_and_no_upward_imports():
    problems = []
    for path in _modules():
        problems += _rule_problems(_subpackage(path), _imports(path), str(path.relative_to(SRC)))
    assert not problems, "\n".join(problems)


def test_internal_is_the_top_layer():
    assert LAYERS["internal"] == max(LAYERS.values())


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
    assert len(_rule_problems("texture", found, "probe")) == 3  # two private, one upward


def test_only_internal_may_import_private_names_and_nothing_imports_internal():
    white_box = "from ..texture._linalg import _factor as block_tridiag_factor\n"
    assert not _rule_problems("internal", _imports_of(white_box, ("internal", "__init__.py")), "")
    assert _rule_problems("viz", _imports_of(white_box, ("viz", "_probe.py")), "")
    uses = "from ..internal import path_core\nfrom mtex_jax.internal import TO_PLOT\n"
    for own in ("cli", "texture"):  # cli may import any layer, but not internal
        assert len(_rule_problems(own, _imports_of(uses, (own, "_probe.py")), "")) == 2
    top = "from .internal import path_core\nfrom mtex_jax.internal import TO_PLOT\n"
    assert len(_rule_problems(None, _imports_of(top, ("__init__.py",)), "")) == 2


def test_internal_all_lists_its_re_exports():
    import mtex_jax.internal as internal

    public = {n for n in vars(internal) if not n.startswith("_")}
    assert set(internal.__all__) == public
    assert internal.__all__ == sorted(internal.__all__, key=lambda n: (not n.isupper(), n))


def test_small_top_level():
    assert len(mtex_jax.__all__) <= 30
    importlib.import_module("mtex_jax.texture")
    importlib.import_module("mtex_jax.implicit")
    assert mtex_jax.texture.MotionTexture.__module__ == "mtex_jax.texture._model"
    assert mtex_jax.implicit.ImplicitModel is mtex_jax.ImplicitModel
    for name in mtex_jax.__all__:
        assert hasattr(mtex_jax, name)
