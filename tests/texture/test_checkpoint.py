"""Checkpoints of a learn (issue 57, design §4.9): a learn stopped at any EM iteration and
resumed gives the model of an uninterrupted learn, bit for bit; a checkpoint of another learn
is refused. The clips and settings visit every stage: EM on the greedy segments, selection
rounds that refit, and the final EM."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mtex_jax as mj

NAMES = ("dance_a", "dance_b", "walk", "run", "kick", "punch", "spin")
KW = dict(tmin=10, tmax=30, fps=30.0, min_segments=1, init="greedy", selection="bic")


class Stop(Exception):
    pass


@pytest.fixture(scope="module")
def clips() -> list[mj.Motion]:
    return [mj.load_example(n) for n in NAMES]


@pytest.fixture(scope="module")
def reference(clips) -> tuple[mj.MotionTexture, list[str]]:
    """The uninterrupted learn, and a record of each of its EM iterations."""
    lines: list[str] = []
    model = mj.learn(clips, mj.LearnConfig(**KW), callback=lambda info: lines.append("it"))
    return model, lines


def same_model(a: mj.MotionTexture, b: mj.MotionTexture) -> None:
    (xa, ma), (xb, mb) = a.to_arrays_json(), b.to_arrays_json()
    assert ma == mb
    assert sorted(xa) == sorted(xb)
    for k in xa:
        assert xa[k].dtype == xb[k].dtype and xa[k].tobytes() == xb[k].tobytes(), k


def test_a_learn_stopped_at_every_iteration_resumes_to_the_same_model(clips, reference, tmp_path):
    model, iterations = reference
    assert len(iterations) >= 4  # the greedy EM, two selection refits, the final EM
    for k in range(1, len(iterations) + 1):
        ck = tmp_path / f"ck{k}.npz"
        seen = [0]

        def stop_at(info, k=k, seen=seen):
            seen[0] += 1
            if seen[0] == k:
                raise Stop

        with pytest.raises(Stop):
            mj.learn(clips, mj.LearnConfig(**KW), callback=stop_at, checkpoint=ck)
        assert ck.is_file()
        after: list[int] = []
        resumed = mj.learn(
            clips,
            mj.LearnConfig(**KW),
            checkpoint=ck,
            resume=True,
            callback=lambda info, after=after: after.append(1),
        )
        assert len(after) == len(iterations) - k  # the iterations done are not run again
        same_model(resumed, model)


def test_a_checkpoint_of_another_learn_is_refused(clips, tmp_path):
    ck = tmp_path / "ck.npz"

    def stop(info):
        raise Stop

    with pytest.raises(Stop):
        mj.learn(clips, mj.LearnConfig(**KW), callback=stop, checkpoint=ck)
    with pytest.raises(ValueError, match="exists: resume from it"):
        mj.learn(clips, mj.LearnConfig(**KW), checkpoint=ck)
    other = {**KW, "max_iter": 3}
    with pytest.raises(ValueError, match="other clips or another configuration"):
        mj.learn(clips, mj.LearnConfig(**other), checkpoint=ck, resume=True)
    with pytest.raises(ValueError, match="other clips or another configuration"):
        mj.learn(clips[:-1], mj.LearnConfig(**KW), checkpoint=ck, resume=True)
    model_file = tmp_path / "model.npz"
    mj.learn(clips[:2], mj.LearnConfig(tmin=10, tmax=30, fps=30.0, max_iter=1)).save(model_file)
    with pytest.raises(ValueError, match=r"model\.npz"):
        mj.learn(clips, mj.LearnConfig(**KW), checkpoint=model_file, resume=True)
    with pytest.raises(ValueError, match="bic_thresholds is not checkpointed"):
        cfg = mj.LearnConfig(tmin=10, tmax=30, fps=30.0, init="greedy", bic_thresholds=(0.2, 0.3))
        mj.learn(clips, cfg, checkpoint=tmp_path / "b.npz")


def _mtex(*args: str) -> list[str]:
    return [sys.executable, "-m", "mtex_jax", *args]


def _learn_args(out: Path, ck: Path | None) -> list[str]:
    args = ["learn", *(f"example:{n}" for n in NAMES), "-o", str(out), "--fps", "30"]
    args += ["--tmin", "0.34", "--tmax", "1", "--min-segments", "1"]
    args += ["--init", "greedy", "--selection", "bic"]
    return args + ([] if ck is None else ["--checkpoint", str(ck)])


@pytest.mark.slow  # three fresh processes, each compiling the learn
def test_a_learn_killed_at_a_random_iteration_resumes_bit_for_bit(tmp_path):
    """SIGKILL at a random EM iteration (a seeded draw), then ``--resume``: the model file is
    byte-identical to an uninterrupted learn's. SIGKILL gives the learn no chance to save
    anything: what survives is the last checkpoint written (atomically) before it."""
    env = {**os.environ, "MTEX_NO_CACHE": "1"}
    ref = tmp_path / "ref.npz"
    r = subprocess.run(_mtex(*_learn_args(ref, None)), capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    n_iter = r.stdout.count("[mtex learn] iter ")
    k = random.Random(57).randint(1, n_iter - 1)
    out, ck = tmp_path / "out.npz", tmp_path / "ck.npz"
    p = subprocess.Popen(
        _mtex(*_learn_args(out, ck)),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert p.stdout is not None
    seen = 0
    for line in p.stdout:
        seen += line.startswith("[mtex learn] iter ")
        if seen == k:
            p.send_signal(signal.SIGKILL)
            break
    p.communicate(timeout=600)
    assert p.returncode == -signal.SIGKILL and ck.is_file() and not out.exists()
    r = subprocess.run(
        _mtex(*_learn_args(out, ck), "--resume"), capture_output=True, text=True, env=env
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert f"resuming from {ck}" in r.stdout
    assert r.stdout.count("[mtex learn] iter ") == n_iter - k
    assert out.read_bytes() == ref.read_bytes()
    assert not ck.exists() and f"removed the checkpoint {ck}" in r.stdout


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupted_learn_says_in_one_line_how_to_resume(tmp_path, sig):
    out, ck = tmp_path / "out.npz", tmp_path / "ck.npz"
    # Ctrl-C's handler, as in a terminal: a pytest-xdist worker ignores SIGINT, and a child that
    # inherits SIG_IGN never sees it (as a job started with nohup)
    terminal = (
        "import runpy, signal, sys\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "sys.argv = ['mtex', *sys.argv[1:]]\n"
        "runpy.run_module('mtex_jax', run_name='__main__', alter_sys=True)\n"
    )
    p = subprocess.Popen(
        [sys.executable, "-c", terminal, *_learn_args(out, ck)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert p.stdout is not None
    for line in p.stdout:
        if line.startswith("[mtex learn] iter "):
            p.send_signal(sig)
            break
    _, err = p.communicate(timeout=600)
    assert p.returncode == 130, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines == [
        f"mtex: interrupted; the checkpoint {ck} keeps the EM iterations: run the same command "
        "with --resume"
    ], err
    assert ck.is_file() and not out.exists()
    r = subprocess.run(_mtex(*_learn_args(out, ck), "--resume"), capture_output=True, text=True)
    assert r.returncode == 0 and out.is_file(), r.stderr[-2000:]
    np.testing.assert_array_equal(  # the model of the resumed learn is complete
        np.asarray(mj.load_texture(out).segments)[:, 2].sum(),
        sum(mj.load_example(n).resample(30.0).n_frames for n in NAMES),
    )
