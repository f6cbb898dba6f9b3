"""The synthesis limit runs at its value in bounded memory (issue 57, design §5.11).

``synthesize(..., n_frames=MAX_GENERATED_FRAMES)`` of the default model used to die with
``RESOURCE_EXHAUSTED`` allocating 2.2 GB in one piece; ``mtex synth --frames 1000000`` with
it. Here both run at the limit in one child process whose address space is held to 2 GiB above
its warmed-up baseline (``RLIMIT_AS``; JAX reserves several GiB of virtual memory when it
starts, so the limit is set after a warm-up, as in ``test_hostile``). An allocation past the
budget is a ``MemoryError`` or an XLA ``RESOURCE_EXHAUSTED`` in the child: the test fails.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

BUDGET = 2 << 30

CHILD = textwrap.dedent(
    """
    import resource, sys, time
    from pathlib import Path
    import numpy as np
    import jax
    import mtex_jax as mj
    from mtex_jax.cli import main
    from mtex_jax.core import MAX_GENERATED_FRAMES

    model, out = Path(sys.argv[1]), Path(sys.argv[2])
    tex = mj.load_texture(model)
    mj.synthesize(jax.random.key(0), tex, n_frames=2000)  # warm-up: the programs in place

    def vm(field):
        for line in open("/proc/self/status"):
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024

    base = vm("VmSize")
    budget = int(sys.argv[3])
    resource.setrlimit(resource.RLIMIT_AS, (base + budget, base + budget))
    t0 = time.perf_counter()
    s = mj.synthesize(jax.random.key(1), tex, n_frames=MAX_GENERATED_FRAMES)
    rot = np.asarray(s.motion.rotations)
    print("API", s.n_frames, rot.shape[0], bool(np.isfinite(np.asarray(s.Y)).all()),
          f"{time.perf_counter() - t0:.0f}", vm("VmPeak") - base, flush=True)
    del s, rot
    t0 = time.perf_counter()
    code = main(["synth", str(model), "--frames", str(MAX_GENERATED_FRAMES), "-o", str(out)])
    print("CLI", code, f"{time.perf_counter() - t0:.0f}", vm("VmPeak") - base, flush=True)
    """
)


@pytest.mark.slow  # a million frames, twice: about ten minutes on two cores
def test_a_million_frames_synthesise_and_write_within_2_gib(tmp_path):
    """The default model learned on the shipped split (float32 model file, as ``mtex learn``
    writes it), then in a child under ``RLIMIT_AS`` = baseline + 2 GiB: ``synthesize`` of
    ``MAX_GENERATED_FRAMES`` frames returns them all, finite, and ``mtex synth --frames
    1000000`` writes a BVH file of a million frames with a progress line per piece on
    stderr. The address space stays under the budget."""
    from mtex_jax.io import salsa_split

    model = tmp_path / "tex.npz"
    clips = [f"example:salsa/{n}" for n in salsa_split()[0]]
    r = subprocess.run(
        [sys.executable, "-m", "mtex_jax", "learn", *clips, "-o", str(model)],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    out = tmp_path / "million.bvh"
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=1")
    r = subprocess.run(
        [sys.executable, "-c", CHILD, str(model), str(out), str(BUDGET)],
        capture_output=True,
        text=True,
        timeout=2400,
        env=env,
    )
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    api = next(ln for ln in r.stdout.splitlines() if ln.startswith("API")).split()
    assert api[1:4] == ["1000000", "1000000", "True"], r.stdout
    assert int(api[5]) < BUDGET, r.stdout
    cli = next(ln for ln in r.stdout.splitlines() if ln.startswith("CLI")).split()
    assert cli[1] == "0" and int(cli[3]) < BUDGET, r.stdout
    progress = [ln for ln in r.stderr.splitlines() if ln.startswith("[mtex synth]")]
    assert progress and progress[-1].startswith("[mtex synth] 1,000,000 / 1,000,000 frames")
    # the file: its header and a million frame lines (each with every channel)
    with open(out, encoding="utf-8") as fh:
        lines = 0
        widths = set()
        in_motion = False
        for ln in fh:
            if in_motion:
                lines += 1
                if lines % 99_991 == 1:
                    widths.add(len(ln.split()))
            elif ln.startswith("Frame Time:"):
                in_motion = True
            elif ln.startswith("Frames:"):
                assert ln.split() == ["Frames:", "1000000"]
    assert lines == 1_000_000 and len(widths) == 1
    print(r.stdout)
