"""Issue 43: the hostile-input campaign as tests.

Families (the case tables are in ``hostile_cases.py``): file kinds for every reader, sizes
beyond the limits (configuration, generators, the implicit model), values of model files,
motions and motion files, indexing, the numbers of every CLI flag, and the overwrite rules of
every command that writes. Each case asserts the error type and message (or a correct
result). The default run takes the representative cases; ``-m slow`` runs all of them. Under
an address-space limit, the size cases fail before they allocate 2 GiB or run 60 s.

The families of issue 57 that need a process of their own live beside this file:

- limits at their value, under ``RLIMIT_AS``: ``test_limits_at_value.py`` (every ``MAX_*``),
  ``test_long_synthesis_memory.py`` (a million frames by ``synthesize`` and ``mtex synth``),
  the particle limit in ``test_size_cases_stay_within_2_gib_and_60_s`` below and
  ``tests/core/test_memory.py``;
- a learn stopped by SIGKILL at a random EM iteration, or by SIGINT/SIGTERM, and resumed:
  ``tests/texture/test_checkpoint.py`` (a distributed one: ``test_distributed.py``);
- integers no float holds, NaN and infinity in every spelling, in each text format: the BVH
  and DeepMimic cases here, ``tests/io`` (BVH, DeepMimic, salsa metadata),
  ``tests/tracking/test_keypoints.py`` (keypoint and camera files) and the model-metadata
  cases (``texture-meta-*-401-digits``) here;
- nothing but progress lines on stderr after a default learn and ``log_likelihood`` with both
  cores busy: ``test_reliability.py``.
"""

from __future__ import annotations

import importlib
import json
import os
import re
import shutil
import stat
import subprocess
import sys
import textwrap
import threading
from pathlib import Path
from typing import Any

import jax
import numpy as np
import pytest

import mtex_jax as mj
from hostile_cases import (
    BVH_CASES,
    CLI_FILE_CASES,
    CLI_FILE_CMDS,
    CLI_NUMBER_CASES,
    CONFIG_CASES,
    DEEPMIMIC_CASES,
    FILE_CASES,
    GENERATOR_CASES,
    IMPLICIT_CASES,
    MOTION_CASES,
    OVERWRITE_CASES,
    OVERWRITE_CMDS,
    READERS,
    TEXTON_INDEX_CASES,
    TEXTURE_FILE_CASES,
    Case,
    params,
    rewrite_npz,
)
from mtex_jax.cli import main
from mtex_jax.edit import load_contacts, save_contacts
from mtex_jax.metrics import density_report
from mtex_jax.motion import fit_contacts
from shared_textures import dance_pair_texture

DATA = Path(mj.__file__).resolve().parent / "data" / "deepmimic"


# --------------------------------------------------------------------------------------------
# fixtures
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def world(tmp_path_factory) -> dict[str, Any]:
    """A small texture (learned from two embedded clips at 30 Hz) and its model file, a
    contact model, a feature map, a BVH clip and a DeepMimic clip, in one folder."""
    d = tmp_path_factory.mktemp("world")
    clips = [mj.load_example("dance_a"), mj.load_example("dance_b")]
    tex = dance_pair_texture()  # learned from these clips, shared with other test modules
    tex.save(d / "tex.npz")
    save_contacts(d / "contacts.npz", fit_contacts(clips, fps=60.0))
    assert tex.feature_map is not None
    tex.feature_map.save(d / "fm.npz")
    mj.write_bvh(d / "clip.bvh", clips[0][:40])
    shutil.copy(DATA / "humanoid3d_dance_a.txt", d / "clip.txt")
    return dict(
        dir=d,
        tex=tex,
        model=d / "tex.npz",
        contacts=d / "contacts.npz",
        fm=d / "fm.npz",
        bvh=d / "clip.bvh",
        clip=d / "clip.txt",
    )


def _reader(name: str):
    mod, fn = READERS[name][0].rsplit(".", 1)
    return getattr(importlib.import_module(f"mtex_jax.{mod}"), fn)


def _call_with_timeout(fn, *args, timeout: float = 60.0):
    """``fn(*args)`` in a daemon thread: its result, or the exception it raised; a call that
    does not return within ``timeout`` seconds fails the test (a FIFO that blocks)."""
    out: dict[str, Any] = {}

    def run():
        try:
            out["value"] = fn(*args)
        except BaseException as e:
            out["error"] = e

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout)
    assert not t.is_alive(), f"{fn.__name__}{args} did not return within {timeout} s"
    if "error" in out:
        raise out["error"]
    return out.get("value")


def _make_file(kind: str, path: Path, world: dict[str, Any]) -> Path:
    """A file of the hostile ``kind`` at ``path`` (or the system file it names)."""
    if kind == "missing":
        return path
    if kind == "directory":
        path.mkdir()
    elif kind in ("dev_null", "dev_zero", "dev_urandom"):
        return Path("/dev/" + kind[4:])
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "symlink_to_dev_zero":
        path.symlink_to("/dev/zero")
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "text":
        path.write_text("hello, this is not a motion or a model\n" * 10)
    elif kind == "binary":
        path.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, np.uint8).tobytes())
    elif kind == "sparse_3gb":
        with open(path, "wb") as fh:
            fh.truncate(3 << 30)
    elif kind == "truncated_zip":
        data = Path(world["model"]).read_bytes()
        path.write_bytes(data[: len(data) // 2])
    else:
        raise AssertionError(kind)
    return path


def _one_line_error(code: int, err: str) -> str:
    assert code == 2, err
    lines = err.strip("\n").splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("mtex: error: "), err
    assert "Traceback" not in err and "internal error" not in err, err
    return lines[0]


# --------------------------------------------------------------------------------------------
# 1. file kinds
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", params(FILE_CASES))
def test_file_kinds(case: Case, world, tmp_path):
    reader, kind = case.make
    path = _make_file(kind, tmp_path / f"input{READERS[reader][1]}", world)
    with pytest.raises(case.error, match=case.match) as info:
        _call_with_timeout(_reader(reader), path)
    assert str(path) in str(info.value) or path.name in str(info.value), info.value


def test_readers_accept_what_they_should(world):
    """The valid files of the fixture load (the other side of the file-kind cases)."""
    assert mj.read_motion(world["bvh"]).n_frames == 40
    assert mj.read_motion(world["clip"]).n_frames > 40
    assert mj.load_texture(world["model"]).n_textons == world["tex"].n_textons
    assert load_contacts(world["contacts"]).feet
    assert mj.motion.load_feature_map(world["fm"]).fps == 30.0


# --------------------------------------------------------------------------------------------
# 2. sizes
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", params(CONFIG_CASES))
def test_config_limits(case: Case):
    with pytest.raises(case.error, match=case.match):
        mj.LearnConfig(**case.make)


@pytest.mark.parametrize("case", params(GENERATOR_CASES))
def test_generator_limits(case: Case, world):
    with pytest.raises(case.error, match=case.match):
        _call_with_timeout(case.make, mj, world["tex"], jax.random.key(0))


@pytest.fixture(scope="module")
def implicit_world():
    m = mj.load_example("walk")
    return mj.implicit.learn([m], 5), m


@pytest.mark.parametrize("case", params(IMPLICIT_CASES))
def test_implicit_limits(case: Case, implicit_world):
    model, m = implicit_world
    with pytest.raises(case.error, match=case.match):
        case.make(mj, model, m, jax.random.key(0))


def test_a_limit_can_be_raised_and_restored():
    """The error says how to raise a limit, and raising it works (then it is restored)."""
    with pytest.raises(ValueError, match=r"set_limit\('MAX_TEXTONS', N\)"):
        mj.LearnConfig(n_textons=20_000)
    old = int(mj.core.set_limit("MAX_TEXTONS", 50_000))
    try:
        assert mj.LearnConfig(n_textons=20_000).n_textons == 20_000
    finally:
        mj.core.set_limit("MAX_TEXTONS", old)
    with pytest.raises(ValueError, match="MAX_TEXTONS"):
        mj.LearnConfig(n_textons=20_000)
    with pytest.raises(KeyError, match="unknown limit"):
        mj.core.set_limit("MAX_EVERYTHING", 1)
    with pytest.raises(ValueError, match="positive int"):
        mj.core.set_limit("MAX_TEXTONS", 0)


# --------------------------------------------------------------------------------------------
# 3. values
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", params(TEXTURE_FILE_CASES))
def test_texture_file_values(case: Case, world, tmp_path):
    arrays, meta = case.make
    path = tmp_path / "hostile.npz"
    rewrite_npz(world["model"], path, arrays, meta)
    with pytest.raises(case.error, match=case.match) as info:
        mj.load_texture(path)
    assert str(path) in str(info.value)


def test_a_saved_texture_passes_the_load_checks(world, tmp_path):
    """The checks of a loaded file are those a learned texture passes (the round trip)."""
    path = tmp_path / "again.npz"
    rewrite_npz(world["model"], path, {}, None)  # the same arrays, written by np.savez
    tex = mj.load_texture(path)
    np.testing.assert_array_equal(np.asarray(tex.M), np.asarray(world["tex"].M))


@pytest.mark.parametrize("case", params(MOTION_CASES))
def test_motion_values(case: Case):
    m = mj.load_example("dance_a")[:12]
    kw = case.make(m)
    if case.error is None:
        out = mj.Motion(**kw)
        assert np.asarray(out.rotations).dtype == np.float64
        assert np.asarray(out.root_positions).dtype == np.float64
        n = np.linalg.norm(np.asarray(out.rotations), axis=-1)
        np.testing.assert_allclose(n, 1.0, atol=1e-12)
        return
    with pytest.raises(case.error, match=case.match):
        mj.Motion(**kw)


def _bvh_with(world, where: str, token: str) -> str:
    lines = Path(world["bvh"]).read_text().splitlines()
    i_motion = lines.index("MOTION")
    if where == "frame":
        vals = lines[i_motion + 3].split()
        vals[2] = token
        lines[i_motion + 3] = " ".join(vals)
    elif where == "offset":
        k = next(i for i, ln in enumerate(lines) if ln.strip().startswith("OFFSET") and i > 3)
        lines[k] = re.sub(r"OFFSET\s+\S+", f"OFFSET {token}", lines[k])
    elif where == "frames":
        lines[i_motion + 1] = f"Frames: {token}"
    elif where == "time":
        lines[i_motion + 2] = f"Frame Time: {token}"
    text = "\n".join(lines) + "\n"
    if where == "bom":
        text = "\ufeff" + text
    elif where == "crlf":
        text = text.replace("\n", "\r\n")
    return text


@pytest.mark.parametrize("case", params(BVH_CASES))
def test_bvh_numbers_are_strict(case: Case, world, tmp_path):
    where, token = case.make
    path = tmp_path / "hostile.bvh"
    path.write_bytes(_bvh_with(world, where, token).encode("utf-8"))
    if case.error is None:
        m = mj.read_bvh(path)
        ref = mj.read_bvh(world["bvh"])
        np.testing.assert_array_equal(np.asarray(m.rotations), np.asarray(ref.rotations))
        assert mj.read_motion(path).n_frames == ref.n_frames
        return
    with pytest.raises(case.error, match=case.match) as info:
        mj.read_bvh(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("case", params(DEEPMIMIC_CASES))
def test_deepmimic_values(case: Case, world, tmp_path):
    path = tmp_path / "hostile.txt"
    path.write_bytes(case.make(Path(world["clip"]).read_text()).encode("utf-8"))
    if case.error is None:
        m = mj.read_deepmimic(path)
        ref = mj.read_deepmimic(world["clip"])
        np.testing.assert_array_equal(np.asarray(m.rotations), np.asarray(ref.rotations))
        assert mj.read_motion(path).n_frames == ref.n_frames
        return
    with pytest.raises(case.error, match=case.match) as info:
        mj.read_deepmimic(path)
    assert str(path) in str(info.value)


def test_zip_members_are_refused_before_they_are_inflated(world, tmp_path):
    """A zip bomb (two members of 280 MiB of zeros, about a MB compressed) whose members
    declare more than ``MAX_MODEL_BYTES`` in all is refused from the zip directory, before
    anything is decompressed."""
    import zipfile

    big = tmp_path / "bomb.npz"
    with zipfile.ZipFile(world["model"]) as src, zipfile.ZipFile(big, "w") as dst:
        bombs = ("texton.mu.npy", "texton.C.npy")  # known names: read if not refused
        for info in src.infolist():
            if info.filename not in bombs:
                dst.writestr(info.filename, src.read(info))
        zeros = bytes(280 << 20)
        for name in bombs:
            info = zipfile.ZipInfo(name)
            info.compress_type = zipfile.ZIP_DEFLATED
            dst.writestr(info, zeros, compresslevel=1)
    assert big.stat().st_size < 8 << 20
    with pytest.raises(ValueError, match=r"declare [\d,]+ bytes, more than the limit MAX_MODEL"):
        mj.load_texture(big)


# --------------------------------------------------------------------------------------------
# 4. indexing
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", params(TEXTON_INDEX_CASES))
def test_texton_index(case: Case, world):
    textons = world["tex"].textons
    n = textons.n_textons
    index = case.make(n)
    if case.error is None:
        t = textons[index]
        want = np.asarray(textons.mu)[np.asarray(index) if not isinstance(index, slice) else index]
        np.testing.assert_array_equal(np.asarray(t.mu), want)
        return
    with pytest.raises(case.error, match=case.match):
        textons[index]


def test_motion_frame_index_out_of_range():
    m = mj.load_example("dance_a")
    with pytest.raises(IndexError, match="out of range for a motion of 98 frames"):
        m[np.array([0, 98])]
    with pytest.raises(IndexError):
        m[np.array([-99])]
    assert m[np.array([0, 97, -1])].n_frames == 3


def test_synthesize_texton_of_a_missing_texton_is_refused(world):
    tex = world["tex"]
    with pytest.raises(IndexError, match=f"texton index {tex.n_textons} is out of range"):
        mj.texture.synthesize_texton(
            jax.random.key(0), tex.textons[tex.n_textons], 20, np.zeros((2, tex.obs_dim))
        )


# --------------------------------------------------------------------------------------------
# 5. CLI numbers
# --------------------------------------------------------------------------------------------
def _argv(template: list[str], world, tmp_path, **extra: str) -> list[str]:
    fill = dict(
        model=str(world["model"]),
        clip="example:dance_a",
        bvh=str(world["bvh"]),
        out=str(tmp_path / "out"),
        **extra,
    )
    return [a.format(**fill) for a in template]


@pytest.mark.parametrize("case", params(CLI_NUMBER_CASES))
def test_cli_numbers(case: Case, world, tmp_path, capsys):
    template, flag, value = case.make
    argv = [*_argv(template, world, tmp_path), f"{flag}={value}"]
    code = main(argv)
    _, err = capsys.readouterr()
    line = _one_line_error(code, err)
    assert case.match in line, line
    assert not list(tmp_path.iterdir()), "a refused command wrote a file"


@pytest.mark.parametrize("case", params(CLI_FILE_CASES))
def test_cli_files(case: Case, world, tmp_path, capsys):
    """Every reading command on every hostile file kind: one line, exit 2, the file named,
    never ``internal error``, never a hang."""
    cmd, kind = case.make
    template, suffix = CLI_FILE_CMDS[cmd]
    path = _make_file(kind, tmp_path / f"input{suffix}", world)
    argv = _argv(template, world, tmp_path, file=str(path))
    code = _call_with_timeout(main, argv)
    assert isinstance(code, int)
    line = _one_line_error(code, capsys.readouterr().err)
    assert re.search(case.match, line), line
    assert str(path) in line or path.name in line, line


# --------------------------------------------------------------------------------------------
# 6. overwrite rules
# --------------------------------------------------------------------------------------------
def _other_kind(kind: str, world) -> bytes:
    return {
        "bvh": Path(world["bvh"]).read_bytes(),
        "texture": Path(world["model"]).read_bytes(),
        "deepmimic": Path(world["clip"]).read_bytes(),
    }[kind]


def _state(path: Path) -> tuple[int, bytes | None]:
    st = os.lstat(path)
    return stat.S_IFMT(st.st_mode), (path.read_bytes() if stat.S_ISREG(st.st_mode) else None)


@pytest.mark.parametrize("case", params(OVERWRITE_CASES))
def test_overwrite_rules(case: Case, world, tmp_path, capsys):
    cmd, target = case.make
    template, suffix, input_kind, other = OVERWRITE_CMDS[cmd]
    inputs = {"clip": world["clip"], "bvh": world["bvh"], "model": world["model"]}
    given = tmp_path / f"input{Path(inputs[input_kind]).suffix}"
    shutil.copy(inputs[input_kind], given)
    out = tmp_path / f"out{suffix}"
    if target == "is-input":  # the input itself, under the output's suffix
        out = tmp_path / f"input_as_output{suffix}"
        shutil.copy(inputs[input_kind], out)
        given = out
    elif target == "other-kind":
        out.write_bytes(_other_kind(other, world))
    elif target == "fifo":
        os.mkfifo(out)
    elif target == "directory":
        out.mkdir()
    elif target == "char-device":
        try:
            os.mknod(out, stat.S_IFCHR | 0o666, os.makedev(1, 7))  # a copy of /dev/full
        except PermissionError:
            pytest.skip("creating a device node needs root")
    elif target == "missing-folder":
        out = tmp_path / "nodir" / f"x{suffix}"
    before = _state(out) if target != "missing-folder" else None
    argv = _argv(template, world, tmp_path, **{"in": str(given)})
    argv = [str(out) if a == str(tmp_path / "out") else a for a in argv]
    code = main(argv)
    _, err = capsys.readouterr()
    line = _one_line_error(code, err)
    assert re.search(case.match, line), line
    assert str(out) in line, line  # the target is named, never a temporary file
    if before is not None:
        assert _state(out) == before, "the refused command changed the file"
    folder = out.parent if out.parent.exists() else tmp_path
    leftovers = [p.name for p in folder.iterdir() if p.name.endswith(".tmp")]
    assert not leftovers, leftovers


COMMANDS_THAT_WRITE = ("learn", "synth", "implicit-synth", "contacts", "edit", "evaluate")


def test_no_command_overwrites_an_input_or_another_kind_without_force(world, tmp_path, capsys):
    """learn, synth, implicit-synth, contacts, edit and evaluate, each with -o naming one of
    its inputs and -o naming a file of another kind: refused, the file unchanged."""
    for cmd in COMMANDS_THAT_WRITE:
        template, suffix, input_kind, other = OVERWRITE_CMDS[cmd]
        inputs = {"clip": world["clip"], "bvh": world["bvh"], "model": world["model"]}
        for target in ("is-input", "other-kind"):
            d = tmp_path / f"{cmd}-{target}"
            d.mkdir()
            out = d / f"out{suffix}"
            if target == "is-input":
                shutil.copy(inputs[input_kind], out)
                given = out
            else:
                given = d / f"input{Path(inputs[input_kind]).suffix}"
                shutil.copy(inputs[input_kind], given)
                out.write_bytes(_other_kind(other, world))
            before = out.read_bytes()
            argv = _argv(template, world, d, **{"in": str(given)})
            argv = [str(out) if a == str(d / "out") else a for a in argv]
            code = main(argv)
            line = _one_line_error(code, capsys.readouterr().err)
            want = "is also an input" if target == "is-input" else "needs --force"
            assert want in line, (cmd, line)
            assert out.read_bytes() == before, cmd


def test_force_replaces_a_file_of_another_kind_but_never_an_input(world, tmp_path, capsys):
    out = tmp_path / "c.npz"
    shutil.copy(world["model"], out)
    argv = ["contacts", str(world["clip"]), "-o", str(out)]
    assert "needs --force" in _one_line_error(main(argv), capsys.readouterr().err)
    assert main([*argv, "--force"]) == 0, capsys.readouterr().err
    assert mj.core.file_kind(out) == "mtex_jax.ContactModel"
    clip = tmp_path / "clip.npz"
    shutil.copy(world["clip"], clip)
    line = _one_line_error(
        main(["contacts", str(clip), "-o", str(clip), "--force"]), capsys.readouterr().err
    )
    assert "is also an input" in line


def test_file_kind_names_what_is_there(world, tmp_path):
    fk = mj.core.file_kind
    assert fk(world["model"]) == "mtex_jax.MotionTexture"
    assert fk(world["contacts"]) == "mtex_jax.ContactModel"
    assert fk(world["fm"]) == "mtex_jax.FeatureMap"
    assert fk(world["bvh"]) == "bvh"
    assert fk(world["clip"]) == "deepmimic"
    assert fk(tmp_path / "none") is None
    assert fk(tmp_path) == "directory"
    assert fk("/dev/null") == "device"
    os.mkfifo(tmp_path / "f")
    assert fk(tmp_path / "f") == "fifo"


# --------------------------------------------------------------------------------------------
# temporary files of killed saves
# --------------------------------------------------------------------------------------------
def test_the_next_save_removes_the_temporaries_of_a_killed_save(world, tmp_path):
    """A saver killed (SIGKILL) in the middle of its write leaves its temporary file; the
    next save to the same path removes it. A temporary file of a process that still runs (a
    concurrent save) is left alone."""
    target = tmp_path / "model.npz"
    child = textwrap.dedent(
        f"""
        import os, signal
        from mtex_jax.core import atomic_write
        with atomic_write({str(target)!r}) as fh:
            fh.write(b"x" * 100000)
            fh.flush()
            os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    r = subprocess.run([sys.executable, "-c", child], capture_output=True, timeout=300)
    assert r.returncode == -9, r.stderr
    stale = [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert len(stale) == 1 and stale[0].name.startswith(".model.npz."), stale
    alive = tmp_path / f".model.npz.{os.getpid()}.concurrent.tmp"
    alive.write_bytes(b"a save in progress")
    old = tmp_path / ".model.npz.oldstyle.tmp"  # a name without a process id, old: removed
    old.write_bytes(b"")
    os.utime(old, (0, 0))
    world["tex"].save(target)
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == [alive.name, "model.npz"], left
    assert mj.load_texture(target).n_textons == world["tex"].n_textons


def test_atomic_write_replaces_only_regular_files(tmp_path):
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "dir").mkdir()
    for name, what in (("fifo", "FIFO"), ("dir", "directory")):
        with pytest.raises(ValueError, match=what):
            with mj.core.atomic_write(tmp_path / name) as fh:
                fh.write(b"x")
        assert not any(p.name.endswith(".tmp") for p in tmp_path.iterdir())
    with pytest.raises(FileNotFoundError, match=r"nodir/x.bin: the output folder .*nodir"):
        with mj.core.atomic_write(tmp_path / "nodir" / "x.bin") as fh:
            fh.write(b"x")


# --------------------------------------------------------------------------------------------
# API contract
# --------------------------------------------------------------------------------------------
def test_functions_that_take_motions_resample_to_the_models_rate(world):
    """A 60 Hz clip given to a 30 Hz texture is resampled, as learn and MotionJudge do."""
    tex = world["tex"]
    m60 = mj.load_example("dance_b")
    m30 = m60.resample(30.0)
    assert tex.log_likelihood(m60) == pytest.approx(tex.log_likelihood(m30), rel=1e-12)
    rows = density_report(tex, [mj.load_example("dance_a")], [m60])
    rows30 = density_report(tex, [mj.load_example("dance_a").resample(30.0)], [m30])
    assert rows["AR(2)"]["loglik_per_frame"] == pytest.approx(
        rows30["AR(2)"]["loglik_per_frame"], rel=1e-9
    )


def test_evaluate_refuses_the_same_clip_for_training_and_test_up_front(world, capsys):
    clip = str(world["clip"])
    code = main(["evaluate", str(world["model"]), "--test", clip, "--train", clip])
    line = _one_line_error(code, capsys.readouterr().err)
    assert "is also a --train clip" in line
    code = main(
        ["evaluate", str(world["model"]), "--test", "example:walk", "--train", "example:walk"]
    )
    assert "is also a --train clip" in _one_line_error(code, capsys.readouterr().err)


def test_choreograph_default_length_is_the_planned_path(world, tmp_path, capsys):
    out = tmp_path / "c.bvh"
    argv = [
        "choreograph",
        str(world["model"]),
        "--start",
        "example:dance_a:0",
        "--end",
        "example:dance_b:10",
        "-o",
        str(out),
    ]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "the most probable texton path" in text
    path_m = re.search(r"texton path (\[.*\])", text)
    frames_m = re.search(r"\((\d+) frames", text)
    assert path_m and frames_m, text
    path, frames = json.loads(path_m.group(1)), int(frames_m.group(1))
    tex = world["tex"]
    assert len(path) <= tex.n_textons  # no sampled self-repeats
    assert frames <= len(path) * int(np.asarray(tex.segment_lengths).max()) + 4


# --------------------------------------------------------------------------------------------
# memory and time under an address-space limit
# --------------------------------------------------------------------------------------------
BUDGET = 2 << 30  # bytes of address space above the baseline after imports and warm-up
SECONDS = 60.0

CHILD = textwrap.dedent(
    """
    import resource, sys, time, os
    from pathlib import Path
    import numpy as np
    import jax
    jax.config.update("jax_enable_x64", True)
    import mtex_jax as mj
    sys.path.insert(0, sys.argv[4])
    from hostile_cases import rewrite_npz

    folder, budget, model = Path(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3])
    tex = mj.load_texture(model)  # warm-up: imports and the code paths in place
    key = jax.random.key(0)
    walk = mj.load_example("walk")
    implicit = mj.implicit.learn([walk], 5)
    problem = mj.tracking.make_problem(key, implicit, walk, n_frames=5)
    rewrite_npz(model, folder / "long.npz",
                {"segment_lengths": lambda a: np.full_like(a["segment_lengths"], 10**12)}, None)
    with open(folder / "sparse.bvh", "wb") as fh:
        fh.truncate(3 << 30)
    os.mkfifo(folder / "model.fifo")

    def vm(field):
        for line in open("/proc/self/status"):
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024

    base = vm("VmSize")
    resource.setrlimit(resource.RLIMIT_AS, (base + budget, base + budget))
    cases = {
        "LearnConfig(tmax=1e9)": lambda: mj.LearnConfig(tmax=10**9),
        "learn(tmax=1e9)": lambda: mj.learn([walk], mj.LearnConfig(tmax=10**9)),
        "synthesize(lengths=[1e8])": lambda: mj.synthesize(key, tex, path=[0], lengths=[10**8]),
        "synthesize(n_frames=1e9)": lambda: mj.synthesize(key, tex, n_frames=10**9),
        "path_of_length(1e7)": lambda: mj.texture.path_of_length(tex, 0, 0, 10**7),
        "random_path(1e9)": lambda: mj.texture.random_path(key, tex, 10**9),
        "track(1e7 particles)": lambda: mj.tracking.track(key, implicit, problem,
                                                           n_particles=10**7),
        # the limit itself: measured before it runs, refused with what it would need
        "track(1e6 particles)": lambda: mj.tracking.track(key, implicit, problem,
                                                           n_particles=10**6),
        "implicit n_components 1e6": lambda: mj.implicit.learn([walk], 5, n_components=10**6),
        "implicit window 1e4": lambda: mj.implicit.learn([walk.resample(3000.0)], 10**4),
        "model with 1e12-frame segments": lambda: mj.load_texture(folder / "long.npz"),
        "model is a FIFO": lambda: mj.load_texture(folder / "model.fifo"),
        "read /dev/zero": lambda: mj.read_bvh("/dev/zero"),
        "read /dev/urandom": lambda: mj.read_deepmimic("/dev/urandom"),
        "read a 3 GB sparse file": lambda: mj.read_bvh(folder / "sparse.bvh"),
        "read_motion 3 GB": lambda: mj.read_motion(folder / "sparse.bvh"),
        "resample to 1e9 fps": lambda: walk.resample(1e9),
    }
    for name, fn in cases.items():
        t0 = time.perf_counter()
        try:
            fn()
            print("ACCEPTED", name, flush=True)
        except (ValueError, TypeError) as e:
            print("OK", f"{time.perf_counter() - t0:.3f}", name, "|", str(e)[:90], flush=True)
    print("PEAK", vm("VmPeak") - base)
    """
)


def test_size_cases_stay_within_2_gib_and_60_s(world, tmp_path):
    """Every size case fails with a clear error before the process allocates 2 GiB of
    address space above its baseline (``RLIMIT_AS``, set in a child after ``import jax`` and
    a warm-up: JAX reserves several GiB of virtual memory when it starts) or runs 60 s. An
    allocation beyond the budget would be a ``MemoryError`` (not caught: the child fails)."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=1")
    r = subprocess.run(
        [
            sys.executable,
            "-c",
            CHILD,
            str(tmp_path),
            str(BUDGET),
            str(world["model"]),
            str(Path(__file__).parent),
        ],
        capture_output=True,
        text=True,
        timeout=900,
        env=env,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    lines = r.stdout.splitlines()
    assert not [ln for ln in lines if ln.startswith("ACCEPTED")], r.stdout
    oks = [ln for ln in lines if ln.startswith("OK")]
    assert len(oks) == 17, r.stdout
    assert "needs about" in next(ln for ln in oks if "track(1e6 particles)" in ln), r.stdout
    for ln in oks:
        assert float(ln.split()[1]) < SECONDS, ln
    peak = int(lines[-1].split()[1])
    assert peak < BUDGET, r.stdout
