"""``mtex demo`` on the shipped salsa clips, shortened: every output file is checked."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

import mtex_jax as mj
from mtex_jax.cli import main


def test_demo_pipeline_writes_every_file(tmp_path, capsys):
    out = tmp_path / "out"
    args = ["demo", "--out", str(out), "--train-clips", "2", "--held-clips", "1"]
    assert main([*args, "--seconds", "3", "--max-iter", "2", "--seed", "1"]) == 0
    text = capsys.readouterr().out
    for line in ("EM iteration  0", "segments per texton", "quality of the new salsa", "done in"):
        assert line in text, line
    for step in (
        "learn (EM + selection)",
        "texton gallery",
        "synthesise",
        "GIF beside a real clip",
    ):
        assert f"[{step}: " in text and step in text.split("time per step:")[1]

    tex = mj.load_texture(out / "texture.npz")
    salsa = mj.io.load_salsa("60_01")
    assert tex.feature_map is not None and tex.feature_map.fps == 60.0
    assert tex.feature_map.skeleton.same_structure(salsa.skeleton)
    segs = np.asarray(tex.segments)
    assert set(segs[:, 0].tolist()) == {0, 1}  # the two training clips

    dance = mj.read_bvh(out / "new_dance.bvh")
    assert dance.n_frames == 180 and dance.fps == 60.0
    assert dance.skeleton.same_structure(salsa.skeleton)
    assert np.isfinite(np.asarray(mj.forward_kinematics(dance))).all()

    with Image.open(out / "new_dance.gif") as im:
        assert im.format == "GIF" and im.n_frames == 45  # 2.98 s at 15 frames per second
        assert im.size[0] == 2 * im.size[1]  # two square panels side by side
    for png in ("timeline.png", "new_dance.png", "textons.png"):
        with Image.open(out / png) as im:
            assert im.format == "PNG" and im.size[0] > 100

    report = json.loads((out / "quality.json").read_text())
    assert report["training"] == ["60_01", "60_02"] and report["held_out"] == ["60_12"]
    assert report["texture"]["textons"] == tex.n_textons
    for row in ("synthesised", "real (held out)"):
        for key in ("speed_ratio", "jerk_ratio", "skating_median", "penetration_max"):
            assert isinstance(report["motion"][row][key], float), (row, key)
    for key in ("boundary_share_above_p99", "novelty_median", "copy_fraction"):
        assert key in report["motion"]["synthesised"]
    assert set(report["step_seconds"]) >= {"learn (EM + selection)", "quality report"}
    # a 3 s dance is one 2 s window, too few for 5 folds: the report says so (the full demo's
    # 20 s dance gives ten)
    assert "the generated clips give 1 window" in report["two_sample"]["not_run"]
    assert "two-sample test not run" in text

    # the vocabulary of the demo's texture: printed, and drawn as a gallery of samples
    assert main(["textons", str(out / "texture.npz"), "-o", str(tmp_path / "voc.png")]) == 0
    text = capsys.readouterr().out
    assert f"{tex.n_textons} textons; largest" in text and "successors" in text
    with Image.open(tmp_path / "voc.png") as im:
        assert im.format == "PNG"


def test_demo_refuses_bad_options(capsys):
    for bad in (["--seconds", "0"], ["--seconds", "1e9"], ["--train-clips", "0"]):
        assert main(["demo", *bad]) == 2
        err = capsys.readouterr().err
        assert err.startswith("mtex: error: --") and err.count("\n") == 1, err
    # the validated option types of every command (issue 43): refused by the parser
    for bad, why in (
        (["--seconds", "inf"], "finite"),
        (["--seed", str(2**70)], "seed must be in"),
        (["--max-iter", "1.5"], "expected an integer"),
        (["--held-clips", "1e3"], "expected an integer"),
    ):
        assert main(["demo", *bad]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"mtex: error: mtex demo: argument {bad[0]}: ") and why in err, err
    assert main(["demo", "--max-iter", "0"]) == 2
    assert "--max-iter must be at least 1" in capsys.readouterr().err


def test_gif_pair_same_scale_loops_the_shorter_clip(tmp_path):
    salsa = mj.io.load_salsa("60_10")[:90]  # 1.5 s at 60 Hz
    walk = mj.io.load_example("walk")  # 1.27 s at 30 Hz, another skeleton: loops
    gif = mj.viz.render_gif_pair(salsa, walk, tmp_path / "pair.gif", fps=10, dpi=40)
    with Image.open(gif) as im:
        assert im.n_frames == 15 and im.size == (320, 160)
    with pytest.raises(ValueError, match="at most"):
        mj.viz.render_gif_pair(salsa, walk, tmp_path / "x.gif", fps=40)
    with pytest.raises(ValueError, match="unknown joint"):
        mj.viz.render_gif_pair(salsa, walk, tmp_path / "x.gif", trajectories=["lFoot"])


def test_texton_gallery_shows_training_segments_or_samples(tmp_path):
    """The gallery's instances are the texton's own training segments (the clips cut where the
    segmentation says), or samples of its dynamics from its key poses without the clips."""
    clips = [mj.io.load_salsa(n).resample(60.0) for n in ("60_01", "60_02")]
    tex = mj.learn(clips, mj.LearnConfig(tmin=60, tmax=180, max_iter=2))
    inst, what = mj.viz.texton_instances(tex, clips, per_texton=2)
    assert what == "training segments" and len(inst) == tex.n_textons
    segs = np.asarray(tex.segments)
    for i, row in enumerate(inst):
        mine = segs[segs[:, 3] == i]
        assert 1 <= len(row) <= 2
        s, b, n, _ = mine[0]
        np.testing.assert_array_equal(row[0].rotations, clips[s][b : b + n].rotations)
    samples, what = mj.viz.texton_instances(tex, None, per_texton=1)
    assert what == "samples" and [len(r) for r in samples] == [1] * tex.n_textons
    assert all(np.isfinite(np.asarray(mj.forward_kinematics(r[0]))).all() for r in samples)
    png = mj.viz.render_texton_gallery(tex, tmp_path / "g.png", clips, per_texton=2, dpi=40)
    with Image.open(png) as im:
        assert im.format == "PNG" and im.size[1] > 40 * tex.n_textons
    with pytest.raises(ValueError, match="training clips"):
        mj.viz.texton_instances(tex, clips[:1])
