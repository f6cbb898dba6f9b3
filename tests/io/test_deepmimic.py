"""DeepMimic reader and the embedded example data."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import mtex_jax as mj
from mtex_jax.io._deepmimic import FRAME_SIZE as DEEPMIMIC_FRAME_SIZE


def test_examples_load_with_plausible_values():
    names = mj.example_names()
    assert len(names) == 15 and "dance_a" in names and "walk" in names
    for name in names:
        m = mj.load_example(name)
        assert m.skeleton == mj.io.HUMANOID3D
        assert m.n_frames >= 20 and m.fps in (16.0, 24.0, 30.0, 60.0)
        q = np.asarray(m.rotations)
        np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
        pelvis = np.asarray(m.root_positions)[:, 1]
        p = np.asarray(mj.forward_kinematics(m, end_sites=True))
        if name.startswith(("getup", "crawl", "roll")):
            assert 0.05 < pelvis.min() and pelvis.max() < 1.2, name
        else:
            assert 0.6 < np.median(pelvis) < 1.0, name  # standing pelvis height in metres
            # someone standing: the lowest point of the figure is near the floor
            assert abs(np.median(p[:, :, 1].min(axis=1))) < 0.1, name
    dance = mj.load_example("dance_a")
    assert dance.fps == 60.0 and dance.n_frames == 98


def test_examples_match_shared_copies():
    from conftest import DEEPMIMIC_DIR, _require

    shared = _require(DEEPMIMIC_DIR)  # fails (not skips) in CI when the data is missing
    for name in ["dance_a", "walk"]:
        a = mj.read_deepmimic(shared / f"humanoid3d_{name}.txt")
        b = mj.load_example(name)
        np.testing.assert_array_equal(np.asarray(a.rotations), np.asarray(b.rotations))


def test_unknown_example_lists_names():
    with pytest.raises(ValueError, match="dance_a"):
        mj.load_example("tango")


def test_nonuniform_keyframes_are_resampled():
    from importlib import resources

    text = resources.files("mtex_jax.data.deepmimic").joinpath("humanoid3d_roll.txt").read_text()
    raw = np.asarray(json.loads(text)["Frames"])
    dt = raw[:-1, 0]
    assert np.sum(dt != dt[0]) == 1  # keyframe 5 lasts 0.032666 s, the others 0.016666 s
    m = mj.load_example("roll")
    assert m.fps == 60.0
    assert m.n_frames == int(np.floor(dt.sum() * 60.0)) + 1
    rp = np.asarray(m.root_positions)
    np.testing.assert_allclose(rp[:6], raw[:6, 1:4], atol=1e-3)  # on the keyframes (±0.02 %)
    # frame 6 (t = 0.1 s) falls inside the long keyframe: between keyframes 5 and 6
    u = (6 / 60 - dt[:5].sum()) / dt[5]
    np.testing.assert_allclose(rp[6], raw[5, 1:4] + u * (raw[6, 1:4] - raw[5, 1:4]), atol=1e-12)


def _frames_text(frames: list[list[float]]) -> str:
    body = ",\n".join(json.dumps(f) for f in frames)
    return '{\n"Loop": "wrap",\n"Frames":\n[\n' + body + "\n]\n}\n"


def test_deepmimic_malformed_inputs(tmp_path):
    walk = mj.load_example("walk")
    assert walk.n_frames == 39
    frame = [0.0333] + [0.0, 0.85, 0.0] + [1.0, 0.0, 0.0, 0.0] * 2
    frame += [1.0, 0, 0, 0] * 2 + [0.3] + [1.0, 0, 0, 0] * 2 + [0.2]
    frame += [1.0, 0, 0, 0] + [0.3] + [1.0, 0, 0, 0] * 2 + [0.2]
    assert len(frame) == DEEPMIMIC_FRAME_SIZE
    frames = [list(frame) for _ in range(4)]
    good = tmp_path / "good.txt"
    good.write_text(_frames_text(frames))
    m = mj.read_deepmimic(good)
    assert m.n_frames == 4 and m.fps == 30.0  # 1/0.0333 = 30.03 Hz, snapped (within 0.1 %)

    def case(name, fr=None, text=None):
        p = tmp_path / f"{name}.txt"
        p.write_text(text if text is not None else _frames_text(fr))
        return p

    short = [list(f) for f in frames]
    short[2] = short[2][:-3]
    nonnum = [list(f) for f in frames]
    nonnum[1][5] = "x"  # type: ignore[call-overload]
    badq = [list(f) for f in frames]
    badq[3][4:8] = [0.0, 0.0, 0.0, 0.0]
    baddt = [list(f) for f in frames]
    baddt[1][0] = -0.1
    full = _frames_text(frames)
    bigint = [list(f) for f in frames]
    bigint[2][7] = int("9" * 401)  # no float holds it
    checks = [
        # (path, expected 1-based line, fragment)
        (case("short", short), 7, "has 41 values"),
        (case("nonnum", nonnum), 6, "non-numeric"),
        (case("badq", badq), 8, "not a rotation"),
        (case("baddt", baddt), 6, "inconsistent frame time"),
        (case("bigint", bigint), 7, "Frames[2][7]: a 401-digit integer is too large for a float"),
        (case("denormal", text=full.replace("0.85", "1e-320", 1)), None, None),
        (case("negzero", text=full.replace("0.85", "-0.0", 1)), None, None),
        (case("nan", text=full.replace("0.85", "NaN", 1)), 5, "Frames[0][2]: non-finite value NaN"),
        (case("nanlower", text=full.replace("0.85", "nan", 1)), 5, "invalid JSON: 'nan' is not"),
        (case("truncated", text=full[: len(full) // 2]), None, "invalid JSON"),
        (case("zero", text='{"Loop": "wrap", "Frames": []}'), 1, "zero frames"),
        (case("nota", text=json.dumps({"Loop": "wrap"})), 1, "no 'Frames'"),
    ]
    for path, line, frag in checks:
        if frag is None:  # a denormal or a negative zero is a number like any other
            assert mj.read_deepmimic(path).n_frames == 4
            continue
        with pytest.raises(ValueError) as ei:
            mj.read_deepmimic(path)
        msg = str(ei.value)
        assert str(path) in msg and frag in msg, msg
        if line is not None:
            assert f"{path}:{line}:" in msg, msg
        else:
            assert f"{path}:" in msg and msg.split(":")[1].strip().isdigit(), msg
    with pytest.raises(ValueError, match="cannot read"):
        mj.read_deepmimic(tmp_path / "absent.txt")


def test_read_motion_dispatch(tmp_path, cmu_files):
    assert mj.read_motion("example:walk").n_frames == 39
    assert mj.read_motion(cmu_files[0]).skeleton.n_joints == 43
    renamed = tmp_path / "clip.motion"
    renamed.write_text(Path(cmu_files[0]).read_text())
    assert mj.read_motion(renamed).n_frames == mj.read_bvh(cmu_files[0]).n_frames
    other = tmp_path / "x.csv"
    other.write_text("a,b,c\n")
    with pytest.raises(ValueError, match="unknown motion format"):
        mj.read_motion(other)
    with pytest.raises(ValueError, match="no such file"):
        mj.read_motion(tmp_path / "absent.bvh")


# --------------------------------------------------------------------------------------------
# hostile numbers (issue 57): a ValueError naming the file and the line, never an
# OverflowError, a traceback or a NaN passed on
# --------------------------------------------------------------------------------------------
def _frame() -> list[float]:
    f = [0.0333] + [0.0, 0.85, 0.0] + [1.0, 0.0, 0.0, 0.0] * 2
    f += [1.0, 0, 0, 0] * 2 + [0.3] + [1.0, 0, 0, 0] * 2 + [0.2]
    f += [1.0, 0, 0, 0] + [0.3] + [1.0, 0, 0, 0] * 2 + [0.2]
    return f


def _with_token(token: str, k: int, col: int) -> str:
    """Four frames, one per line from line 5, value ``col`` of frame ``k`` written as
    ``token`` (``k = -1``: the value of "Loop", line 2)."""
    frames = [_frame() for _ in range(4)]
    if k >= 0:
        frames[k][col] = "@@"  # type: ignore[call-overload]
        return _frames_text(frames).replace('"@@"', token)
    return _frames_text(frames).replace('"wrap"', token)


HOSTILE_JSON_NUMBERS = [
    # (token, message fragment after "FILE:LINE: PATH: ")
    ("9" * 401, "a 401-digit integer is too large for a float"),
    ("-" + "1" * 401, "a 401-digit integer is too large for a float"),
    ("9" * 5000, "a 5000-digit integer is too large for a float"),  # beyond Python's int limit
    ("1e400", "the number '1e400' is too large for a float"),  # json.loads reads inf
    ("-1.5E+400", "the number '-1.5E+400' is too large for a float"),
    ("NaN", "non-finite value NaN"),
    ("Infinity", "non-finite value Infinity"),
    ("-Infinity", "non-finite value -Infinity"),
    ("nan", "invalid JSON: 'nan' is not a JSON number"),
    ("NAN", "invalid JSON: 'NAN' is not a JSON number"),
    ("inf", "invalid JSON: 'inf' is not a JSON number"),
    ("-INF", "invalid JSON: '-INF' is not a JSON number"),
    ("-infinity", "invalid JSON: '-infinity' is not a JSON number"),
]


@pytest.mark.parametrize(("token", "frag"), HOSTILE_JSON_NUMBERS)
@pytest.mark.parametrize(
    ("k", "col", "path"),
    [(0, 0, "Frames[0][0]"), (2, 7, "Frames[2][7]"), (3, 43, "Frames[3][43]"), (-1, 0, "Loop")],
    ids=["duration", "quaternion", "last", "loop"],
)
def test_hostile_numbers_name_the_file_and_line(tmp_path, token, frag, k, col, path):
    p = tmp_path / "hostile.txt"
    p.write_text(_with_token(token, k, col))
    line = 2 if k < 0 else 5 + k
    with pytest.raises(ValueError) as ei:
        mj.read_deepmimic(p)
    msg = str(ei.value)
    assert msg.startswith(f"{p}:{line}: "), msg
    assert frag in msg, msg
    if "invalid JSON" not in frag:
        assert f"{p}:{line}: {path}: " in msg, msg
    assert len(msg) < 300, msg  # the 5000 digits are not echoed


def test_denormals_and_negative_zero_are_numbers(tmp_path):
    """A denormal (4e-320) is a finite float: read as its value; -0.0 reads as zero."""
    p = tmp_path / "ok.txt"
    good = mj.read_deepmimic(_write(tmp_path / "good.txt", _with_token("0.0", 1, 1)))
    for token, value in [("4e-320", 4e-320), ("-0.0", -0.0), ("-0", 0.0), ("1e-400", 0.0)]:
        p.write_text(_with_token(token, 1, 1))  # the root x of frame 1
        m = mj.read_deepmimic(p)
        x = np.asarray(m.root_positions)[1, 0]
        assert x == value and np.signbit(x) == np.signbit(value), (token, x)
        np.testing.assert_array_equal(np.asarray(m.rotations), np.asarray(good.rotations))
    p.write_text(_with_token("4e-320", 3, 0))  # the last keyframe's duration (unused)
    assert mj.read_deepmimic(p).n_frames == 4
    p.write_text(_with_token("-0.0", 1, 0))  # a duration must be positive
    with pytest.raises(ValueError, match=rf"{p}:6: inconsistent frame time: frame 1 lasts -0 s"):
        mj.read_deepmimic(p)


def _write(p: Path, text: str) -> Path:
    p.write_text(text)
    return p


@pytest.mark.parametrize("token", ["9" * 401, "1e400", "NaN", "-Infinity", "inf"])
def test_mtex_info_on_hostile_numbers_is_one_error_line(tmp_path, capsys, token):
    from mtex_jax.cli import main

    p = _write(tmp_path / "clip.txt", _with_token(token, 2, 7))
    code = main(["info", str(p)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith(f"mtex: error: {p}:7: "), err
    assert "Traceback" not in err and "internal error" not in err, err
