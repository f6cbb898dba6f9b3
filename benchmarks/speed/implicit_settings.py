"""Paths and settings of ``bench_implicit.py``, shared with ``implicit_report.py``
(``bench_implicit.py`` puts ``benchmarks/`` on ``sys.path`` for ``_common`` first)."""

from __future__ import annotations

from _common import RESULTS as RESULTS, SHARED

CMU = SHARED / "data" / "cmu-salsa"
WINDOW = 10
N_PROBES = 300
TUNE_CLIP = 2  # 60_03
EVAL_CLIPS = (4, 7, 10)  # 60_05, 60_09, 60_12
