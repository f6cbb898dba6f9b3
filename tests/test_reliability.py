"""Issue 20: no model lost, bounded resources on hostile files, values checked, one error
contract. One test per numbered failure of the issue and per smaller item (each failed on the
code before the fix); the CLI contract over every sub-command."""

from __future__ import annotations

import io
import json
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mtex_jax as mj
from mtex_jax.cli import main
from mtex_jax.texture import Texton
from paper_settings import UNTIED
from shared_textures import dance_pair_texture

DATA = Path(mj.__file__).resolve().parent / "data" / "deepmimic"


# --------------------------------------------------------------------------------------------
# fixtures and helpers
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_texture(tmp_path_factory):
    """A small texture learned from two embedded clips, and its model file."""
    tex = dance_pair_texture()  # shared with other test modules (learned once per process)
    path = tmp_path_factory.mktemp("model") / "texture.npz"
    tex.save(path)
    return tex, path


def rewrite_npz(src: Path, dst: Path, **changes) -> Path:
    """Copy a model file with some members replaced (a value) or dropped (``None``)."""
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    for k, v in changes.items():
        if v is None:
            arrays.pop(k, None)
        else:
            arrays[k] = v
    with open(dst, "wb") as fh:
        np.savez(fh, **arrays)
    return dst


def cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code: int, err: str, match: str | None = None) -> None:
    assert code == 2, err
    lines = err.strip("\n").splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("mtex: error: "), err
    assert "Traceback" not in err
    if match is not None:
        assert match in lines[0], lines[0]


def unstable_texton(D: int = 3, k: int = 2, rho: float = 1.5) -> Texton:
    return Texton(
        mu=jnp.zeros(D),
        C=jnp.eye(D)[:, :k],
        A1=rho * jnp.eye(k),
        A2=jnp.zeros((k, k)),
        d=jnp.zeros(k),
        B=0.1 * jnp.eye(k),
        sigma2=jnp.asarray(0.01),
        m0=jnp.zeros(2 * k),
        S0=jnp.eye(2 * k),
    )


def small_bvh_text(n_frames: int = 3) -> str:
    return bvh_text_of(mj.load_example("dance_a")[:n_frames])


def bvh_text_of(m: mj.Motion) -> str:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "m.bvh"
        mj.write_bvh(p, m)
        return p.read_text()


def deep_bvh(n: int) -> str:
    lines = [
        "HIERARCHY",
        "ROOT j0",
        "{",
        "OFFSET 0 0 0",
        "CHANNELS 3 Zrotation Xrotation Yrotation",
    ]
    for i in range(1, n):
        lines += [f"JOINT j{i}", "{", "OFFSET 0 1 0", "CHANNELS 3 Zrotation Xrotation Yrotation"]
    lines += ["}"] * n
    lines += ["MOTION", "Frames: 1", "Frame Time: 0.0333333", " ".join(["0"] * (3 * n))]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# 1. saving is atomic
# --------------------------------------------------------------------------------------------
def test_1_failed_model_save_keeps_the_old_file(small_texture, tmp_path, monkeypatch):
    tex, _ = small_texture
    path = tmp_path / "model.npz"
    tex.save(path)
    old = path.read_bytes()

    real = np.lib.format.write_array

    def write_then_fail(fp, array, *a, **k):
        fp.write(b"partial")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np.lib.format, "write_array", write_then_fail)
    with pytest.raises(OSError, match="No space"):
        tex.save(path)
    monkeypatch.setattr(np.lib.format, "write_array", real)
    assert path.read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.npz"]  # no temporary left
    mj.load_texture(path)


def test_1_failed_bvh_and_picture_writes_keep_the_old_files(tmp_path, monkeypatch):
    m = mj.load_example("dance_a")[:20]
    bvh, png = tmp_path / "m.bvh", tmp_path / "m.png"
    mj.write_bvh(bvh, m)
    mj.viz.render_filmstrip(m, png, n_frames=2, height=1.0, dpi=30)
    old_bvh, old_png = bvh.read_bytes(), png.read_bytes()

    def fail(fd):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr("os.fsync", fail)
    with pytest.raises(OSError):
        mj.write_bvh(bvh, m[:5])
    with pytest.raises(OSError):
        mj.viz.render_filmstrip(m, png, n_frames=3, height=1.0, dpi=30)
    assert bvh.read_bytes() == old_bvh and png.read_bytes() == old_png
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.bvh", "m.png"]


# --------------------------------------------------------------------------------------------
# 2. a long DeepMimic keyframe
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seconds", [1000.0, 1e6])
def test_2_long_deepmimic_keyframe_is_refused(tmp_path, seconds):
    doc = json.loads((DATA / "humanoid3d_dance_a.txt").read_text())
    doc["Frames"][3][0] = seconds
    p = tmp_path / "long.txt"
    p.write_text(json.dumps(doc, indent=1))
    with pytest.raises(ValueError, match=r"long\.txt:\d+: .*(limit|lasts)"):
        mj.read_deepmimic(p)


# --------------------------------------------------------------------------------------------
# 3. unstable textons never give NaN/inf silently
# --------------------------------------------------------------------------------------------
def test_3_unstable_texton_noise_driven_raises_naming_rho():
    tex = unstable_texton()
    start = jnp.ones((2, 3))
    with pytest.raises(ValueError, match=r"spectral radius 1\.5.*rho_max=0\.999"):
        mj.texture.synthesize_texton(jax.random.key(0), tex, 3000, start)
    with pytest.raises(ValueError, match="spectral radius"):
        mj.texture.sample_texton(jax.random.key(0), tex, 3000, jnp.ones(2), jnp.ones(2))
    short = mj.texture.synthesize_texton(jax.random.key(0), tex, 50, start)  # finite: returned
    assert np.isfinite(np.asarray(short)).all()


# --------------------------------------------------------------------------------------------
# 4. bad quaternions
# --------------------------------------------------------------------------------------------
def test_4_motion_rejects_nan_and_zero_quaternions_and_normalises_near_unit():
    m = mj.load_example("dance_a")[:30].numpy()
    for value, what in ((np.nan, "NaN"), (0.0, "zero")):
        q = np.array(m.rotations)
        q[7, 3] = value
        with pytest.raises(ValueError, match=rf"frame 7, joint 3 .*{what}"):
            mj.Motion(m.skeleton, m.fps, m.root_positions, q)
    q = np.array(m.rotations)
    q[5, 2] *= 2.0
    with pytest.raises(ValueError, match=r"frame 5, joint 2.*norm 2"):
        mj.Motion(m.skeleton, m.fps, m.root_positions, q)
    q = np.array(m.rotations) * 1.0005
    near = mj.Motion(m.skeleton, m.fps, m.root_positions, q)
    assert np.allclose(np.linalg.norm(np.asarray(near.rotations), axis=-1), 1.0, atol=1e-12)


# --------------------------------------------------------------------------------------------
# 5. sizes are bounded
# --------------------------------------------------------------------------------------------
def test_5_size_limits(small_texture, tmp_path, capsys):
    tex, path = small_texture
    with pytest.raises(ValueError, match="limit"):
        mj.synthesize(jax.random.key(0), tex, n_frames=10**9)
    with pytest.raises(ValueError, match="limit"):
        mj.load_example("dance_a").resample(1e6)
    code, _, err = cli(
        capsys, "synth", str(path), "-o", str(tmp_path / "x.bvh"), "--frames", "1000000000"
    )
    assert_one_line_error(code, err, "limit")
    text = re.sub(r"Frame Time: \S+", "Frame Time: 1e-300", small_bvh_text())
    with pytest.raises(ValueError, match=r"tiny\.bvh:\d+: frame time 1e-300"):
        mj.io.parse_bvh(text, "tiny.bvh")


# --------------------------------------------------------------------------------------------
# 6. no recursion on nested input
# --------------------------------------------------------------------------------------------
def test_6_deep_bvh_and_json_give_value_errors(tmp_path, capsys):
    p = tmp_path / "deep.bvh"
    p.write_text(deep_bvh(1000))
    with pytest.raises(ValueError, match=r"deep\.bvh:\d+: .*nested more than"):
        mj.read_bvh(p)
    code, _, err = cli(capsys, "info", str(p))
    assert_one_line_error(code, err, "deep.bvh")
    chain = mj.io.parse_bvh(deep_bvh(200), "chain.bvh")  # within the limits: parsed iteratively
    assert chain.n_joints == 200
    j = tmp_path / "deep.txt"
    j.write_text('{"Frames": ' + "[" * 100_000 + "]" * 100_000 + "}")
    with pytest.raises(ValueError, match=r"deep\.txt: JSON nested 100001 levels"):
        mj.read_deepmimic(j)


# --------------------------------------------------------------------------------------------
# 7. model-file members are checked before allocation; unknown ones rejected
# --------------------------------------------------------------------------------------------
def test_7_model_members_checked_before_allocation(small_texture, tmp_path):
    _, src = small_texture
    big = tmp_path / "big.npz"
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(big, "w") as zout:
        for info in zin.infolist():
            if info.filename != "M.npy":
                zout.writestr(info, zin.read(info))
        buf = io.BytesIO()
        header = {"descr": "<f8", "fortran_order": False, "shape": (100000, 100000)}
        np.lib.format.write_array_header_1_0(buf, header)
        zout.writestr("M.npy", buf.getvalue() + b"\0" * 64)
    with pytest.raises(ValueError, match=r"big\.npz: .*'M' declares shape \(100000, 100000\)"):
        mj.load_texture(big)
    junk = rewrite_npz(src, tmp_path / "junk.npz", junk=np.zeros(1000))
    with pytest.raises(ValueError, match=r"junk\.npz: unknown arrays \['junk'\]"):
        mj.load_texture(junk)


# --------------------------------------------------------------------------------------------
# 8. values are checked on load
# --------------------------------------------------------------------------------------------
def test_8_model_values_checked_on_load(small_texture, tmp_path):
    tex, src = small_texture
    M = np.asarray(tex.M)
    nan = M.copy()
    nan[0, 0] = np.nan
    neg = M.copy()
    neg[0, 0] = -0.5
    neg[0, 1] += 0.5
    half = 0.5 * M
    for name, value, match in (
        ("M", nan, "'M' contains NaN"),
        ("M", neg, "M has negative entries"),
        ("M", half, "row 0 of M sums to"),
        ("pi", -np.asarray(tex.pi), "pi has negative"),
    ):
        bad = rewrite_npz(src, tmp_path / f"bad_{name}.npz", **{name: value})
        with pytest.raises(ValueError, match=rf"bad_{name}\.npz: .*{match}"):
            mj.load_texture(bad)


# --------------------------------------------------------------------------------------------
# smaller items
# --------------------------------------------------------------------------------------------
def test_render_rejects_unknown_extensions(tmp_path, capsys):
    out = tmp_path / "out.txt"
    code, _, err = cli(capsys, "render", "example:dance_a", "-o", str(out))
    assert_one_line_error(code, err, ".gif")
    assert not out.exists()


def test_broken_pipe_is_quiet(capsys, monkeypatch):
    class Closed(io.StringIO):
        def write(self, s: str) -> int:
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self) -> None:
            raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(sys, "stdout", Closed())
    code = main(["examples"])
    monkeypatch.undo()
    _, err = capsys.readouterr()
    assert code == 0 and err == ""


def test_broken_pipe_in_a_real_pipe():
    exe = Path(sys.executable).with_name("mtex")
    p = subprocess.Popen([str(exe), "examples"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert p.stdout is not None and p.stderr is not None
    p.stdout.close()  # the reader goes away before anything is written
    err = p.stderr.read()
    assert p.wait(timeout=120) == 0 and err == b""


def test_interrupt_while_starting_exits_130(capsys, monkeypatch):
    import mtex_jax.cli._main as cli_main

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli_main, "_parser", interrupted)
    code, _, err = cli(capsys, "examples")
    assert code == 130 and err == "mtex: interrupted\n"


def test_int_instead_of_key_is_a_clear_type_error(small_texture):
    tex, _ = small_texture
    calls = [
        lambda: mj.synthesize(0, tex, n_frames=60),
        lambda: mj.texture.synthesize_texton(0, tex.textons[0], 20, np.asarray(tex.key_poses[0])),
        lambda: mj.texture.random_path(0, tex, 5),
        lambda: mj.texture.sample_texton(0, tex.textons[0], 20),
        lambda: mj.choreograph(
            0, tex, np.asarray(tex.key_poses[0]), np.asarray(tex.key_poses[1]), n_frames=60
        ),
    ]
    for call in calls:
        with pytest.raises(TypeError, match=r"key must be a JAX PRNG key .*got int"):
            call()


def test_learn_tmax_below_tmin_reports_seconds(tmp_path, capsys):
    argv = ["learn", "example:dance_a", "--tmin", "3", "--tmax", "1", "-o", str(tmp_path / "x.npz")]
    code, _, err = cli(capsys, *argv)
    assert_one_line_error(code, err, "--tmax (1 s) must be at least --tmin (3 s)")


def test_choreograph_start_without_frame(small_texture, tmp_path, capsys):
    _, path = small_texture
    argv = ["choreograph", str(path), "--start", "example:dance_a", "--end", "example:dance_b:3"]
    code, _, err = cli(capsys, *argv, "-o", str(tmp_path / "c.bvh"))
    assert_one_line_error(code, err, "expected CLIP:FRAME")
    assert "'example:dance_a'" in err


def test_text_file_as_model_is_not_a_model_file(tmp_path, capsys):
    p = tmp_path / "notes.txt"
    p.write_text("hello\n")
    with pytest.raises(ValueError, match="not a model file") as e:
        mj.load_texture(p)
    assert "pickle" not in str(e.value)
    code, _, err = cli(capsys, "synth", str(p), "-o", str(tmp_path / "x.bvh"))
    assert_one_line_error(code, err, "not a model file")


def test_constant_clip_does_not_move(tmp_path, capsys):
    m = mj.load_example("dance_a")[:90].numpy()
    const = mj.Motion(
        m.skeleton,
        m.fps,
        np.repeat(np.asarray(m.root_positions)[:1], 90, axis=0),
        np.repeat(np.asarray(m.rotations)[:1], 90, axis=0),
    )
    with pytest.raises(ValueError, match="the clip does not move"):
        mj.learn([const], mj.LearnConfig(tmin=10, tmax=30, state_dim=4, fps=30.0, **UNTIED))
    p = tmp_path / "const.bvh"
    mj.write_bvh(p, const)
    code, _, err = cli(capsys, "learn", str(p), "--tmin", "0.4", "-o", str(tmp_path / "c.npz"))
    assert_one_line_error(code, err, "the clip does not move")


# --------------------------------------------------------------------------------------------
# the CLI contract: every sub-command, bad arguments -> one line on stderr, status 2
# --------------------------------------------------------------------------------------------
def test_every_subcommand_bad_arguments_one_line_exit_2(small_texture, tmp_path, capsys):
    _, model = small_texture
    text = tmp_path / "notes.txt"
    text.write_text("hello\n")
    deep = tmp_path / "deep.bvh"
    deep.write_text(deep_bvh(600))
    o = str(tmp_path / "o.bvh")
    bad: dict[str, list[list[str]]] = {
        "info": [[], ["missing.bvh"], [str(text)], [str(deep)], [str(tmp_path)], ["example:nope"]],
        "render": [
            ["example:dance_a"],
            ["example:dance_a", "-o", "x.txt"],
            ["missing.bvh", "-o", str(tmp_path / "x.gif")],
            ["example:dance_a", "-o", str(tmp_path / "no" / "x.gif")],
        ],
        "examples": [["--bogus"], ["extra"]],
        "mirror": [
            ["example:walk"],
            ["example:walk", "-o", str(tmp_path / "x.gif")],
            ["missing.bvh", "-o", o],
            [str(text), "-o", o],
            ["example:walk", "-o", o, "--axis", "w"],
            ["example:walk", "-o", o, "--axis", "y"],
            ["example:walk", "-o", str(tmp_path / "no" / "x.bvh")],
        ],
        "learn": [
            ["example:dance_a"],
            ["example:dance_a", "-o", o, "--tmin", "3", "--tmax", "1"],
            ["example:dance_a", "-o", o, "--tmin", "-1"],
            ["example:dance_a", "-o", o, "--state-dim", "x"],
            [str(text), "-o", o],
        ],
        "segment": [[str(model)], [str(text), "example:dance_a"], [str(model), "missing.bvh"]],
        "demo": [["--seconds", "-1"], ["--seconds", "nan"], ["--max-iter", "x"], ["--seed", "x"]],
        "synth": [
            [str(model)],
            [str(model), "-o", "x.txt"],
            [str(model), "-o", o, "--frames", "2"],
            [str(model), "-o", o, "--frames", "1000000000"],
            [str(text), "-o", o],
            [str(model), "-o", o, "--gif", "x.png"],
            [str(model), "-o", o, "--clean", "--contacts", "gone.npz"],  # no such contact file
            [str(model), "-o", o, "--contacts", "c.npz"],  # --contacts without --clean
        ],
        "edit": [
            [str(model)],
            [str(model), "example:dance_a", "--joint", "nope", "--frame", "1", "--at", "0,0,0"],
            [
                str(model),
                "example:dance_a",
                *("--joint", "chest", "--frame", "1", "--at", "1,2"),
                "-o",
                o,
            ],
            [str(model), "example:dance_a", *("--joint", "chest", "--frame", "99999"), "-o", o],
            [str(text), "example:dance_a", *("--joint", "chest", "--frame", "1", "--at", "0,0,0")],
        ],
        "contacts": [
            [],
            ["example:dance_a"],
            ["example:dance_a", "-o", "x.txt"],
            ["missing.bvh", "-o", str(tmp_path / "c.npz")],
            ["example:dance_a", "-o", str(tmp_path / "c.npz"), "--fps", "-1"],
        ],
        "choreograph": [
            [str(model), "--start", "example:dance_a", "--end", "example:dance_a:2", "-o", o],
            [str(model), "--start", "example:dance_a:x", "--end", "example:dance_a:2", "-o", o],
            [str(model), "--start", "example:dance_a:99999", "--end", "example:dance_a:2", "-o", o],
            [str(text), "--start", "example:dance_a:1", "--end", "example:dance_a:2", "-o", o],
        ],
        "implicit-synth": [
            ["example:dance_a"],
            ["example:dance_a", "-o", o, "--frames", "0"],
            ["example:dance_a", "-o", o, "--beta", "-1"],
            ["missing.bvh", "-o", o],
        ],
        "evaluate": [
            [str(model)],
            [str(text), "--test", "example:dance_a"],
            [str(model), "--test", "missing.bvh"],
            [str(model), "--test", "example:dance_a", "--synth", "0"],
            [str(model), "--test", "example:dance_a", "--seconds", "-2"],
        ],
        "track": [
            ["example:dance_a"],
            ["example:dance_a", "--test", "missing.bvh"],
            ["example:dance_a", "--test", "example:dance_b", "--particles", "0"],
            ["example:dance_a", "--test", "example:dance_b", "--fps", "-3"],
        ],
        "textons": [[str(model)], [str(text), "-o", str(tmp_path / "g.png")]],
        "view": [["example:dance_a"], ["missing.bvh", "-o", str(tmp_path / "v.html")]],
    }
    out = subprocess.run(
        [sys.executable, "-m", "mtex_jax", "--help"], capture_output=True, text=True, check=True
    ).stdout
    # the sub-commands: the lines indented by four spaces under COMMAND in 'mtex --help'
    listed = {m.group(1) for m in re.finditer(r"(?m)^    ([a-z][a-z-]*)\b", out)}
    assert listed == set(bad), f"sub-commands without bad-argument cases: {listed ^ set(bad)}"
    n = 0
    for command, cases in bad.items():
        for args in cases:
            code, _, err = cli(capsys, command, *args)
            assert code == 2 and len(err.strip("\n").splitlines()) == 1, (command, args, err)
            assert err.startswith("mtex: error: ") and "Traceback" not in err, (command, args)
            n += 1
    assert n >= 40
    assert not Path("x.txt").exists()


# --------------------------------------------------------------------------------------------
# issue 57: nothing but progress reaches the user's terminal, also on a loaded machine
# --------------------------------------------------------------------------------------------
_AFTER_LEARN = """
import sys
import mtex_jax as mj
from mtex_jax.io import load_salsa, salsa_split

tex = mj.load_texture(sys.argv[1])
fm = tex.feature_map
train, test = ([load_salsa(n).resample(fm.fps) for n in part] for part in salsa_split())
print(float(tex.log_likelihood(test[0], mean=True)), [float(v) for v in tex.log_likelihood(test)])
print(mj.metrics.density_report(tex, train, test))
"""


@pytest.mark.slow  # a default learn on the shipped split, with both cores kept busy
def test_a_default_learn_and_log_likelihood_print_no_compiler_alarm(tmp_path):
    """XLA printed "Constant folding an instruction is taking > 1s" alarms (twenty lines each)
    after a learn followed by ``log_likelihood`` on a busy machine: the folding ran at every
    compile, only its duration changed with the load. With both cores busy, the default
    ``mtex learn`` on the shipped training clips, then ``log_likelihood`` and the density
    report on the held-out clips, write nothing to stderr."""
    from mtex_jax.io import salsa_split

    env = {**__import__("os").environ, "MTEX_NO_CACHE": "1"}  # every program compiled here
    spin = "import time\nt = time.time()\nwhile time.time() - t < 900: pass"
    busy = [subprocess.Popen([sys.executable, "-c", spin]) for _ in range(2)]
    try:
        model = tmp_path / "tex.npz"
        clips = [f"example:salsa/{n}" for n in salsa_split()[0]]
        r = subprocess.run(
            [sys.executable, "-m", "mtex_jax", "learn", *clips, "-o", str(model)],
            capture_output=True, text=True, timeout=1800, env=env,
        )  # fmt: skip
        assert r.returncode == 0, r.stderr[-3000:]
        assert r.stderr == "", r.stderr[-3000:]
        r = subprocess.run(
            [sys.executable, "-c", _AFTER_LEARN, str(model)],
            capture_output=True, text=True, timeout=1800, env=env,
        )  # fmt: skip
        assert r.returncode == 0, r.stderr[-3000:]
        assert r.stderr == "", r.stderr[-3000:]
    finally:
        for p in busy:
            p.kill()
