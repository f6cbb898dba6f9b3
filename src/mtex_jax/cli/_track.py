"""``mtex track MODEL --keypoints FILE``: 3-D motion from real 2-D keypoints with a texture's MAP
smoother (design §12).

The keypoint form of ``mtex track`` (the particle-filter comparison on a synthetic problem,
``mtex track CLIPS... --test CLIP``, is in :mod:`._implicit`, which owns the sub-command and
hands the keypoint form to :func:`run`). Every check of the inputs is done before the work;
bad input raises ``ValueError`` with a one-line message (the main CLI prints it, status 2).
"""

from __future__ import annotations

import argparse
import base64
import dataclasses
import html
import io
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..core import atomic_write
from ._validators import float_arg, int_arg, output, positive, positive_int

__all__ = ["KEYPOINT_OPTIONS", "add_arguments", "run"]

#: the options of the keypoint form (``dest`` names); none of them may be given without
#: ``--keypoints``
KEYPOINT_OPTIONS = (
    "keypoints",
    "camera",
    "focal",
    "center",
    "lag",
    "bones",
    "output",
    "json",
    "html",
    "overlay",
)
#: the level camera's focal length (pixels) when neither ``--camera`` nor ``--focal`` is given
DEFAULT_FOCAL = 1000.0
#: frames drawn in the keypoint overlay figure
OVERLAY_FRAMES = 4
#: a mean reprojection error above ``max(MISS_PIXELS, MISS_SIGMAS * --pixel-noise)`` pixels
#: is reported as an unreliable track
MISS_PIXELS, MISS_SIGMAS = 10.0, 5.0


def add_arguments(s: argparse.ArgumentParser) -> None:
    """Add the keypoint form's options to the ``track`` parser."""
    g = s.add_argument_group(
        "tracking real keypoints (mtex track MODEL --keypoints FILE -o out.bvh)"
    )
    g.add_argument(
        "--keypoints",
        default=None,
        metavar="FILE",
        help="2-D keypoints to track (COCO results JSON, .npz, or mtex-keypoints JSON); the "
        "positional argument is then one texture model (.npz from 'mtex learn')",
    )
    g.add_argument(
        "--camera",
        default=None,
        metavar="CAMERA.json",
        help="pin-hole camera: focal, center, optionally rotation and translation (world to "
        "camera); without a pose, or without --camera, the floor is estimated",
    )
    g.add_argument(
        "--focal",
        type=float_arg,
        default=None,
        metavar="F",
        help=f"without --camera: the focal length in pixels (default {DEFAULT_FOCAL:g})",
    )
    g.add_argument(
        "--center",
        default=None,
        metavar="CX,CY",
        help="without --camera: the principal point in pixels (default: the centre of the "
        "keypoints' extent)",
    )
    g.add_argument(
        "--lag",
        type=int_arg,
        default=None,
        metavar="L",
        help="fixed-lag smoothing: each frame final L frames later (default: the whole clip "
        "at once)",
    )
    g.add_argument(
        "--bones", action="store_true", help="estimate the person's bone lengths (the BVH's too)"
    )
    g.add_argument("-o", "--output", default=None, help="the tracked motion (.bvh)")
    g.add_argument(
        "--json",
        default=None,
        metavar="OUT.json",
        help="per frame: the texton and every joint's 3-D position",
    )
    g.add_argument(
        "--html",
        default=None,
        metavar="VIEW.html",
        help="a page with a 3-D player of the tracked motion (its texton timeline) and the "
        "keypoints beside the reprojected joints",
    )
    g.add_argument(
        "--overlay",
        default=None,
        metavar="PNG",
        help=f"a PNG of {OVERLAY_FRAMES} frames: the keypoints and the tracked joints reprojected",
    )


# --------------------------------------------------------------------------- checks
def _center(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    parts = text.split(",")
    try:
        vals = [float_arg(p.strip()) for p in parts]
    except argparse.ArgumentTypeError as e:
        raise ValueError(f"--center: {e}") from None
    if len(vals) != 2:
        raise ValueError(f"--center must be two numbers CX,CY (pixels), got {text!r}")
    return vals[0], vals[1]


def _check_args(args: argparse.Namespace) -> list[str]:
    """Check the options and every output before any work; returns the input files."""
    given = [o for o in ("test", "plot") if getattr(args, o, None) is not None]
    if given:
        raise ValueError(
            f"--{given[0]} belongs to the particle-filter form (mtex track CLIPS... --test "
            "CLIP), not to --keypoints"
        )
    if len(args.clips) != 1:
        raise ValueError(
            f"with --keypoints give one texture model (.npz from 'mtex learn'), got "
            f"{len(args.clips)} files: {' '.join(args.clips[:4])}"
        )
    if args.output is None:
        raise ValueError("-o/--output is required with --keypoints (the tracked motion, .bvh)")
    if args.camera is not None and (args.focal is not None or args.center is not None):
        what = "--focal" if args.focal is not None else "--center"
        raise ValueError(
            f"{what} is for the level camera without --camera; set it in {args.camera}"
        )
    if args.focal is not None:
        positive("focal", args.focal)
    if args.lag is not None:
        positive_int("lag", args.lag)
    positive("pixel-noise", args.pixel_noise)
    inputs = [args.clips[0], args.keypoints] + ([args.camera] if args.camera else [])
    outs: list[str] = []
    for path, kind, option in (
        (args.output, "bvh", "-o/--output"),
        (args.json, "json", "--json"),
        (args.html, "html", "--html"),
        (args.overlay, "png", "--overlay"),
    ):
        if path is None:
            continue
        if any(Path(path).resolve() == Path(o).resolve() for o in outs):
            raise ValueError(f"{option} {path} is named twice as an output")
        output(path, kind, (*inputs, *outs), args.force, option=option)
        outs.append(path)
    return inputs


# --------------------------------------------------------------------------- geometry
def _camera_arrays(cam: Any) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    return (
        np.asarray(cam.rotation, dtype=np.float64),
        np.asarray(cam.translation, dtype=np.float64),
        float(np.asarray(cam.focal)),
        np.asarray(cam.center, dtype=np.float64),
    )


def _project(cam: Any, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(pixels (..., 2), depths (...))`` of world points."""
    R, t, f, c = _camera_arrays(cam)
    xc = np.asarray(points, dtype=np.float64) @ R.T + t
    z = xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        px = f * xc[..., :2] / z[..., None] + c
    return px, z


def _rest_heights(skeleton: Any) -> np.ndarray:
    """Each joint's height in the rest pose (offsets summed from the root)."""
    pos = np.zeros((skeleton.n_joints, 3))
    off = np.asarray(skeleton.offsets, dtype=np.float64)
    for j, p in enumerate(skeleton.parents):  # parents come before their children
        pos[j] = off[j] + (pos[p] if p >= 0 else 0.0)
    return pos[:, skeleton.up_axis]


def _upside_down(kp: Any, cam: Any, skeleton: Any) -> tuple[int, int]:
    """``(frames upside down, frames judged)``: frames whose upper keypoints (the third highest
    in the rest pose) lie below the lower third in the image for ``cam``, as a person behind
    the camera is seen (the pin-hole image of a point behind it is turned by 180°).

    Moving a point in front of the camera up the world's up axis moves its pixel ``p`` along
    ``a_xy − a_z (p − c) / f`` with ``a = R e_up`` (the direction reverses behind the camera)."""
    h = _rest_heights(skeleton)[np.asarray(kp.joints)]
    K = len(h)
    if K < 2:
        return 0, 0
    order = np.argsort(h, kind="stable")
    n = max(1, K // 3)
    low, high = order[:n], order[-n:]
    if h[high].min() <= h[low].max():
        return 0, 0
    R, _, f, c = _camera_arrays(cam)
    a = R[:, skeleton.up_axis]
    px = np.asarray(kp.pixels, dtype=np.float64)
    seen = np.asarray(kp.confidence) > 0
    judged = inverted = 0
    for t in range(px.shape[0]):
        lo, hi = seen[t, low], seen[t, high]
        if not (lo.any() and hi.any()):
            continue
        p_lo, p_hi = px[t, low][lo].mean(axis=0), px[t, high][hi].mean(axis=0)
        g = a[:2] - a[2] * (0.5 * (p_lo + p_hi) - c) / f
        judged += 1
        inverted += int(np.dot(p_hi - p_lo, g) < 0)
    return inverted, judged


def _level_camera(skeleton: Any, focal: float, center: tuple[float, float]) -> Any:
    """The camera of :func:`~mtex_jax.tracking.read_camera` without a pose: level at the
    world origin, looking along the second horizontal axis."""
    from ..motion import ground_axes
    from ..tracking import Camera

    u, _, h1 = ground_axes(skeleton.up_axis)
    e = np.eye(3)
    return Camera.look_at(np.zeros(3), e[h1], e[u], focal=focal, center=center)


def _keypoint_center(kp: Any) -> tuple[float, float]:
    px = np.asarray(kp.pixels, dtype=np.float64)[np.asarray(kp.confidence) > 0]
    lo, hi = px.min(axis=0), px.max(axis=0)
    return float(0.5 * (lo[0] + hi[0])), float(0.5 * (lo[1] + hi[1]))


# --------------------------------------------------------------------------- labels
def _runs(labels: np.ndarray) -> np.ndarray:
    """``(n, 3)`` rows ``(start, length, texton)`` of a per-frame label sequence."""
    rows, start = [], 0
    for t in range(1, len(labels) + 1):
        if t == len(labels) or labels[t] != labels[start]:
            rows.append((start, t - start, int(labels[start])))
            start = t
    return np.asarray(rows, dtype=np.int64).reshape(-1, 3)


def _labels(texture: Any, result: Any, T: int) -> np.ndarray | None:
    """The texton of every frame: the smoother's, or (fixed-lag) the texture's segmentation of
    the tracked motion; ``None`` if the clip is too short to segment."""
    if result.labels is not None:
        return np.asarray(result.labels, dtype=np.int64)
    try:
        rows = np.asarray(texture.segment(result.motion).to_list(), dtype=np.int64)
    except ValueError:
        return None
    if rows.size == 0 or int(rows[:, 1].sum()) != T:
        return None
    return np.repeat(rows[:, 2], rows[:, 1])


# --------------------------------------------------------------------------- outputs
def _overlay_png(
    kp: Any,
    cam: Any,
    skeleton: Any,
    world: np.ndarray,
    labels: np.ndarray | None,
    title: str,
) -> bytes:
    """PNG bytes: :data:`OVERLAY_FRAMES` frames, the keypoints beside the tracked skeleton
    reprojected (every bone, and the tracked keypoint joints)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover - matplotlib is an optional dependency
        raise ImportError(
            "the keypoint overlay needs matplotlib (pip install mtex_jax[plot])"
        ) from e
    T = world.shape[0]
    frames = sorted({round(v) for v in np.linspace(0, T - 1, min(OVERLAY_FRAMES, T))})
    obs = np.asarray(kp.pixels, dtype=np.float64)
    seen = np.asarray(kp.confidence) > 0
    sk_px, _ = _project(cam, world)
    joints = list(kp.joints)
    fig, axes = plt.subplots(1, len(frames), figsize=(3.2 * len(frames), 3.6), dpi=100)
    axes = np.atleast_1d(axes)
    pts = np.concatenate([obs[seen], sk_px[np.isfinite(sk_px).all(-1)]])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.08 * float(max(hi - lo)) + 10.0
    for ax, t in zip(axes, frames, strict=True):
        for j, p in enumerate(skeleton.parents):
            if p >= 0:
                seg = sk_px[t, [p, j]]
                ax.plot(seg[:, 0], seg[:, 1], color="0.6", lw=1.2, zorder=1)
        mine, theirs = sk_px[t, joints], obs[t][seen[t]]
        kw: dict[str, Any] = {"marker": "x", "color": "tab:red", "s": 28, "zorder": 3}
        ax.scatter(mine[:, 0], mine[:, 1], label="tracked, reprojected", **kw)
        kw = {"facecolors": "none", "edgecolors": "tab:blue", "s": 36, "zorder": 2}
        ax.scatter(theirs[:, 0], theirs[:, 1], label="keypoints", **kw)
        lab = "" if labels is None else f", texton {int(labels[t])}"
        ax.set_title(f"frame {t}{lab}", fontsize=9)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(hi[1] + pad, lo[1] - pad)  # image rows grow downwards
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
    axes[0].legend(fontsize=7, loc="lower left")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png")
    finally:
        plt.close(fig)
    return buf.getvalue()


def _write_json(path: str, doc: dict[str, Any]) -> None:
    with atomic_write(path, "w", encoding="utf-8") as fh:
        json.dump(doc, fh, allow_nan=False, separators=(",", ":"))


def _embed_figure(page: Path, png: bytes, caption: str) -> None:
    """Put the overlay figure under the player of the page :func:`~mtex_jax.viz.write_html`
    wrote (inline, so the page stays one file)."""
    text = page.read_text(encoding="utf-8")
    src = base64.b64encode(png).decode("ascii")
    block = (
        '<section id="keypoint-overlay"><h2>keypoints and the tracked joints</h2>'
        f'<p class="hint">{html.escape(caption)}</p>'
        f'<img alt="2-D keypoints and the tracked joints reprojected" '
        f'style="max-width:100%" src="data:image/png;base64,{src}"></section>\n'
    )
    i = text.rfind("</body>")
    text = text[:i] + block + text[i:] if i >= 0 else text + block
    with atomic_write(page, "w", encoding="utf-8") as fh:
        fh.write(text)


def _scaled(motion: Any, bone_scale: np.ndarray) -> Any:
    """The motion on the person's bones (each joint's offset scaled)."""
    from ..tracking import scaled_skeleton

    m = dataclasses.replace(motion, skeleton=scaled_skeleton(motion.skeleton, bone_scale))
    if motion.local_positions is not None:
        lp = np.asarray(motion.local_positions) * bone_scale[None, :, None]
        m = dataclasses.replace(m, local_positions=lp)
    return m


# --------------------------------------------------------------------------- the command
def run(args: argparse.Namespace) -> int:
    """``mtex track MODEL --keypoints FILE ...`` (module notes)."""
    import jax

    from ..io import write_bvh
    from ..motion import forward_kinematics
    from ..tracking import problem_from_keypoints, read_camera, read_keypoints, track
    from ._texture_cmds import load_model

    t_all = time.perf_counter()
    _check_args(args)
    center = _center(args.center)
    model, kp_file = args.clips[0], args.keypoints
    texture = load_model(model)
    fm = texture.feature_map
    assert fm is not None  # checked by load_model
    sk = fm.skeleton
    fps = float(fm.fps)
    kp = read_keypoints(kp_file, sk, fps=args.fps)
    if not (np.asarray(kp.confidence) > 0).any():
        raise ValueError(f"{kp_file}: no keypoint has a positive score: nothing to track")
    if kp.fps is not None and not math.isclose(kp.fps, fps, rel_tol=1e-6):
        raise ValueError(
            f"{kp_file}: the keypoints are at {kp.fps:g} Hz but the texture model {model} is at "
            f"{fps:g} Hz; resample the keypoints to {fps:g} Hz (or learn the texture at "
            f"{kp.fps:g} Hz, 'mtex learn --fps {kp.fps:g}')"
        )
    if args.camera is not None:
        cam, extrinsics = read_camera(args.camera, up_axis=sk.up_axis)
        cam_text = f"{args.camera}" + ("" if extrinsics else " (no pose: a level camera)")
    else:
        extrinsics = False
        guessed = center is None
        center = _keypoint_center(kp) if center is None else center
        focal = DEFAULT_FOCAL if args.focal is None else args.focal
        cam = _level_camera(sk, focal, center)
        cam_text = (
            f"a level camera, focal {focal:g} px, principal point ({center[0]:.0f}, "
            f"{center[1]:.0f})" + (" (the keypoints' centre; --center CX,CY)" if guessed else "")
        )
    inverted, judged = _upside_down(kp, cam, sk)
    if judged and inverted > judged / 2:
        where = args.camera if extrinsics else kp_file
        why = (
            "the subject is behind the camera (are 'rotation' and 'translation' world to camera?)"
            if extrinsics
            else "the image is upside down for a level camera (give --camera with its pose)"
        )
        raise ValueError(
            f"{where}: the keypoints show the person upside down in {inverted} of {judged} "
            f"frames: {why}"
        )
    problem = problem_from_keypoints(kp, cam, pixel_noise=args.pixel_noise)
    floor = "known" if extrinsics else "estimate"
    T, K = problem.n_frames, len(problem.joints)
    seen = np.asarray(kp.confidence) > 0
    n_tx = texture.n_textons
    print(
        f"tracking {T} frames ({T / fps:.1f} s at {fps:g} Hz"
        + (", the model's rate: the file gives none, see --fps" if kp.fps is None else "")
        + f") of {kp_file}: {K} keypoints on "
        f"joints of {model} ({n_tx} texton{'' if n_tx == 1 else 's'}); camera: {cam_text}; "
        + ("batch" if args.lag is None else f"fixed-lag {args.lag}")
        + (", bones estimated" if args.bones else "")
        + ("" if extrinsics else ", floor estimated")
    )
    t0 = time.perf_counter()
    result = track(jax.random.key(0), texture, problem, lag=args.lag, bones=args.bones, floor=floor)
    t_track = time.perf_counter() - t0
    est = np.asarray(result.mean_joints, dtype=np.float64)
    if not np.isfinite(est).all() or result.motion is None:
        raise ValueError(f"{kp_file}: tracking failed (non-finite joint positions)")
    px, depth = _project(cam, est)
    if not (depth > 0).all():
        t_bad = int(np.argwhere(~(depth > 0))[0][0])
        raise ValueError(
            f"{args.camera or 'the camera'}: the tracked joints are behind the camera (depth "
            f"{float(depth.min()):.3g} at frame {t_bad}): the subject is behind it; check the "
            "camera's pose"
        )
    motion = result.motion.numpy()
    bone_scale = None if result.bone_scale is None else np.asarray(result.bone_scale)
    if bone_scale is not None:
        motion = _scaled(motion, bone_scale)
    world = np.asarray(forward_kinematics(motion), dtype=np.float64)
    if not np.isfinite(world).all():
        raise ValueError(f"{kp_file}: tracking failed (non-finite joint positions)")
    err = np.linalg.norm(px - np.asarray(kp.pixels, dtype=np.float64), axis=-1)
    err = np.where(seen, err, np.nan)
    labels = _labels(texture, result, T)

    write_bvh(args.output, motion)
    print(f"wrote {args.output}: {motion.n_frames} frames at {motion.fps:g} Hz")
    if args.json is not None:
        doc = _document(args, texture, kp, cam, extrinsics, world, labels, err, bone_scale)
        _write_json(args.json, doc)
        print(f"wrote {args.json}")
    png = None
    if args.overlay is not None or args.html is not None:
        title = f"{Path(kp_file).name}: keypoints and the tracked joints reprojected"
        try:
            png = _overlay_png(kp, cam, sk, world, labels, title)
        except ImportError:
            if args.overlay is not None:
                raise
            print("note: no keypoint figure on the page (matplotlib is not installed)")
    if args.overlay is not None and png is not None:
        with atomic_write(args.overlay, "wb") as fh:
            fh.write(png)
        print(f"wrote {args.overlay}")
    if args.html is not None:
        from ..viz import write_html

        timeline = None if labels is None else _runs(labels)
        page = write_html(
            args.html,
            motion,
            labels=[f"tracked: {Path(kp_file).name}"],
            title=f"mtex track: {Path(kp_file).name}",
            timelines=[timeline],
            texture=texture if labels is not None else None,
            gallery=False,
        )
        if png is not None:
            note = "circles: the keypoints; crosses and grey bones: the tracked skeleton, seen"
            _embed_figure(page, png, note + " by the camera")
        print(f"wrote {args.html}; open it in a web browser")
    low = np.asarray(forward_kinematics(motion, end_sites=True))[..., sk.up_axis].min(axis=1)
    _summary(kp, texture, err, labels, low, bone_scale, extrinsics, sk, t_track, t_all)
    e = err[np.isfinite(err)]
    bound = max(MISS_PIXELS, MISS_SIGMAS * args.pixel_noise)
    if e.size and e.mean() > bound:
        print(
            f"warning: the tracked joints miss the keypoints by {e.mean():.0f} px on average "
            f"(more than {bound:g} px): the track is unreliable (check the camera; try without "
            "--lag or --bones)"
        )
    return 0


def _document(
    args: argparse.Namespace,
    texture: Any,
    kp: Any,
    cam: Any,
    extrinsics: bool,
    world: np.ndarray,
    labels: np.ndarray | None,
    err: np.ndarray,
    bone_scale: np.ndarray | None,
) -> dict[str, Any]:
    """The ``--json`` document: per frame the texton and every joint's 3-D position."""
    fm = texture.feature_map
    sk = fm.skeleton
    R, t, f, c = _camera_arrays(cam)
    rnd = lambda a: np.round(np.asarray(a, dtype=np.float64), 6).tolist()
    frames = []
    for i in range(world.shape[0]):
        e = err[i][np.isfinite(err[i])]
        frames.append(
            {
                "frame": i,
                "texton": None if labels is None else int(labels[i]),
                "reprojection_px": round(float(e.mean()), 3) if e.size else None,
                "joints": rnd(world[i]),
            }
        )
    return {
        "format": "mtex-track",
        "model": str(args.clips[0]),
        "keypoints": str(args.keypoints),
        "fps": float(fm.fps),
        "up_axis": "xyz"[sk.up_axis],
        "joints": list(sk.names),
        "observed": [sk.names[j] for j in kp.joints],
        "camera": {
            "focal": f,
            "center": rnd(c),
            "rotation": rnd(R),
            "translation": rnd(t),
            "pose_given": bool(extrinsics),
        },
        "floor": "known" if extrinsics else "estimated",
        "bone_scale": None if bone_scale is None else rnd(bone_scale),
        "frames": frames,
    }


def _summary(
    kp: Any,
    texture: Any,
    err: np.ndarray,
    labels: np.ndarray | None,
    world_low: np.ndarray,
    bone_scale: np.ndarray | None,
    extrinsics: bool,
    sk: Any,
    t_track: float,
    t_all: float,
) -> None:
    seen = np.asarray(kp.confidence) > 0
    T, K = seen.shape
    names = [sk.names[j] for j in kp.joints]
    any_seen = np.asarray(seen.any(axis=0)).reshape(-1)
    never = [n for k, n in enumerate(names) if not any_seen[k]]
    e = err[np.isfinite(err)]
    per_frame = np.array([np.nanmean(r) if np.isfinite(r).any() else np.nan for r in err])
    worst = int(np.nanargmax(per_frame)) if np.isfinite(per_frame).any() else None
    print(f"frames: {T}")
    print(
        f"joints seen: {K - len(never)} of {K} ({100 * seen.mean():.0f}% of the keypoints "
        "observed)" + (f"; never seen: {', '.join(never)}" if never else "")
    )
    if e.size:
        print(
            f"mean reprojection error: {e.mean():.2f} px (median {np.median(e):.2f}, worst "
            f"frame {worst}: {per_frame[worst]:.2f} px)"
        )
    if labels is None:
        print("textons used: none (the clip is shorter than the texture's shortest segment)")
    else:
        rows = _runs(labels)
        used = {}
        for _, n, lab in rows.tolist():
            used[lab] = used.get(lab, 0) + n
        listed = ", ".join(f"{lab} ({n} frames)" for lab, n in used.items())
        print(f"textons used: {listed}; {len(rows)} segment(s)")
    if bone_scale is not None:
        print(f"bone scales: {float(np.min(bone_scale)):.3f} to {float(np.max(bone_scale)):.3f}")
    if not extrinsics:  # the camera is the world's origin: its height is minus the floor's
        floor = float(np.median(world_low))
        print(f"the camera is about {-floor:.2f} above the floor (estimated)")
    print(f"time: {t_track:.1f} s tracking, {time.perf_counter() - t_all:.1f} s in all")
