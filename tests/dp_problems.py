"""Tiny segmentation problems shared by the Viterbi and forward-algorithm tests: textons fitted
on sinusoids, and every composition of T frames into segment lengths."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from mtex_jax.texture import fit_texton, stack_textons


def small_textons(rng, n_t, D=4, k=2):
    out = []
    for i in range(n_t):
        t = np.arange(60)
        y = np.stack([np.sin(0.2 * (i + 1) * t + j) for j in range(D)], axis=1)
        y = y + 0.3 * rng.normal(size=y.shape) + i
        out.append(fit_texton(jnp.asarray(y), state_dim=k))
    return stack_textons(out)


def compositions(T, tmin, tmax):
    if T == 0:
        yield ()
        return
    for L in range(tmin, min(tmax, T) + 1):
        for rest in compositions(T - L, tmin, tmax):
            yield (L, *rest)
