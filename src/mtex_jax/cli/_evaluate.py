"""``mtex evaluate``: the quality report of a motion texture on held-out clips (design §10.4)."""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Any

import numpy as np

from ..core import atomic_write
from ._validators import (
    SOURCE_HELP,
    add_force,
    float_arg,
    int_arg,
    output,
    positive,
    positive_int,
    read_source,
    seed_arg,
)

__all__ = ["register"]

MAX_SYNTH_SECONDS = 600.0
MAX_SYNTHESES = 64


def _read_clips(specs: list[str], fps: float, tmin: int, what: str) -> list[Any]:
    out = []
    for s in specs:
        m = read_source(s)
        if m.fps != fps:
            m = m.resample(fps)
        if m.n_frames < max(tmin, 4):
            raise ValueError(
                f"{what} clip {s} has {m.n_frames} frames at {fps:g} Hz; the texture needs at "
                f"least tmin = {tmin}"
            )
        out.append(m)
    return out


def _refuse_shared_clips(test: list[str], train: list[str]) -> None:
    """``ValueError`` if a held-out clip is also a training clip (the same file or the same
    example): the report would compare the clips with themselves."""
    for t in test:
        for r in train:
            same = t == r
            if not same and not t.startswith("example:") and not r.startswith("example:"):
                try:
                    same = os.path.samefile(t, r)
                except OSError:
                    same = False
            if same:
                raise ValueError(
                    f"--test {t} is also a --train clip ({r}); held-out clips must differ "
                    "from the training clips"
                )


def _fmt(x: Any) -> str:
    if x is None:
        return "—"
    return f"{x:.3f}" if isinstance(x, float) else str(x)


def write_json(path: str, report: dict[str, Any]) -> None:
    text = json.dumps(report, indent=1, default=float)  # fails before the file is touched
    with atomic_write(path, "w", encoding="utf-8") as f:
        f.write(text)


def _two_sample(test: list[Any], motions: list[Any], train: list[Any] | None, seed: int) -> Any:
    """The classifier two-sample test of the syntheses against the held-out clips, with the
    training clips as the real-against-real reference; printed, and returned for the report
    (a dict, or the reason it could not run)."""
    from ..metrics import two_sample_auc

    print("\nclassifier two-sample test (2 s windows, gradient-boosted trees, 5-fold AUC):")
    try:
        r = two_sample_auc(test, motions, reference=train, seed=seed)
    except (ImportError, ValueError) as e:
        print(f"  not run: {e}")
        return {"not_run": str(e)}
    print(f"  synthesised against held out: AUC {r.auc:.3f} ± {r.auc_std:.3f} (0.5: alike)")
    if r.reference_auc is not None:
        print(f"  training against held out:    AUC {r.reference_auc:.3f} ± {r.reference_std:.3f}")
    return r.as_dict()


def _cmd_evaluate(args: argparse.Namespace) -> int:
    import jax

    from ..metrics import MotionJudge, density_report
    from ..texture import synthesize
    from ._texture_cmds import load_model

    positive_int("synth", args.synth)
    if args.synth > MAX_SYNTHESES:
        raise ValueError(f"--synth {args.synth} exceeds the limit of {MAX_SYNTHESES}")
    positive("seconds", args.seconds)
    if args.seconds > MAX_SYNTH_SECONDS:
        raise ValueError(f"--seconds {args.seconds:g} exceeds the limit of {MAX_SYNTH_SECONDS:g}")
    inputs = (args.model, *args.test, *(args.train or ()))
    output(args.output, "json", inputs, args.force)
    plot_path = args.plot
    if plot_path is None and args.output is not None:
        plot_path = os.path.splitext(args.output)[0] + ".png"
    plot_inputs = (*inputs, args.output) if args.output is not None else inputs
    output(plot_path, "png", plot_inputs, args.force, option="--plot")
    _refuse_shared_clips(args.test, args.train or [])
    t0 = time.perf_counter()
    tex = load_model(args.model)
    fm = tex.feature_map
    assert fm is not None  # checked by load_model
    tmin = tex.config.tmin
    test = _read_clips(args.test, fm.fps, tmin, "--test")
    train = _read_clips(args.train, fm.fps, tmin, "--train") if args.train else None
    report: dict[str, Any] = dict(
        model=args.model, test=args.test, train=args.train, fps=fm.fps, textons=tex.n_textons
    )
    print(f"{len(test)} held-out clips, {sum(m.n_frames for m in test):,} frames at {fm.fps:g} Hz")

    print("held-out density: the forward algorithm over every clip...", flush=True)
    if train is not None:
        dens = density_report(tex, train, test)
    else:  # without training clips there are no baselines, only the texture's own rows
        ys = [tex.observations(m) for m in test]  # at the model's rate
        n = sum(int(y.shape[0]) for y in ys)
        best = sum(float(seg.score) for seg in tex.segment(ys))  # the clips as one list
        dens = {
            "motion texture (marginal)": dict(
                loglik_per_frame=float(np.sum(tex.log_likelihood(ys))) / n
            ),
            "motion texture (best path)": dict(loglik_per_frame=best / n),
        }
    report["density"] = dens
    print("\nheld-out density (nats/frame) and one-step error (z² per dimension):")
    for name, r in dens.items():
        print(f"  {name:28s} {r['loglik_per_frame']:10.2f}   {_fmt(r.get('prediction_mse'))}")

    n_frames = round(args.seconds * fm.fps)
    print(f"\nsynthesising {args.synth} clips of {args.seconds:g} s...", flush=True)
    keys = jax.random.split(jax.random.key(args.seed), args.synth)
    syn = [synthesize(k, tex, n_frames=n_frames) for k in keys]
    motions = [s.motion for s in syn if s.motion is not None]
    print("judging realism, contacts, transitions and novelty...", flush=True)
    judge = MotionJudge(train if train is not None else test, test, fps=fm.fps)
    rows = {"synthesised": judge.judge(motions, boundaries=[s.boundaries() for s in syn])}
    rows |= judge.real_rows()
    report["motion"] = rows
    keys_shown = [
        ("speed_ratio", "speed W1 / floor"),
        ("acceleration_ratio", "acceleration W1 / floor"),
        ("jerk_ratio", "jerk W1 / floor"),
        ("skating_median", "skating median (m/s)"),
        ("skating_p95", "skating p95 (m/s)"),
        ("penetration_max", "penetration max (m)"),
        ("penetration_share", "frames below floor"),
        ("jump_share_above_p99", "jumps above real p99"),
        ("boundary_share_above_p99", "boundaries above real p99"),
        ("novelty_median", "novelty median (m)"),
        ("copy_fraction", "copied steps"),
        ("copy_longest_s", "longest copy (s)"),
    ]
    print(f"\n{args.synth} syntheses of {args.seconds:g} s against the held-out clips:")
    print(f"  {'':28s} {'synthesised':>12s} {'real':>12s}")
    real = rows["real (held out)"]
    for k, label in keys_shown:
        print(f"  {label:28s} {_fmt(rows['synthesised'].get(k)):>12s} {_fmt(real.get(k)):>12s}")
    if train is None:
        print("  (no --train clips: no realism floor, contacts and novelty from the test clips)")
    report["two_sample"] = _two_sample(test, motions, train, args.seed)
    if args.output is not None:
        write_json(args.output, report)
        print(f"\nreport: {args.output}")
    plot = args.plot
    if plot is None and args.output is not None:
        plot = os.path.splitext(args.output)[0] + ".png"
    if plot is not None:
        from ..viz import plot_speed_distributions

        sets = {"real (held out)": test, "synthesised": motions}
        if train is not None:
            sets = {"real (training)": train, **sets}
        plot_speed_distributions(sets, plot, fps=fm.fps, title=f"{args.model}: joint dynamics")
        print(f"plot: {plot}")
    print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser(
        "evaluate",
        help="quality report of a learned texture on held-out clips",
        description="Held-out log-likelihood and one-step prediction beside closed-form "
        "baselines (with --train), and the realism, foot skating, floor penetration, "
        "transitions and novelty of synthesised motion against the held-out clips, and how well "
        "a classifier tells it from them (two-sample AUC).",
    )
    s.add_argument("model", help="a model file written by 'mtex learn' or 'mtex demo'")
    s.add_argument("--test", nargs="+", required=True, help=f"held-out clips: {SOURCE_HELP}")
    s.add_argument(
        "--train",
        nargs="+",
        default=None,
        help="the training clips (baselines, realism floor, contact thresholds, novelty)",
    )
    s.add_argument("--synth", type=int_arg, default=4, help="syntheses to judge (default 4)")
    s.add_argument("--seconds", type=float_arg, default=10.0, help="length of each (default 10)")
    s.add_argument("--seed", type=seed_arg, default=0, help="random seed (default 0)")
    s.add_argument("-o", "--output", default=None, help="write the report as JSON here")
    s.add_argument("--plot", default=None, help="distribution plot (.png; default beside -o)")
    add_force(s)
    s.set_defaults(func=_cmd_evaluate)
