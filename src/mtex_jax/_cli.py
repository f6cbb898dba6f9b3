"""The ``mtex`` command line.

Every sub-command reports a user error as one line on stderr (``mtex: error: ...``) and exits
with status 2; it never shows a traceback for bad input.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

__all__ = ["main"]

_SOURCE_HELP = "a .bvh file, a DeepMimic JSON motion file, or example:NAME (see 'mtex examples')"


class _UserError(Exception):
    """An error caused by the user's input: printed as one line."""


def _read(source: str):
    from ._readers import read_motion

    return read_motion(source)


def _cmd_info(args: argparse.Namespace) -> int:
    m = _read(args.file)
    sk = m.skeleton
    n_rot = sum(1 for j in range(sk.n_joints) if sk.rotation_order(j))
    print(f"file:      {args.file}")
    print(f"frames:    {m.n_frames}")
    print(f"fps:       {m.fps:g}")
    print(f"duration:  {m.duration:.3f} s")
    print(f"joints:    {sk.n_joints} ({n_rot} rotating, {len(sk.end_sites)} end sites)")
    print(f"channels:  {sk.n_channels}")
    print(f"up axis:   {'xyz'[sk.up_axis]}")
    print(f"size:      {sk.size:.3f} (longest root-to-leaf chain, file units)")
    if args.joints:
        print("skeleton:")
        depth = sk.depth()
        for j in range(sk.n_joints):
            order = sk.rotation_order(j) or "-"
            pos = sk.position_channels(j)
            extra = f" pos {pos}" if pos else ""
            print(f"  {'  ' * depth[j]}{sk.names[j]}  [rot {order}{extra}]")
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from ._render import render_filmstrip, render_gif

    m = _read(args.file)
    out = Path(args.output)
    traj = args.trajectories.split(",") if args.trajectories else None
    t0 = time.perf_counter()
    if out.suffix.lower() == ".png":
        render_filmstrip(m, out, trajectories=traj, title=args.title)
    else:
        render_gif(m, out, fps=args.fps, trajectories=traj, title=args.title)
    print(f"wrote {out} ({m.n_frames} frames, {time.perf_counter() - t0:.1f} s)")
    return 0


def _cmd_examples(args: argparse.Namespace) -> int:
    from ._data import example_names, load_example

    for name in example_names():
        m = load_example(name)
        print(f"{name:18s} {m.n_frames:5d} frames  {m.fps:5.1f} Hz  {m.duration:6.2f} s")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    """The main job on the embedded default data."""
    from ._data import load_example
    from ._features import FeatureMap
    from ._render import render_filmstrip, render_gif

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    m = load_example(args.example)
    fm = FeatureMap.fit(m)
    y = fm.encode(m)
    print(
        f"loaded example:{args.example}: {m.n_frames} frames at {m.fps:g} Hz, "
        f"{m.skeleton.n_joints} joints, observation dimension D = {fm.dim}"
    )
    gif = render_gif(m, out / f"{args.example}.gif", trajectories=["left_ankle", "right_ankle"])
    png = render_filmstrip(m, out / f"{args.example}_filmstrip.png")
    fm.save(out / "features.npz")
    print(f"wrote {gif}, {png} and {out / 'features.npz'} (Y: {tuple(y.shape)})")
    print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


def _parser() -> argparse.ArgumentParser:
    from . import __version__

    p = argparse.ArgumentParser(
        prog="mtex",
        description="Motion Texture and implicit motion models in JAX: inspect, render, learn "
        "and synthesise motion capture.",
    )
    p.add_argument("--version", action="version", version=f"mtex_jax {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    s = sub.add_parser(
        "info",
        help="describe a motion file",
        description="Print skeleton, frame rate, number of frames and duration of a motion.",
    )
    s.add_argument("file", help=_SOURCE_HELP)
    s.add_argument("--joints", action="store_true", help="also print the joint tree")
    s.set_defaults(func=_cmd_info)

    s = sub.add_parser(
        "render",
        help="render a motion as an animated GIF or a PNG filmstrip",
        description="Render a stick-figure animation (GIF) or, if the output "
        "ends in .png, a filmstrip of key frames.",
    )
    s.add_argument("file", help=_SOURCE_HELP)
    s.add_argument("-o", "--output", required=True, help="output .gif (animation) or .png")
    s.add_argument(
        "--fps",
        type=float,
        default=None,
        help="playback frame rate of the GIF (default: min(clip fps, 30))",
    )
    s.add_argument(
        "--trajectories",
        default=None,
        help="comma-separated joint names whose paths are drawn, e.g. lFoot,rFoot",
    )
    s.add_argument("--title", default=None, help="title drawn on the picture")
    s.set_defaults(func=_cmd_render)

    s = sub.add_parser(
        "examples",
        help="list the embedded example clips",
        description="List the embedded DeepMimic example clips.",
    )
    s.set_defaults(func=_cmd_examples)

    s = sub.add_parser(
        "demo",
        help="run the main job on the embedded default data",
        description="Load the embedded dance, fit its observation features and "
        "render it (GIF + filmstrip).",
    )
    s.add_argument("--out", default="out", help="output folder (default: out)")
    s.add_argument("--example", default="dance_a", help="embedded clip to use (default dance_a)")
    s.set_defaults(func=_cmd_demo)

    try:  # the implicit-model commands live with that model
        from ._implicit_cli import register as _register_implicit
    except ImportError:  # pragma: no cover - module not present in this build
        _register_implicit = None
    if _register_implicit is not None:
        _register_implicit(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mtex`` console script."""
    parser = _parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args))
    except (ValueError, TypeError, OSError, ImportError, _UserError) as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        print(f"mtex: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mtex: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
