"""Shape buckets: lengths rounded up to a few sizes, so that a jitted program is compiled once
per bucket rather than once per length (design §11).

XLA compiles one program per input shape. A public call that takes a sequence of ``T`` frames
pads it to :func:`bucket_length` ``(T)`` frames and tells the kernel how many are real; the
kernels are causal (a frame's terms depend on earlier frames only) or masked, so the padding
never changes a result beyond rounding. Multiples of :data:`BUCKET_FRAMES` frames keep the
padding below one block and the number of programs over lengths of 200 to 3,000 frames at
three.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "BUCKET_FRAMES",
    "CompileCount",
    "as_array",
    "bucket_length",
    "count_compiles",
    "cut_frames",
    "pad_frames",
]

#: Frames of one bucket step: lengths are padded up to a multiple of it.
BUCKET_FRAMES = 1024


def bucket_length(n: int, step: int = BUCKET_FRAMES) -> int:
    """``n`` rounded up to a positive multiple of ``step``.

    Args:
        n: a length (frames, path entries), ``>= 0``.
        step: the bucket step.

    Returns:
        the smallest multiple of ``step`` that is ``>= max(n, 1)``.
    """
    n = int(n)
    if n < 0 or step < 1:
        raise ValueError(f"bucket_length needs n >= 0 and step >= 1, got n={n}, step={step}")
    return step * max(1, math.ceil(n / step))


def as_array(x: Any) -> jax.Array:
    """``x`` as a JAX array, like ``jnp.asarray`` (same dtype rules), but a host array is
    transferred with ``jax.device_put``: ``jnp.asarray`` of a NumPy array compiles a copy
    program for every new shape."""
    if isinstance(x, jax.Array):
        return x
    return jax.device_put(np.asarray(x))


def pad_frames(Y: Any, n: int, axis: int = -2) -> Any:
    """``Y`` with its last frame repeated along ``axis`` up to ``n`` frames.

    A concrete array is padded with numpy (no XLA program per shape); a traced one with
    ``jnp`` (differentiable: the padded frames carry no gradient into a masked result).
    """
    size = Y.shape[axis]
    if n < size:
        raise ValueError(f"pad_frames: cannot pad {size} frames down to {n}")
    if n == size:
        return Y
    try:
        arr = np.asarray(Y)
    except jax.errors.TracerArrayConversionError:
        last = jax.lax.slice_in_dim(Y, size - 1, size, axis=axis)
        reps = [1] * Y.ndim
        reps[axis] = n - size
        return jnp.concatenate([Y, jnp.tile(last, reps)], axis=axis)
    widths = [(0, 0)] * arr.ndim
    widths[axis] = (0, n - size)
    return jax.device_put(np.pad(arr, widths, mode="edge"))  # jnp.asarray would compile a copy


def cut_frames(a: Any, n: int) -> Any:
    """The first ``n`` entries of ``a`` along axis 0 (the inverse of :func:`pad_frames`).

    A concrete array is cut on the host and transferred back with ``jax.device_put`` (an eager
    slice of a JAX array compiles a program for every new length); a traced one is sliced in
    the program.
    """
    try:
        arr = np.asarray(a)
    except jax.errors.TracerArrayConversionError:
        return a[:n]
    return jax.device_put(arr[:n])


class CompileCount:
    """What :func:`count_compiles` saw: ``programs``, the programs lowered to XLA (one per new
    function and input shape, whether the executable is then compiled or loaded from the
    persistent cache)."""

    programs: int = 0


@contextmanager
def count_compiles() -> Iterator[CompileCount]:
    """Count the programs that the enclosed code lowers to XLA (JAX's monitoring events: the
    compilations that ``jax_log_compiles`` logs)."""
    count = CompileCount()

    def listener(event: str, duration_secs: float, **kwargs: str | int) -> None:
        if event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
            count.programs += 1

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield count
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
