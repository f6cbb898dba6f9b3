"""The shipped salsa data (mtex_jax/data/salsa) against the CMU BVH files it was made from."""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

import mtex_jax as mj
from mtex_jax.io import _salsa

DATA = Path(mj.__file__).resolve().parent / "data" / "salsa"
REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow  # the default run's budget (about 15 min); CI runs it after
def test_every_clip_equals_the_bvh_resampled_to_60_hz(cmu_files):
    names = mj.io.salsa_names()
    assert names == [f.stem for f in cmu_files]
    clips = mj.io.load_salsa()
    assert len(clips) == 14
    worst_deg = worst_mm = 0.0
    for f, got in zip(cmu_files, clips, strict=True):
        ref = mj.read_bvh(f).resample(60.0)
        assert got.fps == 60.0 and got.n_frames == ref.n_frames, f.stem
        assert got.skeleton == ref.skeleton and got.local_positions is None
        a, b = np.asarray(ref.rotations), np.asarray(got.rotations)
        dot = np.clip(np.abs(np.sum(a * b, axis=-1)), 0.0, 1.0)
        deg = float(np.degrees(2 * np.arccos(dot)).max())
        pa = np.asarray(mj.forward_kinematics(ref, end_sites=True))
        pb = np.asarray(mj.forward_kinematics(got, end_sites=True))
        mm = float(np.linalg.norm(pa - pb, axis=-1).max() * 1000)
        worst_deg, worst_mm = max(worst_deg, deg), max(worst_mm, mm)
        assert deg < 0.01 and mm < 0.1, (f.stem, deg, mm)
    assert worst_deg > 0 and worst_mm > 0  # quantised, not a copy
    # one clip by name, and through the example mechanism
    one = mj.io.load_salsa("60_12")
    same = mj.read_motion("example:salsa/60_12")
    np.testing.assert_array_equal(np.asarray(one.rotations), np.asarray(same.rotations))
    np.testing.assert_array_equal(np.asarray(one.root_positions), clips[10].root_positions)


def test_split_credit_size_and_errors():
    train, held = mj.io.salsa_split()
    assert held == ["60_12", "60_13", "60_14", "60_15"] and len(train) == 10
    assert not set(train) & set(held)
    credit = mj.io.salsa_credit()
    assert (
        "The data used in this project was obtained from mocap.cs.cmu.edu. The database was "
        "created\nwith funding from NSF EIA-0196217." in credit
    )
    assert (DATA / "salsa.npz").stat().st_size < 5_000_000
    with pytest.raises(ValueError, match="unknown salsa clip '60_08'"):
        mj.io.load_salsa("60_08")
    with pytest.raises(ValueError, match="salsa/NAME"):
        mj.read_motion("example:salsa60_01")


def _copy(tmp_path: Path) -> Path:
    folder = tmp_path / "salsa"
    shutil.copytree(DATA, folder)
    return folder


def test_damaged_data_gives_a_clear_error(tmp_path):
    folder = _copy(tmp_path)
    assert _salsa._load_pack(folder).names == mj.io.salsa_names()

    npz = folder / "salsa.npz"
    raw = bytearray(npz.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    npz.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"damaged.*checksum"):
        _salsa._load_pack(folder)

    folder = _copy(tmp_path / "b")
    (folder / "salsa.npz").write_bytes(b"")
    meta = json.loads((folder / "salsa.json").read_text())
    with pytest.raises(ValueError, match="damaged"):
        _salsa._load_pack(folder)

    # a consistent checksum but wrong content: shapes and values are checked too
    for change in ("frames", "values", "scale"):
        folder = _copy(tmp_path / change)
        with np.load(DATA / "salsa.npz") as z:
            arrays = {k: z[k] for k in z.files}
        m = dict(meta)
        if change == "frames":
            m["frames"] = [*meta["frames"][:-1], meta["frames"][-1] + 1]
        elif change == "values":
            arrays["values"] = arrays["values"].astype(np.int32)
        else:
            arrays["scale"] = arrays["scale"] * np.nan
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        m["sha256"] = hashlib.sha256(buf.getvalue()).hexdigest()
        (folder / "salsa.npz").write_bytes(buf.getvalue())
        (folder / "salsa.json").write_text(json.dumps(m))
        with pytest.raises(ValueError, match="damaged"):
            _salsa._load_pack(folder)

    folder = _copy(tmp_path / "json")
    (folder / "salsa.json").write_text("{")
    with pytest.raises(ValueError, match=r"damaged.*salsa\.json"):
        _salsa._load_pack(folder)


def test_wheel_ships_the_salsa_data(tmp_path):
    r = subprocess.run(
        [
            *(sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q"),
            *("-w", str(tmp_path / "dist"), str(REPO)),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    (wheel,) = list((tmp_path / "dist").glob("mtex_jax-*.whl"))
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        for f in ("salsa.npz", "salsa.json", "CREDIT.txt", "__init__.py"):
            assert f"mtex_jax/data/salsa/{f}" in names
        z.extractall(tmp_path / "site")
    assert wheel.stat().st_size < 5_000_000
    code = (
        "import mtex_jax as mj; m = mj.read_motion('example:salsa/60_15');"
        "print(mj.__file__); print(m.n_frames)"
    )
    env = {**os.environ, "PYTHONPATH": str(tmp_path / "site")}
    r = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr[-2000:]
    where, frames = r.stdout.split()
    assert where.startswith(str(tmp_path / "site")) and frames == "1070"


@pytest.mark.parametrize(
    ("token", "frag"),
    [
        ("9" * 401, "fps: a 401-digit integer is too large for a float"),
        ("1e400", "fps: the number '1e400' is too large for a float"),
        ("NaN", "fps: non-finite value NaN"),
        ("-Infinity", "fps: non-finite value -Infinity"),
        ("inf", "invalid JSON: 'inf' is not a JSON number"),
    ],
)
def test_hostile_numbers_in_salsa_json_name_the_line(tmp_path, token, frag):
    """A damaged salsa.json with a number no float holds, or NaN / Infinity: the damaged-data
    error, naming salsa.json and the line (issue 57), never an OverflowError."""
    folder = _copy(tmp_path)
    text = (folder / "salsa.json").read_text()
    assert '\n "fps": 60.0,\n' in text  # line 3
    (folder / "salsa.json").write_text(text.replace('"fps": 60.0', f'"fps": {token}', 1))
    with pytest.raises(ValueError, match="damaged") as ei:
        _salsa._load_pack(folder)
    assert f"salsa.json:3: {frag}" in str(ei.value), ei.value
