"""Shared by the benchmark scripts: where the results go, the command that made a results file,
and what the machine is.

A script in ``speed/`` or ``quality/`` puts this folder on ``sys.path`` first::

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from _common import RESULTS, made_by, use
"""

from __future__ import annotations

import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
RESULTS = BENCH / "results"
SHARED = Path(os.environ.get("MTEX_SHARED", REPO.parent / "shared"))


def use(folder: str) -> None:
    """Let a script import the helpers of another benchmark folder (``"speed"``, ``"quality"``)."""
    path = str(BENCH / folder)
    if path not in sys.path:
        sys.path.insert(1, path)


def command() -> str:
    """The command line that is running, from the repository root (``python benchmarks/…``)."""
    script = Path(sys.argv[0]).resolve()
    try:
        name = script.relative_to(REPO).as_posix()
    except ValueError:
        name = str(script)
    return shlex.join(["python", name, *sys.argv[1:]])


def made_by() -> str:
    """The line under a Markdown report's title that names the command that made it."""
    return f"Made by: `{command()}`"


def cpu_and_memory() -> tuple[str, float]:
    """CPU model name (from ``lscpu`` when available) and physical memory in GB."""
    model = platform.processor()
    try:
        lscpu = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
        for line in lscpu.splitlines():
            if line.startswith("Model name:"):
                model = line.split(":", 1)[1].strip()
    except OSError:
        pass
    try:
        mem_gb = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1e9
    except (ValueError, OSError):
        mem_gb = float("nan")
    return model, mem_gb
