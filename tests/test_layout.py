"""The package layout rules of ARCHITECTURE.md, checked on the source tree.

- modules are sized by their concept: no line or folder-size cap (issue 56);
- no private name (``_x``) imported from another subpackage, except by ``internal`` (the one
  white-box namespace, which re-exports private building blocks under public names);
- no module imports from a subpackage of a higher layer (nor from a sibling of its layer);
- ``internal`` is the top layer: nothing in the package imports it (not even the top level);
- the top level re-exports at most 30 names; ``MotionTexture`` lives outside the trainer.
"""

from __future__ import annotations

import ast
import importlib
import types
from pathlib import Path

import mtex_jax
from names import resolves

SRC = Path(mtex_jax.__file__).resolve().parent

# lower number = lower layer; a module may import only from its own subpackage or a lower layer
LAYERS = {
    "core": 0,
    "linalg": 0,
    "internal": 8,
    "motion": 1,
    "io": 2,
    "texture": 3,
    "implicit": 3,
    "metrics": 4,
    "edit": 5,
    "viz": 5,
    "tracking": 6,
    "cli": 7,
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
    white_box = "from ..texture._linalg import block_tridiag_factor as block_tridiag_factor\n"
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
    assert len(internal.__all__) <= 5, "internal holds what downstream libraries need, no more"


def test_small_top_level():
    assert len(mtex_jax.__all__) <= 30
    importlib.import_module("mtex_jax.texture")
    importlib.import_module("mtex_jax.implicit")
    assert mtex_jax.texture.MotionTexture.__module__ == "mtex_jax.texture._model"
    assert mtex_jax.implicit.ImplicitModel is mtex_jax.ImplicitModel
    for name in mtex_jax.__all__:
        assert hasattr(mtex_jax, name)


# --------------------------------------------------------------------------------------------
# Rooms (issue 40): private imports, import cycles, references that resolve
# --------------------------------------------------------------------------------------------

MAX_PRIVATE_IMPORTS = 0
REPO = SRC.parents[1]
DESIGN = REPO / "docs" / "design.md"


def _module_name(path: Path) -> str:
    parts = ("mtex_jax", *path.relative_to(SRC).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def _import_edges(path: Path) -> list[tuple[str, list[str]]]:
    """``(absolute module, imported names)`` of every package-internal ``from`` import, at any
    depth: imports inside functions count (they are how cycles hide), and so do imports under
    ``if TYPE_CHECKING:`` (a type a module needs is a dependency; a cycle through annotations is
    still a cycle of concepts)."""
    name = _module_name(path)
    pkg = name if _is_package(path) else name.rsplit(".", 1)[0]
    out = []
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] == "mtex_jax":
                out.append((mod, [a.name for a in node.names]))
    return out


def _module_graph() -> dict[str, set[str]]:
    paths = {_module_name(p): p for p in _modules()}
    graph: dict[str, set[str]] = {m: set() for m in paths}
    for mod, path in paths.items():
        for target, names in _import_edges(path):
            for n in names:  # "from . import x" imports the module x
                if f"{target}.{n}" in paths:
                    graph[mod].add(f"{target}.{n}")
            if target in paths and not all(f"{target}.{n}" in paths for n in names):
                graph[mod].add(target)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), ignoring the edges
    into a package's ``__init__`` from its own members (re-exports, not dependencies)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def edges(v: str) -> set[str]:
        return {w for w in graph[v] if not v.startswith(w + ".")}

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges(v):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles():
    cycles = _cycles(_module_graph())
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_each_name_is_exported_by_one_subpackage():
    """No object is in the ``__all__`` of two subpackages (the top level may re-export)."""
    seen: dict[int, str] = {}
    twice = []
    for sub in sorted(p.parent.name for p in SRC.glob("*/__init__.py")):
        mod = importlib.import_module(f"mtex_jax.{sub}")
        for name in getattr(mod, "__all__", []):
            obj = getattr(mod, name)
            if isinstance(obj, types.ModuleType) or isinstance(obj, int | float | str | tuple):
                continue  # constants and modules are values, not definitions
            where = f"{sub}.{name}"
            if id(obj) in seen:
                twice.append(f"{seen[id(obj)]} = {where}")
            else:
                seen[id(obj)] = where
    assert not twice, "exported twice:\n" + "\n".join(twice)


def test_type_checking_imports_are_edges():
    """``base.py`` imports the statistics types only under ``TYPE_CHECKING``; the graph sees it."""
    base = SRC / "texture" / "_observation" / "base.py"
    assert "if TYPE_CHECKING:" in base.read_text()
    assert "mtex_jax.texture._texton.stats" in {m for m, _ in _import_edges(base)}


def test_cycle_finder_sees_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _cycles({"p": set(), "p.x": {"p"}}) == []  # a member importing its package: no cycle


def _private_imports() -> list[str]:
    """Every private name (``_x``, not a module) that one module of ``src`` imports from
    another."""
    paths = {_module_name(p) for p in _modules()}
    found = []
    for path in _modules():
        for target, names in _import_edges(path):
            for n in names:
                if n.startswith("_") and not n.startswith("__") and f"{target}.{n}" not in paths:
                    found.append(f"{path.relative_to(SRC)}: {n} from {target}")
    return found


def test_no_private_name_is_imported_between_modules():
    found = _private_imports()
    assert len(found) <= MAX_PRIVATE_IMPORTS, f"{len(found)} private imports:\n" + "\n".join(found)


def _text_files() -> list[Path]:
    return [
        *_modules(),
        *sorted((REPO / "tests").rglob("*.py")),
        *sorted((REPO / "benchmarks").rglob("*.py")),
    ]


def _design_sections() -> set[str]:
    import re

    heads = re.findall(r"^#{2,4} (\d+(?:\.\d+)*)[. ]", DESIGN.read_text(), flags=re.M)
    return set(heads)


def test_design_references_resolve():
    """Every ``design §N`` cited in the code is a numbered heading of ``docs/design.md``, and
    nothing cites the old specification outside the repository."""
    import re

    sections = _design_sections()
    assert {"1", "2", "3", "4", "5", "10.1", "10.4"} <= sections
    problems = []
    for path in _text_files():
        text = path.read_text()
        if re.search(r"\bSPEC\b", text) and path.name != "test_layout.py":
            problems.append(f"{path.relative_to(REPO)} cites SPEC (not in the repository)")
        for ref in re.findall(r"design\s+§(\d+(?:\.\d+)*)", text):
            if ref not in sections:
                problems.append(f"{path.relative_to(REPO)} cites design §{ref}: no such section")
    assert not problems, "\n".join(problems)


def test_module_references_resolve():
    """Every dotted ``mtex_jax.…`` name in the source, tests and benchmarks names a module or
    an attribute that exists (no references into the old flat layout)."""
    import re

    problems = set()
    for path in _text_files():
        if path.name == "test_layout.py":  # names deliberate non-references below
            continue
        # a quoted "mtex_jax.X" is a model-file kind or a package name, not a reference
        for ref in re.findall(r"(?<![\"'\w])mtex_jax(?:\.\w+)+", path.read_text()):
            if not resolves(ref):
                problems.add(f"{path.relative_to(REPO)}: {ref}")
    assert not problems, "\n".join(sorted(problems))


def test_reference_checks_can_fail():
    assert resolves("mtex_jax.texture.MotionTexture")
    assert not resolves("mtex_jax._learn.MotionTexture")
    assert not resolves("mtex_jax.texture._synthesis.no_such_name")


def _dead_definitions() -> list[str]:
    """Module-level functions and classes of ``src`` named nowhere else (in ``src``, the tests
    or the benchmarks) and not in any subpackage's ``__all__``. A decorated function is
    registered by its decorator (a JVP or vmap rule), which counts as its use."""
    import re
    from collections import Counter

    texts = {p: p.read_text() for p in _text_files()}
    words = Counter(w for text in texts.values() for w in re.findall(r"\w+", text))
    public: set[str] = set()
    for path in SRC.rglob("__init__.py"):
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.Assign) and any(
                getattr(t, "id", None) == "__all__" for t in node.targets
            ):
                public |= {e.value for e in getattr(node.value, "elts", [])}
    dead = []
    for path in _modules():
        for node in ast.parse(texts[path]).body:
            if not isinstance(node, ast.FunctionDef | ast.ClassDef) or node.decorator_list:
                continue
            if node.name in public:
                continue
            if words[node.name] <= 1:
                dead.append(f"{path.relative_to(SRC)}:{node.lineno} {node.name}")
    return dead


def test_no_dead_code():
    dead = _dead_definitions()
    assert not dead, "defined but never used:\n" + "\n".join(dead)
