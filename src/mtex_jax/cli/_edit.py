"""``mtex edit`` (a joint at a point at a frame, the texture's dynamics otherwise) and
``mtex contacts`` (fit the foot-contact model of clips, which ``synth --clean`` may use instead
of the one a model file carries)."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from ._validators import SOURCE_HELP, add_force, float_arg, int_arg, output, read_source

__all__ = ["clean_contacts", "contacts_path", "register"]


def contacts_path(model: str) -> Path:
    """The contact-model file beside a model file: ``NAME.contacts.npz``."""
    p = Path(model)
    return p.with_name(p.stem + ".contacts.npz")


def clean_contacts(tex: Any, model: str, option: str | None) -> Any:
    """The contact model of ``synth --clean``: the file of ``--contacts``, else the one the
    model file carries (fitted by ``learn`` on its training clips), else ``MODEL.contacts.npz``
    beside it (a model saved before model files carried their contacts)."""
    from ..edit import load_contacts

    if option:
        return load_contacts(option)
    if tex.contacts is not None:
        return tex.contacts
    beside = contacts_path(model)
    if beside.is_file():
        return load_contacts(beside)
    raise ValueError(
        f"--clean needs the training clips' contact model: {model} carries none (it was saved "
        "before model files carried their contacts; learn it again, or make one with "
        "'mtex contacts CLIPS... -o FILE' and pass --contacts FILE)"
    )


def _point(text: str, option: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        xyz = tuple(float(p) for p in parts)
    except ValueError:
        xyz = ()
    if len(xyz) != 3 or not all(math.isfinite(v) for v in xyz):
        raise ValueError(f"{option} must be three finite numbers X,Y,Z in metres, got {text!r}")
    return xyz  # type: ignore[return-value]


def _cmd_edit(args: argparse.Namespace) -> int:
    from ..edit import edit, make_constraints
    from ..io import write_bvh
    from ..motion import forward_kinematics
    from ..texture import load_texture

    if not args.tolerance > 0:
        raise ValueError(f"--tolerance must be a positive distance in metres, got {args.tolerance}")
    output(args.output, "bvh", (args.model, args.clip), args.force)
    point = _point(args.at, "--at") if args.at is not None else _point(args.by, "--by")
    tex = load_texture(args.model)
    fm = tex.feature_map
    if fm is None:
        raise ValueError(f"{args.model} was learned from arrays, not motions; it cannot edit")
    if args.joint not in fm.skeleton.names:
        raise ValueError(f"--joint {args.joint!r} is not a joint of the model's skeleton")
    m = read_source(args.clip)
    if m.fps != fm.fps:
        m = m.resample(fm.fps)
    if not 0 <= args.frame < m.n_frames:
        raise ValueError(f"--frame {args.frame} outside 0..{m.n_frames - 1} (at {fm.fps:g} Hz)")
    if m.n_frames < 3:
        raise ValueError(f"{args.clip} has {m.n_frames} frames; editing needs at least 3")
    if args.at is not None:
        at = point
    else:  # --by: an offset from where the joint is at that frame
        if args.joint not in m.skeleton.names:
            raise ValueError(f"--joint {args.joint!r} is not a joint of {args.clip}")
        j = m.skeleton.names.index(args.joint)
        now = np.asarray(forward_kinematics(m)[args.frame, j], dtype=np.float64)
        at = tuple(float(v) for v in now + np.asarray(point))
        print(
            f"{args.joint} at frame {args.frame}: {_xyz(now)} m; target {_xyz(at)} m (--by)",
            flush=True,
        )
    print(f"editing {m.n_frames} frames (a least-squares solve)...", flush=True)
    t0 = time.perf_counter()
    cons = make_constraints(
        fm.skeleton, m.n_frames, fm.dim, positions=[(args.joint, args.frame, at)]
    )
    res = edit(tex, m, cons)
    sp, sh = fm.start_of(m)
    write_bvh(args.output, fm.decode(res.Y, sp, sh))
    print(res.report(tolerance=args.tolerance))
    print(f"edited in {time.perf_counter() - t0:.1f} s; wrote {args.output}")
    return 0 if res.met_within(args.tolerance) else 1


def _xyz(p: Any) -> str:
    return ",".join(f"{float(v):.4f}" for v in p)


def _cmd_contacts(args: argparse.Namespace) -> int:
    from ..edit import save_contacts
    from ..motion import fit_contacts

    output(args.output, "mtex_jax.ContactModel", args.clips, args.force)
    if args.fps is not None and not (math.isfinite(args.fps) and args.fps > 0):
        raise ValueError(f"--fps must be positive, got {args.fps}")
    motions = [read_source(c) for c in args.clips]
    fps = args.fps if args.fps is not None else motions[0].fps
    motions = [mm if mm.fps == fps else mm.resample(fps) for mm in motions]
    cm = fit_contacts(motions, fps=fps)
    save_contacts(args.output, cm)
    print(
        f"feet {', '.join(cm.foot_names)}; height thresholds "
        f"{', '.join(f'{h:.3f}' for h in cm.height_threshold)} m; speed thresholds "
        f"{', '.join(f'{s:.2f}' for s in cm.speed_threshold)} m/s; floor {cm.floor:.3f} m"
    )
    print(f"wrote {args.output}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser(
        "edit",
        help="move a joint to a point at a frame, the texture's dynamics otherwise",
        description="Edit a clip by optimisation through the texture's decode and forward "
        "kinematics (banded Gauss-Newton, the default solver for position targets): JOINT "
        "at X,Y,Z (metres, world; or moved by DX,DY,DZ with --by) at FRAME, every "
        "other frame as likely under the textons as before. Exit status 1 if the target "
        "was missed by more than --tolerance (the report says by how much).",
    )
    s.add_argument("model", help="a model file written by 'mtex learn' or 'mtex demo'")
    s.add_argument("clip", help=SOURCE_HELP)
    s.add_argument("--joint", required=True, help="joint name, e.g. rHand")
    s.add_argument("--frame", required=True, type=int_arg, help="frame (at the model's rate)")
    where = s.add_mutually_exclusive_group(required=True)
    where.add_argument("--at", default=None, help="target world position X,Y,Z in metres")
    where.add_argument(
        "--by",
        default=None,
        metavar="DX,DY,DZ",
        help="target as an offset in metres from where the joint is at --frame (see "
        "'mtex info CLIP --joint J --frame F')",
    )
    s.add_argument("-o", "--output", required=True, help="BVH file to write")
    s.add_argument(
        "--tolerance",
        type=float_arg,
        default=0.01,
        help="largest miss of the target (and of planted feet and the floor) that counts as "
        "met, metres (default 0.01: 1 cm); exit status 1 beyond it",
    )
    add_force(s)
    s.set_defaults(func=_cmd_edit)

    s = sub.add_parser(
        "contacts",
        help="fit the foot-contact model of clips (for 'synth --clean --contacts')",
        description="Per-foot height and speed thresholds and the floor, from training clips "
        "(mtex_jax.motion.fit_contacts). A model file learned from clips carries its own; "
        "'mtex synth --clean --contacts FILE' uses this one instead (and a file "
        "MODEL.contacts.npz beside a model file without one).",
    )
    s.add_argument("clips", nargs="+", help=SOURCE_HELP)
    s.add_argument(
        "--fps", type=float_arg, default=None, help="frame rate (default the first clip's)"
    )
    s.add_argument("-o", "--output", required=True, help=".npz file to write")
    add_force(s)
    s.set_defaults(func=_cmd_contacts)
