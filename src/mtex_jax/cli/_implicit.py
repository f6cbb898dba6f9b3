"""``mtex implicit-synth`` and ``mtex track``: the implicit motion model on the command line.

:func:`register` adds both sub-commands to the main parser (:mod:`mtex_jax.cli`). ``mtex track``
has two forms: ``CLIPS... --test CLIP`` (the particle filters on a synthetic problem, here) and
``MODEL --keypoints FILE`` (real keypoints with a texture's smoother, :mod:`._track`). Bad input
raises ``ValueError`` with a one-line message; the main CLI prints it and exits with status 2.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from ..core import atomic_write
from . import _track
from ._validators import (
    add_force,
    float_arg,
    int_arg,
    non_negative,
    output,
    positive,
    positive_int,
    seed_arg,
)

__all__ = ["register"]

_CLIP_HELP = "training clips: .bvh files, DeepMimic JSON files or example:NAME"


def _load(sources: list[str], fps: float | None):
    from ..io import read_motion

    if not sources:
        raise ValueError("no training clips given")
    motions = [read_motion(s) for s in sources]
    if fps is None:
        rates = {m.fps for m in motions}
        if len(rates) > 1:
            listed = ", ".join(f"{r:g}" for r in sorted(rates))
            raise ValueError(f"the clips have different frame rates ({listed} Hz); use --fps")
        return motions
    return [m if m.fps == fps else m.resample(fps) for m in motions]


def _build(args: argparse.Namespace, motions):
    from ..implicit import learn as implicit_learn

    positive_int("window", args.window)
    me = getattr(args, "min_explained", None)
    if me is not None and not 0 < me <= 1:
        raise ValueError(f"--min-explained must be in (0, 1], got {me}")
    rw = getattr(args, "recent_weight", None)
    if rw is not None and not 0 <= rw < float("inf"):
        raise ValueError(f"--recent-weight must be a finite number ≥ 0, got {rw}")
    extra: dict[str, Any] = {} if rw is None else {"recent_weight": float(rw)}
    t0 = time.perf_counter()
    model = implicit_learn(
        motions,
        args.window,
        weighting=getattr(args, "weighting", "body"),
        min_explained=me,
        **extra,
    )
    s = model.summary()
    print(
        f"database: {s['n_examples']} windows of {s['window']} frames at {s['fps']:g} Hz from "
        f"{s['clips']} clip(s); PCA tree depth b = {s['n_components']} "
        f"({100 * s['explained_variance']:.1f}% of the variance), "
        f"{s['nonempty_leaves']} non-empty leaves, largest {s['leaf_max']} "
        f"({time.perf_counter() - t0:.1f} s)"
    )
    return model


def _cmd_synth(args: argparse.Namespace) -> int:
    import jax

    from ..io import write_bvh

    positive_int("frames", args.frames)
    positive("beta", args.beta)
    non_negative("noise", args.noise)
    out = Path(args.output)
    output(out, "bvh", args.clips, args.force)
    output(args.gif, "gif", (*args.clips, out), args.force, option="--gif")
    motions = _load(args.clips, args.fps)
    model = _build(args, motions)
    if args.start < 0:
        raise ValueError(f"--start must be ≥ 0, got {args.start}")
    start = motions[0][args.start :]
    if start.n_frames < model.database.window + 1:
        raise ValueError(
            f"the first clip has fewer than {model.database.window + 1} frames from "
            f"--start {args.start}"
        )
    t0 = time.perf_counter()
    motion = model.synthesize(
        jax.random.PRNGKey(args.seed),
        start,
        args.frames,
        args.beta,
        args.noise,
        sampler=args.sampler,
        config=_synthesis_config(args),
    ).numpy()
    write_bvh(out, motion)
    print(
        f"wrote {out}: {motion.n_frames} frames at {motion.fps:g} Hz "
        f"({model.database.window} seed frames "
        f"from {args.clips[0]} + {args.frames} synthesised, beta={args.beta:g}, "
        f"noise={args.noise:g}, seed={args.seed}; {time.perf_counter() - t0:.1f} s)"
    )
    if args.gif:
        from ..viz import render_gif

        gif = render_gif(motion, args.gif, title=f"implicit model, beta={args.beta:g}")
        print(f"wrote {gif}")
    return 0


def _synthesis_config(args: argparse.Namespace):
    from ..implicit import SynthesisConfig

    for name in ("blend", "lookahead", "max_run", "leaf_cap", "seam_smoothing"):
        value = getattr(args, name)
        if value is not None and value < 0:
            raise ValueError(f"--{name.replace('_', '-')} must be ≥ 0, got {value}")
    for name in ("continuation", "candidates"):
        value = getattr(args, name)
        if value is not None:
            positive_int(name, value)
    base = SynthesisConfig.paper() if args.paper else SynthesisConfig()
    if args.hubness is not None and not (0 <= args.hubness < float("inf")):
        raise ValueError(f"--hubness must be a finite number ≥ 0, got {args.hubness}")
    if args.root_blend is not None and args.root_blend < -1:
        raise ValueError(f"--root-blend must be ≥ -1, got {args.root_blend}")
    if args.foot_lock is not None and not 0 <= args.foot_lock <= 1:
        raise ValueError(f"--foot-lock must be in [0, 1], got {args.foot_lock}")
    fields = (
        "blend",
        "leaf",
        "lookahead",
        "continuation",
        "max_run",
        "candidates",
        "leaf_cap",
        "hubness",
        "root_blend",
        "foot_lock",
        "seam_smoothing",
    )
    opts = {f: getattr(base, f) for f in (*fields, "velocity")}
    opts |= {f: getattr(args, f) for f in fields if getattr(args, f) is not None}
    if args.velocity is not None:
        opts["velocity"] = args.velocity == "on"
    if not opts["velocity"] and opts["blend"] > 0:
        raise ValueError("--blend > 0 needs --velocity on (it fades the velocity form's offset)")
    return SynthesisConfig(**opts)


#: the options of the particle-filter form of ``track`` and their defaults (``None`` in the
#: parser, so that the keypoint form can refuse them when they are given)
_PF_DEFAULTS: dict[str, Any] = {
    "particles": 300,
    "frames": None,
    "start": 0,
    "seed": 0,
    "window": 10,
    "fps": 30.0,
    "beta": 0.1,
    "noise": 0.1,
    "cv_noise": 0.1,
    "likelihood_sigma": 20.0,
}


def _cmd_track(args: argparse.Namespace) -> int:
    if args.keypoints is not None:
        given = [k for k in _PF_DEFAULTS if k != "fps" and getattr(args, k) is not None]
        if given:
            raise ValueError(
                f"--{given[0].replace('_', '-')} belongs to the particle-filter form (mtex track "
                "CLIPS... --test CLIP), not to --keypoints"
            )
        return _track.run(args)
    for name in _track.KEYPOINT_OPTIONS:
        if getattr(args, name) not in (None, False):
            option = "-o/--output" if name == "output" else f"--{name}"
            raise ValueError(
                f"{option} belongs to the keypoint form (mtex track MODEL --keypoints FILE)"
            )
    if args.test is None:
        raise ValueError(
            "give --test CLIP (the particle filters on a synthetic problem) or --keypoints FILE "
            "(track real keypoints with a texture model)"
        )
    for name, value in _PF_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    return _track_particles(args)


def _track_particles(args: argparse.Namespace) -> int:
    import jax
    import numpy as np

    from ..io import read_motion
    from ..tracking import ParticleFilter, make_problem, track

    positive_int("particles", args.particles)
    if args.frames is not None:
        positive_int("frames", args.frames)
    positive("beta", args.beta)
    non_negative("noise", args.noise)
    non_negative("cv-noise", args.cv_noise)
    non_negative("pixel-noise", args.pixel_noise)
    positive("likelihood-sigma", args.likelihood_sigma)
    if args.start < 0:
        raise ValueError(f"--start must be ≥ 0, got {args.start}")
    if args.plot:
        output(args.plot, "png", (*args.clips, args.test), args.force, option="--plot")
    motions = _load(args.clips, args.fps)
    test = read_motion(args.test)
    if test.fps != motions[0].fps:
        test = test.resample(motions[0].fps)
    model = _build(args, motions)
    if args.test in args.clips:
        print("note: the test clip is also in the database (not a held-out test)")
    key = jax.random.PRNGKey(args.seed)
    k_obs, k_filter = jax.random.split(key)
    problem = make_problem(
        k_obs, model, test, n_frames=args.frames, start=args.start, pixel_noise=args.pixel_noise
    )
    print(
        f"tracking {problem.n_frames} frames of {args.test} (frames {problem.frames[0]}–"
        f"{problem.frames[-1]}), {len(problem.joints)} joints seen by one pin-hole camera with "
        f"{args.pixel_noise:g} px noise; {args.particles} particles; seed {args.seed}"
    )
    results = {}
    for prior in ("implicit", "constant_velocity"):
        t0 = time.perf_counter()
        pf = ParticleFilter(
            dynamics=prior,
            n_particles=args.particles,
            beta=args.beta,
            noise=args.noise,
            cv_noise=args.cv_noise,
            likelihood_sigma=args.likelihood_sigma,
        )
        r = track(k_filter, model, problem, pf)
        results[prior] = r
        print(f"  {prior}: {time.perf_counter() - t0:.1f} s")
    imp = 1000 * np.asarray(results["implicit"].error)
    cv = 1000 * np.asarray(results["constant_velocity"].error)
    print("3-D joint error (mm, mean over joints, world coordinates; lengths assumed in metres)")
    print(f"{'frame':>8} {'implicit':>10} {'const.vel.':>10}")
    for f, a, b in zip(problem.frames, imp, cv, strict=True):
        print(f"{f:8d} {a:10.1f} {b:10.1f}")
    rel_i = 1000 * float(np.mean(results["implicit"].error_root_relative))
    rel_c = 1000 * float(np.mean(results["constant_velocity"].error_root_relative))
    print(f"{'mean':>8} {imp.mean():10.1f} {cv.mean():10.1f}")
    print(f"{'root-rel':>8} {rel_i:10.1f} {rel_c:10.1f}")
    if args.plot:
        _plot(args.plot, problem.frames, imp, cv, args.particles, args.test)
        print(f"wrote {args.plot}")
    return 0


def _plot(path: str, frames, imp, cv, n: int, name: str) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover - matplotlib is an optional dependency
        raise ImportError("--plot needs matplotlib (pip install mtex_jax[plot])") from e
    fig, ax = plt.subplots(figsize=(6, 3), dpi=100)
    ax.plot(frames, imp, label=f"implicit prior ({n} particles)")
    ax.plot(frames, cv, label=f"constant velocity ({n} particles)")
    ax.set_xlabel("frame")
    ax.set_ylabel("mean 3-D joint error (mm)")
    ax.set_title(f"tracking {Path(name).name}", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    try:
        with atomic_write(path, "wb") as fh:
            fig.savefig(fh, format=Path(path).suffix.lstrip(".").lower() or "png")
    finally:
        plt.close(fig)


def register(subparsers) -> None:
    """Add ``implicit-synth`` and ``track`` to the ``mtex`` sub-command parsers."""
    s = subparsers.add_parser(
        "implicit-synth",
        help="synthesise motion with the implicit (example-based) model",
        description="Build the implicit probabilistic motion model (Sidenbladh, Black & Sigal "
        "2002) from the clips and generate motion frame by frame from the first clip's start.",
    )
    s.add_argument("clips", nargs="+", help=_CLIP_HELP)
    s.add_argument("-o", "--output", required=True, help="output .bvh file")
    s.add_argument("--frames", type=int_arg, default=300, help="frames to generate (default 300)")
    s.add_argument("--beta", type=float_arg, default=0.1, help="sampling temperature (default 0.1)")
    s.add_argument(
        "--noise",
        type=float_arg,
        default=0.02,
        help="pose noise in database standard deviations (default 0.02)",
    )
    s.add_argument("--seed", type=seed_arg, default=0, help="random seed (default 0)")
    s.add_argument("--window", type=int_arg, default=10, help="window length d (default 10)")
    s.add_argument(
        "--fps",
        type=float_arg,
        default=30.0,
        help="resample the clips to this rate first (default 30, as in the paper)",
    )
    s.add_argument(
        "--paper",
        action="store_true",
        help="start from the paper's sampler (absolute poses, a search every frame, p(c_i|c_t) "
        "in the leaf) instead of the defaults; the options below still override",
    )
    s.add_argument("--sampler", choices=("tree", "exact"), default="tree", help="default tree")
    s.add_argument(
        "--leaf",
        choices=("uniform", "weighted", "exact"),
        default=None,
        help="choice within the tree's leaf (default exact; --paper: weighted)",
    )
    s.add_argument(
        "--velocity",
        choices=("on", "off"),
        default=None,
        help="apply the example's change of pose (on, default) or jump to its pose (off)",
    )
    s.add_argument(
        "--blend", type=int_arg, default=None, help="transition blend frames (default 6)"
    )
    s.add_argument(
        "--lookahead", type=int_arg, default=None, help="frames a searched example must continue"
    )
    s.add_argument(
        "--continuation", type=int_arg, default=None, help="frames played per search (default 6)"
    )
    s.add_argument(
        "--max-run", type=int_arg, default=None, help="cap on verbatim frames (0: none; default 12)"
    )
    s.add_argument("--candidates", type=int_arg, default=None, help="tree walks per search")
    s.add_argument(
        "--leaf-cap", type=int_arg, default=None, help="leaf members examined per walk (0: all)"
    )
    s.add_argument(
        "--hubness",
        type=float_arg,
        default=None,
        help="weight of the kernel's hubness correction (default 0.2; 0: the paper's kernel)",
    )
    s.add_argument(
        "--root-blend",
        type=int_arg,
        default=None,
        help="frames over which the root velocity's offset fades (default 1; -1: --blend)",
    )
    s.add_argument(
        "--weighting",
        choices=("body", "channel"),
        default="body",
        help="database channel weighting: body (joint reach, default) or channel (the paper)",
    )
    s.add_argument(
        "--min-explained",
        type=float_arg,
        default=None,
        help="choose the tree depth b by explained variance (default b = floor(log2 n))",
    )
    s.add_argument(
        "--recent-weight",
        type=float_arg,
        default=None,
        help="extra weight of the newest pose in the window distance (default 32; 0: the paper)",
    )
    s.add_argument(
        "--foot-lock",
        type=float_arg,
        default=None,
        help="strength in [0, 1] of the root correction that keeps planted feet in place "
        "(default 1; --paper: 0)",
    )
    s.add_argument(
        "--seam-smoothing",
        type=int_arg,
        default=None,
        help="frames around each transition that are low-passed (default 2; 0 and --paper: off)",
    )
    s.add_argument(
        "--start",
        type=int_arg,
        default=0,
        help="frame of the first clip that starts the seed window",
    )
    s.add_argument("--gif", default=None, help="also render an animated GIF here")
    add_force(s)
    s.set_defaults(func=_cmd_synth)

    s = subparsers.add_parser(
        "track",
        help="track 3-D motion from 2-D joints: real keypoints with a texture model, or a "
        "particle-filter comparison on a held-out clip",
        description="Two forms. 'mtex track MODEL --keypoints FILE -o out.bvh': track the 3-D "
        "motion behind 2-D keypoints (COCO results JSON, .npz or mtex-keypoints JSON) with the "
        "texture model's MAP smoother; a camera file gives the focal length, principal point "
        "and optionally the pose (without a pose, or without --camera, a level camera and the "
        "floor is estimated); write the motion (BVH), per-frame 3-D joints and textons (JSON), "
        "a 3-D player page (HTML) and a keypoint overlay (PNG). "
        "'mtex track CLIPS... --test CLIP': project the joints of the test clip through a "
        "pin-hole camera, add pixel noise and track its 3-D pose with a particle filter, once "
        "with the implicit-model prior and once with a constant-velocity prior; print the 3-D "
        "error per frame.",
    )
    s.add_argument(
        "clips",
        nargs="+",
        metavar="MODEL|CLIPS",
        help=f"with --keypoints: one texture model (.npz); otherwise {_CLIP_HELP}",
    )
    _track.add_arguments(s)
    g = s.add_argument_group("the particle-filter comparison (mtex track CLIPS... --test CLIP)")
    g.add_argument("--test", default=None, help="the clip to track (should not be in CLIPS)")
    g.add_argument("--particles", type=int_arg, default=None, help="particles (default 300)")
    g.add_argument("--frames", type=int_arg, default=None, help="frames to track (default all)")
    g.add_argument(
        "--start", type=int_arg, default=None, help="first frame of the initial window (0)"
    )
    g.add_argument("--seed", type=seed_arg, default=None, help="random seed (default 0)")
    g.add_argument("--window", type=int_arg, default=None, help="window length d (default 10)")
    s.add_argument(
        "--fps",
        type=float_arg,
        default=None,
        help="frame rate of the clips (default 30); with --keypoints: the keypoints' (default "
        "the file's; COCO files have none: the model's)",
    )
    g.add_argument("--beta", type=float_arg, default=None, help="implicit prior temperature (0.1)")
    g.add_argument(
        "--noise", type=float_arg, default=None, help="implicit prior pose noise (γ units, 0.1)"
    )
    g.add_argument(
        "--cv-noise",
        type=float_arg,
        default=None,
        help="constant-velocity noise (units of the database acceleration std, 0.1)",
    )
    g.add_argument(
        "--likelihood-sigma",
        type=float_arg,
        default=None,
        help="pixel std assumed by the likelihood (default 20)",
    )
    g.add_argument("--plot", default=None, help="write a PNG of the error per frame")
    s.add_argument(
        "--pixel-noise",
        type=float_arg,
        default=2.0,
        help="pixel noise (px, default 2): added to the synthetic problem; with --keypoints "
        "the detections' standard deviation",
    )
    add_force(s)
    s.set_defaults(func=_cmd_track)
