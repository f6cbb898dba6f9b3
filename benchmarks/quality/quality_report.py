"""The markdown report of ``bench_quality`` (``quality.md``; the raw numbers go to ``.json``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from quality_profile import lines, spread_lines
from quality_replay import lines as replay_lines


def _f(x: Any, nd: int = 3) -> str:
    if x is None:
        return "—"
    if isinstance(x, float) and not np.isfinite(x):
        return str(x)
    return f"{x:.{nd}f}" if isinstance(x, float) else str(x)


def _innovations_text(p: dict[str, Any] | None, bank: dict[str, Any] | None) -> str:
    if p is None:
        return " Synthesis draws independent innovations."
    acf = ", ".join(f"{r:.2f}" for r in p["acf"])
    text = (
        " The fitted innovation process: autocorrelation "
        f"{acf} at lags 1–{len(p['acf'])}, scale persistence {p['persistence']:.3f}."
    )
    if bank is None:
        return " Synthesis draws from the fitted process." + text
    return (
        " Synthesis replays blocks of the training residuals (the default): "
        f"{bank['rows']:,} rows of {bank['segments_kept']} of the {bank['segments']} "
        "training segments (the others hold a capture glitch)." + text
    )


def _vocabulary_lines(v: dict[str, Any] | None) -> list[str]:
    """The vocabulary table (issue 39): textons, the largest one's share, segments per
    texton, successors, mean segment length; then one row per texton."""
    if v is None:
        return []
    L = [
        "## Vocabulary (the texture's textons on the training clips)",
        "",
        "| textons | largest texton's share of segments | fewest segments | median segments "
        "| median successors (M ≥ 0.1, not itself) | mean segment length (frames) |",
        "| ---: | ---: | ---: | ---: | ---: | ---: |",
        f"| {v['textons']} | {100 * v['largest_share']:.0f} % | {v['segments_min']} "
        f"| {v['segments_median']:g} | {v['median_successors']:g} "
        f"| {v['mean_segment_frames']:.1f} |",
        "",
        "| texton | segments | share | mean length (s) | stays | successors (M ≥ 0.1) |",
        "| ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    for r in v["per_texton"]:
        succ = ", ".join(f"{j} ({p:.2f})" for j, p in r["successors"]) or "—"
        sec = "—" if r["mean_seconds"] is None else f"{r['mean_seconds']:.2f}"
        L.append(
            f"| {r['texton']} | {r['segments']} | {100 * r['share']:.0f} % | {sec} "
            f"| {r['self']:.2f} | {succ} |"
        )
    return [*L, ""]


def write(res: dict[str, Any], out: Path, seed: int) -> None:
    """Write ``out`` (markdown) and ``out`` with suffix ``.json`` (atomically the former)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    js = out.with_suffix(".json")
    js.write_text(json.dumps(res, indent=1, default=float))
    t = res["texture"]
    L = [
        "# Motion quality on the held-out split",
        "",
        f"Made by: `{res.get('command', 'python benchmarks/quality/bench_quality.py')}`",
        "",
        "One run; raw numbers in `quality.json`. Split fixed by",
        f"`shared/data/README.md`: train {', '.join(res['split']['train'])}; held out "
        f"{', '.join(res['split']['held_out'])} ({res['frames']['train']:,} / "
        f"{res['frames']['held']:,} frames at 60 Hz). Machine: {res['machine']['cpus']} CPUs, "
        f"load {res['machine']['load_before'][0]:.1f} before, "
        f"{res['machine']['load_after'][0]:.1f} after; total {res['total_s']:.0f} s.",
        "",
        f"Texture (README settings, 60 Hz; observation model {t.get('observation')}, "
        f"k = {t.get('state_dim')}, {t.get('innovations')} innovations, "
        f"{t.get('durations')} durations): "
        f"{t['textons']} textons from {t['segments']} "
        f"segments ({t['segments_per_texton']:.2f} per texton, "
        f"{100 * t['single_segment_share']:.0f} % with a single segment), largest spectral "
        f"radius {t['spectral_radius_max']:.3f}, learned in {t['learn_s']:.1f} s. Every "
        f"texton run by its dynamics with sampled noise for 10,000 frames from its key poses: "
        f"finite {t['noise_driven_10k']['finite']}, largest |y| "
        f"{t['noise_driven_10k']['max_over_key_pose_range']:.2f}× the key poses' largest "
        "with independent innovations, "
        f"{t['noise_driven_10k'].get('max_over_key_pose_range_fitted', float('nan')):.2f}× "
        "with the fitted innovation process."
        + _innovations_text(t.get("synthesis_innovations"), t.get("synthesis_residuals")),
        "",
        *_vocabulary_lines(res.get("vocabulary")),
        "## Density and one-step prediction (held-out clips, texture's observation vectors)",
        "",
        "| model | log-likelihood / frame (nats) | median frame | worst frame "
        "| one-step MSE / dim (z²) |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for name, r in res["density"].items():
        L.append(
            f"| {name} | {r['loglik_per_frame']:.2f} | {_f(r.get('median_frame'), 1)} "
            f"| {_f(r.get('worst_frame'), 0)} | {r['prediction_mse']:.4f} |"
        )
    fc = res["forward_cost"]
    L += [
        "",
        "The ARHMM's figure conditions on the first two frames of each clip (dynamax's inputs);",
        "all other rows score every frame. The mean per frame is dominated by a few capture",
        "glitches in the held-out clips (a single frame costs up to millions of nats under a",
        "model that learned a near-constant channel); the median frame (texture: along the best",
        "segmentation, transitions left out; baselines: one-step densities) shows typical",
        "frames. Per clip (marginal ≥ best path on every clip):",
        "",
        "| clip | frames | marginal / frame | best path / frame |",
        "| --- | ---: | ---: | ---: |",
    ]
    others = res.get("per_clip_others", {})
    if others:
        L[-2] = L[-2] + "".join(f" {tag} / frame |" for tag in others)
        L[-1] = L[-1] + " ---: |" * len(others)
    for j, c in enumerate(res["per_clip"]):
        n = c["frames"]
        extra = "".join(f" {v[j]:.2f} |" for v in others.values())
        L.append(
            f"| {c['clip']} | {n} | {c['marginal'] / n:.2f} | {c['best_path'] / n:.2f} |{extra}"
        )
    if "moseq" in res and "reason" in res["moseq"]:
        L += ["", f"jax-moseq's AR-HMM: no row: {res['moseq']['reason']}"]
    elif "moseq" in res:
        m = res["moseq"]
        L += [
            "",
            f"jax-moseq AR-HMM ({json.dumps(m.get('versions', {}))}): "
            f"{m.get('iterations')} Gibbs sweeps, "
            f"{m['states_used_1pct']} of {m['max_states']} states on at least 1 % of the "
            f"training frames; training log-likelihood "
            f"{_f(m.get('train_loglik_per_frame'), 2)} / frame; its held-out figure conditions "
            "on the first two frames of each clip (keypoint-moseq's default priors, nothing "
            "tuned).",
        ]
    L += [
        "",
        f"Forward algorithm vs Viterbi on the same segment scores ({fc['frames']:,} frames, "
        f"{fc['textons']} textons): {fc['forward_s'] * 1e3:.0f} ms vs "
        f"{fc['viterbi_s'] * 1e3:.0f} ms warm (median of 5, ratio {fc['ratio']:.2f}); "
        f"first calls {fc['forward_first_call_s']:.1f} s / {fc['viterbi_first_call_s']:.1f} s.",
        "",
        "## Motion (each set against the held-out clips)",
        "",
        "Ratios divide each W1 distance by the real-vs-real floor (training vs held-out clips",
        "at the same rate): 1.0 is as far from the held-out dancers as other real dancing is.",
        "Skating: horizontal foot speed while the foot is low (m/s). Penetration: depth below",
        "the training clips' lowest foot (m) and share of frames. Jumps: share of frame-to-",
        "frame maximum joint jumps above the held-out clips' p99 (and at texton boundaries).",
        "Novelty: median distance of 1 s windows to the nearest training window (m). Copy:",
        "share of steps that continue the previous step's training frame, longest run (s).",
        "",
        "| set | speed | acc | jerk | skate med / p95 | pen. max / share | jumps > p99 "
        "| boundary > p99 / max | novelty | copy / longest |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, r in res["rows"].items():
        bnd = (
            f"{_f(r.get('boundary_share_above_p99'), 2)} / {_f(r.get('boundary_max'), 3)}"
            if "boundary_max" in r
            else "—"
        )
        L.append(
            f"| {name} | {_f(r['speed_ratio'], 2)} | {_f(r['acceleration_ratio'], 2)} "
            f"| {_f(r['jerk_ratio'], 2)} | {_f(r['skating_median'], 2)} / "
            f"{_f(r['skating_p95'], 2)} | {_f(r['penetration_max'], 3)} / "
            f"{_f(r['penetration_share'], 3)} | {_f(r['jump_share_above_p99'], 3)} | {bnd} "
            f"| {_f(r['novelty_median'], 3)} | {_f(r.get('copy_fraction'), 2)} / "
            f"{_f(r.get('copy_longest_s'), 1)} |"
        )
    imp = res["implicit"]
    L += [
        "",
        f"Implicit model: {imp['examples']:,} windows, {imp['components']} components "
        f"explaining {100 * imp['explained_variance']:.0f} % of the window variance (body "
        f"weighting; the paper's per-channel weighting: "
        f"{100 * imp.get('paper_explained_variance', float('nan')):.0f} %), built in "
        f"{imp['learn_s']:.1f} s; sampled with β = 1, no added noise, default synthesis "
        "options (`SynthesisConfig()`); the paper-settings row uses `SynthesisConfig.paper()`.",
    ]
    if "seed_spread" in res:
        L += spread_lines(res["seed_spread"], seed, "the first texture row")
    if "seed_spread_fitted" in res:
        L += spread_lines(res["seed_spread_fitted"], seed, "the fitted-process row")
    if "profile" in res:
        L += lines(res["profile"])
    if "replay" in res:
        L += replay_lines(res["replay"])
    L.append("")
    tmp = out.with_suffix(".md.tmp")
    tmp.write_text("\n".join(L) + "\n")
    tmp.replace(out)
