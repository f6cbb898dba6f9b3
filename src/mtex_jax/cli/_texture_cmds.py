"""``mtex learn``, ``segment``, ``synth``, ``choreograph``: the Motion Texture (``demo`` is in
``_demo``)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..core import MAX_GENERATED_FRAMES
from ..texture import CHUNK_FRAMES, OBSERVATION_MODELS
from ._validators import (
    SOURCE_HELP,
    add_force,
    float_arg,
    frames_of_seconds,
    int_arg,
    output,
    read_source,
    seed_arg,
    source_path,
)

__all__ = ["register"]


def _cmd_learn(args: argparse.Namespace) -> int:
    from ..texture import LearnConfig, learn_distributed, texture_summary
    from . import _distributed

    t0 = time.perf_counter()
    pid, n_proc = 0, 1
    if args.split_clips and not args.distributed:
        raise ValueError("--split-clips needs --distributed")
    output(args.output, "mtex_jax.MotionTexture", args.clips, args.force)
    if args.resume and args.checkpoint is None:
        raise ValueError("--resume needs --checkpoint FILE (the checkpoint to continue from)")
    if args.checkpoint is not None:
        output(
            args.checkpoint,
            "mtex_jax.LearnCheckpoint",
            (*args.clips, args.output),
            False,
            option="--checkpoint",
        )
    if args.fps is not None and not 0 < args.fps <= 10_000:
        raise ValueError(f"--fps must be in (0, 10000] frames per second, got {args.fps:g}")
    clips = list(args.clips)
    if args.distributed:
        pid, n_proc = _distributed.start(args)
        if args.split_clips:
            clips = _distributed.share(clips, pid, n_proc)
        error = None
        try:
            if not clips:
                raise ValueError(f"process {pid} has no clips ({len(args.clips)} for {n_proc})")
            motions = [read_source(c) for c in clips]
        except (ValueError, TypeError, OSError) as e:
            error = e
        _distributed.agree(error)  # all processes stop together, none waits for a failed one
    else:
        motions = [read_source(c) for c in clips]
    fps = args.fps if args.fps is not None else motions[0].fps
    if args.fps is None and any(m.fps != fps for m in motions):
        raise ValueError("the clips have different frame rates; choose one with --fps")
    if args.threshold is not None and args.textons is not None:
        raise ValueError("give --threshold or --textons, not both")
    if args.tmin is not None and args.tmax is not None and args.tmax < args.tmin:
        raise ValueError(
            f"--tmax ({args.tmax:g} s) must be at least --tmin ({args.tmin:g} s); "
            "both are in seconds"
        )
    cfg = LearnConfig(
        tmin=frames_of_seconds(args.tmin, fps, "tmin") or 3,
        tmax=frames_of_seconds(args.tmax, fps, "tmax"),
        state_dim=args.state_dim,
        threshold=args.threshold,
        n_textons=args.textons,
        max_iter=args.max_iter,
        fps=float(fps),
        min_segments=args.min_segments,
        observation=args.observation,
        durations=args.durations,
        selection=args.selection,
        init=args.init,
        dof=args.dof,
        innovations=args.innovations,
    )
    where = f"process {pid} of {n_proc}: " if args.distributed else ""
    print(
        f"{where}learning from {len(motions)} clip(s), {sum(m.duration for m in motions):.1f} s "
        f"of motion at {fps:g} Hz; tmin {cfg.tmin} frames, tmax {cfg.tmax} frames, "
        f"state dim {cfg.state_dim if cfg.state_dim is not None else 'by BIC'}, "
        f"observation model {cfg.observation}",
        flush=True,
    )
    # distributed: process 0 writes the checkpoint and reads it to resume (design §4.9)
    tex = _learn_checkpointed(args, motions, cfg, learn_distributed if args.distributed else None)
    if tex is None:
        return 130
    if args.distributed and pid != 0:  # every process has the model; process 0 writes it
        print(f"{where}done in {time.perf_counter() - t0:.1f} s")
        return 0
    tex.save(args.output)
    print(texture_summary(tex))
    print(f"wrote {args.output} in {time.perf_counter() - t0:.1f} s")
    if args.checkpoint is not None and Path(args.checkpoint).exists():
        Path(args.checkpoint).unlink()  # the model file holds what it kept
        print(f"removed the checkpoint {args.checkpoint}")
    return 0


def _learn_checkpointed(
    args: argparse.Namespace, motions: list[Any], cfg: Any, learner: Any = None
) -> Any:
    """``learn`` (or ``learner``: ``learn_distributed``) with ``--checkpoint``/``--resume``;
    on SIGINT or SIGTERM, one line on how to resume and ``None`` (exit status 130)."""
    import signal

    from ..texture import learn

    learner = learn if learner is None else learner

    ck = args.checkpoint
    if ck is not None and args.resume and not Path(ck).exists():
        print(f"no checkpoint {ck} yet: learning from the start", flush=True)

    def stop(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, stop)
    try:
        return learner(
            motions,
            cfg,
            verbose=not args.quiet,
            checkpoint=ck,
            resume=bool(args.resume),
        )
    except KeyboardInterrupt:
        if ck is None:
            how = "nothing was kept (--checkpoint FILE keeps the EM iterations)"
        elif Path(ck).exists():
            how = f"the checkpoint {ck} keeps the EM iterations: run the same command with --resume"
        else:
            how = f"no EM iteration had ended, so {ck} was not written: run the command again"
        print(f"mtex: interrupted; {how}", file=sys.stderr, flush=True)
        return None
    finally:
        signal.signal(signal.SIGTERM, old)


def _cmd_segment(args: argparse.Namespace) -> int:
    from ..texture import load_texture
    from ..viz import plot_timeline

    output(args.output, "png", (args.model, args.clip), args.force)
    tex = load_texture(args.model)
    if tex.feature_map is None:
        raise ValueError(
            f"{args.model} was learned from arrays, not motions; cannot segment a clip"
        )
    m = read_source(args.clip)
    if m.fps != tex.feature_map.fps:
        m = m.resample(tex.feature_map.fps)
    seg = tex.segment(m)
    rows = seg.to_list()
    fps = tex.feature_map.fps
    print(
        f"{args.clip}: {m.n_frames} frames at {fps:g} Hz, {len(rows)} segments, "
        f"log-likelihood {float(seg.score):.2f}"
    )
    print("  start(s)  length(s)  texton")
    for b, length, lab in rows:
        print(f"  {b / fps:8.2f}  {length / fps:9.2f}  {lab:6d}")
    if args.output:
        plot_timeline(
            [rows],
            args.output,
            fps=fps,
            n_textons=tex.n_textons,
            names=[Path(args.clip).stem],
            title=f"texton labels of {args.clip}",
        )
        print(f"wrote {args.output}")
    return 0


def _cmd_textons(args: argparse.Namespace) -> int:
    from ..viz import render_texton_gallery

    output(args.output, "png", (args.model, *args.clips), args.force)
    if not 1 <= args.per_texton <= 10:
        raise ValueError(f"--per-texton must be in 1..10, got {args.per_texton}")
    tex = load_model(args.model)
    print(tex.summary())
    clips = [read_source(c) for c in args.clips] if args.clips else None
    render_texton_gallery(tex, args.output, clips, per_texton=args.per_texton)
    what = "training segments" if clips else "samples of each texton's dynamics"
    print(f"wrote {args.output} ({tex.n_textons} rows of {what})")
    return 0


def load_model(path: str):
    from ..texture import load_texture

    tex = load_texture(path)
    if tex.feature_map is None:
        raise ValueError(f"{path} was learned from arrays, not motions; it cannot make a BVH")
    return tex


def _check_outputs(
    out: str, gif: str | None, inputs: tuple[str, ...] = (), force: bool = False
) -> None:
    """Refuse output names of the wrong kind, outputs that are inputs and files of another
    kind (without ``force``) before any work is done."""
    output(out, "bvh", inputs, force)
    output(gif, "gif", (*inputs, out), force, option="--gif")


def _write_outputs(syn, out: str, gif: str | None, title: str) -> None:
    from ..io import write_bvh

    assert syn.motion is not None  # the outputs were checked before the work (_check_outputs)
    write_bvh(out, syn.motion)
    fps = syn.motion.fps
    print(
        f"texton path {np.asarray(syn.path).tolist()}\n"
        f"lengths (frames) {np.asarray(syn.lengths).tolist()}\n"
        f"wrote {out} ({syn.n_frames} frames, {syn.n_frames / fps:.2f} s at {fps:g} Hz)"
    )
    if gif:
        from ..viz import render_gif

        render_gif(syn.motion, gif, title=title)
        print(f"wrote {gif}")


def _cmd_synth(args: argparse.Namespace) -> int:
    import jax

    from ..texture import synthesize

    _check_outputs(
        args.output, args.gif, tuple(c for c in (args.model, args.contacts) if c), args.force
    )
    tex = load_model(args.model)
    assert tex.feature_map is not None  # checked by load_model
    fps = tex.feature_map.fps
    n = args.frames if args.frames is not None else round(10.0 * fps)
    if n < 4:
        raise ValueError(f"--frames must be >= 4, got {n}")
    if n > MAX_GENERATED_FRAMES:
        raise ValueError(f"--frames {n:,} exceeds the limit of {MAX_GENERATED_FRAMES:,}")
    if args.contacts and not args.clean:
        raise ValueError("--contacts is only used with --clean")
    long = f"--frames {n:,} is more than one piece of {CHUNK_FRAMES:,} frames"
    if n > CHUNK_FRAMES and args.gif:
        raise ValueError(
            f"--gif: {long} ({CHUNK_FRAMES / fps / 60:.0f} min), too long to draw; write the "
            "BVH alone and render a shorter synthesis"
        )
    if n > CHUNK_FRAMES and args.clean:
        raise ValueError(
            f"--clean: {long}; the cleaning solve holds the whole motion: clean up to "
            f"{CHUNK_FRAMES:,} frames at a time"
        )
    print(f"synthesising {n} frames ({n / fps:.1f} s at {fps:g} Hz)...", flush=True)
    t0 = time.perf_counter()
    if n > CHUNK_FRAMES:
        return _synth_stream(args, tex, n, t0)
    if not args.clean:
        syn = synthesize(jax.random.key(args.seed), tex, n_frames=n)
        took = time.perf_counter() - t0
        print(f"synthesised {n} frames from {tex.n_textons} textons in {took:.1f} s")
    else:  # the function of the API: mtex_jax.edit.synthesize(..., clean=True)
        from ..edit import synthesize as synthesize_edit
        from ._edit import clean_contacts

        cm = clean_contacts(tex, args.model, args.contacts)
        own = None if cm is tex.contacts else cm  # None: the model's own, as the API does
        print("and cleaning: foot contacts and the floor (a least-squares solve)...", flush=True)
        syn = synthesize_edit(jax.random.key(args.seed), tex, n_frames=n, clean=True, contacts=own)
        assert syn.motion is not None
        sk, pen = cm.skating(syn.motion), cm.penetration(syn.motion)
        print(
            f"synthesised {n} frames from {tex.n_textons} textons and cleaned in "
            f"{time.perf_counter() - t0:.1f} s: foot skating median {sk.median:.2f} m/s, "
            f"deepest foot below the training floor {100 * pen.max_depth:.1f} cm"
        )
    _write_outputs(syn, args.output, args.gif, f"mtex synth (seed {args.seed})")
    return 0


def _synth_stream(args: argparse.Namespace, tex, n: int, t0: float) -> int:
    """``mtex synth`` of more than one piece: planned whole, then synthesised, decoded and
    written a piece at a time (:func:`~mtex_jax.texture.synthesize_chunks`), with a progress
    line on stderr per piece."""
    import jax

    from ..io import write_bvh_chunks
    from ..texture import synthesize_chunks

    stream = synthesize_chunks(
        jax.random.key(args.seed), tex, n_frames=n, chunk_frames=CHUNK_FRAMES
    )
    fps = tex.feature_map.fps
    print(
        f"planned {stream.path.size:,} textons; synthesising and writing {stream.n_frames:,} "
        f"frames in pieces of {stream.chunk_frames:,}",
        flush=True,
    )

    def pieces():
        for piece in stream:
            assert piece.motion is not None
            yield piece.motion
            done = piece.start + piece.n_frames
            took = time.perf_counter() - t0
            print(
                f"[mtex synth] {done:,} / {n:,} frames ({100 * done / n:.0f} %), {took:.0f} s",
                file=sys.stderr,
                flush=True,
            )

    write_bvh_chunks(args.output, pieces(), n)
    path, lens = stream.path, stream.lengths
    show = lambda a: (
        str(a.tolist()) if a.size <= 40 else f"{a[:20].tolist()} ... ({a.size:,} in all)"
    )
    print(
        f"synthesised {n} frames from {tex.n_textons} textons in {time.perf_counter() - t0:.1f} s\n"
        f"texton path {show(path)}\n"
        f"lengths (frames) {show(lens)}\n"
        f"wrote {args.output} ({n} frames, {n / fps:.2f} s at {fps:g} Hz)"
    )
    return 0


def _clip_frame(spec: str, tex) -> tuple[np.ndarray, np.ndarray, float]:
    """``CLIP:FRAME`` -> observation pair (2, D), root position and heading at that frame."""
    # split on the last colon: CLIP may itself hold one (example:NAME, C:\\path)
    clip, sep, frame_s = spec.rpartition(":")
    try:
        frame = int(frame_s)
    except ValueError:
        frame = None
    if not sep or not clip or frame is None:
        raise ValueError(
            f"expected CLIP:FRAME; FRAME must be an integer (e.g. example:dance_a:10 or "
            f"salsa.bvh:120), got {spec!r}; add the frame: {spec}:0"
        )
    m = read_source(clip)
    fm = tex.feature_map
    if m.fps != fm.fps:
        m = m.resample(fm.fps)
    if not 0 <= frame < m.n_frames - 1:
        raise ValueError(
            f"{spec!r}: frame {frame} out of range; the clip has {m.n_frames} frames at "
            f"{fm.fps:g} Hz (the pose uses frames FRAME and FRAME+1)"
        )
    Y = np.asarray(fm.encode(m))
    pos, heading = fm.start_of(m[frame:])
    return Y[frame : frame + 2], pos, heading


def _cmd_choreograph(args: argparse.Namespace) -> int:
    import jax

    from ..texture import choreograph

    _check_outputs(
        args.output,
        args.gif,
        (args.model, source_path(args.start), source_path(args.end)),
        args.force,
    )
    tex = load_model(args.model)
    start, pos, heading = _clip_frame(args.start, tex)
    end, _, _ = _clip_frame(args.end, tex)
    plan = (
        "the most probable texton path, each texton as long as its key poses' training segment"
        if args.frames is None
        else f"{args.frames} frames"
    )
    print(f"choreographing {args.start} -> {args.end}: {plan}...", flush=True)
    t0 = time.perf_counter()
    syn = choreograph(
        jax.random.key(args.seed),
        tex,
        start,
        end,
        n_frames=args.frames,
        start_position=pos,
        start_heading=heading,
    )
    print(f"choreographed {syn.n_frames} frames in {time.perf_counter() - t0:.1f} s")
    _write_outputs(syn, args.output, args.gif, f"{args.start} -> {args.end}")
    return 0


def _dof_arg(text: str) -> float | None:
    """``--dof``: a number > 0, or ``gaussian``."""
    if text.strip().lower() == "gaussian":
        return None
    try:
        nu = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a number > 0 or 'gaussian', got {text!r}"
        ) from None
    if not np.isfinite(nu) or nu <= 0:
        raise argparse.ArgumentTypeError(
            f"expected a finite number > 0 or 'gaussian', got {text!r}"
        )
    return nu


def register(sub: argparse._SubParsersAction) -> None:
    """Add the Motion Texture commands to the ``mtex`` sub-command parsers."""
    from ._distributed import RECIPE, add_arguments

    s = sub.add_parser(
        "learn",
        help="learn a motion texture from clips",
        description="Learn a motion texture (textons + transition matrix) from motion clips "
        "by EM from an initial segmentation (clustered chunks by default, or the paper's "
        "greedy one) with a dynamic-programming segmentation (MT §4).",
        epilog=RECIPE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    s.add_argument("clips", nargs="+", help=SOURCE_HELP + "; one or more")
    s.add_argument("-o", "--output", required=True, help="model file to write (.npz)")
    s.add_argument(
        "--tmin", type=float_arg, default=1.0, help="shortest segment, seconds (default 1)"
    )
    s.add_argument(
        "--tmax", type=float_arg, default=3.0, help="longest segment, seconds (default 3)"
    )
    s.add_argument(
        "--state-dim",
        type=int_arg,
        default=None,
        help="texton state dimension: the default tied and full models take D (the "
        "observation's dimension); paper and residual choose it by BIC unless given (the "
        "paper used 12)",
    )
    s.add_argument(
        "--observation",
        choices=tuple(OBSERVATION_MODELS),
        default="tied",
        help="observation model of the textons (default tied: shared dynamics, own offsets "
        "and shrunk covariances; paper = MT-11)",
    )
    s.add_argument(
        "--dof",
        type=_dof_arg,
        default=4.0,
        metavar="NU|gaussian",
        help="innovations of full-dimensional textons: Student-t with NU degrees of freedom "
        "(default 4) or gaussian (the paper)",
    )
    s.add_argument(
        "--durations",
        choices=("lognormal", "flat"),
        default="lognormal",
        help="segment-length distribution per texton (default lognormal; flat = the paper)",
    )
    s.add_argument(
        "--innovations",
        choices=("fitted", "white", "residuals"),
        default="residuals",
        help="innovations of synthesis: blocks of the training residuals themselves "
        "(residuals, default), a process fitted on them (fitted) or independent (white, the "
        "paper)",
    )
    s.add_argument(
        "--selection",
        choices=("aic", "bic", "none"),
        default="aic",
        help="choose the number of textons by AIC after EM (default), by BIC, or keep EM's (none)",
    )
    s.add_argument(
        "--init",
        choices=("chunks", "greedy"),
        default="chunks",
        help="initial segmentation: clustered chunks (default) or the paper's greedy one",
    )
    g = s.add_mutually_exclusive_group()
    g.add_argument(
        "--threshold",
        type=float_arg,
        default=None,
        help="greedy-initialisation error threshold (with --init greedy; default 0.3)",
    )
    g.add_argument(
        "--textons",
        type=int_arg,
        default=None,
        help="initial textons (--init chunks; default one per 4 chunks) or the greedy "
        "threshold's target (--init greedy)",
    )
    s.add_argument(
        "--fps",
        type=float_arg,
        default=None,
        help="resample the clips to this frame rate first (default: theirs)",
    )
    s.add_argument("--max-iter", type=int_arg, default=20, help="most EM iterations (default 20)")
    s.add_argument(
        "--min-segments",
        type=int_arg,
        default=3,
        help="prune textons with fewer training segments (default 3; 1: no pruning, the paper)",
    )
    s.add_argument("--quiet", action="store_true", help="no per-iteration progress lines")
    s.add_argument(
        "--checkpoint",
        default=None,
        metavar="FILE",
        help="write the progress to FILE (.npz) after every EM iteration, atomically; an "
        "interrupted learn continues from it with --resume (removed once the model is written)",
    )
    s.add_argument(
        "--resume",
        action="store_true",
        help="continue from --checkpoint FILE (the same clips and options): the model is the "
        "one an uninterrupted learn writes, bit for bit",
    )
    add_force(s)
    add_arguments(s)
    s.set_defaults(func=_cmd_learn)

    s = sub.add_parser(
        "textons",
        help="a gallery of a texture's vocabulary",
        description="Print every texton's training segments, mean duration and successors, "
        "and draw one row per texton with a few of its instances: its training segments when "
        "the training clips are given (in the order they were learned from), else samples of "
        "its dynamics from its key poses.",
    )
    s.add_argument("model", help="a model file written by 'mtex learn'")
    s.add_argument("clips", nargs="*", help="the training clips (optional); " + SOURCE_HELP)
    s.add_argument("-o", "--output", required=True, help="gallery picture to write (.png)")
    s.add_argument("--per-texton", type=int_arg, default=3, help="instances per texton (default 3)")
    add_force(s)
    s.set_defaults(func=_cmd_textons)

    s = sub.add_parser(
        "segment",
        help="segment a clip with a learned motion texture",
        description="Print the texton labels of a clip over time (and plot them, MT Fig. 2).",
    )
    s.add_argument("model", help="a model file written by 'mtex learn'")
    s.add_argument("clip", help=SOURCE_HELP)
    s.add_argument("-o", "--output", default=None, help="timeline picture to write (.png)")
    add_force(s)
    s.set_defaults(func=_cmd_segment)

    s = sub.add_parser(
        "synth",
        help="synthesise a new motion from a learned texture",
        description="Random texton path, key poses, constrained synthesis of every texton "
        "(MT §5); writes BVH and optionally an animated GIF.",
    )
    s.add_argument("model", help="a model file written by 'mtex learn' or 'mtex demo'")
    s.add_argument("-o", "--output", required=True, help="BVH file to write")
    s.add_argument("--frames", type=int_arg, default=None, help="frames to make (default 10 s)")
    s.add_argument("--seed", type=seed_arg, default=0, help="random seed (default 0)")
    s.add_argument("--gif", default=None, help="also render an animated GIF here")
    s.add_argument(
        "--clean",
        action="store_true",
        help="remove foot skating and floor penetration with the training clips' contact model "
        "the model file carries (mtex_jax.edit.synthesize with clean=True)",
    )
    s.add_argument(
        "--contacts",
        default=None,
        help="another contact model for --clean (a file of 'mtex contacts'; default: the model "
        "file's own, else MODEL.contacts.npz beside it)",
    )
    add_force(s)
    s.set_defaults(func=_cmd_synth)

    s = sub.add_parser(
        "choreograph",
        help="make a motion from a start pose to an end pose (virtual choreographer)",
        description="Match the start and end poses to textons, plan a texton path between "
        "them and synthesise it (MT Fig. 1). Poses are CLIP:FRAME, e.g. example:dance_a:10 "
        "or salsa.bvh:120 (frames counted at the model's frame rate).",
    )
    s.add_argument("model", help="a model file written by 'mtex learn' or 'mtex demo'")
    s.add_argument("--start", required=True, help="start pose, CLIP:FRAME")
    s.add_argument("--end", required=True, help="end pose, CLIP:FRAME")
    s.add_argument("-o", "--output", required=True, help="BVH file to write")
    s.add_argument(
        "--frames",
        type=int_arg,
        default=None,
        help="total frames (default: the most probable texton path between the poses, each "
        "texton as long as its training segment)",
    )
    s.add_argument("--seed", type=seed_arg, default=0, help="random seed (default 0)")
    s.add_argument("--gif", default=None, help="also render an animated GIF here")
    add_force(s)
    s.set_defaults(func=_cmd_choreograph)
