"""The innovations of a padded synthesis path (design §10.8, §11).

A path of ``n`` textons is synthesised as ``(n_pad, l_pad)`` padded blocks (shape buckets).
Its innovations are, for a texture with a :class:`~mtex_jax.texture.ResidualBank`, blocks of
the training residuals (:func:`~mtex_jax.texture.draw_residuals`; aligned replay takes each
texton's own segment). An aligned block longer than its segment's residuals takes the rows
past them from the texture's :class:`~mtex_jax.texture.InnovationProcess` (:func:`tail_draws`)
instead of the segment's start again: those residuals would meet a state they were not
measured in (the figures are in :mod:`~mtex_jax.texture._noise.residual_bank`). A texture
without a bank draws from its process, or independently (:func:`padded_draws`).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._model import MotionTexture
from .._noise.draws import independent_innovations
from .._noise.innovation_process import draw_innovations
from .._noise.residual_bank import draw_residuals

__all__ = ["TAIL_ROWS", "padded_draws", "path_innovations", "round_up", "tail_draws"]

#: Tail draws are made per path row for a multiple of this many frames.
TAIL_ROWS = 256


def round_up(x: int, m: int) -> int:
    """``x`` rounded up to a multiple of ``m``."""
    return -(-x // m) * m


def path_innovations(
    key: Array,
    texture: MotionTexture,
    labels: np.ndarray,
    instances: np.ndarray | None,
    n: int,
    padded: tuple[int, int, int],
    longest: int,
    dtype: Any,
    dof: float | None,
) -> Array:
    """Innovations ``padded = (n_pad, l, k)`` of a path of ``n`` textons (module notes).

    Args:
        key: JAX PRNG key.
        texture: the motion texture.
        labels: ``(n_pad,)`` the padded path's textons.
        instances: ``(n_pad,)`` each texton's own training segment (aligned replay, ``-1``:
            none), or ``None`` (shuffled replay).
        n: the path's textons (the rest pad it).
        padded: the padded shape.
        longest: the longest texton's rows (``l`` pads it).
        dtype: of the innovations.
        dof: the Student-t degrees of freedom (``None``: Gaussian).
    """
    n_pad, length, k = padded
    if texture.residuals is not None:  # blocks of the training residuals
        beyond = None
        if instances is not None:  # past the instance's residuals: the process
            beyond = tail_draws(jax.random.fold_in(key, 1), texture.innovations, padded, dtype, dof)
        lab = jnp.asarray(labels)
        return draw_residuals(key, texture.residuals, lab, length, dtype, instances, beyond)
    # these draws are not prefix-stable in the frame axis: drawn at the unbucketed shape
    # (the path to a multiple of 8, the frames to a multiple of 16, as they always were),
    # then padded with zeros to the bucket
    shape = (round_up(n, 8), round_up(longest + 2, 16) - 2, k)
    return padded_draws(key, texture.innovations, shape, (n_pad, length), dtype, dof)


@eqx.filter_jit
def tail_draws(
    key: Array, process: Any, shape: tuple[int, int, int], dtype: Any, dof: float | None
) -> Array:
    """Innovations ``(n, l, k)`` for the rows of aligned residual blocks past their segment
    (:mod:`~mtex_jax.texture._noise.residual_bank`, *past the segment's end*): from the
    texture's :class:`~mtex_jax.texture.InnovationProcess`, or independent ones without it.

    Row ``m`` is drawn from ``fold_in(key, m)`` for ``l`` rounded up to a multiple of
    ``TAIL_ROWS`` frames and cut, so that the padding of the path and frame axes (design
    §11) changes no draw."""
    n, length, k = shape
    rows = round_up(length, TAIL_ROWS)
    if process is None:
        one = lambda kk: independent_innovations(kk, (rows, k), dtype, dof)
    else:
        one = lambda kk: draw_innovations(kk, process, (rows, k), dtype, dof)
    keys = jax.vmap(lambda m: jax.random.fold_in(key, m))(jnp.arange(n))
    return jax.vmap(one)(keys)[:, :length]


@eqx.filter_jit
def padded_draws(
    key: Array,
    process: Any,
    shape: tuple[int, int, int],
    padded: tuple[int, int],
    dtype: Any,
    dof: float | None,
) -> Array:
    """Innovations of the shape they always had, zero-padded to the bucket: one program."""
    if process is None:
        v = independent_innovations(key, shape, dtype, dof)
    else:  # each texton's stretch of innovations from the fitted process
        v = draw_innovations(key, process, shape, dtype, dof)
    return jnp.pad(v, ((0, padded[0] - shape[0]), (0, padded[1] - shape[1]), (0, 0)))
