"""Shared by the benchmark scripts: what the machine is (for the results files)."""

from __future__ import annotations

import os
import platform
import subprocess


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
