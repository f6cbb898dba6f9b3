"""``mtex view``: one self-contained HTML page with a 3-D player of motions and textures."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ._validators import (
    SOURCE_HELP,
    add_force,
    float_arg,
    output,
    positive,
    read_source,
    seed_arg,
)

__all__ = ["register"]

#: the longest synthesis shown for a texture model (seconds)
MAX_SECONDS = 120.0


def _cmd_view(args: argparse.Namespace) -> int:
    import jax

    from ..viz import write_html

    out = Path(args.output)
    # one may replace an older page, but not an input or a motion or model file (without --force)
    output(out, "html", args.files, args.force)
    positive("fps", args.fps)
    positive("seconds", args.seconds)
    if args.seconds > MAX_SECONDS:
        raise ValueError(f"--seconds {args.seconds:g} exceeds the limit of {MAX_SECONDS:g}")
    models = [f for f in args.files if f.lower().endswith(".npz")]
    if len(models) > 1:
        raise ValueError(f"give at most one texture model (.npz), got {len(models)}")
    labels = args.labels.split(",") if args.labels is not None else None
    if labels is not None and len(labels) != len(args.files):
        raise ValueError(
            f"--labels needs {len(args.files)} comma-separated names (one per file), "
            f"got {len(labels)}"
        )
    t0 = time.perf_counter()
    motions: list = []
    names: list[str] = []
    texture = None
    for i, f in enumerate(args.files):
        name = labels[i] if labels is not None else Path(f).name
        if f.lower().endswith(".npz"):
            from ..texture import synthesize
            from ._texture_cmds import load_model

            texture = load_model(f)
            assert texture.feature_map is not None  # checked by load_model
            n = max(4, round(args.seconds * texture.feature_map.fps))
            motions.append(synthesize(jax.random.key(args.seed), texture, n_frames=n))
            names.append(f"{name}: synthesis (seed {args.seed})")
        else:
            motions.append(read_source(f))
            names.append(name)
    write_html(
        out,
        motions,
        labels=names,
        title=args.title,
        texture=texture,
        gallery=not args.no_gallery,
        fps=args.fps,
        contacts=not args.no_contacts,
    )
    size = out.stat().st_size
    print(
        f"wrote {out} ({size / 1e6:.2f} MB, {len(motions)} motion(s)"
        + (f", {texture.n_textons} textons" if texture is not None else "")
        + f", {time.perf_counter() - t0:.1f} s); open it in a web browser"
    )
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``view`` to the ``mtex`` sub-command parsers."""
    s = sub.add_parser(
        "view",
        help="write an HTML page with a 3-D player of motions or a texture model",
        description="Write one self-contained HTML page (no network, opens from disk) with a "
        "3-D stick-figure player: the motions side by side on a floor with foot contacts "
        "marked, orbit/zoom/pan, play/pause, frame slider and speed. For a texture model "
        "(.npz from 'mtex learn'): a short synthesis with its texton timeline and a gallery "
        "of the vocabulary, one small player per texton.",
    )
    s.add_argument(
        "files", nargs="+", metavar="FILE", help=f"{SOURCE_HELP}, or a texture model (.npz)"
    )
    s.add_argument("-o", "--output", required=True, help="output page (.html)")
    s.add_argument("--labels", default=None, help="comma-separated names, one per file")
    s.add_argument("--title", default=None, help="page title")
    s.add_argument("--fps", type=float_arg, default=30.0, help="player frame rate (default 30)")
    s.add_argument(
        "--seconds", type=float_arg, default=10.0, help="length of a texture's synthesis (10)"
    )
    s.add_argument("--seed", type=seed_arg, default=0, help="random seed of the synthesis")
    s.add_argument("--no-gallery", action="store_true", help="leave out the texton gallery")
    s.add_argument("--no-contacts", action="store_true", help="do not mark foot contacts")
    add_force(s)
    s.set_defaults(func=_cmd_view)
