"""The documentation site: the API reference lists every public name, and the nav holds every page.

Each subpackage's ``__all__`` is its public API (ARCHITECTURE.md). Its reference page,
``docs/api/<subpackage>.md``, documents a name either with a mkdocstrings directive
(``::: mtex_jax.<subpackage>.<name>``) or, for a name re-exported from another subpackage, with a
cross-reference to where it is documented (``[`name`][mtex_jax.<other>.<name>]``). The top-level
names are listed on ``docs/api/index.md``. ``mkdocs build --strict`` (run by ``.ci/run``) then
checks that every directive renders and every cross-reference resolves.
"""

import importlib
import pkgutil
import re
from pathlib import Path

import pytest

import mtex_jax
from names import resolves

ROOT = Path(__file__).resolve().parents[1]
API = ROOT / "docs" / "api"
SUBPACKAGES = sorted(
    m.name
    for m in pkgutil.iter_modules(mtex_jax.__path__)
    if m.ispkg and not m.name.startswith("_")
)
DOCUMENTED = [
    s for s in SUBPACKAGES if hasattr(importlib.import_module(f"mtex_jax.{s}"), "__all__")
]


def _names_on_page(text: str, sub: str) -> tuple[set[str], set[str]]:
    """Names documented by a directive of ``mtex_jax.<sub>``, and names cross-referenced."""
    directives = set(re.findall(rf"^::: mtex_jax\.{sub}\.(\w+)\s*$", text, flags=re.M))
    links = set(re.findall(r"\[`(\w+)`\]\[mtex_jax\.\w+\.(?:\w+\.)*\w+\]", text))
    return directives, links


def test_subpackages_found():
    assert {"texture", "implicit", "motion", "io", "edit", "metrics", "viz"} <= set(DOCUMENTED)


@pytest.mark.parametrize("sub", DOCUMENTED)
def test_reference_page_lists_all(sub):
    page = API / f"{sub}.md"
    assert page.is_file(), f"no API page {page.relative_to(ROOT)} for mtex_jax.{sub}"
    text = page.read_text(encoding="utf-8")
    directives, links = _names_on_page(text, sub)
    public = set(importlib.import_module(f"mtex_jax.{sub}").__all__)
    missing = sorted(public - directives - links)
    extra = sorted(directives - public)
    fix = "run tools/api_pages.py"
    assert not missing, f"docs/api/{sub}.md does not document {missing} (in __all__): {fix}"
    assert not extra, f"docs/api/{sub}.md documents {extra}, not in __all__: {fix}"


def test_top_level_names_listed():
    text = (API / "index.md").read_text(encoding="utf-8")
    _, links = _names_on_page(text, "")
    missing = sorted(set(mtex_jax.__all__) - links - {"__version__"})
    assert not missing, f"docs/api/index.md does not list {missing}"


def test_nav_holds_every_page():
    nav = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    pages = sorted(p.relative_to(ROOT / "docs").as_posix() for p in (ROOT / "docs").rglob("*.md"))
    missing = [p for p in pages if p not in nav]
    assert not missing, f"pages missing from the nav of mkdocs.yml: {missing}"
    for sub in DOCUMENTED:
        assert f"api/{sub}.md" in nav


def test_dotted_names_in_docs_resolve():
    """Every ``mtex_jax.…`` name in the README and the hand-written pages exists."""
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    problems = []
    for page in pages:
        if page.name == "results.md":  # generated from the benchmarks' reports
            continue
        for ref in re.findall(r"(?<![\w/])mtex_jax(?:\.\w+)+", page.read_text(encoding="utf-8")):
            if not resolves(ref.rstrip(".")):
                problems.append(f"{page.relative_to(ROOT)}: {ref}")
    assert not problems, "\n".join(problems)


def test_no_docstring_links_into_benchmarks():
    """Docstrings cite the design document or the papers; results live on the results page."""
    problems = []
    for path in sorted((ROOT / "src" / "mtex_jax").rglob("*.py")):
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if re.search(r"benchmarks/", line):
                problems.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not problems, "links into benchmarks/:\n" + "\n".join(problems)
