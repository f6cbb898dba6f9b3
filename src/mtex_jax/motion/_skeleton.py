"""Skeleton: the static description of an articulated figure (names, tree, offsets, channels)."""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import numpy as np

__all__ = ["POSITION_CHANNELS", "ROTATION_CHANNELS", "Skeleton", "sub_skeleton"]

ROTATION_CHANNELS = ("Xrotation", "Yrotation", "Zrotation")
POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")
_ALL_CHANNELS = ROTATION_CHANNELS + POSITION_CHANNELS


@dataclasses.dataclass(frozen=True)
class Skeleton:
    """An articulated figure, immutable and hashable (it is static metadata under ``jit``).

    Joints are stored in file (depth-first) order, so every parent precedes its children and
    joint 0 is the root.

    Attributes:
        names: joint names, ``(J,)``.
        parents: parent index of each joint, ``-1`` for the root.
        offsets: rest offset of each joint in its parent's frame, ``(J, 3)`` as tuples (the unit
            is the file's: metres for the CMU and DeepMimic data).
        channels: per joint, the BVH channel names in file order, e.g.
            ``("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")``.
            The rotation channels, in order, give the intrinsic Euler order: ``Zrotation
            Xrotation Yrotation`` means ``R = Rz(a) @ Rx(b) @ Ry(c)``.
        end_sites: ``(parent_index, offset)`` pairs for the BVH ``End Site`` entries.
        up_axis: index of the vertical world axis (0 = x, 1 = y, 2 = z).
    """

    names: tuple[str, ...]
    parents: tuple[int, ...]
    offsets: tuple[tuple[float, float, float], ...]
    channels: tuple[tuple[str, ...], ...]
    end_sites: tuple[tuple[int, tuple[float, float, float]], ...] = ()
    up_axis: int = 1

    def __post_init__(self) -> None:
        j = len(self.names)
        if j == 0:
            raise ValueError("Skeleton needs at least one joint")
        for field in ("parents", "offsets", "channels"):
            if len(getattr(self, field)) != j:
                raise ValueError(
                    f"Skeleton.{field} has {len(getattr(self, field))} entries, expected {j} "
                    "(one per joint)"
                )
        if len(set(self.names)) != j:
            dup = sorted({n for n in self.names if self.names.count(n) > 1})
            raise ValueError(f"Skeleton joint names must be unique; repeated: {dup}")
        if self.parents[0] != -1:
            raise ValueError("Skeleton joint 0 must be the root (parent -1)")
        for i, p in enumerate(self.parents[1:], start=1):
            if not 0 <= p < i:
                raise ValueError(
                    f"Skeleton joint {i} ({self.names[i]!r}) has parent {p}; parents must precede "
                    "their children"
                )
        for i, off in enumerate(self.offsets):
            if len(off) != 3 or not all(np.isfinite(off)):
                raise ValueError(
                    f"Skeleton offset of joint {self.names[i]!r} is not 3 finite numbers"
                )
        for i, ch in enumerate(self.channels):
            for c in ch:
                if c not in _ALL_CHANNELS:
                    raise ValueError(f"Skeleton joint {self.names[i]!r}: unknown channel {c!r}")
            if len(set(ch)) != len(ch):
                raise ValueError(f"Skeleton joint {self.names[i]!r}: repeated channel in {ch}")
        for p, off in self.end_sites:
            if not 0 <= p < j or len(off) != 3:
                raise ValueError(f"Skeleton end site ({p}, {off}) is invalid")
        if self.up_axis not in (0, 1, 2):
            raise ValueError(f"Skeleton.up_axis must be 0, 1 or 2, got {self.up_axis}")

    # ------------------------------------------------------------------ properties
    @property
    def n_joints(self) -> int:
        """Number of joints ``J`` (end sites excluded)."""
        return len(self.names)

    @property
    def offsets_array(self) -> np.ndarray:
        """Rest offsets as a float64 array ``(J, 3)``."""
        return np.asarray(self.offsets, dtype=np.float64).reshape(-1, 3)

    @property
    def end_site_parents(self) -> tuple[int, ...]:
        return tuple(p for p, _ in self.end_sites)

    @property
    def end_site_offsets_array(self) -> np.ndarray:
        return np.asarray([o for _, o in self.end_sites], dtype=np.float64).reshape(-1, 3)

    def rotation_order(self, joint: int) -> str:
        """Intrinsic Euler order of a joint's rotation channels, e.g. ``"ZXY"`` (may be ``""``)."""
        return "".join(c[0] for c in self.channels[joint] if c.endswith("rotation"))

    def position_channels(self, joint: int) -> str:
        """Axes of a joint's position channels in file order, e.g. ``"XYZ"`` (may be ``""``)."""
        return "".join(c[0] for c in self.channels[joint] if c.endswith("position"))

    @property
    def n_channels(self) -> int:
        return sum(len(c) for c in self.channels)

    def index(self, name: str) -> int:
        """Index of the joint called ``name``."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueError(f"no joint named {name!r}; joints are {list(self.names)}") from None

    def depth(self) -> tuple[int, ...]:
        """Depth of every joint in the tree (root = 0)."""
        d: list[int] = []
        for p in self.parents:
            d.append(0 if p < 0 else d[p] + 1)
        return tuple(d)

    @property
    def size(self) -> float:
        """A length scale of the figure: the largest root-to-leaf chain length (> 0)."""
        off = self.offsets_array
        lengths = np.linalg.norm(off, axis=1)
        lengths[0] = 0.0
        acc = np.zeros(self.n_joints)
        for i in range(1, self.n_joints):
            acc[i] = acc[self.parents[i]] + lengths[i]
        ends = [acc[p] + float(np.linalg.norm(o)) for p, o in self.end_sites]
        return float(max([*acc.tolist(), *ends, 1e-12]))

    def same_structure(self, other: Skeleton) -> bool:
        """True when names, parents and channels agree (offsets may differ)."""
        return (
            self.names == other.names
            and self.parents == other.parents
            and self.channels == other.channels
        )

    # ------------------------------------------------------------------ left and right
    def mirror_pairs(self) -> tuple[int, ...]:
        """The left-right partner of every joint, found by name (itself for a joint on the
        midline).

        The sides are spelled as in the common skeletons: ``left``/``right`` anywhere in the
        name, in any case (``leftEye``, ``left_hip``, ``LeftArm``); a one-letter prefix
        ``l``/``r`` or ``L``/``R`` (``lThigh``, ``L_Hip``, ``lfemur``); a suffix ``_l``/``_r``,
        ``.l``/``.r`` (either case). A swapped spelling counts only where it names a joint.

        Raises:
            ValueError: if a joint's partner would have another partner.
        """
        names = self.names
        index = {n: i for i, n in enumerate(names)}
        pairs = [
            next((index[c] for c in _other_sides(n) if c in index), i) for i, n in enumerate(names)
        ]
        for i, j in enumerate(pairs):
            if pairs[j] != i:
                raise ValueError(
                    f"mirror: the joints {names[i]!r} and {names[j]!r} are not each other's "
                    "left-right partner"
                )
        return tuple(pairs)

    def lateral_axis(self) -> int:
        """The world axis from left to right at rest: of the two horizontal axes, the one along
        which the partners of :meth:`mirror_pairs` lie apart the most.

        Raises:
            ValueError: if the skeleton has no left-right pair (no side to mirror).
        """
        pairs = np.asarray(self.mirror_pairs())
        sided = np.nonzero(pairs != np.arange(self.n_joints))[0]
        if sided.size == 0:
            raise ValueError(
                "mirror: no joint has a left-right partner by name (e.g. lThigh/rThigh, "
                "left_hip/right_hip); give the lateral axis"
            )
        off = self.offsets_array
        spread = np.abs(off[sided] - off[pairs[sided]]).sum(axis=0)
        _, h0, h1 = ground_axes(self.up_axis)
        return h0 if spread[h0] >= spread[h1] else h1

    # ------------------------------------------------------------------ serialisation
    def to_json_dict(self) -> dict[str, Any]:
        return {
            "names": list(self.names),
            "parents": list(self.parents),
            "offsets": [list(o) for o in self.offsets],
            "channels": [list(c) for c in self.channels],
            "end_sites": [[p, list(o)] for p, o in self.end_sites],
            "up_axis": self.up_axis,
        }

    @classmethod
    def from_json_dict(cls, d: dict[str, Any]) -> Skeleton:
        try:
            return cls(
                names=tuple(str(n) for n in d["names"]),
                parents=tuple(int(p) for p in d["parents"]),
                offsets=tuple(_vec3(o) for o in d["offsets"]),
                channels=tuple(tuple(str(c) for c in ch) for ch in d["channels"]),
                end_sites=tuple((int(p), _vec3(o)) for p, o in d.get("end_sites", [])),
                up_axis=int(d.get("up_axis", 1)),
            )
        except (KeyError, TypeError) as e:
            raise ValueError(f"malformed skeleton description: {e!r}") from None

    def to_json(self) -> str:
        return json.dumps(self.to_json_dict())


def ground_axes(up_axis: int) -> tuple[int, int, int]:
    """``(up, h0, h1)``: the up axis and the two horizontal axes, in cyclic order.

    The heading frame, the ground plane and the camera of the tracker all use this order, so
    that ``(h0, h1, up)`` is a right-handed frame.
    """
    return up_axis, (up_axis + 1) % 3, (up_axis + 2) % 3


_SIDES = {"left": "right", "right": "left", "Left": "Right", "Right": "Left"}
_SIDES.update({k.upper(): v.upper() for k, v in list(_SIDES.items())[:2]})


def _other_sides(name: str) -> list[str]:
    """``name`` with its side swapped, in each spelling that might be meant (see
    :meth:`Skeleton.mirror_pairs`); the first that names a joint is the partner."""
    out = [name.replace(a, b, 1) for a, b in _SIDES.items() if a in name]
    swap = {"l": "r", "r": "l", "L": "R", "R": "L"}
    if len(name) > 1 and name[0] in swap:  # lThigh, L_Hip, lfemur (CMU's ASF names)
        out.append(swap[name[0]] + name[1:])
    if len(name) > 2 and name[-2] in "_." and name[-1] in swap:  # hand_l, foot.R
        out.append(name[:-1] + swap[name[-1]])
    return out


def _vec3(o: Any) -> tuple[float, float, float]:
    a, b, c = (float(x) for x in o)
    return (a, b, c)


def sub_skeleton(skeleton: Skeleton, joints: tuple[int, ...]) -> tuple[Skeleton, tuple[int, ...]]:
    """The joints and all their ancestors, as a skeleton of their own (parents remapped).

    Returns:
        ``(sub, order)``: the smaller skeleton and, for each of its joints, the index of the
        joint in ``skeleton`` (increasing; the root first).
    """
    keep = set()
    for j in joints:
        while j >= 0 and j not in keep:
            keep.add(j)
            j = skeleton.parents[j]
    order = tuple(sorted(keep | {0}))
    new = {j: i for i, j in enumerate(order)}
    sub = Skeleton(
        names=tuple(skeleton.names[j] for j in order),
        parents=tuple(-1 if skeleton.parents[j] < 0 else new[skeleton.parents[j]] for j in order),
        offsets=tuple(skeleton.offsets[j] for j in order),
        channels=tuple(skeleton.channels[j] for j in order),
        up_axis=skeleton.up_axis,
    )
    return sub, order
