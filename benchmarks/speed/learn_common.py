"""Timing and logging helpers shared by ``bench_learn.py`` and its helper modules."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any

import jax


def _timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    return time.perf_counter() - t0, out


def _timed_cpu(fn: Callable[[], Any]) -> tuple[float, float, Any]:
    """Wall time, process CPU time (all threads) and result of one call."""
    c0 = time.process_time()
    wall, out = _timed(fn)
    return wall, time.process_time() - c0, out


def _median(xs: list[float]) -> float:
    return float(statistics.median(xs))


def _log(msg: str) -> None:
    print(f"[bench_learn {time.strftime('%H:%M:%S')}] {msg}", flush=True)
