"""Cleaning a synthesised motion: planted feet that do not slide, no foot below the floor.

Contacts come from a :class:`~mtex_jax.motion.ContactModel` fitted on the *training* clips
(:func:`~mtex_jax.motion.fit_contacts`: per-foot height and speed thresholds and the training
floor): the one a learned texture carries, or one passed by hand (:func:`save_contacts` /
:func:`load_contacts` store it in a file of its own). On the raw motion a step ``t → t+1`` of
foot ``f`` is a contact when the foot is low at both ends (``h < H_f``; optionally also slow,
``s < S_f``, the model's own rule). Each run of contact steps becomes a plant (no horizontal
motion, at the run's mean height clipped to ``[floor, H_f]``); a foot that was above ``H_f``
outside the contacts is kept above it (a swing foot stays a swing foot), the floor applies to
every moving joint, and the banded solver (design §6.6) solves for the motion.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
from typing import Any

import numpy as np

from ..core import as_array, load_arrays_json, save_arrays_json
from ..motion import ContactModel, Motion, PenetrationResult, SkatingResult, Skeleton, sub_skeleton
from ..texture import MotionTexture, Synthesis
from ._api import (
    check_constraints,
    edit,
    feature_map_of,
    kept_channels,
    observations_of,
    segments_of,
)
from ._banded.terms import PointTargets
from ._bucket import solve_gn_bucketed
from ._constraints import EditWeights, make_constraints
from ._prior import WhitenedTextons
from ._solve import EditResult

__all__ = [
    "CleanResult",
    "clean",
    "clean_weights",
    "contact_plants",
    "contacts_of",
    "load_contacts",
    "save_contacts",
    "swing_guidance",
]

_KIND = "mtex_jax.ContactModel"


def clean_weights(solver: str = "gn") -> EditWeights:
    """The weights :func:`clean` uses.

    ``"gn"`` (banded Gauss–Newton; the root moves as a smooth offset, see :func:`clean`):
    plants and the floor cost one unit per millimetre (a direct banded solve is not slowed by
    stiff weights) and the change is as smooth as an edit's (``smooth=10``: on three
    development syntheses of the training-only texture, not the held-out clips, ``smooth=3``
    raised the mean joint acceleration and jerk by 0.5 % and 1.4 %, ``smooth=10`` lowered them
    by 2 %). ``"lm"``: the root may move (``root=3``, its trajectory carries the feet), plants
    and floor one unit per 3.3 mm (stricter weights make the conjugate-gradient solves slow),
    a weaker smoothness term, since stopping a sliding foot needs a quick change of its
    velocity."""
    if solver == "lm":
        return EditWeights(root=3.0, anchor=1.0, smooth=3.0, plant=300.0, floor=300.0)
    return EditWeights(anchor=1.0, smooth=10.0, plant=1e3, floor=1e3)


def contact_plants(
    contacts: ContactModel,
    motion: Motion,
    *,
    min_steps: int = 1,
    rule: str = "low",
    max_gap: int = 0,
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
        max_gap: two runs separated by at most this many non-contact steps become one (a
            foot that rises above the threshold for a frame or two has not made a step; two
            plants that close would make it jump between their positions).

    Returns:
        ``labels (T − 1, F)`` bool and ``[(foot joint, first frame, last frame, height)]``.
    """
    ((h, s),) = contacts.heights_and_speeds(motion, "clean")
    return _plants_of(contacts, h, s, min_steps=min_steps, rule=rule, max_gap=max_gap)


def _plants_of(
    contacts: ContactModel, h: np.ndarray, s: np.ndarray, *, min_steps: int, rule: str, max_gap: int
) -> tuple[np.ndarray, list[tuple[int, int, int, float]]]:
    """:func:`contact_plants` from the foot heights ``(T, F)`` and step speeds ``(T − 1, F)``."""
    if rule not in ("low", "low_and_slow"):
        raise ValueError(f"rule must be 'low' or 'low_and_slow', got {rule!r}")
    H = contacts.height_threshold
    labels = (h[:-1] < H) & (h[1:] < H)
    if rule == "low_and_slow":  # ContactModel.labels: low at both ends and slow
        labels = labels & (s < contacts.speed_threshold)
    plants = []
    if isinstance(max_gap, bool) or not isinstance(max_gap, int) or max_gap < 0:
        raise ValueError(f"max_gap must be an integer >= 0, got {max_gap!r}")
    for k in range(len(contacts.feet)):  # close gaps of at most max_gap steps between runs
        idx = np.flatnonzero(labels[:, k])
        for a, b in itertools.pairwise(idx):
            if 1 < b - a <= max_gap + 1:
                labels[a:b, k] = True
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


def swing_guidance(
    contacts: ContactModel,
    P0: np.ndarray,
    labels: np.ndarray,
    *,
    ramp: float = 0.25,
    margin: float = 0.005,
) -> tuple[np.ndarray, np.ndarray]:
    """Targets for the feet between their plants, so that corrections blend in and out.

    Planting a foot moves it by ``c_t = plant target − original`` during the run. Between two
    runs the correction goes smoothly (smoothstep in time) from the first run's last ``c`` to
    the next run's first ``c``; before the first run and after the last it fades to zero over
    ``ramp`` seconds. The swing foot is guided to ``original + c_t``: no jump of position or
    velocity at a plant's ends, so cleaning does not add acceleration or jerk there. A swing
    foot that was above the contact height threshold is guided to at least ``margin`` above
    it (the correction must not lower it into the "low" band, where it would count as a
    sliding contact).

    Args:
        contacts: the contact model (its feet are the columns of ``labels``).
        P0: ``(T, J, 3)`` original joint positions.
        labels: ``(T − 1, F)`` planted steps (from :func:`contact_plants`).
        ramp: seconds over which a correction fades at the motion's ends.
        margin: metres above the height threshold for the swing feet's guidance.

    Returns:
        ``targets (T, F, 3)`` and ``swing (T, F)`` bool (frames that get a guidance target).
    """
    T = P0.shape[0]
    up = contacts.skeleton.up_axis
    ramp_n = max(round(ramp * contacts.fps), 1)
    H = contacts.height_threshold
    targets = np.zeros((T, len(contacts.feet), 3))
    swing = np.zeros((T, len(contacts.feet)), bool)
    for k, foot in enumerate(contacts.feet):
        on = np.zeros(T, bool)
        on[:-1] |= labels[:, k]
        on[1:] |= labels[:, k]
        p = P0[:, foot]
        corr = np.zeros((T, 3))
        edges = np.flatnonzero(np.diff(np.concatenate([[0], on.astype(np.int8), [0]])))
        for a, b in zip(edges[::2], edges[1::2], strict=True):  # frames a..b-1 planted
            h = float(np.clip(p[a:b, up].mean(), contacts.floor, contacts.height_threshold[k]))
            tgt = p[a:b].mean(axis=0)
            tgt[up] = h
            corr[a:b] = tgt - p[a:b]
        idx = np.flatnonzero(on)
        if idx.size == 0:
            continue
        for t0 in np.flatnonzero(~on):
            left, right = idx[idx < t0], idx[idx > t0]
            if left.size and right.size:
                a, b = left[-1], right[0]
                x = (t0 - a) / (b - a)
                s = x * x * (3 - 2 * x)
                corr[t0] = (1 - s) * corr[a] + s * corr[b]
            else:
                a = left[-1] if left.size else right[0]
                x = min(abs(t0 - a) / ramp_n, 1.0)
                corr[t0] = (1 - x * x * (3 - 2 * x)) * corr[a]
        targets[:, k] = p + corr
        # a swing foot that was above the contact height is guided to stay above it
        high = ~on & (p[:, up] >= H[k])
        targets[high, k, up] = np.maximum(targets[high, k, up], H[k] + margin)
        swing[:, k] = ~on
    return targets, swing


def clean(
    texture: MotionTexture,
    motion: Synthesis | Motion,
    contacts: ContactModel | None = None,
    *,
    weights: EditWeights | None = None,
    min_steps: int = 1,
    rule: str = "low",
    max_gap: int | None = None,
    solver: str = "gn",
    swing_weight: float = 100.0,
    move_root: bool = True,
    root_smooth: float = 1000.0,
    max_steps: int | None = None,
    rtol: float = 1e-2,
    floor_rounds: int = 3,
    cg_steps: int = 1000,
    loglik: bool = True,
) -> CleanResult:
    """Remove foot skating and floor penetration, staying close to the texture's dynamics.

    Contacts are detected on the raw motion with the training clips' thresholds (module
    notes); each contact run is planted (a penalty: one horizontal position per run, at the
    run's height), every moving joint is kept above the training floor and a swing foot that
    was above the contact height stays above it (one-sided bounds, met by multiplier rounds
    with ``"gn"``), and the texture prior (on the change) plus a smoothness term keep the rest
    of the motion as it was. With the default banded Gauss–Newton solver
    (:mod:`mtex_jax.edit._gn`) the swing feet are also guided so that corrections blend in and
    out (:func:`swing_guidance`).

    Args:
        texture: the motion texture (with its feature map).
        motion: a :class:`Synthesis` (its texton segments are the prior's segmentation) or a
            :class:`Motion` (segmented by the texture).
        contacts: a :class:`ContactModel` fitted on the training clips (same skeleton, at the
            texture's frame rate); ``None``: the one the texture carries
            (``MotionTexture.contacts``, fitted by :func:`~mtex_jax.texture.learn`).
        weights: objective weights (default :func:`clean_weights`).
        min_steps: shortest contact run that is planted.
        rule: contact rule of :func:`contact_plants` (``"low"`` or ``"low_and_slow"``).
        max_gap: contact runs closer than this many steps are merged (default: 0.1 s).
        solver: ``"gn"`` (banded Gauss–Newton, the default) or ``"lm"`` (matrix-free
            Levenberg–Marquardt with conjugate gradients, plant residuals on steps, root free;
            slow: minutes for 10 s of motion).
        swing_weight: per metre, the swing feet's guidance targets (``"gn"`` only).
        move_root: ``"gn"``: let the root's horizontal trajectory change (a smooth world
            offset per frame, so the body follows planted feet instead of the legs stretching
            to reach them); ``False`` holds it.
        root_smooth: per metre of the root offset's second difference (one unit per 1 mm by
            default: the offset changes the root's acceleration little).
        max_steps: solver steps (default 12 for ``"gn"``, per floor round; 30 for ``"lm"``).
        rtol: ``"gn"`` stops a round (and reports convergence) when a step lowers the cost by
            less than this fraction (or moves no variable by more than ``1e-4``). Plants are
            penalties (``EditWeights.plant``), measured in the result.
            ``1e-2`` rather than ``1e-3``: on two training clips and three syntheses of 20 s
            it saved 0–3 of 6–11 steps, the final cost rose by at most 0.4 %, the skating
            median was unchanged (to 0.1 mm/s) and its 95th percentile moved by at most
            0.1 mm/s.
        floor_rounds: ``"gn"``: multiplier rounds of the floor and lift bounds (an augmented
            Lagrangian, design §6.6); ``1``: plain penalties, balanced against the prior.
        cg_steps: conjugate-gradient steps per Levenberg–Marquardt step (``"lm"`` only).
        loglik: also compute the log-likelihood per frame before and after (a forward pass
            each; ``False`` reports NaN).

    Returns:
        :class:`CleanResult`.
    """
    fm = feature_map_of(texture)
    contacts = contacts_of(texture, contacts)
    if not isinstance(contacts, ContactModel):
        raise TypeError(f"contacts must be a ContactModel, got {type(contacts).__name__}")
    if not contacts.skeleton.same_structure(fm.skeleton):
        raise ValueError("contacts: the contact model's skeleton is not the texture's")
    if float(contacts.fps) != float(fm.fps):
        raise ValueError(
            f"contacts: fitted at {contacts.fps:g} Hz, the texture is at {fm.fps:g} Hz"
        )
    if solver not in ("gn", "lm"):
        raise ValueError(f"solver must be 'gn' or 'lm', got {solver!r}")
    if isinstance(floor_rounds, bool) or not isinstance(floor_rounds, int) or floor_rounds < 1:
        raise ValueError(f"floor_rounds must be an integer >= 1, got {floor_rounds!r}")
    if not (np.isfinite(swing_weight) and swing_weight >= 0):
        raise ValueError(f"swing_weight must be a finite number >= 0, got {swing_weight}")
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
    Y, sp, sh = observations_of(texture, motion, None, None)
    gap = round(0.1 * float(fm.fps)) if max_gap is None else max_gap
    ((h, s),) = contacts.heights_and_speeds(raw, "clean")
    labels, plants = _plants_of(contacts, h, s, min_steps=min_steps, rule=rule, max_gap=gap)
    # swing feet stay off the ground: a frame of no planted step whose foot was above its
    # height threshold keeps it above (one-sided)
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
    cons = check_constraints(cons, Y, fm)
    # a Synthesis carries its segmentation; a Motion is segmented from Y (not encoded again)
    seg = segments_of(texture, motion if isinstance(motion, Synthesis) else Y)
    w = clean_weights(solver) if weights is None else weights
    if solver == "lm":
        res = edit(
            texture,
            Y,
            cons,
            weights=w,
            segments=seg,
            start_position=sp,
            start_heading=sh,
            rounds=1,
            max_steps=30 if max_steps is None else max_steps,
            cg_steps=cg_steps,
            cg_rtol=1e-2,
            fallback=False,
            solver="lm",
        )
    else:
        keep = kept_channels(cons, fm, None)
        P0 = np.asarray(fm.joint_positions(Y, sp, sh))
        tgt, swing = swing_guidance(contacts, P0, labels)
        _, order = sub_skeleton(fm.skeleton, keep)  # the solve's kept joints, in order
        slots = np.searchsorted(np.array(order), np.array(contacts.feet))
        T, F = swing.shape
        dt = np.dtype(Y.dtype)
        extra = PointTargets(  # transferred, not jnp.asarray: no copy program per length
            slot=as_array(np.tile(slots, T).astype(np.int32)),
            frame=as_array(np.repeat(np.arange(T), F).astype(np.int32)),
            target=as_array(tgt.reshape(T * F, 3).astype(dt)),
            weight=as_array(np.repeat(swing.reshape(-1, 1) * swing_weight, 3, 1).astype(dt)),
            exact=as_array(np.zeros(T * F, bool)),
            n_sparse=0,
            per_frame=F,
        )
        tx = WhitenedTextons.of(texture.textons, Y.dtype)
        res = solve_gn_bucketed(
            fm,
            tx,
            seg,
            Y,
            sp,
            sh,
            cons,
            w,
            keep=keep,
            extra=extra,
            move_root=move_root,
            root_smooth=root_smooth,
            rounds=int(floor_rounds),
            max_steps=12 if max_steps is None else max_steps,
            rtol=rtol,
            early_rtol=rtol,
            exact_lower=True,  # the floor's bounds shifted between rounds until met to 1 mm
            exact_points=False,  # the plants stay penalties
            lower_tol=1e-3,
            chord=False,  # far from linear: the plants' and floor's active sets change
        )
    out = fm.decode(res.Y, res.start_position, sh)
    # before and after scored in one call: the two motions packed as one sequence list
    ll_before, ll_after = texture.log_likelihood([Y, res.Y], mean=True) if loglik else [np.nan] * 2
    return CleanResult(
        motion=out,
        Y=res.Y,
        edit=res,
        labels=labels,
        skating_before=contacts.skating(raw),
        skating_after=contacts.skating(out),
        penetration_before=contacts.penetration(raw),
        penetration_after=contacts.penetration(out),
        loglik_before=float(ll_before),
        loglik_after=float(ll_after),
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
    if contacts.stance is not None:
        meta["stance"] = float(contacts.stance)
    save_arrays_json(path, arrays, meta)


def load_contacts(path: str | os.PathLike[str]) -> ContactModel:
    """Read a :class:`ContactModel` written by :func:`save_contacts`.

    Every value passes the checks a fitted model passes (:class:`ContactModel`: distinct foot
    joints of the skeleton, finite thresholds of one per foot, heights at or above the floor,
    positive speeds, a frame rate in range); the file is never unpickled.

    Raises:
        ValueError: naming the file and the problem.
    """
    req = ("feet", "height_threshold", "speed_threshold")
    arrays, meta = load_arrays_json(path, kind=_KIND, required=req, allowed=())
    try:
        if meta.get("format_version") != 1:
            raise ValueError(f"format version {meta.get('format_version')!r} is not supported")
        sk = Skeleton.from_json_dict(meta["skeleton"])
        feet = arrays["feet"]
        if feet.dtype.kind not in "iu" or feet.ndim != 1:
            raise ValueError(
                f"feet must be a vector of joint indices, got {feet.dtype} {feet.shape}"
            )
        return ContactModel(
            sk,
            tuple(feet.tolist()),
            arrays["height_threshold"],
            arrays["speed_threshold"],
            meta["floor"],
            meta["fps"],
            meta.get("stance"),
        )
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as e:
        raise ValueError(f"{path}: invalid contact model file: {e}") from None


def contacts_of(texture: MotionTexture, contacts: ContactModel | None = None) -> ContactModel:
    """``contacts`` if given, else the contact model the texture carries (fitted by
    :func:`~mtex_jax.texture.learn` on its training clips, design §6.6).

    Raises:
        ValueError: neither (a texture learned from observation arrays, or saved before
            textures carried their training contacts).
    """
    if contacts is not None:
        return contacts
    own = getattr(texture, "contacts", None)
    if own is None:
        raise ValueError(
            "cleaning needs the training clips' contact model, and this texture carries none "
            "(it was learned from observation arrays, or saved before textures carried their "
            "contacts): pass contacts= (mtex_jax.motion.fit_contacts on the training clips, "
            "or mtex_jax.edit.load_contacts)"
        )
    return own
