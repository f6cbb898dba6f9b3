"""``mtex demo``: the main job on the shipped CMU salsa clips.

Learn a motion texture from the 10 training clips of the fixed split (greedy initialisation +
EM), synthesise a new salsa from it, and write the model, the new dance (BVH, filmstrip, and a
GIF beside a real held-out clip), the texton timeline of the training clips (MT Fig. 2) and the
quality report against the 4 held-out clips; every step is timed.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ._evaluate import write_json
from ._validators import float_arg, int_arg, positive, positive_int, seed_arg

__all__ = ["register", "run_demo"]

FPS = 60.0
MAX_SECONDS = 600.0

#: the quality figures printed (all of them go to the JSON report)
_SHOWN = (
    ("speed_ratio", "joint speed W1 / real floor"),
    ("jerk_ratio", "joint jerk W1 / real floor"),
    ("skating_median", "foot skating median (m/s)"),
    ("penetration_max", "floor penetration max (m)"),
    ("boundary_share_above_p99", "texton boundaries above real p99 jump"),
    ("novelty_median", "novelty median (m)"),
    ("copy_fraction", "copied steps"),
)


class _Steps:
    """Times the demo's steps and prints one line as each ends: wall-clock seconds, and the CPU
    seconds of the process (all threads; on a machine shared with other jobs the wall clock
    grows, the CPU time much less)."""

    def __init__(self, say: Callable[[str], None]) -> None:
        self.say = say
        self.times: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self.t0, self.c0 = time.perf_counter(), time.process_time()

    def run(self, name: str, fn: Callable[[], Any]) -> Any:
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        self.times[name] = time.perf_counter() - t
        self.cpu[name] = time.process_time() - c
        self.say(f"  [{name}: {self.times[name]:.1f} s, CPU {self.cpu[name]:.1f} s]")
        return out

    @property
    def total(self) -> float:
        return time.perf_counter() - self.t0


def texture_stats(tex: Any) -> dict[str, float]:
    """Segments per texton (mean) and the fewest segments of any texton."""
    segs = np.asarray(tex.segments)
    counts = np.bincount(segs[:, 3], minlength=tex.n_textons)
    return {
        "textons": int(tex.n_textons),
        "segments": len(segs),
        "segments_per_texton": float(counts.mean()),
        "fewest_segments": int(counts.min()),
    }


def run_demo(
    out: str | Path,
    *,
    seconds: float = 20.0,
    seed: int = 0,
    n_train: int | None = None,
    n_held: int | None = None,
    max_iter: int = 20,
    gif_fps: float = 15.0,
    say: Callable[[str], None] = print,
) -> dict[str, Any]:
    """The demo's pipeline; returns the files written, the step times and the statistics.

    ``n_train`` / ``n_held`` take only the first clips of each side of the split (a shortened
    run); by default all 10 training and 4 held-out clips.
    """
    import jax

    from ..io import load_salsa, salsa_credit, salsa_split, write_bvh
    from ..metrics import MotionJudge
    from ..texture import LearnConfig, learn, synthesize, texture_summary
    from ..viz import (
        plot_timeline,
        render_filmstrip,
        render_gif_pair,
        render_texton_gallery,
        write_html,
    )

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "model": out / "texture.npz",
        "timeline": out / "timeline.png",
        "gallery": out / "textons.png",
        "dance": out / "new_dance.bvh",
        "gif": out / "new_dance.gif",
        "filmstrip": out / "new_dance.png",
        "report": out / "quality.json",
    }
    steps = _Steps(say)
    train_names, held_names = salsa_split()
    train_names = train_names[:n_train] if n_train else train_names
    held_names = held_names[:n_held] if n_held else held_names

    def load() -> tuple[list[Any], list[Any]]:
        return [load_salsa(n) for n in train_names], [load_salsa(n) for n in held_names]

    train, held = steps.run("load the salsa clips", load)
    say(
        f"CMU salsa, subject 60: {len(train)} training clips ({sum(m.duration for m in train):.0f}"
        f" s), {len(held)} held out ({', '.join(held_names)}), {FPS:g} Hz\n"
        f"  {salsa_credit().splitlines()[2]} {salsa_credit().splitlines()[3]}"
    )
    # the default model: tied textons (design §10.10), a vocabulary chosen by the selection
    cfg = LearnConfig(tmin=60, tmax=180, fps=FPS, max_iter=max_iter)
    say(
        f"learning a motion texture: segments of {cfg.tmin}-{cfg.tmax} frames "
        f"({cfg.tmin / FPS:g}-{(cfg.tmax or 0) / FPS:g} s), {cfg.observation} textons, "
        f"initialised from {cfg.chunk_length}-frame chunks, textons with < {cfg.min_segments} "
        f"segments pruned, their number chosen by {cfg.selection.upper()}"
    )
    say("  initial textons from clustered chunks, then EM and the selection ...")

    def progress(info: dict[str, Any]) -> None:
        pruned = f", pruned {info['pruned']}" if info.get("pruned") else ""
        say(
            f"  EM iteration {info['iteration']:2d}: {info['n_textons']:3d} textons{pruned}, "
            f"{info['changed']:5d} frames relabelled, objective/frame "
            f"{info['objective_e'] / n_frames:8.3f}  ({info['seconds']:.1f} s)"
        )

    n_frames = sum(math.floor(m.duration * FPS + 1e-9) + 1 for m in train)
    tex = steps.run("learn (EM + selection)", lambda: learn(train, cfg, callback=progress))
    tex.save(files["model"])
    say(texture_summary(tex).split("\nobjective")[0])
    stats = texture_stats(tex)
    ok = stats["segments_per_texton"] >= 3 and stats["fewest_segments"] >= 2
    say(
        f"texture: {stats['textons']} textons, {stats['segments']} training segments, "
        f"{stats['segments_per_texton']:.1f} segments per texton on average, every texton used "
        f"at least {stats['fewest_segments']} times: "
        + ("not degenerate (>= 3 on average, >= 2 each)" if ok else "DEGENERATE")
    )

    def timeline() -> None:
        segs = np.asarray(tex.segments)
        rows = [
            [tuple(int(v) for v in r[1:]) for r in segs[segs[:, 0] == s]] for s in range(len(train))
        ]
        plot_timeline(
            rows,
            files["timeline"],
            fps=FPS,
            n_textons=tex.n_textons,
            names=train_names,
            title="texton labels of the training clips (MT Fig. 2)",
        )

    steps.run("timeline", timeline)
    steps.run(
        "texton gallery",
        lambda: render_texton_gallery(tex, files["gallery"], train, per_texton=3),
    )
    say(str(tex.summary()))

    n_out = max(4, round(seconds * FPS))
    say(
        f"synthesising a new salsa: {n_out} frames ({n_out / FPS:g} s), a random texton path "
        f"from M with durations from the textons' duration models (seed {seed}), constrained "
        "synthesis per texton with sampled noise (MT §5)"
    )
    # the default synthesis, as benchmarked: the path and durations drawn from the texture,
    # constrained least squares with innovations replayed from the training residuals
    syn_key = jax.random.key(seed)
    syn = steps.run("synthesise", lambda: synthesize(syn_key, tex, n_frames=n_out))
    dance = syn.motion
    assert dance is not None  # the texture was learned from motions
    write_bvh(files["dance"], dance)
    say(
        f"  texton path {np.asarray(syn.path).tolist()}, lengths "
        f"{np.asarray(syn.lengths).tolist()} frames"
    )

    real_name = max(zip(held, held_names, strict=True), key=lambda p: p[0].n_frames)[1]
    real = held[held_names.index(real_name)]
    steps.run(
        "GIF beside a real clip",
        lambda: render_gif_pair(
            dance,
            real,
            files["gif"],
            titles=(f"new salsa (seed {seed})", f"real: {real_name} (held out)"),
            seconds=dance.duration,
            fps=gif_fps,
            trajectories=["lFoot", "rFoot"],
        ),
    )
    # the page to look at: both dances in a 3-D player, the texton timeline, the vocabulary
    files["player"] = steps.run(
        "HTML player",
        lambda: write_html(
            out / "index.html",
            [syn, real],
            labels=[f"new salsa (seed {seed})", f"real: {real_name} (held out)"],
            title="mtex demo: a new salsa beside a real one",
            texture=tex,
            gallery=train,
        ),
    )
    steps.run(
        "filmstrip",
        lambda: render_filmstrip(
            dance,
            files["filmstrip"],
            n_frames=10,
            height=2.0,
            dpi=80,
            title=f"mtex demo: a new {n_out / FPS:g} s salsa synthesised from the texture "
            f"(seed {seed})",
        ),
    )

    def quality() -> dict[str, Any]:
        judge = MotionJudge(train, held, fps=FPS)
        rows = {"synthesised": judge.judge([dance], boundaries=[syn.boundaries()])}
        return rows | judge.real_rows()

    rows = steps.run("quality report", quality)

    def two_sample() -> dict[str, Any]:
        # can a classifier tell the new dance from the held-out clips? (design §10.4)
        from ..metrics import two_sample_auc

        try:
            r = two_sample_auc(
                [m.resample(FPS) for m in held],
                [dance],
                reference=[m.resample(FPS) for m in train],
                seed=seed,
            )
        except (ImportError, ValueError) as e:
            return {"not_run": str(e)}
        return r.as_dict()

    two = steps.run("two-sample test", two_sample)
    report = {
        "training": train_names,
        "held_out": held_names,
        "fps": FPS,
        "seconds": n_out / FPS,
        "seed": seed,
        "texture": stats,
        "path": np.asarray(syn.path).tolist(),
        "motion": rows,
        "two_sample": two,
        "step_seconds": steps.times,
        "step_cpu_seconds": steps.cpu,
    }
    write_json(str(files["report"]), report)
    say(f"quality of the new salsa against the {len(held)} held-out clips (real: held out):")
    for key, label in _SHOWN:
        a, b = rows["synthesised"].get(key), rows["real (held out)"].get(key)
        fmt = lambda x: "—" if x is None else f"{x:.3f}"
        say(f"  {label:40s} {fmt(a):>8s}   real {fmt(b):>8s}")
    if "auc" in two:
        say(
            f"  {'classifier two-sample AUC (0.5: alike)':40s} {two['auc']:8.3f}   "
            f"real {two['reference_auc']:8.3f}  (real: the training clips against the held out)"
        )
    else:
        say(f"  two-sample test not run: {two['not_run']}")
    say("files:")
    for what, p in files.items():
        say(f"  {what:10s} {p}")
    say("time per step: " + ", ".join(f"{k} {v:.1f} s" for k, v in steps.times.items()))
    say(f"done in {steps.total:.1f} s (CPU {time.process_time() - steps.c0:.1f} s)")
    return {"files": files, "times": steps.times, "stats": stats, "report": report}


def _cmd_demo(args: argparse.Namespace) -> int:
    positive("seconds", args.seconds)
    if args.seconds > MAX_SECONDS:
        raise ValueError(f"--seconds {args.seconds:g} exceeds the limit of {MAX_SECONDS:g}")
    for name in ("train_clips", "held_clips", "max_iter"):
        if getattr(args, name) is not None:
            positive_int(name.replace("_", "-"), getattr(args, name))
    t0 = time.perf_counter()
    run_demo(
        args.out,
        seconds=args.seconds,
        seed=args.seed,
        n_train=args.train_clips,
        n_held=args.held_clips,
        max_iter=args.max_iter,
        say=lambda s: print(s, flush=True),
    )
    print(f"(mtex demo: {time.perf_counter() - t0:.1f} s after start-up)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser(
        "demo",
        help="run the main job on the shipped CMU salsa clips",
        description="Learn a motion texture from the 10 training salsa clips (the default "
        "settings: tied textons, EM and the selection of their number), synthesise a new 20 s "
        "salsa, and write the model, the gallery of its textons, the new dance as BVH, a GIF "
        "of it beside a real held-out clip, a filmstrip, the texton timeline of the training "
        "clips and the quality report against the held-out clips.",
    )
    s.add_argument("--out", default="out", help="output folder (default: out)")
    s.add_argument(
        "--seconds", type=float_arg, default=20.0, help="length of the new dance (default 20)"
    )
    s.add_argument("--seed", type=seed_arg, default=0, help="random seed of the texton path")
    s.add_argument(
        "--train-clips", type=int_arg, default=None, help="use only the first N training clips"
    )
    s.add_argument(
        "--held-clips", type=int_arg, default=None, help="use only the first N held-out clips"
    )
    s.add_argument("--max-iter", type=int_arg, default=20, help="most EM iterations (default 20)")
    s.set_defaults(func=_cmd_demo)
