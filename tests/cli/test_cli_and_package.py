"""The `mtex` command line and the installed package (wheel contents, embedded data)."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import mtex_jax as mj
from mtex_jax.cli import main

REPO = Path(__file__).resolve().parents[2]


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mtex_jax", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=600,
    )


def test_info_on_example_and_bvh(capsys, cmu_files):
    assert main(["info", "example:dance_a"]) == 0
    out = capsys.readouterr().out
    assert "frames:    98" in out and "fps:       60" in out and "joints:    13" in out
    assert main(["info", str(cmu_files[0]), "--joints"]) == 0
    out = capsys.readouterr().out
    assert "frames:    2242" in out and "hip" in out and "rot ZYX pos XYZ" in out


def test_errors_are_one_line_without_traceback(tmp_path):
    r = run_cli("info", str(tmp_path / "nope.bvh"))
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "Traceback" not in r.stderr
    assert "no such file" in r.stderr
    bad = tmp_path / "bad.bvh"
    bad.write_text("HIERARCHY\nROOT a\n{\n OFFSET 0 0 0\n CHANNELS 1 Wrotation\n}\nMOTION\n")
    r = run_cli("render", str(bad), "-o", str(tmp_path / "x.gif"))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert f"{bad}:5:" in r.stderr and "unknown channel" in r.stderr
    r = run_cli("info", "example:tango")
    assert r.returncode == 2 and "unknown example" in r.stderr


def test_help_texts(capsys):
    # the installed entry point once, as a subprocess; every command's parser in-process
    r = run_cli("--help")
    assert r.returncode == 0 and "usage: mtex" in r.stdout
    for cmd in [
        "info",
        "render",
        "demo",
        "examples",
        "learn",
        "segment",
        "synth",
        "choreograph",
        "mirror",
    ]:
        assert main([cmd, "--help"]) == 0, cmd
        assert f"usage: mtex {cmd}" in capsys.readouterr().out, cmd


def test_render_command_writes_gif_and_png(tmp_path, capsys):
    gif = tmp_path / "walk.gif"
    assert main(["render", "example:walk", "-o", str(gif), "--trajectories", "left_ankle"]) == 0
    with Image.open(gif) as im:
        assert im.n_frames > 10
    png = tmp_path / "walk.png"
    assert main(["render", "example:walk", "-o", str(png)]) == 0
    with Image.open(png) as im:
        assert im.size[0] > im.size[1]


def test_mirror_command_writes_the_mirrored_clip(tmp_path, capsys):
    out = tmp_path / "walk_mirrored.bvh"
    assert main(["mirror", "example:walk", "-o", str(out)]) == 0
    assert "mirrored through the z axis (5 left-right joint pairs swapped)" in (
        capsys.readouterr().out
    )
    got = mj.motion.joint_positions(mj.io.read_motion(str(out)))[0]
    want = mj.motion.joint_positions(mj.io.load_example("walk").mirror())[0]
    np.testing.assert_allclose(got, want, atol=1e-5)  # the BVH's six decimals
    # one verdict on a wrong suffix or the up axis, exit status 2, nothing written
    for bad in (["-o", str(tmp_path / "w.png")], ["-o", str(tmp_path / "w.bvh"), "--axis", "y"]):
        assert main(["mirror", "example:walk", *bad]) == 2
        assert "mtex: error:" in capsys.readouterr().err
    assert not (tmp_path / "w.bvh").exists() and not (tmp_path / "w.png").exists()


@pytest.mark.slow  # the default run's budget (about 15 min); CI runs it after
def test_learn_synth_and_choreograph_on_the_embedded_clips(tmp_path):
    # the settings of the former DeepMimic demo (mtex demo now runs on the salsa clips,
    # tests/cli/test_demo.py)
    out = tmp_path / "out"
    out.mkdir()
    clips = [f"example:{n}" for n in mj.io.example_names()]
    r = run_cli(
        *("learn", *clips, "-o", str(out / "texture.npz"), "--fps", "30", "--tmin", "0.6"),
        *("--tmax", "1.8", "--state-dim", "6", "--threshold", "0.3", "--max-iter", "10"),
        *("--observation", "residual", "--init", "greedy"),
    )
    assert r.returncode == 0, r.stderr
    tex = mj.load_texture(out / "texture.npz")
    assert tex.feature_map is not None and tex.feature_map.skeleton == mj.io.HUMANOID3D
    assert "textons:" in r.stdout and "objective per EM iteration" in r.stdout

    # synth and choreograph on that model
    model = str(out / "texture.npz")
    r = run_cli("synth", model, "-o", str(tmp_path / "s.bvh"), "--frames", "90", "--seed", "3")
    assert r.returncode == 0, r.stderr[-2000:]
    assert mj.read_bvh(tmp_path / "s.bvh").n_frames == 90 and "texton path" in r.stdout
    r = run_cli(
        "choreograph",
        model,
        "--start",
        "example:walk:5",
        "--end",
        "example:dance_b:20",
        "-o",
        str(tmp_path / "c.bvh"),
        "--frames",
        "120",
        "--gif",
        str(tmp_path / "c.gif"),
    )
    assert r.returncode == 0, r.stderr[-2000:]
    c = mj.read_bvh(tmp_path / "c.bvh")
    assert c.n_frames == 120 and (tmp_path / "c.gif").is_file()
    # the motion starts at the requested frame of the walk (BVH precision: 6 decimals)
    walk = mj.load_example("walk").resample(30.0)
    qc, qw = np.asarray(c.rotations)[:2, 1:], np.asarray(walk.rotations)[5:7, 1:]
    assert np.abs(np.sum(qc * qw, axis=-1)).min() > 1 - 1e-8  # same joint rotations (±q)
    for bad, msg in (
        ("example:walk", "FRAME must be an integer"),
        ("example:walk:9999", "out of range"),
        ("walk5", "CLIP:FRAME"),
    ):
        r = run_cli("choreograph", model, "--start", bad, "--end", "example:walk:1", "-o", "x.bvh")
        assert r.returncode == 2 and msg in r.stderr and "Traceback" not in r.stderr
    r = run_cli("synth", model, "-o", str(tmp_path / "s.gif"))
    assert r.returncode == 2 and ".bvh" in r.stderr


@pytest.mark.slow  # the default run's budget (about 15 min); CI runs it after
def test_learn_and_segment_commands(tmp_path, cmu_files):
    model = tmp_path / "salsa.npz"
    r = run_cli(
        "learn",
        str(cmu_files[0]),
        str(cmu_files[1]),
        "-o",
        str(model),
        "--fps",
        "30",
        "--tmin",
        "1",
        "--tmax",
        "3",
        "--state-dim",
        "8",
        "--max-iter",
        "3",
        "--min-segments",
        "2",
        "--innovations",
        "residuals",
        "--observation",
        "residual",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "textons:" in r.stdout and "[mtex learn] iter" in r.stdout
    assert "blocks of the" in r.stdout  # the summary names the residual bank
    learned = mj.load_texture(model)
    assert learned.config.min_segments == 2
    assert learned.config.innovations == "residuals" and learned.residuals is not None
    assert learned.textons.dof is None and learned.config.dof is None  # k = 8 < D: Gaussian
    assert np.bincount(np.asarray(learned.key_pose_labels)).min() >= 2
    png = tmp_path / "timeline.png"
    r = run_cli("segment", str(model), str(cmu_files[1]), "-o", str(png))
    assert r.returncode == 0, r.stderr[-2000:]
    assert "segments" in r.stdout and png.is_file()
    with Image.open(png) as im:
        assert im.size[0] > 500
    r = run_cli("learn", str(cmu_files[0]), "-o", str(model), "--tmin", "0")
    assert r.returncode == 2 and "tmin" in r.stderr and "Traceback" not in r.stderr
    r = run_cli("learn", str(cmu_files[0]), "-o", str(model), "--min-segments", "0")
    assert r.returncode == 2 and "min_segments" in r.stderr and "Traceback" not in r.stderr
    r = run_cli("learn", str(cmu_files[0]), "-o", str(model), "--innovations", "bootstrap")
    assert r.returncode == 2 and "--innovations" in r.stderr and "Traceback" not in r.stderr
    for bad in ("0", "-2", "nan", "four"):
        r = run_cli("learn", str(cmu_files[0]), "-o", str(model), "--dof", bad)
        assert r.returncode == 2 and "--dof" in r.stderr and "Traceback" not in r.stderr
    r = run_cli("segment", str(tmp_path / "absent.npz"), str(cmu_files[0]))
    assert r.returncode == 2 and "no such file" in r.stderr


def test_wheel_ships_data_and_works_outside_the_source_tree(tmp_path):
    """Build a wheel, unpack it elsewhere and load an example from there."""
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(tmp_path / "dist"),
            str(REPO),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    if r.returncode != 0 and "hatchling" in r.stderr:
        pytest.fail(f"building the wheel needs hatchling in the environment: {r.stderr[-500:]}")
    assert r.returncode == 0, r.stderr[-2000:]
    (wheel,) = list((tmp_path / "dist").glob("mtex_jax-*.whl"))
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        assert "mtex_jax/data/deepmimic/LICENSE-zlib.txt" in names
        assert "mtex_jax/py.typed" in names
        assert sum(n.startswith("mtex_jax/data/deepmimic/humanoid3d_") for n in names) == 15
        z.extractall(tmp_path / "site")
    code = (
        "import mtex_jax, sys; m = mtex_jax.load_example('dance_a');"
        "print(mtex_jax.__file__); print(m.n_frames)"
    )
    env = {**os.environ, "PYTHONPATH": str(tmp_path / "site")}
    r = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    lines = r.stdout.split()
    assert lines[0].startswith(str(tmp_path / "site")) and lines[1] == "98"


def test_a_state_dim_the_default_model_cannot_take_names_the_models_that_can(tmp_path, cmu_files):
    """``--state-dim 4`` with the default tied model: one line, exit 2, and how to mend it."""
    r = run_cli("learn", str(cmu_files[0]), "-o", str(tmp_path / "m.npz"), "--state-dim", "4")
    assert r.returncode == 2
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith("mtex: error: learn: observation='tied' has state_dim = D")
    assert "paper, residual" in line and "Traceback" not in r.stderr
