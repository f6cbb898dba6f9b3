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

The kernel runs on fixed blocks of :data:`PREDICT_BLOCK` predicted frames (design §11): the
observations are padded (last frame repeated, label 0) to whole blocks, each block (its
frames and the two before) is one call of one compiled program, and the padding's rows are
cut on the host. Every row depends on its own frame's texton and the two frames before, so
the rows are those of the unpadded kernel, and a clip of any length compiles no program
besides its segmentation's.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ..core import bucket_length
from ..texture import MotionTexture, Segmentation, Texton

__all__ = ["texture_predict"]

#: Predicted frames per call of the one-step prediction's kernel (one program for all lengths).
PREDICT_BLOCK = 512


@eqx.filter_jit
def _predict_labelled(textons: Texton, labels: Array, Y: Array) -> Array:
    tex = take(textons, labels)  # one texton per predicted frame
    z1 = Y[1:-1] - tex.mu
    z2 = Y[:-2] - tex.mu
    x1 = jnp.einsum("tdk,td->tk", tex.C, z1)
    x2 = jnp.einsum("tdk,td->tk", tex.C, z2)
    xh = jnp.einsum("tij,tj->ti", tex.A1, x1) + jnp.einsum("tij,tj->ti", tex.A2, x2) + tex.d
    pred = tex.mu + jnp.einsum("tdk,tk->td", tex.C, xh)
    # the residual's own prediction (the residual AR(2); none for a white residual)
    r1 = z1 - jnp.einsum("tdk,tk->td", tex.C, x1)
    r2 = z2 - jnp.einsum("tdk,tk->td", tex.C, x2)
    rh = tex.observation.predict_residual(r1, r2)
    return pred if rh is None else pred + rh


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
    texture: MotionTexture, y: Float[ArrayLike, "T D"], seg: Segmentation
) -> tuple[Float[Array, "T2 D"], np.ndarray]:
    """:func:`texture_predict` with the best segmentation of ``y`` already computed."""
    labels = seg.frame_labels(int(np.shape(y)[0]))
    if np.any(labels < 0):
        raise ValueError("the texture found no segmentation of Y (is it shorter than tmin?)")
    T = int(np.shape(y)[0])
    # fixed blocks of predicted frames, one program for every length (design §11)
    B = PREDICT_BLOCK
    n = bucket_length(T - 2, B)
    lab = np.pad(np.asarray(labels[1:-1], np.int32), (0, n - (T - 2)))
    yp = np.pad(np.asarray(y), ((0, n + 2 - T), (0, 0)), mode="edge")
    put = jax.device_put
    pred = [
        np.asarray(_predict_labelled(texture.textons, put(lab[a : a + B]), put(yp[a : a + B + 2])))
        for a in range(0, n, B)
    ]
    return put(np.concatenate(pred)[: T - 2]), labels
