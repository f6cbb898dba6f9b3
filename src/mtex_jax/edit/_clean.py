"""Cleaning a synthesised motion: planted feet that do not slide, no foot below the floor.

Contacts come from a :class:`~mtex_jax.metrics.ContactModel` fitted on the *training* clips
(:func:`~mtex_jax.metrics.fit_contacts`: per-foot height and speed thresholds and the training
floor); :func:`save_contacts` / :func:`load_contacts` store it beside the model file. On the
raw motion a step ``t → t+1`` of foot ``f`` is a contact when the foot is low at both ends
(``h < H_f``; optionally also slow, ``s < S_f``, the model's own rule). Each run of contact
steps becomes a plant (no horizontal motion, at the run's mean height clipped to
``[floor, H_f]``); a foot that was above ``H_f`` outside the contacts is kept above it (a swing
foot stays a swing foot), the floor applies to every moving joint, and
:func:`~mtex_jax.edit.edit` solves for the motion.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np

from ..core import load_arrays_json, save_arrays_json
from ..metrics import ContactModel, PenetrationResult, SkatingResult
from ..motion import Motion, Skeleton
from ..texture import MotionTexture, Synthesis
from ._api import _feature_map, _observations, edit, segments_of
from ._constraints import EditWeights, make_constraints
from ._solve import EditResult

__all__ = [
    "CleanResult",
    "clean",
    "clean_weights",
    "contact_plants",
    "load_contacts",
    "save_contacts",
]

_KIND = "mtex_jax.ContactModel"


def clean_weights() -> EditWeights:
    """The weights :func:`clean` uses: the root may move (its trajectory carries the feet);
    plants and the floor cost one unit per 3.3 mm (stricter weights make the
    conjugate-gradient solves slow); a weaker smoothness term than for edits, since stopping
    a sliding foot needs a quick change of its velocity."""
    return EditWeights(root=3.0, anchor=1.0, smooth=3.0, plant=300.0, floor=300.0)


def contact_plants(
    contacts: ContactModel, motion: Motion, *, min_steps: int = 1, rule: str = "low"
) -> tuple[np.ndarray, list[tuple[int, int, int, float]]]:
    """Contact labels of a motion and the plants they make.

    Args:
        contacts: thresholds fitted on the training clips.
        motion: the raw motion (at ``contacts.fps``).
        min_steps: runs of fewer contact steps are ignored (a foot passing low for a single
            step is not planted).
        rule: ``"low"``: a step is a contact when the foot is below its height threshold at
            both ends (the default: in real motion a low foot is a supporting foot, so a low
            foot that moves fast is skating, which is what cleaning removes);
            ``"low_and_slow"``: also slower than the speed threshold
            (:meth:`ContactModel.labels`), which leaves fast low feet sliding.

    Returns:
        ``labels (T − 1, F)`` bool and ``[(foot joint, first frame, last frame, height)]``.
    """
    if rule not in ("low", "low_and_slow"):
        raise ValueError(f"rule must be 'low' or 'low_and_slow', got {rule!r}")
    ((h, _),) = contacts.heights_and_speeds(motion, "clean")
    H = contacts.height_threshold
    labels = (h[:-1] < H) & (h[1:] < H)
    if rule == "low_and_slow":
        labels = contacts.labels(motion)
    plants = []
    for k, foot in enumerate(contacts.feet):
        col = np.concatenate([[False], labels[:, k], [False]])
        edges = np.flatnonzero(np.diff(col.astype(np.int8)))
        for a, b in zip(edges[::2], edges[1::2], strict=True):
            if b - a < min_steps:
                labels[a:b, k] = False
                continue
            hh = float(
                np.clip(h[a : b + 1, k].mean(), contacts.floor, contacts.height_threshold[k])
            )
            plants.append((int(foot), int(a), int(b), hh))
    return labels, plants


@dataclasses.dataclass(frozen=True, eq=False)
class CleanResult:
    """A cleaned motion and what cleaning changed, measured.

    Attributes:
        motion: the cleaned :class:`Motion`.
        Y: ``(T, D)`` its observation vectors.
        edit: the :class:`EditResult` of the solve (convergence, constraint errors).
        labels: ``(T − 1, F)`` contact labels detected on the raw motion.
        skating_before, skating_after: :meth:`ContactModel.skating` of the raw and cleaned
            motion (median and p95 horizontal foot speed over low steps).
        penetration_before, penetration_after: :meth:`ContactModel.penetration`.
        loglik_before, loglik_after: the texture's marginal log-likelihood per frame (forward
            algorithm) of the raw and cleaned observation vectors.
    """

    motion: Motion
    Y: Any
    edit: EditResult
    labels: np.ndarray
    skating_before: SkatingResult
    skating_after: SkatingResult
    penetration_before: PenetrationResult
    penetration_after: PenetrationResult
    loglik_before: float
    loglik_after: float

    @property
    def loglik_lost(self) -> float:
        """Nats per frame the texture's log-likelihood dropped by cleaning."""
        return self.loglik_before - self.loglik_after


def clean(
    texture: MotionTexture,
    motion: Synthesis | Motion,
    contacts: ContactModel,
    *,
    weights: EditWeights | None = None,
    min_steps: int = 1,
    rule: str = "low",
    max_steps: int = 30,
    cg_steps: int = 1000,
    loglik: bool = True,
) -> CleanResult:
    """Remove foot skating and floor penetration, staying close to the texture's dynamics.

    Contacts are detected on the raw motion with the training clips' thresholds (module
    notes); each contact run is planted (a penalty: no horizontal motion, at a fixed height),
    every moving joint is kept above the training floor (a one-sided penalty), and the texture
    prior (on the change) plus a smoothness term keep the rest of the motion as it was.

    Args:
        texture: the motion texture (with its feature map).
        motion: a :class:`Synthesis` (its texton segments are the prior's segmentation) or a
            :class:`Motion` (segmented by the texture).
        contacts: a :class:`ContactModel` fitted on the training clips (same skeleton, at the
            texture's frame rate).
        weights: objective weights (default :func:`clean_weights`).
        min_steps: shortest contact run that is planted.
        rule: contact rule of :func:`contact_plants` (``"low"`` or ``"low_and_slow"``).
        max_steps: Levenberg–Marquardt steps (no BFGS fallback here: at this size L-BFGS
            was measured slower and no better; ``edit.converged`` says whether it converged).
        cg_steps: conjugate-gradient steps per Levenberg–Marquardt step.
        loglik: also compute the log-likelihood per frame before and after (a forward pass
            each; ``False`` reports NaN).

    Returns:
        :class:`CleanResult`.
    """
    fm = _feature_map(texture)
    if not isinstance(contacts, ContactModel):
        raise TypeError(f"contacts must be a ContactModel, got {type(contacts).__name__}")
    if not contacts.skeleton.same_structure(fm.skeleton):
        raise ValueError("contacts: the contact model's skeleton is not the texture's")
    if float(contacts.fps) != float(fm.fps):
        raise ValueError(
            f"contacts: fitted at {contacts.fps:g} Hz, the texture is at {fm.fps:g} Hz"
        )
    if isinstance(motion, Synthesis):
        if motion.motion is None:
            raise ValueError("motion: the synthesis was not decoded (decode=False)")
        raw = motion.motion
    elif isinstance(motion, Motion):
        raw = motion
    else:
        raise TypeError(f"motion must be a Synthesis or a Motion, got {type(motion).__name__}")
    if raw.n_frames < 3:
        raise ValueError(f"motion: at least 3 frames are needed, got {raw.n_frames}")
    Y, sp, sh = _observations(texture, motion, None, None)
    labels, plants = contact_plants(contacts, raw, min_steps=min_steps, rule=rule)
    # swing feet stay off the ground: a frame of no planted step whose foot was above its
    # height threshold keeps it above (one-sided)
    ((h, _),) = contacts.heights_and_speeds(raw, "clean")
    in_contact = np.zeros_like(h, bool)
    in_contact[:-1] |= labels
    in_contact[1:] |= labels
    H = contacts.height_threshold
    lift = np.where(~in_contact & (h >= H), H, -np.inf)
    cons = make_constraints(
        fm.skeleton,
        Y.shape[0],
        Y.shape[1],
        plants=plants,
        floor=contacts.floor,
        feet=contacts.feet,
        lift=lift,
    )
    seg = segments_of(texture, motion)
    res = edit(
        texture,
        Y,
        cons,
        weights=clean_weights() if weights is None else weights,
        segments=seg,
        start_position=sp,
        start_heading=sh,
        rounds=1,
        max_steps=max_steps,
        cg_steps=cg_steps,
        cg_rtol=1e-2,
        fallback=False,
    )
    out = fm.decode(res.Y, sp, sh)
    nan = float("nan")
    return CleanResult(
        motion=out,
        Y=res.Y,
        edit=res,
        labels=labels,
        skating_before=contacts.skating(raw),
        skating_after=contacts.skating(out),
        penetration_before=contacts.penetration(raw),
        penetration_after=contacts.penetration(out),
        loglik_before=texture.log_likelihood(Y, per_frame=True) if loglik else nan,
        loglik_after=texture.log_likelihood(res.Y, per_frame=True) if loglik else nan,
    )


# ---------------------------------------------------------------------------------------------
# storing the contact model beside a texture
# ---------------------------------------------------------------------------------------------
def save_contacts(path: str | os.PathLike[str], contacts: ContactModel) -> None:
    """Write a :class:`ContactModel` to ``.npz`` (arrays + JSON, atomically, no pickle)."""
    if not isinstance(contacts, ContactModel):
        raise TypeError(f"contacts must be a ContactModel, got {type(contacts).__name__}")
    arrays = {
        "feet": np.asarray(contacts.feet, np.int64),
        "height_threshold": np.asarray(contacts.height_threshold, np.float64),
        "speed_threshold": np.asarray(contacts.speed_threshold, np.float64),
    }
    meta = {
        "kind": _KIND,
        "format_version": 1,
        "skeleton": contacts.skeleton.to_json_dict(),
        "floor": float(contacts.floor),
        "fps": float(contacts.fps),
    }
    save_arrays_json(path, arrays, meta)


def load_contacts(path: str | os.PathLike[str]) -> ContactModel:
    """Read a :class:`ContactModel` written by :func:`save_contacts` (checked)."""
    req = ("feet", "height_threshold", "speed_threshold")
    arrays, meta = load_arrays_json(path, kind=_KIND, required=req, allowed=())
    try:
        sk = Skeleton.from_json_dict(meta["skeleton"])
        feet = tuple(int(f) for f in arrays["feet"].reshape(-1))
        ht = np.asarray(arrays["height_threshold"], np.float64).reshape(-1)
        st = np.asarray(arrays["speed_threshold"], np.float64).reshape(-1)
        floor, fps = float(meta["floor"]), float(meta["fps"])
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise ValueError(f"{path}: invalid contact model file: {e}") from None
    ok = len(feet) > 0 and ht.shape == st.shape == (len(feet),)
    ok = ok and all(0 <= f < sk.n_joints for f in feet) and np.isfinite([*ht, *st, floor]).all()
    if not ok or not fps > 0:
        raise ValueError(f"{path}: invalid contact model file (shapes or values)")
    return ContactModel(sk, feet, ht, st, floor, fps)
