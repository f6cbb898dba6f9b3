"""``mtex evaluate`` on the embedded data and on CMU clips; its errors are one line, exit 2."""

from __future__ import annotations

import json

import pytest

import mtex_jax as mj
from mtex_jax.cli import main
from paper_settings import PAPER
from shared_textures import salsa30_texture


@pytest.fixture(scope="module")
def cmu_model(tmp_path_factory, cmu_dir):
    """A paper model learned from the first three CMU clips at 30 Hz (shared with other test
    modules: learned once per process), in a model file."""
    path = tmp_path_factory.mktemp("eval") / "salsa.npz"
    salsa30_texture(cmu_dir).save(path)
    return path


@pytest.mark.slow  # the default run's budget (about 15 min); CI runs it after
def test_evaluate_on_cmu_clips(cmu_model, cmu_files, tmp_path, capsys):
    out = tmp_path / "report.json"
    code = main(
        [
            "evaluate",
            str(cmu_model),
            "--test",
            str(cmu_files[12]),
            str(cmu_files[13]),
            "--train",
            *map(str, cmu_files[:3]),
            "--synth",
            "2",
            "--seconds",
            "10",
            "-o",
            str(out),
        ]
    )
    text = capsys.readouterr().out
    assert code == 0, text
    rep = json.loads(out.read_text())
    assert set(rep["density"]) >= {
        "motion texture (marginal)",
        "motion texture (best path)",
        "AR(2)",
        "constant velocity",
        "hold last frame",
    }
    d = rep["density"]
    assert d["motion texture (marginal)"]["loglik_per_frame"] >= (
        d["motion texture (best path)"]["loglik_per_frame"] - 1e-9
    )
    syn, real = rep["motion"]["synthesised"], rep["motion"]["real (held out)"]
    for k in ("speed_ratio", "jerk_ratio", "skating_median", "penetration_max", "novelty_median"):
        assert syn[k] is not None and syn[k] >= 0, k
    assert real["speed_ratio"] == 1.0  # the floor row
    assert (tmp_path / "report.png").stat().st_size > 10_000
    assert "AR(2)" in text and "skating" in text
    two = rep["two_sample"]  # 10 synthesised windows of 2 s against the held-out clips'
    assert 0.0 <= two["auc"] <= 1.0 and len(two["fold_aucs"]) == 5 and two["n_generated"] == 10
    assert two["reference_auc"] is not None and "training against held out" in text


@pytest.mark.slow  # the default run's budget (about 15 min); CI runs it after
def test_evaluate_on_embedded_data(tmp_path, capsys):
    clips = [mj.load_example(n) for n in ("dance_a", "dance_b", "walk", "run")]
    cfg = mj.LearnConfig(
        tmin=12, tmax=36, state_dim=5, fps=30.0, threshold=0.5, max_iter=2, **PAPER
    )
    model = tmp_path / "tex.npz"
    mj.learn(clips, cfg).save(model)
    code = main(
        [
            "evaluate",
            str(model),
            "--test",
            "example:dance_b",
            "--synth",
            "1",
            "--seconds",
            "3",
            "--plot",
            str(tmp_path / "d.png"),
        ]
    )
    text = capsys.readouterr().out
    assert code == 0, text
    assert "no --train clips" in text
    assert "not run: two_sample_auc: the real clips give 1 window of 2.0 s" in text  # 77 frames
    assert (tmp_path / "d.png").exists()


@pytest.mark.parametrize(
    "case",
    ["text_model", "missing_clip", "bad_output", "bad_synth", "short_clip"],
)
def test_evaluate_errors_are_one_line(case, cmu_model, cmu_files, tmp_path, capsys):
    model, test = str(cmu_model), str(cmu_files[12])
    extra: list[str] = []
    if case == "text_model":
        bad = tmp_path / "model.npz"
        bad.write_text("not a model\n")
        model = str(bad)
    elif case == "missing_clip":
        test = str(tmp_path / "nope.bvh")
    elif case == "bad_output":
        extra = ["-o", str(tmp_path / "r.txt")]
    elif case == "bad_synth":
        extra = ["--synth", "0"]
    elif case == "short_clip":
        short = tmp_path / "short.bvh"
        mj.write_bvh(short, mj.read_bvh(cmu_files[12])[:20])
        test = str(short)
    code = main(["evaluate", model, "--test", test, *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("mtex: error:"), err
