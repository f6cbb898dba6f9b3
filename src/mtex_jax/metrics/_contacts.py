"""Foot contacts, foot skating and floor penetration (design §10.4): the contact model of
:mod:`mtex_jax.motion` (where a motion texture can fit and carry its training clips' contacts),
re-exported among the metrics that use it."""

from __future__ import annotations

from ..motion import (
    ContactModel,
    PenetrationResult,
    SkatingResult,
    fit_contacts,
    foot_joints,
)

__all__ = [
    "ContactModel",
    "PenetrationResult",
    "SkatingResult",
    "fit_contacts",
    "foot_joints",
]
