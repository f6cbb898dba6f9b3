"""Which joints of a skeleton are its feet (used by the contact metrics, the implicit model's
foot lock and the cleaning of synthesised motion)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ._skeleton import Skeleton

__all__ = ["foot_joints"]

_FOOT_WORDS = ("foot", "ankle", "toe")


def _side(name: str) -> str | None:
    """``"left"``, ``"right"`` or ``None`` from naming conventions (LeftFoot, lFoot, l_ankle,
    foot_l, Foot.L)."""
    low = name.lower()
    for side, word, letter in (("left", "left", "l"), ("right", "right", "r")):
        if word in low:
            return side
        if len(name) > 1 and low[0] == letter and (name[1].isupper() or name[1] in "_.- "):
            return side
        if len(low) > 1 and low[-1] == letter and low[-2] in "_.- ":
            return side
    return None


def _rest_heights(sk: Skeleton) -> np.ndarray:
    """Height of every joint in the rest pose (identity rotations, root at the origin)."""
    off = sk.offsets_array
    pos = np.zeros_like(off)
    for i in range(1, sk.n_joints):
        pos[i] = pos[sk.parents[i]] + off[i]
    return pos[:, sk.up_axis]


def _lowest_leaf_per_leg(sk: Skeleton, h: np.ndarray) -> tuple[int, ...]:
    children: list[list[int]] = [[] for _ in range(sk.n_joints)]
    for i, p in enumerate(sk.parents[1:], start=1):
        children[p].append(i)
    branch = 0
    while len(children[branch]) == 1:
        branch = children[branch][0]

    def lowest_leaf(j: int) -> int:
        stack, leaves = [j], []
        while stack:
            k = stack.pop()
            stack.extend(children[k])
            if not children[k]:
                leaves.append(k)
        return min(leaves, key=lambda k: h[k])

    leaves = sorted((lowest_leaf(c) for c in children[branch]), key=lambda k: h[k])
    if not leaves:
        raise ValueError("foot_joints: the skeleton has no leaf joint below its root")
    return tuple(sorted(leaves[:2]))


def foot_joints(
    skeleton: Skeleton,
    names: Sequence[str] | None = None,
    *,
    heights: np.ndarray | None = None,
) -> tuple[int, ...]:
    """Indices of the foot joints of a skeleton.

    By name: every joint whose name contains ``foot``, ``ankle`` or ``toe`` and has a side
    (left/right by the usual conventions: ``LeftFoot``, ``lFoot``, ``l_ankle``, ``foot_l``),
    when both sides have at least one. Otherwise, from the skeleton's structure (any exporter's
    names): the lowest leaf joint of each of the two lowest subtrees below the first branching
    joint (the legs), lowest by ``heights`` when given (the training clips' median height of
    every joint: what the figure stands on in its own motion), else in the rest pose.

    Args:
        skeleton: the figure.
        names: explicit joint names, overriding the rules.
        heights: ``(J,)`` height of every joint (world up coordinate) ranking the leaves.

    Returns:
        Joint indices, increasing.
    """
    if names is not None:
        idx = tuple(sorted({skeleton.index(n) for n in names}))
        if not idx:
            raise ValueError("foot_joints: names must not be empty")
        return idx
    found: dict[str, list[int]] = {"left": [], "right": []}
    for i, n in enumerate(skeleton.names):
        side = _side(n)
        if side is not None and any(w in n.lower() for w in _FOOT_WORDS):
            found[side].append(i)
    if found["left"] and found["right"]:
        return tuple(sorted(found["left"] + found["right"]))
    if heights is None:
        return _lowest_leaf_per_leg(skeleton, _rest_heights(skeleton))
    h = np.asarray(heights, np.float64).reshape(-1)
    if h.shape != (skeleton.n_joints,) or not np.isfinite(h).all():
        raise ValueError(f"foot_joints: heights must be {skeleton.n_joints} finite numbers")
    return _lowest_leaf_per_leg(skeleton, h)
