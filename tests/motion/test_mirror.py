"""``Motion.mirror``: a dance reflected left to right (issue 55, item 2), checked in joint
positions: the mirrored motion's joints are where the reflection puts the original's."""

from __future__ import annotations

import numpy as np
import pytest

from mtex_jax.io import load_example, load_salsa
from mtex_jax.motion import Motion, Skeleton, joint_positions


def _reflected(m: Motion, axis: int) -> np.ndarray:
    p = joint_positions(m)[0].copy()
    p[..., axis] *= -1
    return p


def test_a_symmetric_figure_mirrors_exactly_and_twice_is_the_original():
    m = load_example("walk")  # DeepMimic's humanoid: symmetric offsets, z from left to right
    sk = m.skeleton
    assert sk.lateral_axis() == 2
    pairs = sk.mirror_pairs()
    names = sk.names
    assert names[pairs[names.index("left_knee")]] == "right_knee"
    assert names[pairs[names.index("chest")]] == "chest"
    mm = m.mirror()
    got = joint_positions(mm)[0]
    np.testing.assert_allclose(got[:, list(pairs)], _reflected(m, 2), atol=1e-12)
    # the reflection is an involution: the original rotations and path, exactly
    back = mm.mirror()
    np.testing.assert_array_equal(back.rotations, m.rotations)
    np.testing.assert_array_equal(back.root_positions, m.root_positions)


def test_the_salsa_dancer_mirrored_is_off_only_where_his_skeleton_is_not_symmetric():
    m = load_salsa("60_01")[:240]
    sk = m.skeleton
    assert sk.lateral_axis() == 0
    pairs = list(sk.mirror_pairs())
    names = sk.names
    assert names[pairs[names.index("lFoot")]] == "rFoot"
    assert names[pairs[names.index("leftEye")]] == "rightEye"
    err = np.abs(joint_positions(m.mirror())[0][:, pairs] - _reflected(m, 0)).max(axis=(0, 2))
    # the head's and eyes' offsets of this skeleton are off the midline by 1.9 and 3.8 mm
    off = {"head", "leftEye", "rightEye"}
    assert max(e for n, e in zip(names, err, strict=True) if n in off) < 0.005
    assert max(e for n, e in zip(names, err, strict=True) if n not in off) < 1e-9


def _skeleton(names: list[str]) -> Skeleton:
    rot = ("Zrotation", "Xrotation", "Yrotation")
    offsets = [(0.0, 0.0, 0.0)] + [(0.1 * (i + 1), 0.0, 0.0) for i in range(len(names) - 1)]
    return Skeleton(
        names=tuple(names),
        parents=(-1, *([0] * (len(names) - 1))),
        offsets=tuple(offsets),
        channels=(("Xposition", "Yposition", "Zposition", *rot), *([rot] * (len(names) - 1))),
    )


def test_sides_are_found_in_the_common_spellings():
    names = [
        "Hips",
        "LeftUpLeg",
        "RightUpLeg",
        "l_hand",
        "r_hand",
        "foot.L",
        "foot.R",
        "lfemur",
        "rfemur",
        "lowerback",
        "Spine",
    ]
    pairs = _skeleton(names).mirror_pairs()
    got = {names[i]: names[j] for i, j in enumerate(pairs)}
    assert got["LeftUpLeg"] == "RightUpLeg" and got["RightUpLeg"] == "LeftUpLeg"
    assert got["l_hand"] == "r_hand" and got["foot.L"] == "foot.R"
    assert got["lfemur"] == "rfemur"
    assert got["lowerback"] == "lowerback" and got["Hips"] == "Hips" and got["Spine"] == "Spine"


def test_bad_axes_and_figures_without_sides_are_refused():
    m = load_example("walk")
    with pytest.raises(ValueError, match="up axis"):
        m.mirror(axis=1)
    for bad in (3, -1, 0.5, True):
        with pytest.raises(ValueError, match="axis must be 0, 1 or 2"):
            m.mirror(axis=bad)  # type: ignore[arg-type]
    sk = _skeleton(["root", "spine", "head"])
    T = 5
    q = np.tile([1.0, 0.0, 0.0, 0.0], (T, 3, 1))
    plain = Motion(sk, 30.0, np.zeros((T, 3)), q)
    with pytest.raises(ValueError, match="lateral axis"):
        plain.mirror()
    # with the axis given, a figure without sides is reflected joint by joint
    np.testing.assert_array_equal(plain.mirror(axis=0).rotations, q)
    # a joint whose partner pairs with another joint is refused ("left_l" → "left_r", whose
    # partner is "right_r")
    with pytest.raises(ValueError, match="partner"):
        _skeleton(["root", "left_r", "right_r", "left_l"]).mirror_pairs()
