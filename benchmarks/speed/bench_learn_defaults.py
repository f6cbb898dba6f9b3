"""Benchmark: the cost of learning with the default settings (issue 16) against the paper's
model, on all 14 CMU salsa clips at 60 Hz, and the E-step at the paper's scale.

Rows, in one run on the same machine:

1. Learning the 14 clips at 60 Hz (``LearnConfig(tmin=60, tmax=180, fps=60)``, defaults
   otherwise: BIC state dimension, residual/full observation model, log-normal durations,
   stable textons, BIC texton selection), wall time including compilation, with the texture's
   size; beside the paper's model as the README used it before
   (``LearnConfig.paper(min_segments=3)``). With the defaults also at 120 Hz (54,990
   frames, the same lengths in frames), for the texture's size there.
   ``--repeats`` runs each in a fresh process (no compilation cache shared) and reports the
   median.
2. The E-step (segment scores + duration-aware Viterbi) of the default texture on the 14 clips
   at 60 Hz joined three times (about 55k frames, the paper's scale), warm (median of 5) and
   first call.

Run: ``.venv/bin/python benchmarks/speed/bench_learn_defaults.py``; writes
``benchmarks/results/learn_defaults.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import RESULTS, SHARED, command

OUT = RESULTS / "learn_defaults.md"

_CHILD = r"""
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import mtex_jax as mj
from pathlib import Path
cmu = Path(sys.argv[1])
which = sys.argv[2]
clips = [mj.read_bvh(f)[4:] for f in sorted(cmu.glob("*.bvh"))]
fps = 120.0 if which == "default120" else 60.0
if which in ("default", "default120"):
    cfg = mj.LearnConfig(tmin=60, tmax=180, fps=fps)
else:
    cfg = mj.LearnConfig.paper(tmin=60, tmax=180, fps=60.0, min_segments=3)
t0 = time.perf_counter()
tex = mj.learn(clips, cfg)
jax.block_until_ready(tex.textons.mu)
wall = time.perf_counter() - t0
lab = np.asarray(tex.segments)[:, 3]
cnt = np.bincount(lab, minlength=tex.n_textons)
out = dict(wall_s=wall, textons=tex.n_textons, segments=int(lab.size),
           segments_per_texton=float(cnt.mean()), single_segment_share=float(np.mean(cnt == 1)),
           state_dim=tex.config.state_dim, observation=tex.config.observation,
           frames=int(sum(m.resample(fps).n_frames for m in clips)), fps=fps)
if which == "default":  # the E-step at the paper's scale
    from mtex_jax.texture import segment_scores, viterbi_segments
    fm = tex.feature_map
    y120 = np.concatenate([np.asarray(fm.encode(m.resample(60.0))) for m in clips] * 3)
    Y = jax.numpy.asarray(y120)
    lM, lpi = jax.numpy.log(tex.M), jax.numpy.log(tex.pi)
    n = jax.numpy.asarray(Y.shape[0])
    ld = tex.log_durations
    def e_step():
        sc = segment_scores(tex.textons, Y)
        return viterbi_segments(sc, lM, lpi, n, 60, 180, ld).score
    t0 = time.perf_counter(); jax.block_until_ready(e_step()); first = time.perf_counter() - t0
    ts = []
    for _ in range(5):
        t0 = time.perf_counter()
        jax.block_until_ready(e_step())
        ts.append(time.perf_counter() - t0)
    out["e_step"] = dict(frames=int(Y.shape[0]), first_s=first, warm_s=float(np.median(ts)))
print("RESULT " + json.dumps(out))
"""


def run(which: str) -> dict:
    p = subprocess.run(
        [sys.executable, "-c", _CHILD, str(SHARED / "data" / "cmu-salsa"), which],
        capture_output=True,
        text=True,
        check=True,
    )
    line = next(ln for ln in p.stdout.splitlines() if ln.startswith("RESULT "))
    return json.loads(line[len("RESULT ") :])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument(
        "--rows",
        default="default,paper,default120",
        help="rows to (re-)run; the others are kept from the previous results file",
    )
    args = ap.parse_args()
    js = OUT.with_suffix(".json")
    res: dict = json.loads(js.read_text()) if js.exists() else {}
    res = {"command": command(), **{k: v for k, v in res.items() if k != "command"}}
    for which in args.rows.split(","):
        load = os.getloadavg()[0]
        reps = 1 if which == "default120" else args.repeats
        runs = [run(which) for _ in range(reps)]
        walls = sorted(r["wall_s"] for r in runs)
        res[which] = runs[0] | {
            "wall_s_median": walls[len(walls) // 2],
            "walls": walls,
            "load": [load, os.getloadavg()[0]],
            "cpus": os.cpu_count(),
        }
        print(which, res[which], flush=True)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    js.write_text(json.dumps(res, indent=1))
    if not all(w in res for w in ("default", "paper", "default120")):
        return
    d, p, d120 = res["default"], res["paper"], res["default120"]
    e = d["e_step"]
    lines = [
        "# Learning cost with the default settings (14 CMU salsa clips, 60 Hz)",
        "",
        f"Made by: `{res['command']}`",
        "",
        "Each learn in a fresh process, wall time",
        f"including compilation (median of the runs listed). Machine: {d['cpus']} CPUs; the "
        "load average (1 min) before and after each row is listed.",
        "",
        "| settings | Hz | frames | wall (s) | runs | load | textons | k | observation "
        "| segments / texton | single-segment share |",
        "| --- | ---: | ---: | ---: | --- | --- | ---: | ---: | --- | ---: | ---: |",
    ]
    for name, r in (
        ("defaults", d),
        ("paper (previous README)", p),
        ("defaults", d120),
    ):
        runs = ", ".join(f"{w:.1f}" for w in r["walls"])
        lines.append(
            f"| {name} | {r.get('fps', 60.0):g} | {r['frames']:,} | {r['wall_s_median']:.1f} "
            f"| {runs} | {r['load'][0]:.1f} → {r['load'][1]:.1f} | {r['textons']} "
            f"| {r['state_dim']} | {r['observation']} | {r['segments_per_texton']:.1f} "
            f"| {100 * r['single_segment_share']:.0f} % |"
        )
    lines += [
        "",
        f"Ratio defaults / paper at 60 Hz: {d['wall_s_median'] / p['wall_s_median']:.2f}; "
        f"defaults / the issue's 32.6 s (the paper's settings, idle, before issue 16): "
        f"{d['wall_s_median'] / 32.6:.2f}.",
        "",
        f"E-step of the default texture at the paper's scale ({e['frames']:,} frames: the 14 "
        f"clips three times, {d['textons']} textons, k = {d['state_dim']}, duration-aware "
        f"Viterbi): {e['warm_s']:.2f} s warm (median of 5), first call {e['first_s']:.1f} s.",
    ]
    OUT.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
