"""Data-parallel learning over 2 processes (``jax.distributed``, gloo collectives on loopback)
equals the single-process learn on the union of the clips.

The 2-process test starts two workers (one CPU device each, a free loopback port), each with
two short salsa clips, and learns with the default selection (BIC), pruning and log-normal
durations while this process learns on all four clips; the workers are killed after
``TIMEOUT`` seconds, so it cannot hang.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import textwrap
import time

import jax
import numpy as np
import pytest

from jax_cache import child_env
from mtex_jax.io import load_salsa
from mtex_jax.texture import LearnConfig, learn, learn_distributed

# four short salsa clips (the shipped 60 Hz data): process 0 holds the first two
CLIPS = ("60_01", "60_02", "60_03", "60_04")
FRAMES = 600
CONFIG = dict(
    tmin=30,
    tmax=90,
    state_dim=6,
    threshold=2.0,
    max_iter=4,
    fps=60.0,
    observation="residual",
    init="greedy",
)
TIMEOUT = 240.0  # seconds for both workers together; they are killed after it

WORKER = textwrap.dedent(
    """
    import sys
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.config.update("jax_enable_x64", True)
    pid, port, out = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    jax.distributed.initialize(
        f"127.0.0.1:{port}", num_processes=2, process_id=pid, local_device_ids=[0],
        initialization_timeout=60,
    )
    import numpy as np
    from mtex_jax.io import load_salsa
    from mtex_jax.texture import LearnConfig, learn_distributed

    clips = [load_salsa(n)[:FRAMES] for n in CLIPS]
    mine = clips[:2] if pid == 0 else clips[2:]
    cfg = LearnConfig(**CONFIG)
    errors = []
    # bad input on one process is an error on every process (and no hang)
    other = LearnConfig(**{**CONFIG, "tmin": 31 + pid})
    for data, c in (([] if pid else mine, cfg), (mine, other)):
        try:
            learn_distributed(data, c)
        except ValueError as e:
            errors.append(str(e))
    mt = learn_distributed(mine, cfg)
    leaves = {f"leaf{i}": np.asarray(a) for i, a in enumerate(jax.tree.leaves(mt))}
    np.savez(out, errors=np.asarray(errors), **leaves)
    print("WORKER_OK", pid, mt.n_textons, flush=True)
    """
)


def _run_workers(script, args, tmp_path, timeout, ok, meanwhile=None) -> list[str]:
    """Run ``script`` as processes 0 and 1 of a job on a free loopback port (``args(pid)``:
    their other arguments), ``meanwhile()`` in this process while they run; kill them after
    ``timeout`` seconds; assert each exited 0 and printed ``ok``; return their outputs."""
    port = _free_port()
    env = child_env(XLA_FLAGS="", JAX_PLATFORMS="cpu")  # and the compilation cache
    procs, logs = [], []
    for pid in range(2):
        log = open(tmp_path / f"worker{pid}.log", "w")  # closed below
        logs.append(log)
        cmd = [sys.executable, "-c", script, str(pid), str(port), *args(pid)]
        procs.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env))
    try:
        if meanwhile is not None:
            meanwhile()
        deadline = time.monotonic() + timeout
        for p in procs:
            p.wait(timeout=max(1.0, deadline - time.monotonic()))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        for log in logs:
            log.close()
    out = [(tmp_path / f"worker{pid}.log").read_text() for pid in range(2)]
    for pid, p in enumerate(procs):
        assert p.returncode == 0 and ok in out[pid], out[pid][-3000:]
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _clips() -> list:
    return [load_salsa(n)[:FRAMES] for n in CLIPS]


@pytest.mark.parametrize(
    ("extra", "tol"),
    [
        pytest.param({}, 1e-9, id="k6"),
        pytest.param(
            {"state_dim": None, "observation": "full", "dof": 4.0},
            1e-6,
            id="full_t",
            marks=pytest.mark.slow,  # 67 s on 2 cores
        ),
    ],
)
def test_two_processes_equal_one(tmp_path, extra, tol):
    """2 processes × 1 CPU device: the same textons, transition matrix and segmentation as
    :func:`learn` on all four clips, and the same model on both processes; Gaussian textons
    with k = 6 and full-dimensional Student-t ones (the IRLS steps of the M-step, each an
    all-reduce). With k = D, ``C`` holds all 54 eigenvectors of the scatter and the trailing
    ones (near-equal small eigenvalues) move by up to 3e-8 relative with the order of the
    sums, hence ``tol``."""
    config = {**CONFIG, **extra}
    script = f"CLIPS = {CLIPS!r}\nFRAMES = {FRAMES}\nCONFIG = {config!r}\n" + WORKER
    # the reference while the workers run (three processes on the CI's two cores)
    holder: list = []
    _run_workers(
        script,
        lambda pid: [str(tmp_path / f"out{pid}.npz")],
        tmp_path,
        TIMEOUT,
        "WORKER_OK",
        lambda: holder.append(learn(_clips(), LearnConfig(**config))),
    )
    ref = holder[0]
    got = [np.load(tmp_path / f"out{pid}.npz") for pid in range(2)]
    for g in got:
        errors = list(g["errors"])
        assert len(errors) == 2, errors
        assert "process 1: has no clips" in errors[0]
        assert "process 1: its LearnConfig differs" in errors[1]
    ref_leaves = [np.asarray(a) for a in jax.tree.leaves(ref)]
    n = len(ref_leaves)
    for pid in range(2):
        assert len([k for k in got[pid].files if k.startswith("leaf")]) == n
    # every process ends with the same model, bit for bit
    for i in range(n):
        np.testing.assert_array_equal(got[0][f"leaf{i}"], got[1][f"leaf{i}"])
    mt = [got[0][f"leaf{i}"] for i in range(n)]
    # the same model as one process, to rounding
    for a, b in zip(ref_leaves, mt, strict=True):
        assert a.shape == b.shape and a.dtype == b.dtype
        if a.dtype.kind in "iub":
            np.testing.assert_array_equal(a, b)
        else:
            np.testing.assert_allclose(b, a, rtol=tol, atol=tol)
    idx = {id(x): i for i, x in enumerate(jax.tree.leaves(ref))}
    seg = mt[idx[id(ref.segments)]]
    np.testing.assert_array_equal(seg, np.asarray(ref.segments))
    M = mt[idx[id(ref.M)]]
    np.testing.assert_allclose(M, np.asarray(ref.M), rtol=0, atol=1e-12)
    mu = mt[idx[id(ref.textons.mu)]]
    np.testing.assert_allclose(mu, np.asarray(ref.textons.mu), rtol=0, atol=1e-10)


def test_single_process_input_errors():
    """Without jax.distributed it is one process: bad input raises at once."""
    with pytest.raises(ValueError, match="no clips"):
        learn_distributed([], LearnConfig(**CONFIG))
    with pytest.raises(TypeError, match="LearnConfig"):
        learn_distributed([np.zeros((100, 3))], "not a config")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="dtype object"):
        learn_distributed([np.zeros((100, 3), dtype=object)], LearnConfig(**CONFIG))
    with pytest.raises(ValueError, match="shorter than tmin"):
        learn_distributed([np.zeros((10, 3))], LearnConfig(**CONFIG))


def test_cli_distributed_settings_errors(capsys, monkeypatch, tmp_path):
    """``mtex learn --distributed``: incomplete or bad settings are one-line errors, before
    JAX's runtime is started."""
    from mtex_jax.cli import main

    for var in ("MTEX_COORDINATOR", "MTEX_NUM_PROCESSES", "MTEX_PROCESS_ID"):
        monkeypatch.delenv(var, raising=False)
    out = str(tmp_path / "m.npz")
    assert main(["learn", "example:salsa/60_01", "-o", out, "--split-clips"]) == 2
    assert "--split-clips needs --distributed" in capsys.readouterr().err
    argv = ["learn", "example:salsa/60_01", "-o", out, "--distributed"]
    assert main([*argv, "--coordinator", "127.0.0.1:1"]) == 2
    err = capsys.readouterr().err
    assert "missing" in err and "MTEX_NUM_PROCESSES" in err and "MTEX_PROCESS_ID" in err
    monkeypatch.setenv("MTEX_NUM_PROCESSES", "2")
    monkeypatch.setenv("MTEX_PROCESS_ID", "2")
    assert main([*argv, "--coordinator", "127.0.0.1:1"]) == 2
    assert "process id 2 is not in 0..1" in capsys.readouterr().err
    monkeypatch.setenv("MTEX_PROCESS_ID", "x")
    assert main([*argv, "--coordinator", "127.0.0.1:1"]) == 2
    assert "must be an integer" in capsys.readouterr().err
    assert main(["learn", "--help"]) == 0
    assert "--process-id" in capsys.readouterr().out


CK_WORKER = textwrap.dedent(
    """
    import sys
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.config.update("jax_enable_x64", True)
    pid, port, folder, stop = int(sys.argv[1]), sys.argv[2], sys.argv[3], int(sys.argv[4])
    jax.distributed.initialize(
        f"127.0.0.1:{port}", num_processes=2, process_id=pid, local_device_ids=[0],
        initialization_timeout=60,
    )
    from pathlib import Path
    import numpy as np
    from mtex_jax.io import load_salsa
    from mtex_jax.texture import LearnConfig, learn_distributed

    class Stop(Exception):
        pass

    clips = [load_salsa(n)[:FRAMES] for n in CLIPS]
    mine = clips[:2] if pid == 0 else clips[2:]
    cfg = LearnConfig(**CONFIG)
    # each process names its own path: process 1's is never written nor read
    ck = Path(folder) / f"ck{pid}.npz"
    seen = [0]

    def stop_at(info):
        seen[0] += 1
        if seen[0] == stop:
            raise Stop

    try:
        learn_distributed(mine, cfg, callback=stop_at, checkpoint=ck)
    except Stop:
        pass
    print("AFTER_STOP", pid, ck.exists(), flush=True)
    try:  # without resume an existing checkpoint is refused, on every process
        learn_distributed(mine, cfg, checkpoint=Path(folder) / "ck0.npz")
    except ValueError as e:
        print("REFUSED", pid, "exists: resume from it" in str(e), flush=True)
    after = []
    resumed = learn_distributed(
        mine, cfg, checkpoint=ck, resume=True, callback=lambda info: after.append(1)
    )
    total = []
    fresh = learn_distributed(mine, cfg, callback=lambda info: total.append(1))
    a, b = jax.tree.leaves(resumed), jax.tree.leaves(fresh)
    same = len(a) == len(b) and all(
        np.asarray(x).dtype == np.asarray(y).dtype
        and np.asarray(x).tobytes() == np.asarray(y).tobytes()
        for x, y in zip(a, b)
    )
    print("RESUMED", pid, len(after), len(total), seen[0], same, flush=True)
    """
)


def test_a_stopped_distributed_learn_resumes_from_process_0s_checkpoint(tmp_path):
    """Two processes stopped at their third EM iteration: process 0 has written the
    checkpoint, process 1 nothing (its own path stays absent); both resume from process 0's
    file, run only the iterations left, and end with the model of an uninterrupted
    distributed learn, bit for bit. An existing checkpoint without ``resume`` is refused on
    both processes."""
    script = f"CLIPS = {CLIPS!r}\nFRAMES = {FRAMES}\nCONFIG = {CONFIG!r}\n" + CK_WORKER
    out = _run_workers(script, lambda pid: [str(tmp_path), "3"], tmp_path, 2 * TIMEOUT, "RESUMED")
    assert "AFTER_STOP 0 True" in out[0] and "AFTER_STOP 1 False" in out[1]
    assert not (tmp_path / "ck1.npz").exists()
    for pid in range(2):
        assert f"REFUSED {pid} True" in out[pid], out[pid][-2000:]
        line = next(ln for ln in out[pid].splitlines() if ln.startswith("RESUMED"))
        _, _, left, total, seen, same = line.split()
        assert same == "True", line
        # the iterations done before the stop are not run again
        assert seen == "3" and int(left) == int(total) - 3 >= 1, line
