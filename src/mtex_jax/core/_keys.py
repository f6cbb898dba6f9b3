"""The check of PRNG key arguments at the public entry points."""

from __future__ import annotations

from typing import Any

__all__ = ["check_key"]


def check_key(key: Any, where: str, *, allow_none: bool = False) -> None:
    """Raise ``TypeError`` unless ``key`` is a JAX PRNG key.

    Accepted: a typed key (``jax.random.key(0)``), a legacy raw key (``jax.random.PRNGKey(0)``,
    ``uint32`` with last axis 2), or batches of either (also traced under ``jit``/``vmap``);
    ``None`` when ``allow_none``. An int, a float or another array gets a one-line message
    naming the function, instead of an error from inside JAX.
    """
    if key is None and allow_none:
        return
    import jax
    import jax.numpy as jnp
    import numpy as np

    dtype = getattr(key, "dtype", None)
    shape = getattr(key, "shape", None)
    if dtype is not None and shape is not None:
        if jnp.issubdtype(dtype, jax.dtypes.prng_key):
            return
        if np.dtype(dtype) == np.uint32 and len(shape) >= 1 and shape[-1] == 2:
            return
    what = type(key).__name__ if dtype is None else f"{type(key).__name__} of {dtype} {shape}"
    none = " or None" if allow_none else ""
    raise TypeError(
        f"{where}: key must be a JAX PRNG key (e.g. jax.random.key(0)){none}, got {what}"
    )
