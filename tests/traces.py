"""Counting the traces of jitted functions from the tests (no hook in the library).

JAX reports every trace of a function to ``jax.monitoring`` as a
``/jax/core/compile/jaxpr_trace_duration`` event whose ``fun_name`` is the traced Python
function's name. :func:`count_traces` collects them by name while its block runs, so a test
can assert that a call on new data of the same shapes traced nothing.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import jax

TRACE_EVENT = "/jax/core/compile/jaxpr_trace_duration"


@contextmanager
def count_traces() -> Iterator[Counter[str]]:
    """The traces of each function name started inside the block."""
    seen: Counter[str] = Counter()

    def on_event(event: str, duration: float, **kwargs: Any) -> None:
        if event == TRACE_EVENT:
            seen[str(kwargs.get("fun_name"))] += 1

    jax.monitoring.register_event_duration_secs_listener(on_event)
    try:
        yield seen
    finally:
        jax.monitoring.unregister_event_duration_listener(on_event)
