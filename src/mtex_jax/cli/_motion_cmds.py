"""``mtex info``, ``mtex render``, ``mtex examples``, ``mtex mirror``: looking at motion files and
mirroring them."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ._validators import SOURCE_HELP, add_force, float_arg, int_arg, output, read_source

__all__ = ["register"]


def _cmd_info(args: argparse.Namespace) -> int:
    m = read_source(args.file)
    sk = m.skeleton
    if (args.joint is None) != (args.frame is None):
        raise ValueError("--joint and --frame go together: a joint's position at a frame")
    if args.joint is not None:
        if args.joint not in sk.names:
            near = [n for n in sk.names if n.lower() == args.joint.lower()]
            hint = f"did you mean {near[0]}?" if near else "see --joints"
            raise ValueError(f"--joint {args.joint!r} is not a joint of {args.file} ({hint})")
        if not 0 <= args.frame < m.n_frames:
            raise ValueError(f"--frame {args.frame} outside 0..{m.n_frames - 1}")
    n_rot = sum(1 for j in range(sk.n_joints) if sk.rotation_order(j))
    print(f"file:      {args.file}")
    print(f"frames:    {m.n_frames}")
    print(f"fps:       {m.fps:g}")
    print(f"duration:  {m.duration:.3f} s")
    print(f"joints:    {sk.n_joints} ({n_rot} rotating, {len(sk.end_sites)} end sites)")
    print(f"channels:  {sk.n_channels}")
    print(f"up axis:   {'xyz'[sk.up_axis]}")
    print(f"size:      {sk.size:.3f} (longest root-to-leaf chain, file units)")
    if args.joint is not None:
        import numpy as np

        from ..motion import forward_kinematics

        p = np.asarray(forward_kinematics(m)[args.frame, sk.names.index(args.joint)], np.float64)
        xyz = ",".join(f"{float(v):.4f}" for v in p)
        print(
            f"{args.joint} at frame {args.frame} ({args.frame / m.fps:.3f} s): {xyz} "
            f"(world, file units; {'xyz'[sk.up_axis]} up); 'mtex edit --at' takes this form"
        )
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
    from ..viz import render_filmstrip, render_gif

    out = Path(args.output)
    if out.suffix.lower() not in (".gif", ".png"):
        raise ValueError(
            f"-o/--output must end in .gif (animation) or .png (filmstrip), got {str(out)!r}"
        )
    output(out, out.suffix.lower().lstrip("."), (args.file,), args.force)
    m = read_source(args.file)
    traj = args.trajectories.split(",") if args.trajectories else None
    t0 = time.perf_counter()
    if out.suffix.lower() == ".png":
        render_filmstrip(m, out, trajectories=traj, title=args.title)
    else:
        render_gif(m, out, fps=args.fps, trajectories=traj, title=args.title)
    print(f"wrote {out} ({m.n_frames} frames, {time.perf_counter() - t0:.1f} s)")
    return 0


def _cmd_mirror(args: argparse.Namespace) -> int:
    from ..io import write_bvh

    out = Path(args.output)
    output(out, "bvh", (args.file,), args.force)
    m = read_source(args.file)
    axis = None if args.axis is None else "xyz".index(args.axis)
    mirrored = m.mirror(axis)
    write_bvh(out, mirrored)
    sk = m.skeleton
    pairs = sum(1 for i, j in enumerate(sk.mirror_pairs()) if i < j)
    used = "xyz"[sk.lateral_axis() if axis is None else axis]
    print(
        f"wrote {out}: {m.n_frames} frames mirrored through the {used} axis "
        f"({pairs} left-right joint pairs swapped)"
    )
    return 0


def _cmd_examples(args: argparse.Namespace) -> int:
    from ..io import example_names, load_example, load_salsa, salsa_credit, salsa_split

    train, held = salsa_split()
    print("CMU salsa clips (subject 60), the default data; read as example:salsa/NAME")
    for name, m in zip(train + held, [load_salsa(n) for n in train + held], strict=True):
        part = "training" if name in train else "held out"
        print(
            f"salsa/{name:12s} {m.n_frames:5d} frames  {m.fps:5.1f} Hz  {m.duration:6.2f} s  "
            f"({part})"
        )
    print("\nDeepMimic humanoid3d clips (zlib licence); read as example:NAME")
    for name in example_names():
        m = load_example(name)
        print(f"{name:18s} {m.n_frames:5d} frames  {m.fps:5.1f} Hz  {m.duration:6.2f} s")
    print()
    print(salsa_credit().rstrip())
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``info``, ``render``, ``examples`` and ``mirror`` to the ``mtex`` sub-command
    parsers."""
    s = sub.add_parser(
        "info",
        help="describe a motion file",
        description="Print skeleton, frame rate, number of frames and duration of a motion; "
        "with --joint J --frame F, where joint J is at frame F (world position).",
    )
    s.add_argument("file", help=SOURCE_HELP)
    s.add_argument("--joints", action="store_true", help="also print the joint tree")
    s.add_argument(
        "--joint", default=None, help="print this joint's world position at --frame (e.g. rHand)"
    )
    s.add_argument(
        "--frame", type=int_arg, default=None, help="the frame of --joint (at the clip's rate)"
    )
    s.set_defaults(func=_cmd_info)

    s = sub.add_parser(
        "render",
        help="render a motion as an animated GIF or a PNG filmstrip",
        description="Render a stick-figure animation (GIF) or, if the output "
        "ends in .png, a filmstrip of key frames.",
    )
    s.add_argument("file", help=SOURCE_HELP)
    s.add_argument("-o", "--output", required=True, help="output .gif (animation) or .png")
    s.add_argument(
        "--fps",
        type=float_arg,
        default=None,
        help="playback frame rate of the GIF (default: min(clip fps, 30))",
    )
    s.add_argument(
        "--trajectories",
        default=None,
        help="comma-separated joint names whose paths are drawn, e.g. lFoot,rFoot",
    )
    s.add_argument("--title", default=None, help="title drawn on the picture")
    add_force(s)
    s.set_defaults(func=_cmd_render)

    s = sub.add_parser(
        "examples",
        help="list the shipped clips (CMU salsa, DeepMimic) and the CMU credit",
        description="List the shipped clips: the 14 CMU salsa clips of subject 60 (the "
        "default data, read as example:salsa/NAME, with their training / held-out split) and "
        "the DeepMimic humanoid3d clips (read as example:NAME); print the CMU credit.",
    )
    s.set_defaults(func=_cmd_examples)

    s = sub.add_parser(
        "mirror",
        help="mirror a motion left to right (the other side of the body leads)",
        description="Reflect a motion left to right on its own skeleton: every joint takes the "
        "reflected rotation of its left-right partner (joints paired by name: lThigh/rThigh, "
        "left_hip/right_hip, ...), and the root's path is reflected through the vertical "
        "plane of the lateral axis. Writes a BVH file.",
    )
    s.add_argument("file", help=SOURCE_HELP)
    s.add_argument("-o", "--output", required=True, help="output .bvh")
    s.add_argument(
        "--axis",
        choices=("x", "y", "z"),
        default=None,
        help="the world axis to reflect (default: the one along which the left and right "
        "joints lie apart at rest)",
    )
    add_force(s)
    s.set_defaults(func=_cmd_mirror)
