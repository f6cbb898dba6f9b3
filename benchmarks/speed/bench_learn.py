"""Benchmark: segmentation E-step, ``learn`` and a dynamax baseline (issue 4; design §3–4).

Three measurements, in one run, float64 throughout (``jax_enable_x64`` is set here, in the
script; the library never sets it):

(a) **One E-step at the paper's scale** (MT §7): T = 50,000 frames, N_t = 246 textons,
    D = 60, k = 15, tmin = 60, tmax = 180. E-step = ``segment_scores`` (per-frame terms and
    prefix sums) + ``viterbi_segments`` (semi-Markov Viterbi, blocked ``lax.scan``). The 246
    textons are fitted with ``fit_texton`` on 180-frame windows sampled from 246 random stable
    second-order LDS (D = 60, k = 15); ``Y`` is a Markov chain of segments (60–180 frames) of
    those systems. Baseline in the same run: a straightforward numpy semi-Markov Viterbi (loop
    over end frames, vectorised over textons and candidate lengths, same prefix sums, explicit
    back-pointers) on the first ``--numpy-T`` frames, checked equal to the JAX result there.
(b) **Full ``learn``** on the 14 CMU salsa clips resampled to 60 Hz with
    ``LearnConfig(tmin=60, tmax=180, state_dim=12, fps=60.0, threshold=0.3)``: wall time
    (greedy initialisation, compilation and EM included), its split (from ``verbose`` output
    and the ``callback``), textons, segments, iterations.
(c) **dynamax ``LinearAutoregressiveHMM``** (2 lags) against ``learn`` on a train/held-out
    split of the clips (same split, same observation vectors ``Y`` = the texture's
    ``FeatureMap`` encoding), with the same number of states K as our textons, once at the K
    that ``threshold=0.3`` gives and once at a small common K (ours via
    ``LearnConfig(n_textons=K)``): time per EM iteration and held-out log-likelihood per frame
    (ours: Viterbi segmentation score; theirs: marginal likelihood, and also their Viterbi
    joint for a like-for-like number).

Timing: warm-up calls, ``jax.block_until_ready``, compile time = first call − warm median,
medians over repeats (the 2-core machine is shared and noisy). Writes
``benchmarks/results/learn.md`` and ``learn.json`` (``--quick``: a small smoke run written to
a temporary directory unless ``--out`` is given).

Usage: ``python benchmarks/speed/bench_learn.py [--quick] [--repeats 5] [--out DIR]``
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import glob
import io
import math
import os
import platform
import re
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import jax

jax.config.update("jax_enable_x64", True)  # a script, not the library: float64 as in the issue

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import RESULTS, command, cpu_and_memory

try:
    import mtex_jax as mj
except ImportError:  # running from a source checkout without installation
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "src"))
    import mtex_jax as mj

from learn_common import _log, _median, _timed, _timed_cpu
from learn_dynamax import (
    _tail,
    dynamax_run,
    frame_values,
)
from learn_problems import make_problem, numpy_viterbi
from learn_report import write_results

from mtex_jax.texture import (
    LearnConfig,
    greedy_init,
    learn,
    segment_scores,
    viterbi_segments,
)

DEFAULT_DATA = Path(os.environ.get("MTEX_SHARED", "/work/shared")) / "data" / "cmu-salsa"


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def machine_info() -> dict[str, Any]:
    model, mem_gb = cpu_and_memory()
    try:
        import dynamax

        dyn_version = getattr(dynamax, "__version__", "unknown")
    except ImportError:
        dyn_version = "not installed"
    return dict(
        cpu=model,
        cores=os.cpu_count(),
        memory_gb=round(mem_gb, 1),
        python=platform.python_version(),
        jax=jax.__version__,
        numpy=np.__version__,
        dynamax=dyn_version,
        mtex_jax=getattr(mj, "__version__", "unknown"),
        jax_backend=jax.default_backend(),
        jax_devices=len(jax.devices()),
        xla_flags=os.environ.get("XLA_FLAGS", ""),
        platform=platform.platform(),
    )


# --------------------------------------------------------------------------------------------
# (a) one E-step at the paper's scale (problems and numpy baseline: learn_problems.py)
# --------------------------------------------------------------------------------------------


def bench_estep(args: argparse.Namespace) -> dict[str, Any]:
    T, n, D, k, tmin, tmax = args.T, args.n_textons, args.D, args.k, args.tmin, args.tmax
    _log(f"(a) building {n} textons (fit_texton on synthetic LDS windows), T = {T:,}")
    rng = np.random.default_rng(0)
    prob = make_problem(rng, T, n, D, k, tmin, tmax)
    textons = prob["textons"]
    Y = jnp.asarray(prob["Y"])
    log_M = jnp.asarray(prob["log_M"])
    log_pi = jnp.asarray(prob["log_pi"])
    nT = jnp.asarray(T)

    def run_scores() -> Any:
        return segment_scores(textons, Y)

    def run_viterbi(sc: Any) -> Any:
        return viterbi_segments(sc, log_M, log_pi, nT, tmin, tmax)

    _log("(a) first calls (compilation)")
    first_scores, scorer = _timed(run_scores)
    first_viterbi, seg = _timed(lambda sc=scorer: run_viterbi(sc))
    t_scores: list[float] = []
    t_viterbi: list[float] = []
    cpu_scores: list[float] = []
    cpu_viterbi: list[float] = []
    for r in range(args.repeats):
        ts, cs, scorer = _timed_cpu(run_scores)
        tv, cv, seg = _timed_cpu(lambda sc=scorer: run_viterbi(sc))
        t_scores.append(ts)
        t_viterbi.append(tv)
        cpu_scores.append(cs)
        cpu_viterbi.append(cv)
        _log(f"(a) repeat {r}: scores {ts:.2f} s, viterbi {tv:.2f} s")
    t_total = [a + b for a, b in zip(t_scores, t_viterbi, strict=True)]
    seg_list = seg.to_list()
    lens = np.array([s[1] for s in seg_list])
    frame_lab = seg.frame_labels(T)
    label_acc = float(np.mean(frame_lab == prob["truth"]))
    true_starts = np.nonzero(np.diff(prob["truth"]) != 0)[0] + 1
    found_starts = np.array([s[0] for s in seg_list[1:]])
    hits = (
        sum(np.min(np.abs(found_starts - s)) <= 3 for s in true_starts) if len(found_starts) else 0
    )
    recall = hits / max(len(true_starts), 1)

    # --- numpy baseline on the first Tn frames, checked equal to JAX there ---
    Tn = args.numpy_T
    _log(f"(a) numpy baseline on T = {Tn:,}")
    Yn = Y[:Tn]
    sc_n = jax.block_until_ready(segment_scores(textons, Yn))
    sc_np = {f.name: np.asarray(getattr(sc_n, f.name)) for f in dataclasses.fields(sc_n)}
    lM, lpi = np.asarray(log_M), np.asarray(log_pi)
    nTn = jnp.asarray(Tn)
    first_small, seg_small = _timed(lambda: viterbi_segments(sc_n, log_M, log_pi, nTn, tmin, tmax))
    t_jax_small: list[float] = []
    t_numpy: list[float] = []
    np_out: tuple[float, list[tuple[int, int, int]]] = (math.nan, [])
    for _ in range(args.numpy_repeats):
        tj, seg_small = _timed(lambda: viterbi_segments(sc_n, log_M, log_pi, nTn, tmin, tmax))
        t0 = time.perf_counter()
        np_out = numpy_viterbi(sc_np, lM, lpi, tmin, tmax)
        t_numpy.append(time.perf_counter() - t0)
        t_jax_small.append(tj)
    np_score, np_segs = np_out
    jax_small_score = float(seg_small.score)
    same_segs = np_segs == seg_small.to_list()
    rel_err = abs(np_score - jax_small_score) / abs(np_score)
    if not same_segs or rel_err > 1e-9:
        raise AssertionError(
            f"numpy and JAX Viterbi disagree on T={Tn}: scores {np_score!r} vs "
            f"{jax_small_score!r}, same segmentation: {same_segs}"
        )

    med_s, med_v, med_t = _median(t_scores), _median(t_viterbi), _median(t_total)
    med_np, med_js = _median(t_numpy), _median(t_jax_small)
    return dict(
        sizes=dict(
            T=T, n_textons=n, D=D, k=k, tmin=tmin, tmax=tmax, dtype=str(Y.dtype), numpy_T=Tn
        ),
        textons="fit_texton on 180-frame windows sampled from random stable 2nd-order LDS "
        "(D=60, k=15, spectral radius 0.9-0.98); Y = Markov chain of 60-180-frame segments",
        texton_fit_seconds=prob["fit_seconds"],
        times_s=dict(scores=t_scores, viterbi=t_viterbi, total=t_total),
        cpu_s=dict(scores=cpu_scores, viterbi=cpu_viterbi),
        median_cpu_s=dict(
            scores=_median(cpu_scores),
            viterbi=_median(cpu_viterbi),
            total=_median([a + b for a, b in zip(cpu_scores, cpu_viterbi, strict=True)]),
        ),
        median_s=dict(scores=med_s, viterbi=med_v, total=med_t),
        min_s=dict(scores=min(t_scores), viterbi=min(t_viterbi), total=min(t_total)),
        first_call_s=dict(scores=first_scores, viterbi=first_viterbi),
        compile_s=dict(scores=first_scores - med_s, viterbi=first_viterbi - med_v),
        per_frame_us=dict(scores=1e6 * med_s / T, viterbi=1e6 * med_v / T, total=1e6 * med_t / T),
        result=dict(
            n_segments=len(seg_list),
            segment_length_min=int(lens.min()),
            segment_length_max=int(lens.max()),
            score=float(seg.score),
            frame_label_accuracy_vs_generator=label_acc,
            boundary_recall_3frames=recall,
        ),
        numpy_baseline=dict(
            T=Tn,
            times_s=t_numpy,
            median_s=med_np,
            jax_viterbi_times_s=t_jax_small,
            jax_viterbi_median_s=med_js,
            jax_viterbi_first_call_s=first_small,
            per_frame_us_numpy=1e6 * med_np / Tn,
            per_frame_us_jax_same_T=1e6 * med_js / Tn,
            ratio_numpy_over_jax_same_T=med_np / med_js,
            ratio_numpy_over_jax_per_frame_vs_full_T=(med_np / Tn) / (med_v / T),
            numpy_extrapolated_to_full_T_s=med_np / Tn * T,
            same_segmentation=bool(same_segs),
            score_rel_diff=rel_err,
            n_segments=len(np_segs),
        ),
    )


# --------------------------------------------------------------------------------------------
# (b) learn on the CMU clips
# --------------------------------------------------------------------------------------------

_GREEDY_RE = re.compile(r"greedy init: (\d+) textons, (\d+) segments, threshold (\S+), ([\d.]+) s")


def timed_learn(motions: list[Any], cfg: LearnConfig) -> dict[str, Any]:
    """Run ``learn`` and split its wall time with the ``verbose`` output and the callback."""
    infos: list[dict[str, Any]] = []

    def cb(info: dict[str, Any]) -> None:
        infos.append(dict(info, wall=time.perf_counter(), cpu=time.process_time()))

    buf = io.StringIO()
    t_start = time.perf_counter()
    with contextlib.redirect_stdout(buf):
        tex = learn(motions, cfg, verbose=True, callback=cb)
    jax.block_until_ready(tex.textons)
    t_end = time.perf_counter()
    log = buf.getvalue()
    m = _GREEDY_RE.search(log)
    greedy_s = float(m.group(4)) if m else math.nan
    n_init = int(m.group(1)) if m else -1
    secs = [i["seconds"] for i in infos]
    t0_abs = infos[0]["wall"] - secs[0] if infos else t_start
    iters = np.diff([greedy_s, *secs]).tolist() if infos else []
    cpu_iters = np.diff([i["cpu"] for i in infos]).tolist()  # iterations 1..n
    total = t_end - t_start
    hist = np.asarray(tex.history)
    n_frames = int(np.sum(np.asarray(tex.segment_lengths)))
    lens = np.asarray(tex.segment_lengths)
    per_tex = np.bincount(np.asarray(tex.key_pose_labels), minlength=tex.n_textons)
    em_s = secs[-1] - greedy_s if infos else math.nan
    return dict(
        texture=tex,
        log=log,
        wall_s=total,
        split_s=dict(
            setup=t0_abs - t_start,  # resampling, FeatureMap fit/encode, padding
            greedy_init=greedy_s,  # incl. compilation of the texton fits
            em_total=em_s,
            em_iterations=iters,  # iteration 0 includes compiling the M- and E-steps
            finalise=t_end - infos[-1]["wall"] if infos else math.nan,
        ),
        em_per_iteration_s=em_s / max(len(iters), 1),
        em_per_iteration_warm_median_s=_median(iters[1:]) if len(iters) > 1 else math.nan,
        em_cpu_per_iteration_warm_median_s=_median(cpu_iters) if cpu_iters else math.nan,
        iterations=len(hist),
        n_textons_init=n_init,
        n_textons=tex.n_textons,
        n_segments=len(lens),
        n_frames=n_frames,
        obs_dim=tex.obs_dim,
        objective_per_frame_first=float(hist[0, 1] / n_frames),
        objective_per_frame_final=float(hist[:, 1].max() / n_frames),
        changed_per_iteration=[int(i["changed"]) for i in infos],
        segment_length=dict(min=int(lens.min()), mean=float(lens.mean()), max=int(lens.max())),
        segments_per_texton=dict(
            median=float(np.median(per_tex)),
            max=int(per_tex.max()),
            textons_with_one_segment=int(np.sum(per_tex == 1)),
        ),
        threshold=float(tex.threshold),
    )


def load_clips(data: Path, names: list[str] | None) -> tuple[list[str], list[Any]]:
    files = sorted(glob.glob(str(data / "*.bvh")))
    if not files:
        raise SystemExit(f"no .bvh clips in {data}")
    if names is not None:
        files = [f for f in files if Path(f).stem in names]
    return [Path(f).stem for f in files], [mj.read_bvh(f) for f in files]


def bench_learn(args: argparse.Namespace, motions: list[Any], names: list[str]) -> dict[str, Any]:
    cfg = LearnConfig(
        tmin=60, tmax=180, state_dim=12, fps=60.0, threshold=0.3, max_iter=args.max_iter
    )
    _log(f"(b) learn on {len(motions)} clips: {cfg}")
    r = timed_learn(motions, cfg)
    tex = r.pop("texture")
    _log(f"(b) {r['wall_s']:.1f} s, {r['n_textons']} textons, {r['iterations']} iterations")
    # compile share of the greedy initialisation: run it again, warm
    ys = [np.asarray(tex.feature_map.encode(m.resample(60.0))) for m in motions]
    t_warm, (_segs, n_t) = _timed(lambda: greedy_init(ys, cfg, 0.3))
    r.update(
        clips=names,
        clip_frames_60hz=[int(y.shape[0]) for y in ys],
        config=cfg.to_json_dict(),
        greedy_init_warm_rerun_s=t_warm,
        greedy_init_warm_rerun_textons=int(n_t),
        default_max_iter=LearnConfig().max_iter,
    )
    r.pop("log")
    return r


def bench_compare(
    args: argparse.Namespace, motions: list[Any], names: list[str]
) -> list[dict[str, Any]]:
    held = [n for n in args.heldout if n in names]
    train_m = [m for n, m in zip(names, motions, strict=True) if n not in held]
    test_m = [m for n, m in zip(names, motions, strict=True) if n in held]
    train_names = [n for n in names if n not in held]
    configs = [("threshold 0.3 (same K as ours)", dict(threshold=0.3))]
    if args.small_k:
        configs.append((f"small common K (n_textons={args.small_k})", dict(n_textons=args.small_k)))
    rows = []
    for label, extra in configs:
        cfg = LearnConfig(
            tmin=60, tmax=180, state_dim=12, fps=60.0, max_iter=args.max_iter, **extra
        )
        _log(f"(c) ours, {label}: learn on {len(train_m)} train clips")
        r = timed_learn(train_m, cfg)
        tex = r.pop("texture")
        r.pop("log")
        fm = tex.feature_map
        Ytr = [np.asarray(fm.encode(m.resample(60.0))) for m in train_m]
        Yte = [np.asarray(fm.encode(m.resample(60.0))) for m in test_m]
        ours_scores, ours_frames = [], []
        for y in Yte:
            seg = tex.segment(jnp.asarray(y))
            ours_scores.append(float(seg.score))
            ours_frames.append(frame_values(tex, y, seg))
        nf = sum(y.shape[0] for y in Yte)
        ours = dict(
            K=tex.n_textons,
            wall_s=r["wall_s"],
            split_s=r["split_s"],
            iterations=r["iterations"],
            em_per_iteration_s=r["em_per_iteration_s"],
            em_per_iteration_warm_median_s=r["em_per_iteration_warm_median_s"],
            em_cpu_per_iteration_warm_median_s=r["em_cpu_per_iteration_warm_median_s"],
            train_objective_per_frame=r["objective_per_frame_final"],
            heldout_frames=[int(y.shape[0]) for y in Yte],
            heldout_scores=ours_scores,
            heldout_frame_median_viterbi_path=float(np.median(np.concatenate(ours_frames))),
            heldout_path=_tail(np.concatenate(ours_frames)),
            heldout_frame_median_viterbi_path_per_clip=[float(np.median(x)) for x in ours_frames],
            heldout_score_per_frame=sum(ours_scores) / nf,
            threshold=r["threshold"],
            n_segments=r["n_segments"],
            segments_per_texton=r["segments_per_texton"],
        )
        _log(
            f"(c) ours K={tex.n_textons}: {r['wall_s']:.1f} s, held-out "
            f"{ours['heldout_score_per_frame']:.2f}/frame; dynamax LARHMM K={tex.n_textons}"
        )
        theirs = dynamax_run(
            Ytr, Yte, tex.n_textons, args.dynamax_iters, 2, args.dynamax_plain_iters
        )
        _log(
            f"(c) dynamax: {theirs['per_iteration_s']:.2f} s/iter, held-out marginal "
            f"{theirs['heldout_marginal_per_frame']:.2f}/frame"
        )
        tr_max = np.abs(np.concatenate(Ytr)).max(axis=0)
        outliers = []
        for name, y in zip(held, Yte, strict=True):
            ratio = np.abs(y).max(axis=0) / np.maximum(tr_max, 1e-12)
            j = int(np.argmax(ratio))
            outliers.append(
                dict(
                    clip=name,
                    channel=fm.active_names[j],
                    heldout_max_abs=float(np.abs(y[:, j]).max()),
                    train_max_abs=float(tr_max[j]),
                )
            )
        rows.append(
            dict(
                setting=label,
                heldout_largest_excursion=outliers,
                train_clips=train_names,
                heldout_clips=held,
                obs_dim=int(Ytr[0].shape[1]),
                train_frames=int(sum(y.shape[0] for y in Ytr)),
                ours=ours,
                dynamax=theirs,
            )
        )
    return rows


# --------------------------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------------------------


def main() -> None:
    ap = argparse.ArgumentParser(description="Benchmark mtex_jax learning (issue 4).")
    ap.add_argument("--quick", action="store_true", help="small smoke run (< 2 min)")
    ap.add_argument("--parts", default="abc", help="which parts to run, e.g. 'a' or 'bc'")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    if args.quick:
        defaults = dict(
            T=3000, n_textons=16, D=60, k=15, tmin=60, tmax=180, numpy_T=600, repeats=2,
            numpy_repeats=2, max_iter=2, small_k=0, dynamax_iters=3, dynamax_plain_iters=2,
            clips=["60_05", "60_10", "60_12"], heldout=["60_10"],
        )  # fmt: skip
        out = args.out or Path(tempfile.gettempdir()) / "mtex_bench_learn_quick"
    else:
        defaults = dict(
            T=50_000, n_textons=246, D=60, k=15, tmin=60, tmax=180, numpy_T=3000, repeats=5,
            numpy_repeats=3, max_iter=LearnConfig().max_iter, small_k=16, dynamax_iters=30,
            dynamax_plain_iters=3, clips=None, heldout=["60_05", "60_11", "60_15"],
        )  # fmt: skip
        out = args.out or RESULTS
    for key, val in defaults.items():
        if getattr(args, key, None) is None:
            setattr(args, key, val)

    t_run = time.perf_counter()
    result: dict[str, Any] = dict(
        command=command(),
        date=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        quick=bool(args.quick),
        load_average_before=os.getloadavg(),
        machine=machine_info(),
    )
    if "a" in args.parts:
        result["a"] = bench_estep(args)
    if "b" in args.parts or "c" in args.parts:
        t0 = time.perf_counter()
        names, motions = load_clips(args.data, args.clips)
        result["clip_read_s"] = time.perf_counter() - t0
        if "b" in args.parts:
            result["b"] = bench_learn(args, motions, names)
        if "c" in args.parts:
            result["c"] = bench_compare(args, motions, names)
    result["load_average_after"] = os.getloadavg()
    result["wall_s"] = time.perf_counter() - t_run
    write_results(result, out)
    _log(f"wrote {out / 'learn.md'} and {out / 'learn.json'}")
    print((out / "learn.md").read_text())


if __name__ == "__main__":
    main()
