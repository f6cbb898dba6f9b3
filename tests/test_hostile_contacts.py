"""Issue 43: hostile values in contact-model files and in the contacts a texture file carries.

In the style of ``test_hostile.py`` (the case tables of ``hostile_cases.py``): each case rewrites
one member or metadata entry of a valid file and asserts the error type and message; the file's
path is named. ``default=True`` cases run by default, the others with ``-m slow``. Both loaders
build a :class:`~mtex_jax.motion.ContactModel`, so they check what a fitted model passes:
distinct foot joints of the skeleton, one finite threshold per foot, heights at or above the
floor, positive speeds, a finite floor and a frame rate in ``(0, 10000]``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

import mtex_jax as mj
from hostile_cases import Case, params, rewrite_npz
from mtex_jax.edit import load_contacts, save_contacts
from shared_textures import dance_pair_texture


def _meta(keys: tuple[str, ...], value: Any):
    def change(m: dict[str, Any]) -> dict[str, Any]:
        d = m
        for k in keys[:-1]:
            d = d[k]
        if value is _DROP:
            d.pop(keys[-1])
        else:
            d[keys[-1]] = value
        return m

    return change


_DROP = object()


def _below_floor(a: dict[str, np.ndarray], key: str, floor: float) -> np.ndarray:
    h = a[key].copy()
    h[0] = floor - 0.05  # "negative heights": a threshold 5 cm under the floor
    return h


#: contact-model file: id -> (array changes, meta change, match, default)
_FILE: list[tuple[Any, ...]] = [
    (
        "height-nan",
        {"height_threshold": lambda a: a["height_threshold"] * np.nan},
        None,
        r"height_threshold must hold finite",
        True,
    ),
    (
        "height-shape-3",
        {"height_threshold": lambda a: np.r_[a["height_threshold"], 0.1]},
        None,
        r"height_threshold must have shape \(2,\)",
        True,
    ),
    (
        "height-below-floor",
        {"height_threshold": lambda a: a["height_threshold"] - 10.0},
        None,
        r"height_threshold\[0\] = .* is below the floor",
        True,
    ),
    (
        "height-1e30",
        {"height_threshold": lambda a: a["height_threshold"] + 1e30},
        None,
        r"magnitude at most",
        False,
    ),
    (
        "height-bool",
        {"height_threshold": lambda a: a["height_threshold"] > 0},
        None,
        r"must hold real numbers",
        False,
    ),
    (
        "speed-negative",
        {"speed_threshold": lambda a: -a["speed_threshold"]},
        None,
        r"speed_threshold must be positive",
        True,
    ),
    (
        "speed-zero",
        {"speed_threshold": lambda a: 0 * a["speed_threshold"]},
        None,
        r"speed_threshold must be positive",
        False,
    ),
    (
        "speed-inf",
        {"speed_threshold": lambda a: a["speed_threshold"] + np.inf},
        None,
        r"speed_threshold must hold finite",
        False,
    ),
    (
        "speed-2d",
        {"speed_threshold": lambda a: a["speed_threshold"][None]},
        None,
        r"speed_threshold must have shape",
        False,
    ),
    (
        "feet-out-of-range",
        {"feet": lambda a: np.array([0, 99])},
        None,
        r"distinct joint indices in \[0, 13\)",
        True,
    ),
    ("feet-negative", {"feet": lambda a: np.array([-1, 9])}, None, r"distinct joint", False),
    ("feet-repeated", {"feet": lambda a: np.array([9, 9])}, None, r"distinct joint", False),
    (
        "feet-float",
        {"feet": lambda a: a["feet"].astype(float)},
        None,
        r"feet must be a vector of joint indices",
        False,
    ),
    ("feet-2d", {"feet": lambda a: a["feet"][None]}, None, r"vector of joint indices", False),
    ("feet-empty", {"feet": lambda a: np.zeros(0, np.int64)}, None, r"at least one joint", False),
    ("feet-missing", {"feet": lambda a: None}, None, r"feet", False),
    ("meta-floor-nan", {}, _meta(("floor",), math.nan), r"floor must be finite", True),
    ("meta-floor-string", {}, _meta(("floor",), "low"), r"floor must be a real number", False),
    ("meta-floor-above-heights", {}, _meta(("floor",), 5.0), r"below the floor", False),
    ("meta-floor-missing", {}, _meta(("floor",), _DROP), r"floor", False),
    ("meta-fps-zero", {}, _meta(("fps",), 0), r"fps must be > 0", False),
    ("meta-fps-huge", {}, _meta(("fps",), 1e9), r"fps must be <= 10000", False),
    ("meta-fps-bool", {}, _meta(("fps",), True), r"fps must be a real number", False),
    ("meta-skeleton-garbage", {}, _meta(("skeleton",), [1, 2]), r"invalid contact model", False),
    ("meta-version-99", {}, _meta(("format_version",), 99), r"format version 99", False),
]

#: the contacts of a texture file: id -> (array changes, meta change, match, default)
_TEX: list[tuple[Any, ...]] = [
    (
        "nan",
        {"contacts.height_threshold": lambda a: a["contacts.height_threshold"] * np.nan},
        None,
        r"'contacts.height_threshold' contains NaN",
        True,
    ),
    (
        "shape",
        {"contacts.speed_threshold": lambda a: np.r_[a["contacts.speed_threshold"], 1.0]},
        None,
        r"contacts: ContactModel.speed_threshold must have shape \(2,\)",
        True,
    ),
    (
        "below-floor",
        {"contacts.height_threshold": lambda a: a["contacts.height_threshold"] - 10},
        None,
        r"contacts: .*below the floor",
        True,
    ),
    (
        "speed-negative",
        {"contacts.speed_threshold": lambda a: -a["contacts.speed_threshold"]},
        None,
        r"speed_threshold must be positive",
        False,
    ),
    (
        "integer-array",
        {"contacts.height_threshold": lambda a: np.array([0, 1])},
        None,
        r"expected a floating-point array",
        False,
    ),
    (
        "feet-out-of-range",
        {},
        _meta(("contacts", "feet"), [9, 1000]),
        r"contacts: .*distinct joint indices",
        True,
    ),
    ("feet-strings", {}, _meta(("contacts", "feet"), ["a", "b"]), r"integer joint indices", False),
    ("feet-floats", {}, _meta(("contacts", "feet"), [9.0, 12.0]), r"integer joint", False),
    ("feet-not-a-list", {}, _meta(("contacts", "feet"), 9), r"sequence of joint indices", False),
    ("floor-nan", {}, _meta(("contacts", "floor"), math.nan), r"floor must be finite", False),
    ("floor-missing", {}, _meta(("contacts", "floor"), _DROP), r"contacts: 'floor'", False),
    ("meta-missing", {}, _meta(("contacts",), _DROP), r"come together", False),
    ("meta-not-a-dict", {}, _meta(("contacts",), [1, 2]), r"come together", False),
    ("array-missing", {"contacts.speed_threshold": lambda a: None}, None, r"come together", False),
]

FILE_CASES = [Case(f"contacts-{n}", (a, m), ValueError, r, d) for n, a, m, r, d in _FILE]
TEXTURE_CASES = [Case(f"texture-contacts-{n}", (a, m), ValueError, r, d) for n, a, m, r, d in _TEX]


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Any]:
    """A small texture learned from two DeepMimic clips at 30 Hz (so it carries their contact
    model) in a model file, and that contact model in a file of its own."""
    d = tmp_path_factory.mktemp("contacts")
    tex = dance_pair_texture()  # shared with other test modules (learned once per process)
    assert tex.contacts is not None and tex.contacts.feet == (9, 12)
    tex.save(d / "tex.npz")
    save_contacts(d / "contacts.npz", tex.contacts)
    return dict(tex=tex, model=d / "tex.npz", contacts=d / "contacts.npz")


def test_the_valid_files_load(files, tmp_path):
    """The other side of the cases: the files as written, and rewritten unchanged, load."""
    for path in (files["contacts"], tmp_path / "again.npz"):
        if not path.exists():
            rewrite_npz(files["contacts"], path, {}, None)
        cm = load_contacts(path)
        assert cm.feet == files["tex"].contacts.feet and cm.floor == files["tex"].contacts.floor
    assert mj.load_texture(files["model"]).contacts.feet == (9, 12)


@pytest.mark.parametrize("case", params(FILE_CASES))
def test_contact_file_values(case: Case, files, tmp_path):
    arrays, meta = case.make
    path = tmp_path / "hostile.npz"
    rewrite_npz(files["contacts"], path, arrays, meta)
    with pytest.raises(case.error, match=case.match) as info:
        load_contacts(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("case", params(TEXTURE_CASES))
def test_texture_file_contact_values(case: Case, files, tmp_path):
    arrays, meta = case.make
    path = tmp_path / "hostile.npz"
    rewrite_npz(files["model"], path, arrays, meta)
    with pytest.raises(case.error, match=case.match) as info:
        mj.load_texture(path)
    assert str(path) in str(info.value)


def test_a_contact_model_built_by_hand_is_checked_too(files):
    """The constructor is the one validator: what a file may not hold, code may not build."""
    cm = files["tex"].contacts
    sk = cm.skeleton
    with pytest.raises(ValueError, match="below the floor"):
        mj.motion.ContactModel(
            sk, cm.feet, cm.height_threshold - 1.0, cm.speed_threshold, cm.floor, cm.fps
        )
    with pytest.raises(TypeError, match="integer joint indices"):
        mj.motion.ContactModel(
            sk, (True, 12), cm.height_threshold, cm.speed_threshold, cm.floor, cm.fps
        )
    with pytest.raises(ValueError, match="fps must be > 0"):
        mj.motion.ContactModel(sk, cm.feet, cm.height_threshold, cm.speed_threshold, cm.floor, 0.0)
