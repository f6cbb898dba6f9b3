"""Benchmark: what a user waits for (issue 42; design §11). For each public call: the first
call in a fresh process (persistent compilation cache cold, then warm), then the median over
10 new random lengths (200–3,000 frames) after one warm-up call, then the warm repeat, and the
programs compiled over the 10 lengths (JAX's monitoring events, as ``jax_log_compiles``).

The models: the texture learned with the defaults on the 10 training clips of the shipped
salsa data (60 Hz, the demo's settings), learned once and kept in ``--models`` (default a
temporary folder), so that every worker process loads the same model; the implicit model
(window 4) is learned on the same clips in its worker. Each (call, cache state) runs in its
own process. Last, ``mtex demo`` runs twice in fresh processes that share one compilation cache
folder, empty before the first run: the second run's saving in wall time. ``learn`` is the
default learn on the 10 training clips, timed whole in a fresh process (no loop over lengths).
Every worker also reports the compile time of its first call (JAX's monitoring events
``/jax/core/compile/backend_compile_duration`` and ``jaxpr_trace_duration``, summed) and the
lines of its stderr that contain "Constant folding" (XLA's slow-folding alarm).

``--src DIR`` runs the workers on the package in ``DIR`` (``PYTHONPATH=DIR``, e.g. an older
worktree's ``src``), ``--label`` names that tree. ``--baseline DIR`` measures, instead of the
main table, a before / after section: the cold compile and cold first call of each of
``--calls`` with the package from ``DIR`` (before) and from ``--src`` (after), ``--repeats``
fresh processes of each, interleaved (before, after, before, after, ...), each with its own
empty cache; the main table's rows are kept, and a main-table run keeps the section.
``--idle CORES`` starts each process once the rest of the machine uses fewer cores (a shared
machine); every process records the cores the others used while it ran.

Run: ``.venv/bin/python benchmarks/speed/bench_latency.py [--calls log_likelihood ...]
[--models DIR] [--src DIR] [--label TEXT] [--baseline DIR --baseline-label TEXT --repeats 3]
[--idle CORES --idle-wait S]``;
writes ``benchmarks/results/latency.md`` and ``latency.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import REPO, RESULTS, command

FPS = 60.0
SEED = 0
CALLS = [
    "learn",
    "log_likelihood",
    "segment",
    "synthesize",
    "implicit_synthesize",
    "score_held_out",
    "clean",
    "edit",
    "synthesize_texton",
    "texture_predict",
    "demo",
]
COMPILE_EVENTS = (  # JAX's monitoring events of a compilation (jax 0.10)
    "/jax/core/compile/jaxpr_trace_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "/jax/core/compile/backend_compile_duration",
)
FOLDING = "Constant folding"  # XLA's alarm: "Constant folding an instruction is taking > 1s"


def lengths(n: int = 10) -> list[int]:
    return [int(x) for x in np.random.default_rng(SEED).integers(200, 3001, n)]


# ------------------------------------------------------------------------------ worker side


def _setup(models: Path):
    import jax

    jax.config.update("jax_enable_x64", True)  # the benchmark's choice
    import mtex_jax as mj

    _, held_names = mj.io.salsa_split()
    tex = mj.load_texture(models / "texture.npz")
    held = [mj.io.load_salsa(n).resample(FPS) for n in held_names]
    return jax, mj, tex, held


class CompileClock:
    """Sums the durations of JAX's compile events since the process started; ``since(mark)``
    gives the sums after a ``mark()``."""

    def __init__(self) -> None:
        import jax

        self.total: dict[str, float] = dict.fromkeys(COMPILE_EVENTS, 0.0)
        self.count = 0

        def listener(event: str, duration_secs: float, **kwargs: object) -> None:
            if event in self.total:
                self.total[event] += duration_secs
                self.count += event == COMPILE_EVENTS[-1]

        jax.monitoring.register_event_duration_secs_listener(listener)

    def mark(self) -> tuple[dict[str, float], int]:
        return dict(self.total), self.count

    def since(self, mark: tuple[dict[str, float], int]) -> dict:
        d = {e: self.total[e] - mark[0][e] for e in COMPILE_EVENTS}
        return dict(
            compile_s=d[COMPILE_EVENTS[2]],  # XLA's backend compile, where constants are folded
            trace_s=d[COMPILE_EVENTS[0]],
            lower_s=d[COMPILE_EVENTS[1]],
            compiled=self.count - mark[1],  # programs compiled by XLA (not from the cache)
        )


def learn_worker(clock: CompileClock) -> dict:
    """The default learn on the 10 training clips, timed whole (compilation included)."""
    t_import = time.perf_counter()
    import jax

    jax.config.update("jax_enable_x64", True)
    import mtex_jax as mj

    train_names, _ = mj.io.salsa_split()
    train = [mj.io.load_salsa(n).resample(FPS) for n in train_names]
    mark = clock.mark()
    t0 = time.perf_counter()
    tex = mj.learn(train, mj.LearnConfig(fps=FPS))
    jax.block_until_ready(tex.textons)
    first = time.perf_counter() - t0
    out = dict(call="learn", first_s=first, setup_s=t0 - t_import) | clock.since(mark)
    return out | dict(n_textons=int(tex.n_textons), module=mj.__file__)


def worker(call: str, models: Path, loop: bool, clock: CompileClock) -> dict:
    if call == "learn":
        return learn_worker(clock)
    t_import = time.perf_counter()
    jax, mj, tex, held = _setup(models)
    from mtex_jax.core import count_compiles

    Y = np.asarray(tex.observations(held[0]))  # the longest real clip of the split
    Y = np.concatenate([Y, Y[::-1], Y])[:3000]
    key = jax.random.key(1)
    fm = tex.feature_map
    implicit = None
    if call == "implicit_synthesize":  # learned here (a few seconds; it has no model file)
        train_names, _ = mj.io.salsa_split()
        train = [mj.io.load_salsa(n).resample(FPS) for n in train_names]
        implicit = mj.implicit.learn(train, 4)
        seed_clip = held[0]
    contacts = tex.contacts if hasattr(tex, "contacts") else None
    if call in ("clean", "edit") and contacts is None:
        train_names, _ = mj.io.salsa_split()
        contacts = mj.motion.fit_contacts(
            [mj.io.load_salsa(n).resample(FPS) for n in train_names], fps=FPS
        )

    def run(n: int):
        if call == "log_likelihood":
            return tex.log_likelihood(Y[:n])
        if call == "segment":
            return tex.segment(Y[:n]).score.block_until_ready()
        if call == "synthesize":
            return mj.synthesize(key, tex, n_frames=n).Y.block_until_ready()
        if call == "implicit_synthesize":
            m = mj.implicit.synthesize(implicit, key, seed_clip, n, 0.1)
            return m.root_positions.block_until_ready()
        if call == "score_held_out":
            return np.asarray(tex.log_likelihood(held))
        if call == "synthesize_texton":  # texton 0 between two key poses (the bridge)
            t0_ = jax.tree.map(lambda a: a[0], tex.textons)
            kp = np.asarray(tex.key_poses)
            return mj.texture.synthesize_texton(key, t0_, n, kp[0], kp[-1]).block_until_ready()
        if call == "texture_predict":  # a metric's kernel: segmentation + one-step predictions
            return np.asarray(mj.metrics.texture_predict(tex, Y[:n])[0])
        assert fm is not None  # a texture learned from clips has its feature map
        motion = fm.decode(Y[:n])
        if call == "clean":
            return mj.edit.clean(tex, motion, contacts).Y.block_until_ready()
        if call == "edit":
            sk = fm.skeleton
            hand = sk.names.index("rHand")  # the salsa skeleton's right hand
            P = np.asarray(fm.joint_positions(Y[:n]))  # (T, J, 3)
            reach = 0.05 * float(np.ptp(P[0], axis=0).max())  # 5 % of the body's size
            target = P[n // 2, hand] + reach
            cons = mj.edit.make_constraints(sk, n, tex.obs_dim, positions=[(hand, n // 2, target)])
            return mj.edit.edit(tex, motion, cons).Y.block_until_ready()
        raise ValueError(call)

    twenty_s = int(20 * FPS)  # clean and edit: a 20 s motion
    first_n = twenty_s if call in ("clean", "edit") else 1500
    mark = clock.mark()
    t0 = time.perf_counter()
    run(first_n)
    out: dict = dict(call=call, first_s=time.perf_counter() - t0, setup_s=t0 - t_import)
    out |= clock.since(mark) | dict(module=mj.__file__)
    if not loop:
        return out
    t0 = time.perf_counter()
    run(first_n)
    out["repeat_s"] = time.perf_counter() - t0
    if call == "score_held_out":
        return out
    ns = lengths() if call not in ("clean", "edit") else [twenty_s + d for d in range(1, 11)]
    times = []
    with count_compiles() as c:
        for n in ns:
            t0 = time.perf_counter()
            run(n)
            times.append(time.perf_counter() - t0)
    out.update(lengths=ns, times_s=times, median_s=float(np.median(times)), programs=c.programs)
    return out


# ------------------------------------------------------------------------------ driver side


def learn_models(models: Path) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    import mtex_jax as mj

    models.mkdir(parents=True, exist_ok=True)
    train_names, _ = mj.io.salsa_split()
    train = [mj.io.load_salsa(n).resample(FPS) for n in train_names]
    if not (models / "texture.npz").exists():
        print("learning the texture (defaults, 60 Hz, 10 training clips)", flush=True)
        mj.learn(train, mj.LearnConfig(fps=FPS)).save(models / "texture.npz")


def cpu_busy() -> float:
    """CPU-seconds that all cores have spent busy since boot (``/proc/stat``)."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:9]]
    return (sum(v) - v[3] - v[4]) / os.sysconf("SC_CLK_TCK")


def wait_idle(cores: float | None, wait_s: float) -> float | None:
    """Wait (at most ``wait_s``) until the other processes use less than ``cores`` CPU cores
    over 2 s; the use last measured."""
    if cores is None:
        return None
    t_end = time.monotonic() + wait_s
    while True:
        b0 = cpu_busy()
        time.sleep(2.0)
        used = (cpu_busy() - b0) / 2.0
        if used < cores or time.monotonic() > t_end:
            return used


IDLE: dict = dict(cores=None, wait_s=600.0)  # --idle, --idle-wait


def spawn(call: str, models: Path, cache: Path | None, loop: bool, src: Path | None = None) -> dict:
    env = dict(os.environ)
    env.pop("MTEX_NO_CACHE", None)
    if src is not None:  # the package from another tree, ahead of the installed one
        env["PYTHONPATH"] = os.pathsep.join([str(src), *filter(None, [env.get("PYTHONPATH")])])
    args = [sys.executable, __file__, "--worker", call, "--models", str(models)]
    if cache is not None:
        args += ["--cache", str(cache)]
    if loop:
        args.append("--loop")
    idle = wait_idle(IDLE["cores"], IDLE["wait_s"])
    load = os.getloadavg()[0]
    ru0, busy0 = resource.getrusage(resource.RUSAGE_CHILDREN), cpu_busy()
    t0 = time.perf_counter()
    res = subprocess.run(args, capture_output=True, text=True, env=env, check=False)
    wall = time.perf_counter() - t0
    ru1, busy1 = resource.getrusage(resource.RUSAGE_CHILDREN), cpu_busy()
    own = ru1.ru_utime + ru1.ru_stime - ru0.ru_utime - ru0.ru_stime  # the worker's CPU time
    if res.returncode != 0:
        raise RuntimeError(f"worker {call} failed:\n{res.stderr[-3000:]}")
    out = json.loads(res.stdout.strip().splitlines()[-1])
    if src is not None and not Path(out["module"]).is_relative_to(src):
        raise RuntimeError(f"worker {call} imported {out['module']}, not the package in {src}")
    folding = [ln for ln in res.stderr.splitlines() if FOLDING in ln]
    other = max(0.0, (busy1 - busy0 - own) / wall)  # cores the other processes used meanwhile
    out |= dict(process_s=wall, folding=len(folding), load1=load, other_cores=other)
    out |= dict(cpu_s=own, idle_before=idle)
    if folding:
        out["folding_first"] = folding[0][-300:]
    return out


def tree_label(src: Path | None) -> str:
    """The commit of the tree the workers import (``--src``, else this checkout), and whether
    its ``src`` folder has uncommitted changes."""
    where = src if src is not None else REPO / "src"
    git = ["git", "-C", str(where)]
    rev = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    if rev.returncode != 0:
        return str(where)
    dirty = subprocess.run(
        [*git, "status", "--porcelain", "--", "."], capture_output=True, text=True
    )
    return rev.stdout.strip() + (" + uncommitted changes" if dirty.stdout.strip() else "")


def demo_runs(cache: Path) -> dict:
    """``mtex demo`` twice in fresh processes sharing one empty compilation cache folder."""
    env = dict(os.environ, MTEX_JAX_CACHE=str(cache))
    env.pop("MTEX_NO_CACHE", None)
    walls = []
    for _ in range(2):
        out = Path(tempfile.mkdtemp(prefix="mtex_latency_demo_"))
        args = [sys.executable, "-m", "mtex_jax", "demo", "--out", str(out)]
        t0 = time.perf_counter()
        res = subprocess.run(args, capture_output=True, text=True, env=env, check=False)
        walls.append(time.perf_counter() - t0)
        shutil.rmtree(out, ignore_errors=True)  # the demo's files are not what is measured
        if res.returncode != 0:
            raise RuntimeError(f"mtex demo failed:\n{res.stderr[-3000:]}")
    return dict(cold_s=walls[0], warm_s=walls[1], saving=1.0 - walls[1] / walls[0])


def before_after(args, models: Path, doc: dict) -> None:
    """The cold compile and first call of each of ``args.calls`` with the package from
    ``args.baseline`` (before) and from ``args.src`` (after): ``args.repeats`` fresh processes
    of each, interleaved, each with an empty compilation cache; written after every pair."""
    trees = dict(
        before=(args.baseline, args.baseline_label or tree_label(args.baseline)),
        after=(args.src, args.label or tree_label(args.src)),
    )
    calls = [c for c in args.calls if c != "demo"]
    section: dict[str, Any] = dict(
        command=command(),
        labels={k: v[1] for k, v in trees.items()},
        src={k: None if v[0] is None else str(v[0]) for k, v in trees.items()},
        repeats=args.repeats,
        idle=[args.idle, args.idle_wait],
        load=[list(os.getloadavg())],
        measured=time.strftime("%Y-%m-%dT%H:%M"),
        calls={c: dict(before=[], after=[]) for c in calls},
    )
    doc["before_after"] = section
    warm_up = "log_likelihood" if "log_likelihood" in calls else calls[0]
    for name, (src, _) in trees.items():  # discarded: the file system cache of each tree
        spawn(warm_up, models, Path(tempfile.mkdtemp(prefix="mtex_latency_cache_")), False, src)
        print("warm-up", name, flush=True)
    for r in range(args.repeats):
        for call in calls:
            for name, (src, _) in trees.items():
                cache = Path(tempfile.mkdtemp(prefix="mtex_latency_cache_"))
                res = spawn(call, models, cache, loop=False, src=src)
                shutil.rmtree(cache, ignore_errors=True)
                section["calls"][call][name].append(res)
                print(r, call, name, json.dumps(res), flush=True)
            section["load"].append(list(os.getloadavg()))
            write(args.out, doc)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--worker")
    ap.add_argument("--models", type=Path)
    ap.add_argument("--cache", type=Path)
    ap.add_argument("--loop", action="store_true")
    ap.add_argument("--calls", nargs="*", default=CALLS)
    ap.add_argument("--out", type=Path, default=RESULTS / "latency.md")
    ap.add_argument("--src", type=Path, help="workers import the package from DIR (PYTHONPATH)")
    ap.add_argument("--label", help="the name of the --src tree (default: its commit)")
    ap.add_argument("--baseline", type=Path, help="before / after section: DIR is 'before'")
    ap.add_argument("--baseline-label", help="the name of the --baseline tree")
    ap.add_argument("--repeats", type=int, default=3, help="processes per tree (--baseline)")
    ap.add_argument(
        "--idle", type=float, help="before each process, wait until others use < IDLE cores"
    )
    ap.add_argument("--idle-wait", type=float, default=600.0, help="at most this long (s)")
    args = ap.parse_args()
    IDLE.update(cores=args.idle, wait_s=args.idle_wait)
    if args.worker:
        clock = CompileClock()  # before any compilation of the process
        if args.cache is not None:
            import mtex_jax as mj

            mj.enable_compilation_cache(args.cache)
        print(json.dumps(worker(args.worker, args.models, args.loop, clock)))
        return
    for d in (args.src, args.baseline):
        if d is not None and not (d / "mtex_jax" / "__init__.py").exists():
            ap.error(f"{d} holds no mtex_jax package")
    args.src = args.src and args.src.resolve()
    args.baseline = args.baseline and args.baseline.resolve()
    models = args.models or Path(tempfile.mkdtemp(prefix="mtex_latency_models_"))
    learn_models(models)
    old = args.out.with_suffix(".json")
    doc = json.loads(old.read_text()) if old.exists() else {}
    if args.baseline is not None:  # the section only; the main table's rows are kept
        before_after(args, models, doc)
        return
    load0 = os.getloadavg()
    if args.calls == CALLS:
        doc["rows"] = {}
    rows = doc.setdefault("rows", {})
    label = args.label or tree_label(args.src)
    doc |= dict(command=command(), load=[load0, load0])
    for call in args.calls:  # a subset of calls is measured again into the existing results
        cache = Path(tempfile.mkdtemp(prefix="mtex_latency_cache_"))
        if call == "demo":
            try:
                rows[call] = demo_runs(cache) | dict(measured=time.strftime("%Y-%m-%dT%H:%M"))
            except RuntimeError as e:
                print(e, flush=True)
                continue
            print(call, json.dumps(rows[call]), flush=True)
            doc["load"] = [load0, os.getloadavg()]
            write(args.out, doc)
            continue
        try:
            cold = spawn(call, models, cache, loop=call != "learn", src=args.src)  # fills it
            warm = spawn(call, models, cache, loop=False, src=args.src)
        except RuntimeError as e:  # reported, and the other calls still measured
            print(e, flush=True)
            continue
        rows[call] = dict(cold=cold, warm=warm, measured=time.strftime("%Y-%m-%dT%H:%M"))
        if args.src is not None or args.label:  # another tree than this checkout's
            rows[call]["tree"] = label
        print(call, json.dumps(rows[call]), flush=True)
        doc["load"] = [load0, os.getloadavg()]
        write(args.out, doc)


def _med(xs: list[float]) -> float:
    return float(np.median(xs))


def write_before_after(sec: dict) -> list[str]:
    lab = sec["labels"]
    loads = [s["load1"] for c in sec["calls"].values() for v in c.values() for s in v]
    idle = (sec.get("idle") or [None])[0]
    wait = (
        ""
        if idle is None
        else f"; each process started once the others used < {idle:g} cores over 2 s "
        f"(waiting at most {sec['idle'][1]:g} s)"
    )
    lines = [
        "",
        "## Before / after: the residual prefix sums of full-dimensional textons (issue 57 item 4)",
        "",
        f"Made by: `{sec['command']}`",
        "",
        f"Measured {sec['measured']}, {os.cpu_count()} CPUs, float64. Before: `{lab['before']}` "
        f"(package from `{sec['src']['before']}`); after: `{lab['after']}` (package from "
        f"`{sec['src']['after'] or 'this checkout'}`). Each value: the median of "
        f"{sec['repeats']} fresh processes, [the values]; the processes ran interleaved "
        "(before, after, before, after, ...), each with its own empty persistent compilation "
        "cache and the same texture file. XLA compile: the backend compile durations of the "
        "first call, summed (JAX's `/jax/core/compile/backend_compile_duration`); trace: "
        "`/jax/core/compile/jaxpr_trace_duration`, summed (nested traces counted in each); "
        "first call: its wall time after the process loaded its data (`learn`: the whole "
        "default learn on the 10 training clips; `log_likelihood` and `segment`: 1,500 frames). "
        f'"{FOLDING}": the lines of the process\'s stderr that contain it, per process. '
        f"Load average (1 min) before the processes: {min(loads, default=0):.1f}–"
        f"{max(loads, default=0):.1f}{wait}. Other processes: the CPU cores that the rest "
        "of the machine kept busy during each process (all cores' busy time from `/proc/stat` "
        "less the worker's own CPU time, over its wall time).",
        "",
        "| call | tree | XLA compile (s) | trace (s) | first call, cold cache (s) "
        f'| "{FOLDING}" lines | other processes (cores) |',
        "|---|---|---:|---:|---:|---:|---|",
    ]

    def others(v: list[dict]) -> str:
        return ", ".join(f"{s['other_cores']:.2f}" if "other_cores" in s else "–" for s in v)

    def cell(v: list[dict], key: str) -> str:
        xs = [s[key] for s in v]
        return f"{_med(xs):.2f} [{', '.join(f'{x:.2f}' for x in xs)}]" if xs else "–"

    for call, res in sec["calls"].items():
        b, a = res["before"], res["after"]
        for name, v in (("before", b), ("after", a)):
            if not v:
                continue
            first = f"`{call}`" if name == "before" or not b else ""
            lines.append(
                f"| {first} | {name} `{lab[name]}` | {cell(v, 'compile_s')} | "
                f"{cell(v, 'trace_s')} | {cell(v, 'first_s')} | "
                f"{', '.join(str(s['folding']) for s in v)} | {others(v)} |"
            )
        if a and b:
            ratio = {
                k: _med([s[k] for s in a]) / _med([s[k] for s in b])
                for k in ("compile_s", "trace_s", "first_s")
            }
            lines.append(
                f"| | after / before | {ratio['compile_s']:.2f} | {ratio['trace_s']:.2f} | "
                f"{ratio['first_s']:.2f} | | |"
            )
    return lines


def write(out: Path, doc: dict) -> None:
    rows: dict = doc.get("rows", {})
    load0, load1 = doc.get("load") or [[0.0] * 3] * 2
    limits = dict(
        log_likelihood=1.0,
        segment=1.0,
        synthesize=1.0,
        implicit_synthesize=1.0,
        clean=2.0,
        edit=2.0,
        synthesize_texton=1.0,
        texture_predict=1.0,
    )
    lines = [
        "# Latency of the public calls (issue 42)",
        "",
        f"Made by: `{doc.get('command', command())}`",
        "",
        f"Last run {max(str(r.get('measured', '')) for r in rows.values())}, "
        f"{os.cpu_count()} CPUs, float64; load average (1, 5, 15 min) {load0[0]:.1f}, "
        f"{load0[1]:.1f}, {load0[2]:.1f} before / {load1[0]:.1f}, {load1[1]:.1f}, "
        f"{load1[2]:.1f} after it.",
        "",
        "The texture: defaults on the 10 training clips at 60 Hz; the lengths: "
        f"{lengths()} (clean and edit: 20 s motions of 1201–1210 frames). First call: in a "
        "fresh process after loading the models, persistent compilation cache empty (cold) "
        "or filled by the cold process (warm); `learn`: the default learn of that texture, "
        "whole. Compile: XLA's backend compile durations during the cold first call, summed "
        "(JAX's `/jax/core/compile/backend_compile_duration`). Programs: lowered to XLA over "
        "the 10 lengths after the warm-up call.",
        "",
        "A run with `--calls` measures those calls again and keeps the other rows; the last "
        "column says when each row was measured (and the tree, if measured with `--src` or "
        "`--label`).",
        "",
        "| call | first, cold cache (s) | of it compile (s) | first, warm cache (s) "
        "| median of 10 new lengths (s) | target (s) | programs over 10 lengths "
        "| warm repeat (s) | measured |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for call in [c for c in CALLS if c in rows and c != "demo"]:
        c, w = rows[call]["cold"], rows[call]["warm"]
        med = c.get("median_s")
        lim = limits.get(call)
        mark = "" if med is None or lim is None else (" ✓" if med <= lim else " ✗")
        med_s = "–" if med is None else f"{med:.3f}{mark}"
        lim_s = "–" if lim is None else f"≤ {lim:g}"
        progs = c.get("programs", "–")
        comp = "–" if "compile_s" not in c else f"{c['compile_s']:.2f}"
        rep = "–" if "repeat_s" not in c else f"{c['repeat_s']:.3f}"
        when = rows[call].get("measured", "–")
        if "tree" in rows[call]:
            when += f" (`{rows[call]['tree']}`)"
        lines.append(
            f"| `{call}` | {c['first_s']:.2f} | {comp} | {w['first_s']:.2f} | {med_s} | {lim_s} "
            f"| {progs} | {rep} | {when} |"
        )
    if "score_held_out" in rows:
        r = rows["score_held_out"]
        lines += [
            "",
            f"- the 4 held-out clips scored as one list: {r['warm']['first_s']:.2f} s in a fresh "
            f"process with the cache warm (target ≤ 3 s), {r['cold']['repeat_s']:.3f} s warm "
            "(target ≤ 0.5 s).",
        ]
    if "demo" in rows:
        d = rows["demo"]
        ok = "✓" if d["saving"] >= 0.3 else "✗"
        lines += [
            "",
            f"- `mtex demo` twice in fresh processes, one compilation cache folder (empty "
            f"before the first, measured {d['measured']}): {d['cold_s']:.1f} s, then "
            f"{d['warm_s']:.1f} s with the cache warm: {100 * d['saving']:.0f} % less wall time "
            f"(target ≥ 30 %) {ok}.",
        ]
    if "before_after" in doc:
        lines += write_before_after(doc["before_after"])
    out.write_text("\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1) + "\n")
    print(out.read_text())


if __name__ == "__main__":
    main()
