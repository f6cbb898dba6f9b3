"""The implicit-model rows of the quality benchmark, alone (issue 18).

Same split, start windows, generator calls and judge as ``bench_quality.py``'s implicit
section (30 Hz, window 10, β = 1, 20 s from held-out start windows, judged by
``metrics.MotionJudge`` against the held-out clips at 30 Hz).

``--validate`` never touches the held-out clips: it learns on 7 of the 10 training clips and
judges against the other 3 (60_09, 60_10, 60_11, or ``--validate-clips``), for choosing
defaults. Without it, the model
is learned on all 10 training clips and judged on the held-out clips (the reported figures).

Run: ``.venv/bin/python benchmarks/quality/implicit_quality.py [--validate] [NAME:k=v,...]``.
Writes ``benchmarks/results/implicit_quality{,_validation}.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import jax

jax.config.update("jax_enable_x64", True)  # as bench_quality.py

import numpy as np

import mtex_jax as mj
from mtex_jax import metrics
from mtex_jax.implicit import SynthesisConfig

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench_quality import HELD, IMPLICIT_FPS, SECONDS, TRAIN, load

from _common import RESULTS, command

VALID_HELD = ["60_09", "60_10", "60_11"]
# reference row: absolute poses of training clips played to their ends (the speed distribution
# of the training data seen through the same start windows and sample size)
REPLAY = (
    "replay of training clips (reference):"
    "velocity=0,blend=0,continuation=1000000,max_run=0,hubness=0,foot_lock=0,seam_smoothing=0"
)


def parse_config(text: str) -> tuple[str, dict[str, Any], dict[str, Any]]:
    """``name:k=v,k=v`` → (name, synthesis options, learn options); a name starting with
    ``paper`` or containing ``paper settings`` starts from ``SynthesisConfig.paper()`` with
    ``weighting=channel``."""
    name, _, rest = text.partition(":")
    syn: dict[str, Any] = {}
    lrn: dict[str, Any] = {}
    if name.startswith("paper") or "paper settings" in name:
        p = SynthesisConfig.paper()
        syn = {f: getattr(p, f) for f in SynthesisConfig.__dataclass_fields__}
        lrn = {"weighting": "channel", "recent_weight": 0.0}
    for kv in filter(None, rest.split(",")):
        k, _, v = kv.partition("=")
        if k in ("weighting",):
            lrn[k] = v
        elif k in ("min_explained", "recent_weight"):
            lrn[k] = float(v)
        elif k in ("hubness", "foot_lock", "lock_smoothing"):
            syn[k] = float(v)
        elif k == "velocity":
            syn[k] = v.lower() in ("1", "true", "yes")
        elif k == "leaf":
            syn[k] = v
        elif k == "sampler":
            syn["_sampler"] = v
        else:
            syn[k] = int(v)
    return name, syn, lrn


def run(
    configs: list[str],
    validate: bool,
    n_syn: int,
    seconds: float,
    valid_held: list[str] | None = None,
) -> dict[str, Any]:
    vh = VALID_HELD if valid_held is None else valid_held
    if validate and (not vh or any(c not in TRAIN for c in vh)):
        raise SystemExit(f"validation clips must be training clips, got {vh}")
    train_names = [t for t in TRAIN if t not in vh] if validate else TRAIN
    held_names = vh if validate else HELD
    train_raw, held_raw = load(train_names), load(held_names)
    train30 = [m.resample(IMPLICIT_FPS) for m in train_raw]
    held30 = [m.resample(IMPLICIT_FPS) for m in held_raw]
    judge30 = metrics.MotionJudge(train30, held30, fps=IMPLICIT_FPS)
    rows: dict[str, dict[str, Any]] = {k + " @30 Hz": v for k, v in judge30.real_rows().items()}
    keys = jax.random.split(jax.random.key(2026), n_syn)
    n30 = int(seconds * IMPLICIT_FPS)
    models: dict[tuple, Any] = {}
    info: dict[str, Any] = {}
    for text in configs:
        name, syn, lrn = parse_config(text)
        sampler = syn.pop("_sampler", "tree")
        key_l = tuple(sorted(lrn.items()))
        if key_l not in models:
            t0 = time.perf_counter()
            models[key_l] = mj.implicit.learn(train30, window=10, fps=IMPLICIT_FPS, **lrn)
            m = models[key_l]
            info[str(dict(lrn))] = m.summary() | {"learn_s": time.perf_counter() - t0}
        model = models[key_l]
        cfg = SynthesisConfig(**syn)
        succ = metrics.successor_array(model.database.clip_index, model.database.frame_index)
        motions, idx = [], []
        t0 = time.perf_counter()
        for j, k in enumerate(keys):
            h = held30[j % len(held30)]
            s0 = 30 + 97 * (j // len(held30))  # as bench_quality.py (8 syntheses)
            s0 = s0 % max(h.n_frames - model.database.window - 1, 1)  # more syntheses: wrap
            start = h[s0 : s0 + model.database.window + 1]
            motions.append(model.synthesize(k, start, n30, beta=1.0, sampler=sampler, config=cfg))
            idx.append(
                np.asarray(
                    model.synthesize_poses(k, start, n30, 1.0, sampler=sampler, config=cfg)[1]
                )
            )
        wall = time.perf_counter() - t0
        r = judge30.judge(motions, indices=idx, successor=succ, index_fps=IMPLICIT_FPS)
        r["wall_s"] = wall
        r["config"] = text  # type: ignore[assignment]
        rows[name] = r
        print(
            f"{name:28s} speed {r['speed_ratio']:6.2f} acc {r['acceleration_ratio']:6.2f} "
            f"jerk {r['jerk_ratio']:6.2f} jumps {r['jump_share_above_p99']:.3f} "
            f"skate {r['skating_median']:.3f} copy {r.get('copy_fraction', float('nan')):.2f} "
            f"longest {r.get('copy_longest_s', float('nan')):.1f}s  [{wall:.0f}s] {text}",
            flush=True,
        )
    return {
        "validate": validate,
        "syntheses": n_syn,
        "seconds": seconds,
        "train": train_names,
        "held": held_names,
        "rows": rows,
        "models": info,
    }


def _f(x: Any, nd: int = 2) -> str:
    return "—" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))


def write(res: dict[str, Any], out: Path) -> None:
    res = {"command": command(), **res}
    out.with_suffix(".json").write_text(json.dumps(res, indent=1, default=float))
    real = next(v for k, v in res["rows"].items() if k.startswith("real"))
    L = [
        "# Implicit model: motion quality" + (" (validation split)" if res["validate"] else ""),
        "",
        f"Made by: `{res['command']}`",
        "",
        f"Train {', '.join(res['train'])}; judged against {', '.join(res['held'])}; "
        f"30 Hz, window 10, β = 1, no noise, {res.get('syntheses', 8)} syntheses of "
        f"{res.get('seconds', 20.0):g} s from start windows of the judged clips. "
        "Ratios: W1 distance over the real-vs-real floor. Jumps: share of frame-to-frame "
        "maximum joint jumps above the judged clips' p99 (real clips: "
        f"{_f(real.get('jump_share_above_p99'), 3)}). Copy: share of frames continuing the "
        "previous database frame; longest verbatim run. Skating: median horizontal speed of "
        "low feet (``ContactModel.skating``).",
        "",
    ]
    for k, m in res["models"].items():
        L.append(
            f"- model {k}: {m['n_examples']} windows, b = {m['n_components']}, explained "
            f"variance {100 * m['explained_variance']:.1f} %, leaf max {m['leaf_max']}"
        )
    L += [
        "",
        "| set | speed | acc | jerk | jumps > p99 | skating (m/s) | copy | longest (s) | config |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    for name, r in res["rows"].items():
        L.append(
            f"| {name} | {_f(r['speed_ratio'])} | {_f(r['acceleration_ratio'])} "
            f"| {_f(r['jerk_ratio'])} | {_f(r['jump_share_above_p99'], 3)} "
            f"| {_f(r.get('skating_median'))} | {_f(r.get('copy_fraction'))} "
            f"| {_f(r.get('copy_longest_s'), 1)} "
            f"| `{r.get('config', '')}` |"
        )
    out.with_suffix(".md").write_text("\n".join(L) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--validate", action="store_true", help="7 training clips vs 3 (no held-out)")
    ap.add_argument(
        "--validate-clips",
        default=",".join(VALID_HELD),
        help="with --validate: the training clips judged (the others are learned)",
    )
    ap.add_argument("--syntheses", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=SECONDS)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument(
        "configs",
        nargs="*",
        default=[
            "implicit tree sampler (defaults):",
            "implicit exact sampler (defaults):sampler=exact",
            "tree, no seam smoothing:seam_smoothing=0",
            "tree, the defaults before seam smoothing (lock smoothing 0.7):"
            "seam_smoothing=0,lock_smoothing=0.7",
            "tree, no foot lock:foot_lock=0",
            "tree, window distance of the paper (recent_weight 0):recent_weight=0",
            "tree, no recent weight, foot lock or seam smoothing:"
            "recent_weight=0,foot_lock=0,seam_smoothing=0",
            "implicit tree sampler, paper settings:",
            "implicit exact sampler, paper settings:sampler=exact",
            REPLAY,
        ],
        help="NAME:k=v,... (SynthesisConfig fields, weighting, min_explained, sampler)",
    )
    args = ap.parse_args()
    vh = args.validate_clips.split(",")
    res = run(args.configs, args.validate, args.syntheses, args.seconds, vh)
    stem = "implicit_quality_validation" if args.validate else "implicit_quality"
    if args.validate and vh != VALID_HELD:
        stem += "_" + "-".join(vh)
    write(res, args.out or RESULTS / stem)


if __name__ == "__main__":
    main()
