"""Write the API reference pages of the documentation site from the subpackages' ``__all__``.

Usage (from the repository root)::

    python tools/api_pages.py

For every subpackage ``mtex_jax.<sub>`` with an ``__all__`` it writes ``docs/api/<sub>.md``: the
subpackage's docstring, then one mkdocstrings directive (``::: mtex_jax.<sub>.<name>``) per name
defined in that subpackage, grouped by the private module that defines it, and a
cross-reference to the documenting page for every name re-exported from another subpackage.
``tests/test_docs.py`` checks the pages against ``__all__``; run this script when a public name
is added or removed. ``docs/api/index.md`` (the top level) is written by hand.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
API = ROOT / "docs" / "api"

# Section titles by defining module (``<sub>.<private module or folder>``); a module not listed
# gets a title from its name.
SECTIONS = {
    "core._limits": "Limits on input",
    "core._atomic": "Files",
    "core._files": "Files",
    "core._arrays": "Model files",
    "core._keys": "Checks",
    "core._cache": "Compilation cache",
    "linalg._blocktridiag": "Block-tridiagonal Cholesky",
    "linalg._blockpenta": "Block-pentadiagonal Cholesky (one frame per block)",
    "linalg._banded": "Block-banded solves",
    "motion._skeleton": "Skeletons",
    "motion._motion": "Motions",
    "motion._features": "Observation vectors",
    "motion._rotation": "Rotations",
    "motion._kinematics": "Forward kinematics",
    "motion._feet": "Feet",
    "io._deepmimic": "DeepMimic",
    "io._bvh": "BVH",
    "io._data": "Example clips",
    "io._salsa": "The shipped salsa clips",
    "io._readers": "Any motion file",
    "texture._config": "Learning",
    "texture._learning": "Learning",
    "texture._model": "The model",
    "texture._vocabulary": "The model",
    "texture._noise": "Innovations of synthesis",
    "texture._observation": "Observation models",
    "texture._texton": "Textons",
    "texture._scoring": "Segment scores",
    "texture._segmentation": "Segmentation and likelihood",
    "texture._synthesis": "Paths and synthesis",
    "implicit._camera": "Tracking",
    "implicit._tracking": "Tracking",
    "implicit._model": "The model",
    "implicit._database": "The model",
    "implicit._learn": "The model",
    "implicit._tree": "The model",
    "implicit._windows": "Pose vectors and windows",
    "implicit._synthesis": "Synthesis",
    "implicit._synthesis_api": "Synthesis",
    "metrics._contacts": "Contacts, skating and the floor",
    "metrics._novelty": "Novelty and copying",
    "metrics._baselines": "Density and prediction baselines",
    "metrics._prediction": "Density and prediction baselines",
    "metrics._report": "Reports",
    "metrics._realism": "Realism",
    "metrics._transitions": "Transitions",
    "metrics._kinematics": "Kinematics",
    "edit._clean": "Cleaning",
    "edit._constraints": "Constraints",
    "edit._solve": "Solving",
    "edit._api": "Editing",
    "edit._prior": "The texture prior",
    "edit._synth": "Synthesis with cleaning",
    "viz._quality": "Quality plots",
    "viz._panel": "Quality plots",
    "viz._plots": "Timelines",
    "viz._render": "Stick figures",
    "viz._compare": "Stick figures",
    "viz._gallery": "Galleries",
    "viz._html": "HTML player",
    "cli._main": "Entry point",
}

_HEADER = "    options:\n      members: false\n      show_root_heading: false\n"


def subpackages() -> list[str]:
    """The public subpackages of ``mtex_jax`` that declare an ``__all__``."""
    import mtex_jax

    names = [
        m.name
        for m in pkgutil.iter_modules(mtex_jax.__path__)
        if m.ispkg and not m.name.startswith("_")
    ]
    return sorted(n for n in names if hasattr(importlib.import_module(f"mtex_jax.{n}"), "__all__"))


def _targets(sub: str) -> list[tuple[str, str]]:
    """``(name, path of the object it names)`` for every name of ``__all__``, via griffe."""
    import griffe

    pkg = griffe.load(f"mtex_jax.{sub}", search_paths=[str(ROOT / "src")], resolve_aliases=True)
    out = []
    for name in importlib.import_module(f"mtex_jax.{sub}").__all__:
        obj = pkg.members.get(name)
        if obj is None:
            raise SystemExit(f"mtex_jax.{sub}.{name}: in __all__ but not found by griffe")
        out.append((name, obj.target_path if obj.is_alias else obj.path))
    return out


def _public_paths(subs: list[str]) -> dict[str, str]:
    """Object path -> its public name in the subpackage that defines it."""
    found: dict[str, str] = {}
    for sub in subs:
        if sub == "internal":
            continue
        for name, path in _targets(sub):
            if path.startswith(f"mtex_jax.{sub}."):
                found[path] = f"mtex_jax.{sub}.{name}"
    return found


def page(sub: str, public: dict[str, str]) -> str:
    """The Markdown of ``docs/api/<sub>.md``."""
    sections: dict[str, list[str]] = {}
    links: list[tuple[str, str]] = []
    for name, path in _targets(sub):
        own = path.startswith(f"mtex_jax.{sub}.")
        documented = public.get(path)
        if sub == "internal" and documented is None:
            sections.setdefault("Building blocks", []).append(name)
        elif sub == "internal" or not own:
            links.append((name, documented or f"mtex_jax.{path.split('.')[1]}.{name}"))
        else:
            module = ".".join(path.split(".")[1:3])
            title = SECTIONS.get(module, module.split(".")[1].strip("_").replace("_", " "))
            sections.setdefault(title[:1].upper() + title[1:], []).append(name)
    lines = [
        "<!-- Written by tools/api_pages.py from __all__; run it after changing __all__. -->",
        "",
        f"# `mtex_jax.{sub}`",
        "",
        f"::: mtex_jax.{sub}",
        _HEADER,
    ]
    for title, names in sections.items():
        lines += [f"## {title}", ""]
        for name in names:
            lines += [f"::: mtex_jax.{sub}.{name}", ""]
    if links:
        lines += ["## Documented elsewhere" if sub == "internal" else "## Re-exported", ""]
        for name, target in links:
            lines.append(f"- [`{name}`][{target}] (`{target.rsplit('.', 1)[0]}`)")
        lines.append("")
    return "\n".join(lines)


def main() -> int:
    """Write every subpackage's page."""
    sys.path.insert(0, str(ROOT / "src"))
    subs = subpackages()
    public = _public_paths(subs)
    API.mkdir(parents=True, exist_ok=True)
    for sub in subs:
        (API / f"{sub}.md").write_text(page(sub, public), encoding="utf-8")
        print(f"wrote docs/api/{sub}.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
