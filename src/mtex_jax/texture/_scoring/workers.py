"""Host-thread scheduling of an eager kernel over row blocks of textons.

XLA:CPU runs the small GEMMs and elementwise passes of one execution on one core, so an eager
:func:`~mtex_jax.texture.frame_terms` call splits the textons into one block per core and runs
each block as its own execution, started from its own host thread, then assembles the rows in
place."""

from __future__ import annotations

import contextlib
import itertools
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import jax
from jax import lax
from jax.core import Tracer
from jaxtyping import Array

from .._texton.checks import check_positive_int
from .._texton.texton import Texton

# below this many texton-frames an eager frame_terms call runs as one execution
_SPLIT_MIN_WORK = 2**20


def _merge_rows(
    first: tuple[Array, ...], rest: Sequence[tuple[Array, ...]], cuts: tuple[int, ...]
) -> tuple[Array, ...]:
    """Write the row blocks ``rest`` into ``first`` (donated: updated in place) at ``cuts``."""
    out = list(first)
    for c, block in zip(cuts, rest, strict=True):
        out = [
            lax.dynamic_update_slice_in_dim(o, b, c, axis=0)
            for o, b in zip(out, block, strict=True)
        ]
    return tuple(out)


_merge_rows_jit = jax.jit(_merge_rows, static_argnums=2, donate_argnums=0)


def check_workers(workers: Any) -> int | None:
    return None if workers is None else check_positive_int("workers", workers)


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def n_parts(workers: int | None, textons: Texton, Y: Array) -> int:
    """Concurrent executions for an eager :func:`frame_terms` call (1 under a trace)."""
    leaves = jax.tree.leaves((textons, Y))
    if any(isinstance(x, Tracer) for x in leaves):
        return 1
    if any(d.platform != "cpu" for d in Y.devices()):
        return 1
    n = textons.n_textons
    if workers is None:
        if n * Y.shape[0] < _SPLIT_MIN_WORK:
            return 1
        workers = available_cores()
    return max(1, min(workers, n))


def _thread_settings() -> Any:
    """The calling thread's JAX settings that change what a computation is (``enable_x64``,
    ``default_matmul_precision``, ``debug_nans``/``debug_infs``: thread-local when set by
    their context managers), as a function that re-enters them in another thread."""
    # the attributes read each setting's value in this thread (not typed in jax's stubs)
    cfg: Any = jax.config
    x64, precision = cfg.jax_enable_x64, cfg.jax_default_matmul_precision
    nans, infs = cfg.jax_debug_nans, cfg.jax_debug_infs

    def enter(stack: contextlib.ExitStack) -> None:
        stack.enter_context(jax.enable_x64(x64))
        stack.enter_context(jax.default_matmul_precision(precision))
        stack.enter_context(jax.debug_nans(nans))
        stack.enter_context(jax.debug_infs(infs))

    return enter


def run_row_blocks(
    kernel: Callable[[Texton, int | None], tuple[Array, ...]], textons: Texton, parts: int
) -> tuple[Array, ...]:
    """``kernel`` on ``parts`` row blocks of the textons, run concurrently.

    ``kernel(block, out_rows)`` returns ``(dyn, obs)`` rows of one block of textons; with
    ``out_rows`` given (the first block) its outputs have that many rows.

    XLA:CPU runs the kernel's per-block batched GEMM and elementwise passes on one core (only
    the projection GEMM is multi-threaded), so one execution leaves the other cores mostly
    idle. Here each block of textons (sizes differing by at most one) is one execution,
    started from its own host thread (executions from different threads run concurrently)
    under the calling thread's JAX settings; the first writes its rows into outputs of the
    full height and the others' rows are copied into them in place.
    """
    n = textons.n_textons
    cuts = [n * i // parts for i in range(parts + 1)]
    pieces = [
        jax.tree.map(lambda a, lo=lo, hi=hi: a[lo:hi], textons)
        for lo, hi in itertools.pairwise(cuts)
    ]
    settings = _thread_settings()

    def run(i: int) -> tuple[Array, ...]:
        with contextlib.ExitStack() as stack:
            settings(stack)
            out = kernel(pieces[i], n if i == 0 else None)
            return jax.block_until_ready(out)

    with ThreadPoolExecutor(max_workers=parts - 1) as pool:
        futures = [pool.submit(run, i) for i in range(1, parts)]
        first = run(0)
        rest = [f.result() for f in futures]
    return _merge_rows_jit(first, rest, tuple(cuts[1:-1]))
