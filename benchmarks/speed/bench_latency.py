"""Benchmark: what a user waits for (issue 42; design §11). For each public call: the first
call in a fresh process (persistent compilation cache cold, then warm), then the median over
10 new random lengths (200–3,000 frames) after one warm-up call, then the warm repeat, and the
programs compiled over the 10 lengths (JAX's monitoring events, as ``jax_log_compiles``).

The models: the texture learned with the defaults on the 10 training clips of the shipped
salsa data (60 Hz, the demo's settings), learned once and kept in ``--models`` (default a
temporary folder), so that every worker process loads the same model; the implicit model
(window 4) is learned on the same clips in its worker. Each (call, cache state) runs in its
own process. Last, ``mtex demo`` runs twice in fresh processes that share one compilation cache
folder, empty before the first run: the second run's saving in wall time.

Run: ``.venv/bin/python benchmarks/speed/bench_latency.py [--calls log_likelihood ...]``; writes
``benchmarks/results/latency.md`` and ``latency.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import RESULTS, command, made_by

FPS = 60.0
SEED = 0
CALLS = [
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


def worker(call: str, models: Path, loop: bool) -> dict:
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
    t0 = time.perf_counter()
    run(first_n)
    out: dict = dict(call=call, first_s=time.perf_counter() - t0, setup_s=t0 - t_import)
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


def spawn(call: str, models: Path, cache: Path | None, loop: bool) -> dict:
    env = dict(os.environ)
    env.pop("MTEX_NO_CACHE", None)
    args = [sys.executable, __file__, "--worker", call, "--models", str(models)]
    if cache is not None:
        args += ["--cache", str(cache)]
    if loop:
        args.append("--loop")
    t0 = time.perf_counter()
    res = subprocess.run(args, capture_output=True, text=True, env=env, check=False)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        raise RuntimeError(f"worker {call} failed:\n{res.stderr[-3000:]}")
    out = json.loads(res.stdout.strip().splitlines()[-1])
    out["process_s"] = wall
    return out


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--worker")
    ap.add_argument("--models", type=Path)
    ap.add_argument("--cache", type=Path)
    ap.add_argument("--loop", action="store_true")
    ap.add_argument("--calls", nargs="*", default=CALLS)
    ap.add_argument("--out", type=Path, default=RESULTS / "latency.md")
    args = ap.parse_args()
    if args.worker:
        if args.cache is not None:
            import mtex_jax as mj

            mj.enable_compilation_cache(args.cache)
        print(json.dumps(worker(args.worker, args.models, args.loop)))
        return
    models = args.models or Path(tempfile.mkdtemp(prefix="mtex_latency_models_"))
    learn_models(models)
    load0 = os.getloadavg()
    old = args.out.with_suffix(".json")
    rows = json.loads(old.read_text())["rows"] if old.exists() and args.calls != CALLS else {}
    for call in args.calls:  # a subset of calls is measured again into the existing results
        cache = Path(tempfile.mkdtemp(prefix="mtex_latency_cache_"))
        if call == "demo":
            try:
                rows[call] = demo_runs(cache) | dict(measured=time.strftime("%Y-%m-%dT%H:%M"))
            except RuntimeError as e:
                print(e, flush=True)
                continue
            print(call, json.dumps(rows[call]), flush=True)
            write(args.out, rows, load0, os.getloadavg())
            continue
        try:
            cold = spawn(call, models, cache, loop=True)  # fills the cache
            warm = spawn(call, models, cache, loop=False)
        except RuntimeError as e:  # reported, and the other calls still measured
            print(e, flush=True)
            continue
        rows[call] = dict(cold=cold, warm=warm, measured=time.strftime("%Y-%m-%dT%H:%M"))
        print(call, json.dumps(rows[call]), flush=True)
        write(args.out, rows, load0, os.getloadavg())


def write(out: Path, rows: dict, load0, load1) -> None:
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
        made_by(),
        "",
        f"Last run {max(str(r.get('measured', '')) for r in rows.values())}, "
        f"{os.cpu_count()} CPUs, float64; load average (1, 5, 15 min) {load0[0]:.1f}, "
        f"{load0[1]:.1f}, {load0[2]:.1f} before / {load1[0]:.1f}, {load1[1]:.1f}, "
        f"{load1[2]:.1f} after it.",
        "",
        "The texture: defaults on the 10 training clips at 60 Hz; the lengths: "
        f"{lengths()} (clean and edit: 20 s motions of 1201–1210 frames). First call: in a "
        "fresh process after loading the models, persistent compilation cache empty (cold) "
        "or filled by the cold process (warm). Programs: lowered to XLA over the 10 lengths "
        "after the warm-up call.",
        "",
        "A run with `--calls` measures those calls again and keeps the other rows; the last "
        "column says when each row was measured.",
        "",
        "| call | first, cold cache (s) | first, warm cache (s) | median of 10 new lengths (s) "
        "| target (s) | programs over 10 lengths | warm repeat (s) | measured |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for call in [c for c in CALLS if c in rows and c != "demo"]:
        c, w = rows[call]["cold"], rows[call]["warm"]
        med = c.get("median_s")
        lim = limits.get(call)
        mark = "" if med is None or lim is None else (" ✓" if med <= lim else " ✗")
        med_s = "–" if med is None else f"{med:.3f}{mark}"
        lim_s = "–" if lim is None else f"≤ {lim:g}"
        progs = c.get("programs", "–")
        lines.append(
            f"| `{call}` | {c['first_s']:.2f} | {w['first_s']:.2f} | {med_s} | {lim_s} "
            f"| {progs} | {c['repeat_s']:.3f} | {rows[call].get('measured', '–')} |"
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
    out.write_text("\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(
        json.dumps(dict(command=command(), rows=rows, load=[load0, load1]), indent=1) + "\n"
    )
    print(out.read_text())


if __name__ == "__main__":
    main()
