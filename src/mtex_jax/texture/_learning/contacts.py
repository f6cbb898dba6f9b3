"""The training clips' contact model, carried by a learned texture (design §6.6, §10.4)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from ...motion import Motion, fit_contacts
from .._model import MotionTexture

__all__ = ["with_contacts"]


def with_contacts(
    model: MotionTexture, motions: Sequence[Motion] | None, verbose: bool = False
) -> MotionTexture:
    """``model`` carrying the :class:`~mtex_jax.motion.ContactModel` of the clips it was
    learned from (:func:`~mtex_jax.motion.fit_contacts` at the feature map's frame rate: the
    feet by name or by the skeleton's structure, their height and speed thresholds and the
    training floor), which ``mtex_jax.edit.synthesize(..., clean=True)`` uses.

    Unchanged for a texture learned from observation arrays (``motions`` is ``None``), and for
    a figure without two legs to stand on (no two leaf chains below a branching joint: no
    feet, no contacts).
    """
    if motions is None or model.feature_map is None:
        return model
    try:
        contacts = fit_contacts(list(motions), fps=model.feature_map.fps)
    except ValueError as e:  # no feet on this skeleton
        if verbose:
            print(f"[mtex learn] no contact model of the training clips: {e}", flush=True)
        return model
    return dataclasses.replace(model, contacts=contacts)
