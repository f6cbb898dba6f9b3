"""Benchmark: learning at the paper's scale (issue 21).

A full learn with the default settings (``LearnConfig(tmin=60, tmax=180, fps=60)``: tied
textons, chunk initialisation, EM, the selection of the textons) at about 7k, 14k,
28k and 50k frames of 60 Hz salsa, each in a fresh process (compilation included, no
compilation cache), with

* the time split: state dimension (BIC), greedy initialisation, E-steps, M-steps, the rest
  (objective, pruning, selection bookkeeping), and the time spent compiling (tracing, lowering
  and XLA compilation, from ``jax.monitoring``; it falls inside the other parts);
* peak resident memory of the process;
* EM iterations and the texture's size;
* at the largest size, the E-step (segment scores + duration-aware Viterbi) of the learned
  texture, warm, against its flop bound: the frame terms' GEMM flops (projection, dynamics and
  initial-state density) at this machine's measured float64 GEMM rate plus the Viterbi's
  add/max operations at its measured rate;
* a 2-process learn (``learn_distributed``, gloo on loopback, one CPU device each) against the
  1-process learn on the same clips (14k frames).

The 14 CMU salsa clips give 13,723 frames at 60 Hz. The larger sets add the same performances
sampled at the other phase of the 120 Hz capture (the frames in between) and both sets played
backwards: 54,890 frames, distinct as sequences but not new dancing. Sizes are prefixes of
that list (the last clip cut to length).

Run: ``.venv/bin/python benchmarks/speed/bench_scale.py [--sizes 7000,14000,28000,50000]``; writes
``benchmarks/results/scale.md`` and ``scale.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import RESULTS as OUT, command, use

FPS = 60.0
CONFIG = dict(tmin=60, tmax=180, fps=FPS)


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------------------------
# data (used in the child processes)
# --------------------------------------------------------------------------------------------
def corpus() -> list[Any]:
    """The 60 Hz clips in a fixed order: even phase, odd phase, both reversed."""
    use("quality")
    from bench_quality import HELD, TRAIN, load

    raw = [m[4:] for m in load(TRAIN + HELD)]  # 120 Hz (the first frames are a T-pose)
    even = [m.resample(FPS) for m in raw]
    odd = [m[1:].resample(FPS) for m in raw]
    return even + odd + [m[::-1] for m in even + odd]


def take(n_frames: int) -> list[Any]:
    """The first clips of :func:`corpus` up to at least ``n_frames`` frames, the last one cut.

    A cut clip keeps at least ``2·tmax`` frames (a shorter one could not be segmented), so the
    total is ``n_frames`` to ``n_frames + 2·tmax − 1``.
    """
    out, total = [], 0
    for m in corpus():
        if total >= n_frames:
            break
        keep = min(m.n_frames, max(n_frames - total, 2 * int(CONFIG["tmax"])))
        out.append(m[:keep])
        total += keep
    if total < n_frames:
        raise ValueError(f"the corpus has {total:,} frames, fewer than {n_frames:,}")
    return out


# --------------------------------------------------------------------------------------------
# child: one full learn, instrumented
# --------------------------------------------------------------------------------------------
def child_learn(n_frames: int, estep: bool) -> dict[str, Any]:
    import resource

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.monitoring
    import numpy as np

    import mtex_jax as mj
    from mtex_jax.texture._learning import em as em_module, learn as _learn

    clips = take(n_frames)
    compile_s = {"s": 0.0}

    def on_event(event: str, duration: float, **_kw: Any) -> None:
        if event.startswith("/jax/core/compile/") and event.endswith("_duration"):
            compile_s["s"] += duration

    jax.monitoring.register_event_duration_secs_listener(on_event)
    split = {"state_dim": 0.0, "init": 0.0, "e_step": 0.0, "m_step": 0.0}
    calls = {"e_step": 0, "m_step": 0}

    def timed(name: str, f: Any) -> Any:
        def g(*a: Any, **k: Any) -> Any:
            t = time.perf_counter()
            out = f(*a, **k)
            split[name] += time.perf_counter() - t
            if name in calls:
                calls[name] += 1
            return out

        return g

    _learn.resolve_state_dim = timed("state_dim", _learn.resolve_state_dim)
    _learn.greedy_segments = timed("init", _learn.greedy_segments)
    em_module.Runner.e_step = timed("e_step", em_module.Runner.e_step)
    em_module.Runner.e_step_scored = timed("e_step", em_module.Runner.e_step_scored)
    em_module.Runner.m_step = timed("m_step", em_module.Runner.m_step)
    iters: list[int] = []
    t0 = time.perf_counter()
    tex = mj.learn(clips, mj.LearnConfig(**CONFIG), callback=lambda i: iters.append(1))
    jax.block_until_ready(tex.textons.mu)
    wall = time.perf_counter() - t0
    lab = np.asarray(tex.segments)[:, 3]
    out: dict[str, Any] = dict(
        frames=int(sum(m.n_frames for m in clips)),
        clips=len(clips),
        wall_s=wall,
        split_s=dict(split),  # copies: the E-step measurement below calls the runner again
        calls=dict(calls),
        other_s=wall - sum(split.values()),
        compile_s=compile_s["s"],
        em_iterations=len(iters),
        textons=tex.n_textons,
        segments=int(lab.size),
        state_dim=tex.config.state_dim,
        observation=tex.config.observation,
        peak_rss_gb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
    )
    if estep:
        out["e_step"] = e_step_against_bound(tex, clips)
    return out


def e_step_against_bound(tex: Any, clips: list[Any]) -> dict[str, Any]:
    """The learned texture's E-step on its training clips (joined), warm, and its bound."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from mtex_jax.texture import segment_scores, viterbi_segments

    fm = tex.feature_map
    Y = jnp.asarray(np.concatenate([np.asarray(fm.encode(m)) for m in clips]))
    T, D = Y.shape
    lM, lpi, ld = jnp.log(tex.M), jnp.log(tex.pi), tex.log_durations
    n = jnp.asarray(T)
    tmin, tmax = CONFIG["tmin"], CONFIG["tmax"]

    def e_step() -> Any:
        sc = segment_scores(tex.textons, Y)
        return viterbi_segments(sc, lM, lpi, n, tmin, tmax, ld).score

    t = time.perf_counter()
    jax.block_until_ready(e_step())
    first = time.perf_counter() - t
    runs = []
    for _ in range(5):
        t = time.perf_counter()
        jax.block_until_ready(e_step())
        runs.append(time.perf_counter() - t)
    warm = float(np.median(runs))
    # the learner's own E-step on the clips (packed in batches of 4, segment rows on the host)
    from mtex_jax.texture._learning import em as em_module, learn as _learn

    ys = [np.asarray(fm.encode(m)) for m in clips]
    run = em_module.Runner(ys, _learn.resolve_state_dim(ys, tex.config, False))
    M, pi = np.asarray(tex.M), np.asarray(tex.pi)
    ld = None if tex.log_durations is None else np.asarray(tex.log_durations)
    run.e_step(tex.textons, M, pi, ld)
    learner = []
    for _ in range(5):
        t = time.perf_counter()
        run.e_step(tex.textons, M, pi, ld)
        learner.append(time.perf_counter() - t)
    N, k = tex.n_textons, tex.config.state_dim
    # frame terms, per frame and texton: the projection GEMM (k+1)(D+1), the dynamics 2k(k+1)
    # and the initial-state density of a segment starting there, 3k(k+1) (L0⁻¹ of the first
    # two states; every frame is a possible start). Until 2026-11-26 the bound left the
    # initial-state term out, which made it about half of the work the E-step must do. With
    # k = D the kernel (_frame_terms_full) does k(6D + 3) multiply-adds instead, within 2 %
    # of this count.
    gemm_flop = 2.0 * T * N * ((D + 1) * (k + 1) + 2 * k * (k + 1) + 3 * k * (k + 1))
    # Viterbi: every (frame, texton, length) cell is one add and one max
    vit_ops = 2.0 * T * N * (tmax - tmin + 1)
    gemm_rate, maxplus_rate = machine_rates()
    bound = gemm_flop / gemm_rate + vit_ops / maxplus_rate
    return dict(
        frames=int(T),
        textons=N,
        state_dim=k,
        first_s=first,
        warm_s=warm,
        runs_s=runs,
        gemm_gflop=gemm_flop / 1e9,
        viterbi_gops=vit_ops / 1e9,
        gemm_gflops_per_s=gemm_rate / 1e9,
        maxplus_gops_per_s=maxplus_rate / 1e9,
        bound_s=bound,
        ratio=warm / bound,
        learner_warm_s=float(np.median(learner)),
        learner_runs_s=learner,
        learner_ratio=float(np.median(learner)) / bound,
    )


def machine_rates() -> tuple[float, float]:
    """Measured float64 GEMM flop/s (2048², both cores as XLA uses them) and add/max op/s
    (an in-cache max-plus reduction), best of 5."""
    import jax
    import jax.numpy as jnp
    from jax import lax

    a = jnp.ones((2048, 2048)) * 1e-3
    mm = jax.jit(lambda x: x @ x)
    jax.block_until_ready(mm(a))
    best = min(_once(lambda: mm(a)) for _ in range(5))
    gemm = 2 * 2048**3 / best
    x = jnp.linspace(0.0, 1.0, 128 * 121).reshape(128, 121)
    reps = 2000

    @jax.jit
    def maxplus(x: Any) -> Any:
        def body(_i: Any, acc: Any) -> Any:
            return jnp.max(x + acc[:, None], axis=1) * 0.5

        return lax.fori_loop(0, reps, body, jnp.zeros((128,)))

    jax.block_until_ready(maxplus(x))
    best = min(_once(lambda: maxplus(x)) for _ in range(5))
    return gemm, 2 * 128 * 121 * reps / best


def _once(f: Any) -> float:
    import jax

    t = time.perf_counter()
    jax.block_until_ready(f())
    return time.perf_counter() - t


# --------------------------------------------------------------------------------------------
# child: one process of a 2-process learn
# --------------------------------------------------------------------------------------------
def child_distributed(n_frames: int, pid: int, port: int, out_path: str) -> None:
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.config.update("jax_enable_x64", True)
    jax.distributed.initialize(
        f"127.0.0.1:{port}",
        num_processes=2,
        process_id=pid,
        local_device_ids=[0],
        initialization_timeout=120,
    )
    import numpy as np

    from mtex_jax.texture import LearnConfig, learn_distributed

    clips = take(n_frames)
    half = len(clips) // 2
    mine = clips[:half] if pid == 0 else clips[half:]
    t0 = time.perf_counter()
    tex = learn_distributed(mine, LearnConfig(**CONFIG))
    jax.block_until_ready(tex.textons.mu)
    wall = time.perf_counter() - t0
    leaves = {f"leaf{i}": np.asarray(a) for i, a in enumerate(jax.tree.leaves(tex))}
    np.savez(out_path, wall=np.asarray(wall), **leaves)


def child_reference(n_frames: int, out_path: str) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import mtex_jax as mj

    t0 = time.perf_counter()
    tex = mj.learn(take(n_frames), mj.LearnConfig(**CONFIG))
    jax.block_until_ready(tex.textons.mu)
    wall = time.perf_counter() - t0
    leaves = {f"leaf{i}": np.asarray(a) for i, a in enumerate(jax.tree.leaves(tex))}
    np.savez(out_path, wall=np.asarray(wall), **leaves)


# --------------------------------------------------------------------------------------------
# parent
# --------------------------------------------------------------------------------------------
def spawn(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, __file__, "--child", *args],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def run_learn(n: int, estep: bool) -> dict[str, Any]:
    p = spawn("learn", str(n), "1" if estep else "0")
    out, _ = p.communicate(timeout=3600)
    if p.returncode:
        raise RuntimeError(f"learn at {n} frames failed (exit {p.returncode})")
    line = next(ln for ln in out.splitlines() if ln.startswith("RESULT "))
    return json.loads(line[len("RESULT ") :])


def run_distributed(n: int, tmp: Path) -> dict[str, Any]:
    import numpy as np

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.perf_counter()
    ps = [spawn("dist", str(n), str(pid), str(port), str(tmp / f"p{pid}.npz")) for pid in (0, 1)]
    for p in ps:
        p.communicate(timeout=3600)
        if p.returncode:
            raise RuntimeError(f"a distributed process failed (exit {p.returncode})")
    wall2 = time.perf_counter() - t0
    ref = spawn("ref", str(n), str(tmp / "ref.npz"))
    ref.communicate(timeout=3600)
    if ref.returncode:
        raise RuntimeError("the 1-process reference learn failed")
    a, b, r = (np.load(tmp / f) for f in ("p0.npz", "p1.npz", "ref.npz"))
    keys = sorted(k for k in r.files if k.startswith("leaf"))
    diff = max(float(np.max(np.abs(a[k] - r[k]), initial=0.0)) for k in keys)
    same = all(np.array_equal(a[k], b[k]) for k in keys)
    ints = all(np.array_equal(a[k], r[k]) for k in keys if r[k].dtype.kind in "iub")
    return dict(
        frames=sum(m.n_frames for m in take(n)),
        processes_wall_s=wall2,
        process_learn_s=[float(a["wall"]), float(b["wall"])],
        one_process_learn_s=float(r["wall"]),
        max_abs_difference=diff,
        processes_bit_identical=same,
        integer_leaves_equal=ints,
    )


def report(r: dict[str, Any]) -> str:
    m = r["machine"]
    lines = [
        "# Learning at scale (issue 21)",
        "",
        f"Made by: `{r.get('command', 'python benchmarks/speed/bench_scale.py')}`",
        "",
        f"One run; {m['platform']}, {m['cpus']} CPUs, jax "
        f"{m['jax']}, float64; 1-minute load average {m['load_start'][0]:.1f} at the start and "
        f"{m['load_end'][0]:.1f} at the end (shared machine). Defaults "
        f"(`LearnConfig(tmin=60, tmax=180, fps=60)`), each learn in a fresh process without a "
        "compilation cache. Frames beyond 13,723 reuse the performances (other phase of the "
        "120 Hz capture, then played backwards; see the module notes).",
        "",
        "| frames | clips | wall (s) | state dim (s) | init (s) | E-steps (s) | M-steps (s) "
        "| other (s) | compiling (s) | EM iterations | E / M calls | textons | segments "
        "| peak RSS (GB) |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: "
        "| ---: | ---: |",
    ]
    walls = ""
    for row in r["learn"]:
        if len(row.get("walls_s", [])) > 1:
            walls = (
                f"The {row['frames']:,}-frame row is the median of {len(row['walls_s'])} learns "
                f"(walls {', '.join(f'{w:.1f}' for w in row['walls_s'])} s; largest peak RSS "
                f"{row['peak_rss_gb_max']:.2f} GB)."
            )
        s = row["split_s"]
        lines.append(
            f"| {row['frames']:,} | {row['clips']} | {row['wall_s']:.1f} | "
            f"{s['state_dim']:.1f} | {s['init']:.1f} | {s['e_step']:.1f} | {s['m_step']:.1f} | "
            f"{row['other_s']:.1f} | {row['compile_s']:.1f} | {row['em_iterations']} | "
            f"{row['calls']['e_step']} / {row['calls']['m_step']} | {row['textons']} | "
            f"{row['segments']} | {row['peak_rss_gb']:.2f} |"
        )
    lines += [
        "",
        "Compiling overlaps the other columns (it happens inside them). EM iterations count "
        "every iteration of every EM run, the BIC selection's refits included. " + walls,
        "",
    ]
    e = r.get("e_step")
    if e:
        lines += [
            "## E-step against its bound",
            "",
            f"The largest texture ({e['textons']} textons, k = {e['state_dim']}) on its "
            f"{e['frames']:,} training frames: {e['warm_s']:.3f} s warm (median of 5; first "
            f"call {e['first_s']:.2f} s). Bound: {e['gemm_gflop']:.2f} GFLOP of frame-term "
            "GEMMs (per frame and texton 2((D+1)(k+1) + 2k(k+1) + 3k(k+1)): projection, "
            "dynamics and initial state) "
            f"at the measured {e['gemm_gflops_per_s']:.1f} GFLOP/s plus "
            f"{e['viterbi_gops']:.2f} G add/max operations of the Viterbi at the measured "
            f"{e['maxplus_gops_per_s']:.1f} G/s = {e['bound_s']:.3f} s. Ratio "
            f"**{e['ratio']:.2f}** (target <= 2.5) for `segment_scores` + `viterbi_segments` "
            "on the clips joined into one sequence.",
            "",
        ]
        if "learner_warm_s" in e:
            lines += [
                "The learner's own E-step on the same clips and textons (the clips packed end "
                "to end in batches of 4, the segment rows built on the host): "
                f"{e['learner_warm_s']:.3f} s warm (median of 5), ratio "
                f"**{e['learner_ratio']:.2f}**.",
                "",
            ]
    d = r.get("distributed")
    if d:
        lines += [
            "## Two processes against one",
            "",
            f"{d['frames']:,} frames; 2 processes (gloo on loopback, one CPU device each, "
            "each holding half the clips) against one process on all of them: wall "
            f"{d['processes_wall_s']:.1f} s for the pair (learns "
            f"{d['process_learn_s'][0]:.1f} s and {d['process_learn_s'][1]:.1f} s) against "
            f"{d['one_process_learn_s']:.1f} s. Largest difference of any model leaf "
            f"{d['max_abs_difference']:.2g}; integer leaves (segmentation) equal: "
            f"{d['integer_leaves_equal']}; the two processes' models bit-identical: "
            f"{d['processes_bit_identical']}. On 2 cores the pair shares the same CPUs as "
            "one process, so the wall time shows the cost of the collectives, not a speed-up.",
            "",
        ]
    return "\n".join(lines)


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        kind, rest = sys.argv[2], sys.argv[3:]
        if kind == "learn":
            print("RESULT " + json.dumps(child_learn(int(rest[0]), rest[1] == "1")), flush=True)
        elif kind == "dist":
            child_distributed(int(rest[0]), int(rest[1]), int(rest[2]), rest[3])
        else:
            child_reference(int(rest[0]), rest[1])
        return
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--sizes", default="7000,14000,28000,50000", help="frames per learn")
    ap.add_argument("--distributed-frames", type=int, default=14000)
    ap.add_argument("--no-distributed", action="store_true")
    ap.add_argument("--repeats", type=int, default=3, help="learns at the largest size")
    args = ap.parse_args()
    import tempfile

    import jax

    sizes = [int(s) for s in args.sizes.split(",")]
    res: dict[str, Any] = dict(
        command=command(),
        machine=dict(
            platform=platform.platform(),
            cpus=os.cpu_count(),
            jax=jax.__version__,
            load_start=os.getloadavg(),
        ),
        config=CONFIG,
        learn=[],
    )
    for i, n in enumerate(sizes):
        last = i == len(sizes) - 1
        runs = []
        for r in range(args.repeats if last else 1):
            log(
                f"full learn at {n:,} frames"
                + (f" (run {r + 1} of {args.repeats})" if last else "")
            )
            row = run_learn(n, estep=last and r == 0)
            log(f"  {row['wall_s']:.1f} s, {row['textons']} textons, {row['peak_rss_gb']:.2f} GB")
            res["e_step"] = row.pop("e_step", res.get("e_step"))
            runs.append(row)
        # the run of median wall time stands for the size; all walls and the largest RSS kept
        row = sorted(runs, key=lambda x: x["wall_s"])[len(runs) // 2]
        row["walls_s"] = [x["wall_s"] for x in runs]
        row["peak_rss_gb_max"] = max(x["peak_rss_gb"] for x in runs)
        res["learn"].append(row)
        write(res)  # after every row: a long run keeps what it measured
    if not args.no_distributed:
        log(f"2 processes against 1 at {args.distributed_frames:,} frames")
        with tempfile.TemporaryDirectory() as tmp:
            res["distributed"] = run_distributed(args.distributed_frames, Path(tmp))
    write(res)
    log(f"wrote {OUT / 'scale.md'}")


def write(res: dict[str, Any]) -> None:
    from mtex_jax.core import atomic_write

    res["machine"]["load_end"] = os.getloadavg()
    OUT.mkdir(parents=True, exist_ok=True)
    with atomic_write(OUT / "scale.json", "w") as f:
        json.dump(res, f, indent=1)
    with atomic_write(OUT / "scale.md", "w") as f:
        f.write(report(res))


if __name__ == "__main__":
    main()
