"""Benchmark of the implicit probabilistic motion model (issue 6; design §7, §8).

Measures, on the 14 CMU salsa clips (``../shared/data/cmu-salsa``, or ``$MTEX_SHARED/data``):

1. **Sampling speed**: per-sample cost of the tree search (IP Eq. 7–8) and of the exact O(n)
   sampler (IP Eq. 3) for growing databases — 30 Hz, d = 10 (the paper's setting) from 10³
   windows up to all 14 clips, and all 14 clips at their native 120 Hz with d = 10 (the largest
   window set the data gives). 300 probes, jit warm-up, ``block_until_ready``, compile time
   separate, medians.
2. **Sample quality**: mean squared Mahalanobis distance (IP Eq. 3) of the samples to held-out
   probes, tree vs exact, over β — the "stated factor".
3. **Synthesis smoothness** (IP §5): frame-to-frame joint motion of synthesised clips.
4. **Tracking** (IP §6): leave-one-clip-out; hyper-parameters of each prior tuned on 60_03, then
   evaluated on three other held-out clips with five filter seeds; implicit prior with
   100/300/1000 particles, constant velocity with 300/1000/3000/10000.

Writes ``benchmarks/results/implicit.md`` and ``benchmarks/results/implicit.json``.
Run: ``.venv/bin/python benchmarks/speed/bench_implicit.py [--quick]``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)  # the benchmark's choice; the library never does this

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import mtex_jax as mj

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from implicit_report import write_report
from implicit_settings import CMU, EVAL_CLIPS, N_PROBES, RESULTS, TUNE_CLIP, WINDOW

from _common import command
from mtex_jax.implicit import ImplicitModel, SynthesisConfig, tree_sample_indices
from mtex_jax.implicit._tree import exact_sample_indices
from mtex_jax.tracking import make_problem, track


# --------------------------------------------------------------------------- helpers
@eqx.filter_jit
def _tree(model, key, probes, beta):
    idx = tree_sample_indices(model.database, key, probes, beta, "uniform")
    return idx, model.database.successors[idx]


@eqx.filter_jit
def _tree_weighted(model, key, probes, beta):
    idx = tree_sample_indices(model.database, key, probes, beta, "weighted")
    return idx, model.database.successors[idx]


@eqx.filter_jit
def _exact(model, key, probes, beta):
    idx = exact_sample_indices(model.database, key, probes, beta)
    return idx, model.database.successors[idx]


def _time(fn, reps: int) -> tuple[float, float]:
    """(first call incl. compilation, median of ``reps`` later calls), seconds."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(0))
    first = time.perf_counter() - t0
    ts = []
    for r in range(1, reps + 1):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(r))
        ts.append(time.perf_counter() - t0)
    return first, float(np.median(ts))


def _mean_d2_all(model: ImplicitModel, probes) -> tuple[float, float]:
    """Average and nearest-neighbour squared distance of the probes to the database."""
    w = model.database.windows
    tot, nn = 0.0, []
    for chunk in np.array_split(np.arange(probes.shape[0]), max(1, probes.shape[0] // 100)):
        p = probes[chunk]
        d2 = jnp.sum(p**2, 1)[:, None] + jnp.sum(w**2, 1)[None] - 2 * p @ w.T
        tot += float(jnp.sum(d2))
        nn.append(np.asarray(jnp.min(d2, axis=1)))
    return tot / (probes.shape[0] * w.shape[0]), float(np.mean(np.concatenate(nn)))


def _step_stats(m: mj.Motion) -> tuple[float, float]:
    """Mean and 95th percentile over frames of the mean root-relative joint motion per frame."""
    x = np.asarray(mj.forward_kinematics(m))
    x = x - x[:, :1]
    s = np.linalg.norm(np.diff(x, axis=0), axis=-1).mean(axis=1)
    return float(s.mean()), float(np.percentile(s, 95))


def load(fps: float | None) -> list[mj.Motion]:
    files = sorted(CMU.glob("*.bvh"))
    if len(files) != 14:
        raise SystemExit(f"expected 14 CMU salsa clips in {CMU}, found {len(files)}")
    ms = [mj.read_bvh(f) for f in files]
    return ms if fps is None else [m.resample(fps) for m in ms]


# --------------------------------------------------------------------------- 1. speed
SYNTH_FRAMES = 200


def bench_speed(salsa30, salsa120, quick: bool) -> list[dict]:
    rows = []
    targets = [1000, 2000, 4000, None] if not quick else [1000, None]
    configs = []
    for t in targets:
        if t is None:
            configs.append(("30 Hz, all 14 clips", salsa30))
            continue
        k, n = 0, 0
        while n < t:
            n += salsa30[k].n_frames - 1 - WINDOW
            k += 1
        configs.append((f"30 Hz, first {k} clips", salsa30[:k]))
    if not quick:
        configs.append(("120 Hz, all 14 clips", salsa120))
    key = jax.random.PRNGKey(0)
    for label, clips in configs:
        t0 = time.perf_counter()
        model = mj.implicit.learn(clips, WINDOW)
        build = time.perf_counter() - t0
        probes = model.windows_of(clips[0])
        sel = np.linspace(0, probes.shape[0] - 1, N_PROBES).astype(int)
        probes = probes[sel] + 0.05  # probes near, not on, database windows
        beta = jnp.asarray(0.1)

        def call(fn, model=model, probes=probes, beta=beta):
            return lambda r: fn(model, jax.random.fold_in(key, r), probes, beta)

        c_tree, t_tree = _time(call(_tree), 50)
        c_w, t_w = _time(call(_tree_weighted), 50)
        reps_exact = 10 if model.database.n_examples < 20000 else 5
        c_ex, t_ex = _time(call(_exact), reps_exact)
        _, t_api = _time(call(lambda m, k, p, b: m.sample(k, p, 0.1)[1]), 20)
        # the synthesis search with the default options (issue 18: K = 16 walks, exact leaf,
        # look-ahead, run cap), one search per frame, against the same generator with the
        # exact sampler; per generated frame
        search_every = SynthesisConfig(continuation=1)
        seed = clips[0][: WINDOW + 1]

        def synth(sampler, model=model, seed=seed, cfg=search_every):
            return lambda r: model.synthesize_poses(
                jax.random.fold_in(key, r), seed, SYNTH_FRAMES, 1.0, sampler=sampler, config=cfg
            )[0]

        _, t_syn_tree = _time(synth("tree"), 5)
        _, t_syn_exact = _time(synth("exact"), 3)
        s = model.summary()
        row = {
            "database": label,
            "n": model.database.n_examples,
            "b": model.database.n_components,
            "explained_variance": model.explained_variance,
            "leaf_max": model.database.leaf_max,
            "window_dim": model.database.window_dim,
            "nonempty_leaves": s["nonempty_leaves"],
            "build_s": build,
            "tree_uniform_s": t_tree,
            "tree_weighted_s": t_w,
            "exact_s": t_ex,
            "tree_api_s": t_api,
            "compile_tree_s": c_tree - t_tree,
            "compile_tree_weighted_s": c_w - t_w,
            "compile_exact_s": c_ex - t_ex,
            "speedup_uniform": t_ex / t_tree,
            "speedup_weighted": t_ex / t_w,
            "synth_tree_frame_s": t_syn_tree / SYNTH_FRAMES,
            "synth_exact_frame_s": t_syn_exact / SYNTH_FRAMES,
            "speedup_synthesis": t_syn_exact / t_syn_tree,
        }
        rows.append(row)
        print(
            f"[speed] {label:24s} n={row['n']:6d} b={row['b']:2d} "
            f"tree {1e6 * t_tree / N_PROBES:7.2f} µs/sample, weighted "
            f"{1e6 * t_w / N_PROBES:7.2f}, exact {1e6 * t_ex / N_PROBES:8.1f} "
            f"→ ×{row['speedup_uniform']:.0f} / ×{row['speedup_weighted']:.0f}; synthesis "
            f"search (defaults) {1e6 * row['synth_tree_frame_s']:.0f} vs "
            f"{1e6 * row['synth_exact_frame_s']:.0f} µs/frame (×{row['speedup_synthesis']:.0f})",
            flush=True,
        )
    return rows


# --------------------------------------------------------------------------- 2. quality
def bench_quality(model: ImplicitModel, probes, quick: bool) -> dict:
    avg, nn = _mean_d2_all(model, probes)
    betas = [1e-3, 1e-2, 0.1, 1.0, 10.0, 100.0, 1e6] if not quick else [1e-2, 1.0]
    rows = []
    for beta in betas:
        key = jax.random.PRNGKey(11)
        b = jnp.asarray(beta)
        d = {}
        for name, fn in (
            ("tree_uniform", _tree),
            ("tree_weighted", _tree_weighted),
            ("exact", _exact),
        ):
            idx, _ = fn(model, key, probes, b)
            d[name] = float(jnp.mean(model.distance2(probes, idx)))
        idx, _ = model.sample(key, probes, beta, candidates=16)
        d["tree_sir16"] = float(jnp.mean(model.distance2(probes, idx)))
        rows.append({"beta": beta, **d})
        print(
            f"[quality] β={beta:g}: tree {d['tree_uniform']:.0f}, weighted "
            f"{d['tree_weighted']:.0f}, SIR16 {d['tree_sir16']:.0f}, exact {d['exact']:.0f} "
            f"(database average {avg:.0f}, nearest {nn:.0f})",
            flush=True,
        )
    return {"database_average": avg, "nearest_neighbour": nn, "rows": rows}


# --------------------------------------------------------------------------- 3. synthesis
def bench_synthesis(model: ImplicitModel, start: mj.Motion, quick: bool) -> dict:
    n = 300 if not quick else 60
    ref_mean, ref_p95 = _step_stats(start)
    paper = SynthesisConfig.paper()

    def paper_with(**kw) -> SynthesisConfig:
        opts = {f: getattr(paper, f) for f in SynthesisConfig.__dataclass_fields__}
        return SynthesisConfig(**(opts | kw))

    settings: list[tuple[str, float, str, SynthesisConfig]] = [  # label, β, sampler, options
        ("tree, defaults", 1.0, "tree", SynthesisConfig()),
        ("exact, defaults", 1.0, "exact", SynthesisConfig()),
        ("tree, paper settings, uniform leaf", 0.1, "tree", paper_with(leaf="uniform")),
        ("tree, paper settings (weighted leaf)", 0.1, "tree", paper),
        ("tree, paper settings, SIR K=16", 1.0, "tree", paper_with(candidates=16)),
        ("exact, paper settings", 1.0, "exact", paper),
        ("exact, paper settings", 10.0, "exact", paper),
    ]
    rows = []
    for label, beta, sampler, cfg in settings:
        stats = []
        for seed in range(3):
            m = model.synthesize(
                jax.random.PRNGKey(seed),
                start,
                n,
                beta,
                0.02,
                sampler=sampler,  # type: ignore[arg-type]
                config=cfg,
            )
        stats.append(_step_stats(m))
        mean = float(np.mean([s[0] for s in stats]))
        p95 = float(np.mean([s[1] for s in stats]))
        rows.append({"setting": label, "beta": beta, "step_mean": mean, "step_p95": p95})
        print(
            f"[synthesis] {label} β={beta:g}: step mean {1000 * mean:.0f} mm, p95 "
            f"{1000 * p95:.0f} mm (real motion {1000 * ref_mean:.0f} / {1000 * ref_p95:.0f})",
            flush=True,
        )
    return {
        "frames": n,
        "noise": 0.02,
        "seeds": [0, 1, 2],
        "reference_mean": ref_mean,
        "reference_p95": ref_p95,
        "rows": rows,
    }


# --------------------------------------------------------------------------- 4. tracking
def _run(model, problem, seeds, **kw) -> dict:
    err, rel, secs = [], [], []
    for s in seeds:
        t0 = time.perf_counter()
        r = track(jax.random.PRNGKey(s), model, problem, **kw)
        err.append(r.mean_error)
        rel.append(float(jnp.mean(r.error_root_relative)))
        secs.append(time.perf_counter() - t0)
    return {"error": err, "root_relative": rel, "seconds": secs}


def bench_tracking(salsa30, quick: bool) -> dict:
    frames = 150 if not quick else 40
    tune_seeds = (0, 1)
    eval_seeds = (0, 1, 2, 3, 4) if not quick else (0,)

    def model_without(i):
        return mj.implicit.learn([m for k, m in enumerate(salsa30) if k != i], WINDOW)

    def problem_for(model, i):
        return make_problem(
            jax.random.PRNGKey(100 + i), model, salsa30[i], n_frames=frames, start=30
        )

    # ---- tuning on 60_03
    model = model_without(TUNE_CLIP)
    problem = problem_for(model, TUNE_CLIP)
    lsig = (5.0, 10.0, 20.0, 40.0) if not quick else (20.0,)
    tuned: dict[str, dict] = {}
    grid_imp = list(itertools.product((0.01, 0.1, 1.0), (0.03, 0.1, 0.3), lsig))
    if quick:
        grid_imp = [(0.1, 0.1, 20.0)]
    tuning_log = []
    best = None
    for beta, noise, ls in grid_imp:
        r = _run(
            model,
            problem,
            tune_seeds,
            dynamics="implicit",
            n_particles=300,
            beta=beta,
            noise=noise,
            likelihood_sigma=ls,
        )
        e = float(np.mean(r["error"]))
        tuning_log.append(
            {
                "prior": "implicit",
                "n_particles": 300,
                "beta": beta,
                "noise": noise,
                "likelihood_sigma": ls,
                "error": e,
            }
        )
        if best is None or e < best[0]:
            best = (e, {"beta": beta, "noise": noise, "likelihood_sigma": ls})
    assert best is not None
    tuned["implicit"] = best[1]
    print(f"[tracking] tuned implicit prior: {best[1]} ({1000 * best[0]:.0f} mm)", flush=True)
    cv_counts = (300, 1000, 3000) if not quick else (300,)
    grid_cv = list(itertools.product((0.03, 0.1, 0.3, 1.0), lsig))
    if quick:
        grid_cv = [(0.1, 20.0)]
    for n in cv_counts:
        best = None
        for cvn, ls in grid_cv:
            r = _run(
                model,
                problem,
                tune_seeds,
                dynamics="constant_velocity",
                n_particles=n,
                cv_noise=cvn,
                likelihood_sigma=ls,
            )
            e = float(np.mean(r["error"]))
            tuning_log.append(
                {
                    "prior": "constant_velocity",
                    "n_particles": n,
                    "cv_noise": cvn,
                    "likelihood_sigma": ls,
                    "error": e,
                }
            )
            if best is None or e < best[0]:
                best = (e, {"cv_noise": cvn, "likelihood_sigma": ls})
        assert best is not None
        tuned[f"constant_velocity_{n}"] = best[1]
        print(
            f"[tracking] tuned constant velocity, {n} particles: {best[1]} "
            f"({1000 * best[0]:.0f} mm)",
            flush=True,
        )

    # ---- evaluation on other held-out clips
    runs = []
    imp_counts = (100, 300, 1000) if not quick else (300,)
    cv_eval = (300, 1000, 3000, 10000) if not quick else (300,)
    for i in EVAL_CLIPS if not quick else EVAL_CLIPS[:1]:
        model = model_without(i)
        problem = problem_for(model, i)
        for n in imp_counts:
            r = _run(
                model, problem, eval_seeds, dynamics="implicit", n_particles=n, **tuned["implicit"]
            )
            runs.append({"clip": i, "prior": "implicit", "n_particles": n, **r})
            print(
                f"[tracking] clip {i} implicit {n:5d}: "
                f"{1000 * np.mean(r['error']):.0f} ± {1000 * np.std(r['error']):.0f} mm "
                f"(root-rel. {1000 * np.mean(r['root_relative']):.0f})",
                flush=True,
            )
        for n in cv_eval:
            params = tuned[f"constant_velocity_{min(n, max(cv_counts))}"]
            r = _run(
                model, problem, eval_seeds, dynamics="constant_velocity", n_particles=n, **params
            )
            runs.append({"clip": i, "prior": "constant_velocity", "n_particles": n, **r})
            print(
                f"[tracking] clip {i} const.vel. {n:5d}: "
                f"{1000 * np.mean(r['error']):.0f} ± {1000 * np.std(r['error']):.0f} mm "
                f"(root-rel. {1000 * np.mean(r['root_relative']):.0f})",
                flush=True,
            )
    return {
        "frames": frames,
        "start": 30,
        "window": WINDOW,
        "fps": 30.0,
        "pixel_noise": 2.0,
        "observation_seed": "100 + clip index",
        "tune_clip": TUNE_CLIP,
        "tune_seeds": list(tune_seeds),
        "eval_seeds": list(eval_seeds),
        "tuned": tuned,
        "tuning": tuning_log,
        "runs": runs,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description="Benchmark of the implicit motion model.")
    ap.add_argument("--quick", action="store_true", help="small smoke run")
    ap.add_argument("--only", default="speed,quality,synthesis,tracking")
    ap.add_argument("--report-only", action="store_true", help="rewrite the .md from the JSON")
    args = ap.parse_args()
    if args.report_only:
        res = json.loads((RESULTS / "implicit.json").read_text())
        write_report(res, RESULTS / "implicit.md")
        return
    parts = set(args.only.split(","))
    RESULTS.mkdir(parents=True, exist_ok=True)
    json_path = RESULTS / ("implicit.json" if not args.quick else "implicit_quick.json")
    res: dict = json.loads(json_path.read_text()) if json_path.exists() else {}
    res = {"command": command(), **{k: v for k, v in res.items() if k != "command"}}
    res["environment"] = {
        "date": time.strftime("%Y-%m-%d"),
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "quick": args.quick,
    }
    salsa30 = load(30.0)
    if "speed" in parts:
        salsa120 = load(None) if not args.quick else []
        res["speed"] = bench_speed(salsa30, salsa120, args.quick)
    if parts & {"quality", "synthesis"}:
        model = mj.implicit.learn([m for k, m in enumerate(salsa30) if k != TUNE_CLIP], WINDOW)
        probes = model.windows_of(salsa30[TUNE_CLIP])
        probes = probes[np.linspace(0, probes.shape[0] - 1, N_PROBES).astype(int)]
        if "quality" in parts:
            res["quality"] = bench_quality(model, probes, args.quick)
        if "synthesis" in parts:
            # frame 0 of the CMU files is a capture artefact (a 0.3 m jump): seed from frame 30
            res["synthesis"] = bench_synthesis(model, salsa30[TUNE_CLIP][30:], args.quick)
    if "tracking" in parts:
        res["tracking"] = bench_tracking(salsa30, args.quick)
    json_path.write_text(json.dumps(res, indent=1))
    if {"speed", "quality", "synthesis", "tracking"} <= set(res):
        write_report(res, RESULTS / ("implicit.md" if not args.quick else "implicit_quick.md"))
    print(f"wrote {json_path}")


if __name__ == "__main__":
    main()
