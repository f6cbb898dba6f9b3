"""Held-out density and one-step prediction of a motion texture, in the units of the
baselines (:mod:`._baselines`).

A motion texture's one-step prediction of frame ``t`` uses the texton that labels frame
``t − 1`` in the best segmentation of the clip (an optimistic oracle: the labels are chosen
with the whole clip in view), and that texton's dynamics on its own state:

.. code-block:: text

    x_s = Cᵀ (y_s − μ)  (s = t−1, t−2),   ŷ_t = μ + C (A1 x_{t−1} + A2 x_{t−2} + d)

and the part of ``y`` outside the texton's subspace, ``r = (I − C Cᵀ)(y − μ)``, by the
texton's residual AR(2), ``r̂_t = a₁ r_{t−1} + a₂ r_{t−2}`` (``"residual"`` textons; the
others have ``a = 0``: the texton's mean, as in the paper).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ..texture import MotionTexture, Segmentation, Texton

__all__ = ["texture_predict"]


@eqx.filter_jit
def _predict_labelled(textons: Texton, labels: Array, Y: Array) -> Array:
    tex = take(textons, labels)  # one texton per predicted frame
    z1 = Y[1:-1] - tex.mu
    z2 = Y[:-2] - tex.mu
    x1 = jnp.einsum("tdk,td->tk", tex.C, z1)
    x2 = jnp.einsum("tdk,td->tk", tex.C, z2)
    xh = jnp.einsum("tij,tj->ti", tex.A1, x1) + jnp.einsum("tij,tj->ti", tex.A2, x2) + tex.d
    # the residual's own AR(2) ("residual" textons; a = 0 for the others)
    r1 = z1 - jnp.einsum("tdk,tk->td", tex.C, x1)
    r2 = z2 - jnp.einsum("tdk,tk->td", tex.C, x2)
    rh = tex.res_a[:, :1] * r1 + tex.res_a[:, 1:] * r2
    return tex.mu + jnp.einsum("tdk,tk->td", tex.C, xh) + rh


def take(textons: Texton, idx: Int[Array, " n"]) -> Texton:
    """The textons ``idx`` of a stack, stacked again (one per entry of ``idx``)."""
    return jax.tree.map(lambda a: a[idx], textons)


def texture_predict(
    texture: MotionTexture, Y: Float[ArrayLike, "T D"]
) -> tuple[Float[Array, "T2 D"], np.ndarray]:
    """One-step predictions ``ŷ_t`` for ``t = 2…T−1`` under the best segmentation's labels.

    Args:
        texture: a learned :class:`MotionTexture`.
        Y: ``(T, D)`` observation vectors (or a ``Motion``, encoded by the texture's map).

    Returns:
        ``(predictions (T − 2, D), labels (T,))``: the labels are the best segmentation's.
    """
    y = texture.observations(Y)
    return predict_segmented(texture, y, texture.segment(y))


def predict_segmented(
    texture: MotionTexture, y: Array, seg: Segmentation
) -> tuple[Float[Array, "T2 D"], np.ndarray]:
    """:func:`texture_predict` with the best segmentation of ``y`` already computed."""
    labels = seg.frame_labels(y.shape[0])
    if np.any(labels < 0):
        raise ValueError("the texture found no segmentation of Y (is it shorter than tmin?)")
    pred = _predict_labelled(texture.textons, jnp.asarray(labels[1:-1]), y)
    return pred, labels
