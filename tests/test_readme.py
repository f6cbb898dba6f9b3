"""The README teaches: it is short, carries no version history, and its tour runs as written.

The tour's Python blocks (every ```` ```python ```` block under "## A short tour") are checked
statically here (they compile; every name they use is defined by them or is a builtin; every
``mj.…``, ``E.…`` and ``metrics.…`` attribute exists) and executed, in order, in a fresh
Python process in an empty folder, as a new user would paste them (slow: it learns a texture
on the 10 training clips with the default ``LearnConfig`` and compiles every step). The run uses
the shipped clips only, and the test process's persistent compilation cache (set through the
environment, not in the tour's code), so that a second run on the same machine skips most
compilations.
"""

import ast
import builtins
import re
import subprocess
import sys
from pathlib import Path

import pytest

from jax_cache import child_env

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def _tour_blocks() -> list[str]:
    text = README.read_text(encoding="utf-8")
    start = text.index("\n## A short tour")
    end = text.find("\n## ", start + 1)
    tour = text[start : end if end >= 0 else len(text)]
    return re.findall(r"^```python\n(.*?)^```", tour, flags=re.M | re.S)


def test_readme_is_short_and_has_no_history():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 200, f"README.md has {len(lines)} lines (at most 200)"
    text = "\n".join(lines).lower()
    for phrase in ("load average", "before", "previous"):
        assert phrase not in text, f"README.md says {phrase!r}"


def test_quick_start_is_two_commands():
    text = README.read_text(encoding="utf-8")
    quick = text[text.index("## Quick start") :]
    block = re.search(r"```bash\n(.*?)```", quick, flags=re.S)
    assert block is not None
    commands = [c for c in block.group(1).splitlines() if c.strip()]
    assert len(commands) == 2
    assert "mtex demo" in commands[0] and "pip install" in commands[0]
    assert "pytest" in commands[1]


def test_tour_names_are_defined():
    """Every name the tour reads is assigned or imported earlier in it, or is a builtin."""
    blocks = _tour_blocks()
    assert len(blocks) >= 5, "the tour lost its code blocks"
    tree = ast.parse("\n".join(blocks))
    defined = set(dir(builtins))
    undefined = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom):
            defined |= {(a.asname or a.name).split(".")[0] for a in node.names}
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            defined.add(node.id)
        elif isinstance(node, ast.arg):
            defined.add(node.arg)
    # second pass in source order: a name must be defined somewhere in the tour
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Load):
            if node.id not in defined:
                undefined.append(f"line {node.lineno}: {node.id}")
    assert not undefined, "the tour uses undefined names:\n" + "\n".join(undefined)


def test_tour_attributes_exist():
    """``mj.x.y``, ``E.x`` and ``metrics.x`` in the tour name real attributes of the package."""
    import mtex_jax
    from mtex_jax import edit, metrics

    roots = {"mj": mtex_jax, "E": edit, "metrics": metrics}
    tree = ast.parse("\n".join(_tour_blocks()))
    missing = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute):
            continue
        chain = []
        cur: ast.expr = node
        while isinstance(cur, ast.Attribute):
            chain.append(cur.attr)
            cur = cur.value
        if isinstance(cur, ast.Name) and cur.id in roots and len(chain) <= 2:
            obj = roots[cur.id]
            for attr in reversed(chain):
                if not hasattr(obj, attr):
                    missing.append(f"{cur.id}.{'.'.join(reversed(chain))}")
                    break
                obj = getattr(obj, attr)
    assert not missing, f"the tour uses names the package does not have: {sorted(set(missing))}"


@pytest.mark.slow
def test_tour_runs(tmp_path):
    """The tour, pasted into a fresh Python process in an empty folder, runs to the end, and
    writes nothing to stderr, also with both cores kept busy by other work (XLA's "Constant
    folding an instruction is taking > 1s" alarms, twenty lines each, reached a user in the
    Evaluate block of the tour: issue 57)."""
    code = "\n".join(_tour_blocks())
    script = tmp_path / "tour.py"
    script.write_text(code, encoding="utf-8")
    env = {k: v for k, v in child_env(MPLBACKEND="Agg").items() if not k.startswith("PYTEST")}
    spin = "import time\nt = time.time()\nwhile time.time() - t < 3600: pass"
    busy = [subprocess.Popen([sys.executable, "-c", spin]) for _ in range(2)]
    try:
        proc = subprocess.run(
            [sys.executable, str(script)],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=3600,
        )
    finally:
        for p in busy:
            p.kill()
    assert proc.returncode == 0, f"the tour failed:\n{proc.stderr[-4000:]}"
    assert proc.stderr == "", proc.stderr[-4000:]
    assert "textons" in proc.stdout
    assert (tmp_path / "salsa.npz").is_file()
    assert (tmp_path / "new.bvh").is_file()


def test_links_resolve():
    """Every relative link and picture of the README names a file of the repository."""
    text = README.read_text(encoding="utf-8")
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    missing = [t for t in targets if "://" not in t and not (ROOT / t).exists()]
    assert not missing, f"README.md links to missing files: {missing}"
