"""BVH reading and writing, checked against an independent NumPy/SciPy forward kinematics."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from scipy.spatial.transform import Rotation

import mtex_jax as mj

AXES = "XYZ"
#: a small valid BVH file: a hip and a knee, three frames
_GOOD = (
    "HIERARCHY\nROOT hip\n{\n  OFFSET 0 0 0\n"
    "  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n"
    "  JOINT knee\n  {\n    OFFSET 0 -1 0\n    CHANNELS 3 Zrotation Xrotation Yrotation\n"
    "    End Site\n    {\n      OFFSET 0 -1 0\n    }\n  }\n}\n"
    "MOTION\nFrames: 3\nFrame Time: 0.1\n"
    "0 1 0 0 0 0 10 0 0\n0 1 0 0 0 0 20 0 0\n0 1 0 0 0 0 30 0 0\n"
)


# ---------------------------------------------------------------------------------------------
# An independent reference: parse the frame table with NumPy, rotate with SciPy matrices.
# ---------------------------------------------------------------------------------------------
def reference_fk(sk: mj.Skeleton, table: np.ndarray) -> np.ndarray:
    """World joint positions from a raw (T, n_channels) BVH table, with SciPy rotations."""
    t = table.shape[0]
    j = sk.n_joints
    world_r = np.zeros((t, j, 3, 3))
    world_p = np.zeros((t, j, 3))
    col = 0
    for ji in range(j):
        trans = np.tile(np.asarray(sk.offsets[ji], float), (t, 1))
        rot = np.tile(np.eye(3), (t, 1, 1))
        for c in sk.channels[ji]:
            v = table[:, col]
            col += 1
            if c.endswith("position"):
                trans[:, AXES.index(c[0])] = v
            else:
                # compose intrinsically, one elementary rotation at a time
                rot = rot @ Rotation.from_euler(c[0].lower(), v[:, None], degrees=True).as_matrix()
        p = sk.parents[ji]
        if p < 0:
            world_r[:, ji] = rot
            world_p[:, ji] = trans
        else:
            world_r[:, ji] = world_r[:, p] @ rot
            world_p[:, ji] = world_p[:, p] + np.einsum("tij,tj->ti", world_r[:, p], trans)
    return world_p


def frame_table(path: Path) -> np.ndarray:
    lines = path.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.strip() == "MOTION")
    return np.loadtxt(lines[k + 3 :], ndmin=2)


def positions(m: mj.Motion) -> np.ndarray:
    return np.asarray(mj.forward_kinematics(m, end_sites=True))


def positions_pair(
    a: mj.Motion, b: mj.Motion, pad_to: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """FK of two clips on one skeleton in one call (one compilation instead of two; padding
    to a fixed number of frames compiles once for clips of different lengths)."""
    assert b.skeleton == a.skeleton and a.n_frames == b.n_frames
    parts = [a, b]
    if pad_to is not None:
        parts.append(a[np.zeros(pad_to - 2 * a.n_frames, dtype=np.int64)])
    p = positions(mj.motion.concatenate_motions(parts))
    return p[: a.n_frames], p[a.n_frames : 2 * a.n_frames]


# ---------------------------------------------------------------------------------------------
def test_reads_all_cmu_clips(cmu_files):
    """Every CMU clip reads with the expected frames, rate and skeleton (the reading speed is
    a benchmark's business, not a test's: a loaded machine made this a flaky timing test)."""
    motions = [mj.read_bvh(f) for f in cmu_files]
    frames = sum(m.n_frames for m in motions)
    assert 27_000 < frames < 28_000
    assert all(m.fps == 120.0 for m in motions)
    assert all(m.skeleton.n_joints == 43 for m in motions)


def test_cmu_fk_matches_scipy_reference(cmu_files):
    for f in cmu_files[:3]:
        m = mj.read_bvh(f)
        ref = reference_fk(m.skeleton, frame_table(f))
        ours = np.asarray(mj.forward_kinematics(m))
        np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-9 * m.skeleton.size)


def test_cmu_round_trip_every_clip(cmu_motions, tmp_path):
    for i, m in enumerate(cmu_motions):
        out = tmp_path / f"clip{i}.bvh"
        mj.write_bvh(out, m)
        m2 = mj.read_bvh(out)
        assert m2.skeleton == m.skeleton
        assert m2.fps == m.fps and m2.n_frames == m.n_frames
        p1, p2 = positions_pair(m, m2, pad_to=6000)
        err = np.max(np.abs(p2 - p1)) / m.skeleton.size
        assert err < 1e-6, f"clip {i}: relative round-trip error {err:.2e}"


# ---------------------------------------------------------------------------------------------
# Synthetic skeletons with random channel sets and rotation orders per joint.
# ---------------------------------------------------------------------------------------------
@st.composite
def random_bvh(draw):
    n = draw(st.integers(1, 7))
    parents = [-1] + [draw(st.integers(0, i - 1)) for i in range(1, n)]
    # make the order depth-first, as BVH files are
    children: dict[int, list[int]] = {i: [] for i in range(n)}
    for i, p in enumerate(parents[1:], start=1):
        children[p].append(i)
    order, stack = [], [0]
    while stack:
        i = stack.pop()
        order.append(i)
        stack.extend(reversed(children[i]))
    remap = {old: new for new, old in enumerate(order)}
    parents = [-1 if parents[o] < 0 else remap[parents[o]] for o in order]
    floats = st.floats(-1.0, 1.0, allow_nan=False).map(lambda x: round(x, 6))
    offsets = [tuple(draw(floats) for _ in range(3)) for _ in range(n)]
    channels = []
    for i in range(n):
        rot = [f"{a}rotation" for a in draw(st.permutations(AXES))]
        kind = draw(st.sampled_from(["rot3", "rot3", "rot2", "rot1", "six"] if i else ["six"]))
        if kind == "rot2":
            rot = rot[:2]
        elif kind == "rot1":
            rot = rot[:1]
        chs = list(rot)
        if kind == "six":
            chs = draw(st.permutations([f"{a}position" for a in AXES] + rot))
        channels.append(tuple(chs))
    end_sites = [(i, (0.0, 0.1, 0.0)) for i in range(n) if not children[order[i]]]
    sk = mj.Skeleton(
        tuple(f"j{i}" for i in range(n)),
        tuple(parents),
        tuple(offsets),
        tuple(channels),
        tuple(end_sites),
    )
    t = draw(st.integers(1, 4))
    angle = st.floats(-180.0, 180.0, allow_nan=False).map(lambda x: round(x, 6))
    rows = []
    for _ in range(t):
        row = []
        for chs in channels:
            for c in chs:
                row.append(draw(floats) if c.endswith("position") else draw(angle))
        rows.append(row)
    return sk, np.asarray(rows, dtype=float).reshape(t, sk.n_channels)


def bvh_text(sk: mj.Skeleton, table: np.ndarray) -> str:
    """Write BVH text independently of the library's writer."""
    kids: dict[int, list[int]] = {i: [] for i in range(sk.n_joints)}
    for i, p in enumerate(sk.parents[1:], start=1):
        kids[p].append(i)
    ends = {p: o for p, o in sk.end_sites}
    lines = ["HIERARCHY"]

    def emit(i: int, ind: str) -> None:
        lines.append(f"{ind}{'ROOT' if i == 0 else 'JOINT'} {sk.names[i]}")
        lines.append(ind + "{")
        lines.append(f"{ind}  OFFSET {' '.join(repr(x) for x in sk.offsets[i])}")
        lines.append(f"{ind}  CHANNELS {len(sk.channels[i])} {' '.join(sk.channels[i])}")
        for k in kids[i]:
            emit(k, ind + "  ")
        if i in ends:
            lines.extend(
                [f"{ind}  End Site", f"{ind}  {{", f"{ind}    OFFSET 0 0.1 0", f"{ind}  }}"]
            )
        lines.append(ind + "}")

    emit(0, "")
    lines += ["MOTION", f"Frames: {table.shape[0]}", "Frame Time: 0.0333333"]
    lines += [" ".join(repr(float(v)) for v in row) for row in table]
    return "\n".join(lines) + "\n"


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(random_bvh())
def test_random_skeletons_fk_and_round_trip(tmp_path_factory, case):
    sk, table = case
    d = tmp_path_factory.mktemp("bvh")
    src = d / "in.bvh"
    src.write_text(bvh_text(sk, table))
    m = mj.read_bvh(src)
    assert m.skeleton.channels == sk.channels
    assert m.skeleton.parents == sk.parents
    out = d / "out.bvh"
    mj.write_bvh(out, m)
    m2 = mj.read_bvh(out)
    assert m2.skeleton == m.skeleton
    p1, p2 = positions_pair(m, m2)
    ref = reference_fk(sk, table)
    scale = max(sk.size, 1.0)
    np.testing.assert_allclose(p1[:, : sk.n_joints], ref, rtol=0, atol=1e-9 * scale)
    err = np.max(np.abs(p2 - p1)) / scale
    assert err < 1e-6


def test_reader_rejects_bad_files(tmp_path):
    good = _GOOD
    p = tmp_path / "good.bvh"
    p.write_text(good)
    m = mj.read_bvh(p)
    assert m.n_frames == 3 and m.fps == 10.0
    lines = good.splitlines()

    def variant(name: str, new_lines: list[str]) -> Path:
        q = tmp_path / f"{name}.bvh"
        q.write_text("\n".join(new_lines) + "\n")
        return q

    cases = {
        # name: (lines, expected 1-based line number, message fragment)
        "truncated": (lines[:-2], 19, "truncated"),
        "cut_mid_line": ([*lines[:-1], "0 1 0 0"], 21, "has 4 values"),
        "wrong_count": ([*lines[:19], "0 1 0 0 0 0 20 0", lines[20]], 20, "has 8 values"),
        "non_numeric": ([*lines[:19], "0 1 0 0 0 0 2x0 0 0", lines[20]], 20, "non-numeric"),
        "nan_value": ([*lines[:19], "0 1 0 0 0 0 nan 0 0", lines[20]], 20, "non-finite"),
        "unknown_keyword": ([*lines[:3], "  OFFSETT 0 0 0", *lines[4:]], 4, "unknown keyword"),
        "unknown_channel": (
            [*lines[:8], "    CHANNELS 3 Zrotation Qrotation Yrotation", *lines[9:]],
            9,
            "unknown channel",
        ),
        "bad_channel_count": ([*lines[:8], "    CHANNELS 2 Zrotation", *lines[9:]], 10, ""),
        "zero_frames": ([*lines[:16], "Frames: 0", "Frame Time: 0.1"], 17, "zero frames"),
        "bad_frame_time": ([*lines[:17], "Frame Time: 0", *lines[18:]], 18, "Frame Time"),
        "garbled_frame_time": ([*lines[:17], "Frame Time: abc", *lines[18:]], 18, "invalid"),
        "extra_frames": ([*lines, "0 1 0 0 0 0 30 0 0"], 22, "more frame lines"),
        "no_motion": (lines[:15], 15, "no MOTION"),
    }
    for name, (new, line, frag) in cases.items():
        q = variant(name, new)
        with pytest.raises(ValueError) as ei:
            mj.read_bvh(q)
        msg = str(ei.value)
        assert f"{q}:{line}:" in msg, f"{name}: {msg}"
        assert frag in msg, f"{name}: {msg}"
    with pytest.raises(ValueError, match=r"no such file|cannot read"):
        mj.read_bvh(tmp_path / "missing.bvh")


def test_write_preserves_channel_order_and_end_sites(tmp_path, cmu_files):
    m = mj.read_bvh(cmu_files[0])[:10]
    out = tmp_path / "x.bvh"
    mj.write_bvh(out, m)
    text = out.read_text()
    assert "CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation" in text
    assert text.count("End Site") == len(m.skeleton.end_sites)
    assert mj.read_bvh(out).skeleton == m.skeleton


def test_deepmimic_to_bvh_round_trip(tmp_path):
    m = mj.load_example("dance_a")
    out = tmp_path / "dance.bvh"
    mj.write_bvh(out, m)
    m2 = mj.read_bvh(out)
    assert m2.skeleton.names == m.skeleton.names
    assert m2.skeleton.channels == m.skeleton.channels  # knees/elbows are 1-channel hinges
    err = np.max(np.abs(positions(m2) - positions(m))) / m.skeleton.size
    assert err < 1e-6


# --------------------------------------------------------------------------------------------
# hostile numbers (issue 57): a ValueError naming the file and the line, never an
# OverflowError, a traceback or a NaN passed on
# --------------------------------------------------------------------------------------------
#: where a number goes: (1-based line, the line with the token as "@")
_PLACES = {
    "offset": (8, "    OFFSET 0 @ 0"),
    "channels": (9, "    CHANNELS @ Zrotation Xrotation Yrotation"),
    "frames": (17, "Frames: @"),
    "frame_time": (18, "Frame Time: @"),
    "frame_line": (20, "0 1 0 0 0 0 @ 0 0"),
}


def _bvh_with(tmp_path: Path, place: str, token: str) -> Path:
    line, text = _PLACES[place]
    lines = [str(ln) for ln in _GOOD.splitlines()]
    lines[line - 1] = text.replace("@", token)
    p = tmp_path / f"{place}.bvh"
    p.write_text("\n".join(lines) + "\n")
    return p


HOSTILE_BVH_NUMBERS = [
    # (token, message fragment)
    ("9" * 401, "a 401-digit integer"),
    ("-" + "1" * 401, "a 401-digit integer"),
    ("9" * 5000, "a 5000-digit integer"),
    ("1e400", "the number '1e400'"),
    ("-1.5E+400", "the number '-1.5E+400'"),
    ("nan", "non-finite value 'nan'"),
    ("NaN", "non-finite value 'NaN'"),
    ("NAN", "non-finite value 'NAN'"),
    ("inf", "non-finite value 'inf'"),
    ("INF", "non-finite value 'INF'"),
    ("-Infinity", "non-finite value '-Infinity'"),
    ("+infinity", "non-finite value '+infinity'"),
]


@pytest.mark.parametrize(("token", "frag"), HOSTILE_BVH_NUMBERS)
@pytest.mark.parametrize("place", list(_PLACES))
def test_hostile_numbers_name_the_file_and_line(tmp_path, place, token, frag):
    p = _bvh_with(tmp_path, place, token)
    with pytest.raises(ValueError) as ei:
        mj.read_bvh(p)
    msg = str(ei.value)
    assert msg.startswith(f"{p}:{_PLACES[place][0]}: "), msg
    assert frag in msg, msg
    if "digit" in frag or "number" in frag:
        assert "is too large for a float" in msg, msg
    assert len(msg) < 300, msg  # the 5000 digits are not echoed
    with pytest.raises(ValueError, match=f"^{p}:{_PLACES[place][0]}: "):
        mj.read_motion(p)


def test_denormals_and_negative_zero_are_numbers(tmp_path):
    """A denormal (4e-320) is a finite float: read as its value, then checked like any value
    (an offset or an angle is fine; a frame count or a frame time is not); -0.0 is zero."""
    ref = mj.read_bvh(_bvh_with(tmp_path, "frame_line", "0"))
    for token, value in [("4e-320", 4e-320), ("-0.0", -0.0), ("1e-400", 0.0)]:
        m = mj.read_bvh(_bvh_with(tmp_path, "offset", token))
        y = m.skeleton.offsets[1][1]
        assert y == value and np.signbit(y) == np.signbit(value), (token, y)
        m = mj.read_bvh(_bvh_with(tmp_path, "frame_line", token))  # an angle of 4e-320 degrees
        q = np.asarray(m.rotations)  # a rotation by a denormal angle: denormal components
        np.testing.assert_allclose(q, np.asarray(ref.rotations), rtol=0, atol=1e-300)
    refusals = {
        ("channels", "4e-320"): (9, "invalid channel count"),
        ("frames", "4e-320"): (17, "invalid value '4e-320' for 'Frames:'"),
        ("frame_time", "4e-320"): (18, "frame time"),
        ("frames", "-0.0"): (17, "zero frames"),
        ("frame_time", "-0.0"): (18, "Frame Time must be positive"),
    }
    for (place, token), (line, frag) in refusals.items():
        p = _bvh_with(tmp_path, place, token)
        with pytest.raises(ValueError) as ei:
            mj.read_bvh(p)
        assert str(ei.value).startswith(f"{p}:{line}: ") and frag in str(ei.value), ei.value


@pytest.mark.parametrize("token", ["9" * 401, "1e400", "NaN", "-inf"])
@pytest.mark.parametrize("place", ["offset", "frames", "frame_line"])
def test_mtex_info_on_hostile_numbers_is_one_error_line(tmp_path, capsys, place, token):
    from mtex_jax.cli import main

    p = _bvh_with(tmp_path, place, token)
    code = main(["info", str(p)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1, err
    assert err.startswith(f"mtex: error: {p}:{_PLACES[place][0]}: "), err
    assert "Traceback" not in err and "internal error" not in err, err
