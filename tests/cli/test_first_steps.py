"""What a new user hit on a fresh clone (issue 57, item 5), each as the command a user types:
an example clip given where a model belongs, an output name that is not the format written,
and where a joint is at a frame (the position ``mtex edit --at`` takes). The edit's single
verdict and ``--by`` are in tests/edit/test_edit.py; the GIF's title and timing in
tests/viz/test_render.py."""

from __future__ import annotations

import numpy as np
import pytest

import mtex_jax as mj
from mtex_jax.cli import main
from shared_textures import dance_pair_texture


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("first_steps") / "tex.npz"
    dance_pair_texture().save(path)
    return str(path)


def _error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.startswith("mtex: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err and "internal error" not in err
    return err


def test_an_example_clip_given_as_the_model_is_named_as_a_clip(tmp_path, capsys):
    out = tmp_path / "s.bvh"
    assert main(["synth", "example:salsa/60_01", "-o", str(out)]) == 2
    err = _error(capsys)
    assert "example:salsa/60_01: example:NAME names a shipped motion clip, not a model file" in err
    assert "mtex learn example:salsa/60_01 -o model.npz" in err
    # a missing file is still "no such file", a motion file "not a model file"
    assert main(["synth", str(tmp_path / "gone.npz"), "-o", str(out)]) == 2
    assert "gone.npz: no such file" in _error(capsys)
    clip = tmp_path / "walk.bvh"
    mj.write_bvh(clip, mj.load_example("walk"))
    assert main(["synth", str(clip), "-o", str(out)]) == 2
    assert "not a model file" in _error(capsys)
    assert not out.exists()


@pytest.mark.parametrize(
    ("argv", "option", "want"),
    [
        (["learn", "example:walk", "-o", "{d}/tex.png"], "-o/--output", ".npz"),
        (["learn", "example:walk", "-o", "{d}/tex"], "-o/--output", ".npz"),
        (["synth", "{model}", "-o", "{d}/s.gif"], "-o/--output", ".bvh"),
        (["synth", "{model}", "-o", "{d}/s.bvh", "--gif", "{d}/s.png"], "--gif", ".gif"),
        (["render", "example:walk", "-o", "{d}/w.bvh"], "-o/--output", ".gif"),
        (["contacts", "example:walk", "-o", "{d}/c.json"], "-o/--output", ".npz"),
        (["textons", "{model}", "-o", "{d}/g.gif"], "-o/--output", ".png"),
        (["view", "example:walk", "-o", "{d}/v.png"], "-o/--output", ".html"),
        (
            ["evaluate", "{model}", "--test", "example:walk", "-o", "{d}/q.txt"],
            "-o/--output",
            ".json",
        ),
    ],
)
def test_an_output_named_for_another_format_is_refused(tmp_path, capsys, model, argv, option, want):
    """``mtex learn ... -o tex.png`` wrote a zip archive named .png: every output's name must
    end in the suffix of what is written, before any work, and nothing is written."""
    args = [a.format(d=tmp_path, model=model) for a in argv]
    assert main(args) == 2
    err = _error(capsys)
    assert f"{option} " in err and f"must end in {want}" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_the_suffix_is_matched_in_any_case(tmp_path, capsys):
    out = tmp_path / "WALK.GIF"
    assert main(["render", "example:walk", "-o", str(out)]) == 0
    assert out.is_file()


def test_info_gives_a_joints_world_position_at_a_frame(capsys):
    walk = mj.load_example("walk")
    j = walk.skeleton.names.index("right_elbow")
    want = np.asarray(mj.forward_kinematics(walk))[20, j]
    assert main(["info", "example:walk", "--joint", "right_elbow", "--frame", "20"]) == 0
    line = capsys.readouterr().out.splitlines()[-1]
    assert line.startswith(f"right_elbow at frame 20 ({20 / walk.fps:.3f} s): "), line
    got = np.array([float(v) for v in line.split(": ")[1].split(" ")[0].split(",")])
    np.testing.assert_allclose(got, want, atol=1e-4)  # four decimals, as --at takes them
    for argv, msg in (
        (["--joint", "right_elbow"], "--joint and --frame go together"),
        (["--joint", "Right_Elbow", "--frame", "3"], "did you mean right_elbow?"),
        (["--joint", "right_elbow", "--frame", "100000"], "--frame 100000 outside 0.."),
    ):
        assert main(["info", "example:walk", *argv]) == 2
        assert msg in _error(capsys)
        assert capsys.readouterr().out == ""  # refused before the description is printed
