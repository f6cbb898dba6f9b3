"""Paths and settings of ``bench_implicit.py``, shared with ``implicit_report.py``."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MTEX_SHARED", REPO.parent / "shared"))
CMU = SHARED / "data" / "cmu-salsa"
RESULTS = REPO / "benchmarks" / "results"
WINDOW = 10
N_PROBES = 300
TUNE_CLIP = 2  # 60_03
EVAL_CLIPS = (4, 7, 10)  # 60_05, 60_09, 60_12
