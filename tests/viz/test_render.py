"""Stick-figure rendering: GIF animations and filmstrips, checked by reading the files back."""

import dataclasses
import sys
from pathlib import Path

import matplotlib  # noqa: F401  (a test dependency: fail loudly if it is missing)
import numpy as np
import pytest
from PIL import Image

import mtex_jax as mj
from mtex_jax.viz import render_filmstrip, render_gif
from mtex_jax.viz._panel import TO_PLOT

LEFT_RGB = (0x1F, 0x5F, 0xBF)
RIGHT_RGB = (0xD6, 0x27, 0x28)
TRAJ_RGB = (0x2C, 0xA0, 0x2C)  # first trajectory colour


@pytest.fixture(scope="module")
def dance() -> mj.Motion:
    return mj.load_example("dance_a")


def gif_frames(path: Path) -> tuple[list[np.ndarray], list[int], dict]:
    """All frames of a GIF as RGB arrays, their durations (ms), and the first frame's info."""
    frames, durations = [], []
    with Image.open(path) as im:
        assert im.format == "GIF"
        info = dict(im.info)
        for k in range(im.n_frames):
            im.seek(k)
            durations.append(int(im.info["duration"]))
            frames.append(np.asarray(im.convert("RGB")))
    return frames, durations, info


def colour_count(img: np.ndarray, rgb: tuple[int, int, int], tol: int = 40) -> int:
    return int((np.abs(img.astype(int) - np.asarray(rgb)).max(axis=-1) <= tol).sum())


def non_white(img: np.ndarray) -> np.ndarray:
    return (img[..., :3] < 235).any(axis=-1)


# ---------------------------------------------------------------------------------------------
# GIF
# ---------------------------------------------------------------------------------------------
def test_gif_frames_timing_and_content(dance, tmp_path):
    out = render_gif(dance, tmp_path / "dance.gif", title="dance_a")
    assert out == tmp_path / "dance.gif" and out.is_file()
    frames, durations, info = gif_frames(out)
    # 98 frames at 60 Hz played at 30 fps: every second frame, 0, 2, …, 96.
    assert len(frames) == 49
    assert info.get("loop") == 0
    assert frames[0].shape == (400, 400, 3)  # 5 in × 80 dpi
    # GIF durations are in 10 ms units: 30 and 40 ms alternate to average 1000/30 ms.
    assert set(durations) <= {30, 40}
    assert sum(durations) == 1630  # round(49 · 100 / 30) cs
    # Content: a left (blue) and a right (red) side, a real drawing, not a blank canvas.
    for img in (frames[0], frames[-1]):
        assert colour_count(img, LEFT_RGB) > 100
        assert colour_count(img, RIGHT_RGB) > 100
        assert 0.02 < non_white(img).mean() < 0.6
    # The figure moves: frames differ well beyond the frame counter in the corner.
    body = slice(60, 400)
    diff = np.abs(frames[0][body].astype(int) - frames[24][body].astype(int)).max(axis=-1)
    assert (diff > 60).sum() > 500
    changed = sum(
        not np.array_equal(frames[k][body], frames[k + 1][body]) for k in range(len(frames) - 1)
    )
    assert changed == len(frames) - 1


def _ink_box(mask: np.ndarray) -> tuple[int, int, int, int]:
    rows, cols = np.nonzero(mask)
    assert rows.size, "nothing drawn"
    return int(rows.min()), int(rows.max()), int(cols.min()), int(cols.max())


def test_gif_title_never_covers_the_frame_counter(dance, tmp_path):
    """The choreograph GIF's long title was drawn over the frame counter (issue 57). On a
    motion that stands still, what changes from frame to frame is the counter alone; what a
    title adds is the title alone: their boxes must not meet."""
    still = dance[np.zeros(8, dtype=np.int64)]
    title = "example:salsa/60_01:10 -> example:salsa/60_01:900"
    with_title, _, _ = gif_frames(render_gif(still, tmp_path / "t.gif", title=title))
    blank, _, _ = gif_frames(render_gif(still, tmp_path / "b.gif", title=" "))
    counter = np.abs(with_title[0].astype(int) - with_title[-1].astype(int)).max(axis=-1) > 60
    drawn = np.abs(with_title[0].astype(int) - blank[0].astype(int)).max(axis=-1) > 60
    r0, r1, c0, c1 = _ink_box(counter)
    t0, t1, u0, u1 = _ink_box(drawn)
    assert r1 < t0 or t1 < r0 or c1 < u0 or u1 < c0, ((r0, r1, c0, c1), (t0, t1, u0, u1))


def test_gif_keeps_the_clip_duration(dance, tmp_path):
    """150 frames at 30 fps play 5 s: the delays are 30 and 40 ms (GIF counts in 10 ms), not
    30 ms each (4.5 s, 10 % fast)."""
    clip = dance.resample(30.0)
    clip = clip[np.arange(150) % clip.n_frames]
    frames, durations, _ = gif_frames(render_gif(clip, tmp_path / "d.gif", size=(2, 2), dpi=40))
    assert len(frames) == 150
    assert sum(durations) == 5000


def test_gif_fps_and_frame_range(dance, tmp_path):
    out = render_gif(
        dance, tmp_path / "part.gif", fps=20, frame_range=(10, 70), size=(3, 2), dpi=50
    )
    frames, durations, _ = gif_frames(out)
    assert len(frames) == 20  # frames 10, 13, …, 67
    assert durations == [50] * 20
    assert frames[0].shape == (100, 150, 3)

    # The fastest rate GIF players honour: 20 ms a frame.
    out = render_gif(dance, tmp_path / "fast.gif", fps=50, size=(2, 2), dpi=40)
    frames, durations, _ = gif_frames(out)
    assert len(frames) == 81  # floor(97 · 50 / 60) + 1
    assert durations == [20] * 81


def test_gif_frame_rate_not_multiple_of_10ms(dance, tmp_path):
    out = render_gif(dance, tmp_path / "r.gif", fps=24, size=(2, 2), dpi=40)
    frames, durations, _ = gif_frames(out)
    assert len(frames) == 39  # floor(97 · 24 / 60) + 1
    assert set(durations) <= {40, 50}
    # Timing is right over the whole clip, to the 10 ms unit.
    assert abs(sum(durations) - 1000 * len(frames) / 24) <= 10


def test_gif_trajectories(dance, tmp_path):
    plain = gif_frames(render_gif(dance, tmp_path / "plain.gif", size=(3, 3), dpi=60))[0]
    traj = gif_frames(
        render_gif(
            dance,
            tmp_path / "traj.gif",
            trajectories=["right_elbow", 3],
            size=(3, 3),
            dpi=60,
        )
    )[0]
    assert len(plain) == len(traj)
    # No green trajectory colour without trajectories; with them, the path grows with time.
    assert colour_count(plain[-1][40:], TRAJ_RGB) == 0
    first, last = colour_count(traj[0][40:], TRAJ_RGB), colour_count(traj[-1][40:], TRAJ_RGB)
    assert last > 200
    assert last > 5 * max(first, 1)


def test_gif_without_end_sites_draws_less(dance, tmp_path):
    a = gif_frames(render_gif(dance[:10], tmp_path / "a.gif", size=(3, 3), dpi=60))[0][0]
    b = gif_frames(
        render_gif(dance[:10], tmp_path / "b.gif", end_sites=False, size=(3, 3), dpi=60)
    )[0][0]
    bone = lambda img: colour_count(img, LEFT_RGB) + colour_count(img, RIGHT_RGB)
    assert 0 < bone(b) < bone(a)


# ---------------------------------------------------------------------------------------------
# Filmstrip
# ---------------------------------------------------------------------------------------------
def panel_contents(img: np.ndarray, n: int, label_px: int) -> list[int]:
    """Number of bone-coloured pixels in each of ``n`` equal-width panels (labels excluded)."""
    w = img.shape[1]
    body = img[: img.shape[0] - label_px, :, :3]
    counts = []
    for k in range(n):
        part = body[:, k * w // n : (k + 1) * w // n]
        counts.append(colour_count(part, LEFT_RGB) + colour_count(part, RIGHT_RGB))
    return counts


def test_filmstrip_evenly_spaced_panels(dance, tmp_path):
    out = render_filmstrip(dance, tmp_path / "strip.png", n_frames=5, height=2.0, dpi=50)
    assert out == tmp_path / "strip.png"
    with Image.open(out) as im:
        assert im.format == "PNG"
        img = np.asarray(im.convert("RGB"))
    # Five square panels of 2 in plus a 0.3 in label strip: 500 × 115 pixels.
    assert img.shape[:2] == (115, 500)
    counts = panel_contents(img, 5, label_px=15)
    assert all(c > 50 for c in counts), counts
    # The labels strip holds text under every panel.
    labels = img[-15:]
    for k in range(5):
        assert non_white(labels[:, k * 100 : (k + 1) * 100]).sum() > 10


def test_filmstrip_explicit_frames_title_trajectories(dance, tmp_path):
    out = render_filmstrip(
        dance,
        tmp_path / "s.png",
        frames=[0, 50, 97],
        trajectories="left_ankle",
        title="key frames",
        height=2.0,
        dpi=80,
    )
    with Image.open(out) as im:
        img = np.asarray(im.convert("RGB"))
    assert img.shape[:2] == (216, 480)  # (2 + 0.3 + 0.4 title) in × 80 dpi; 3 panels
    assert non_white(img[:24]).sum() > 30  # title
    assert all(c > 50 for c in panel_contents(img, 3, label_px=24))
    # The left ankle's path up to each panel's frame: none at frame 0, then growing.
    green = [colour_count(img[:, k * 160 : (k + 1) * 160], TRAJ_RGB) for k in range(3)]
    assert green[0] == 0
    assert 0 < green[1] < green[2]


def test_filmstrip_short_clip_shows_all_frames(dance, tmp_path):
    out = render_filmstrip(dance[:3], tmp_path / "s.png", height=1.0, dpi=40)
    with Image.open(out) as im:
        assert im.size == (120, 52)  # 3 panels although n_frames defaults to 8


# ---------------------------------------------------------------------------------------------
# Orientation: the up axis is vertical, through a proper rotation
# ---------------------------------------------------------------------------------------------
def test_world_to_plot_maps_are_rotations_taking_up_to_vertical():
    for up, m in TO_PLOT.items():
        np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(m) == pytest.approx(1.0)
        np.testing.assert_allclose(m @ np.eye(3)[up], [0.0, 0.0, 1.0])


def rest_pose(up_axis: int) -> mj.Motion:
    """The DeepMimic figure at rest (arms down), its offsets rotated to have ``up_axis`` up."""
    sk = mj.load_example("walk").skeleton
    to_world = TO_PLOT[up_axis].T @ TO_PLOT[sk.up_axis]
    rot = lambda v: tuple(float(x) for x in to_world @ np.asarray(v))
    sk2 = dataclasses.replace(
        sk,
        offsets=tuple(rot(o) for o in sk.offsets),
        end_sites=tuple((p, rot(o)) for p, o in sk.end_sites),
        up_axis=up_axis,
    )
    q = np.zeros((1, sk.n_joints, 4))
    q[..., 0] = 1.0
    return mj.Motion(sk2, 30.0, np.asarray([rot((0.0, 0.9, 0.0))]), q)


def test_rest_pose_is_upright_whatever_the_up_axis(tmp_path):
    images = []
    for up in (0, 1, 2):
        out = render_filmstrip(rest_pose(up), tmp_path / f"up{up}.png", height=3.0, dpi=60)
        with Image.open(out) as im:
            images.append(np.asarray(im.convert("RGB")))
    # Same figure, same picture.
    for img in images[1:]:
        assert np.abs(img.astype(int) - images[0].astype(int)).max() <= 2
    # The figure (its bones) is much taller than wide, and stands above the ground.
    body = images[0][:180]
    ys, xs = np.nonzero(
        (np.abs(body.astype(int) - LEFT_RGB).max(-1) < 40)
        | (np.abs(body.astype(int) - RIGHT_RGB).max(-1) < 40)
        | (body.max(-1) < 90)
    )
    assert np.ptp(ys) > 1.8 * np.ptp(xs)
    assert np.ptp(ys) > 0.4 * body.shape[0]


# ---------------------------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------------------------
def test_not_a_motion(tmp_path):
    with pytest.raises(TypeError, match="Motion"):
        render_gif(np.zeros((10, 3)), tmp_path / "x.gif")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="Motion"):
        render_filmstrip("dance_a", tmp_path / "x.png")  # type: ignore[arg-type]


def test_empty_motion(dance, tmp_path):
    with pytest.raises(ValueError, match="no frames"):
        render_gif(dance[0:0], tmp_path / "x.gif")
    with pytest.raises(ValueError, match="no frames"):
        render_filmstrip(dance[0:0], tmp_path / "x.png")


def test_unknown_trajectory_joint_lists_valid_names(dance, tmp_path):
    with pytest.raises(ValueError, match=r"'left_foot'.*valid names:.*left_ankle"):
        render_gif(dance, tmp_path / "x.gif", trajectories=["left_foot"])
    with pytest.raises(ValueError, match="out of range"):
        render_filmstrip(dance, tmp_path / "x.png", trajectories=[99])
    with pytest.raises(ValueError, match="names or integer indices"):
        render_gif(dance, tmp_path / "x.gif", trajectories=[1.5])  # type: ignore[list-item]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"fps": 0}, "fps"),
        ({"fps": -5.0}, "fps"),
        ({"fps": float("nan")}, "fps"),
        ({"fps": True}, "fps"),
        ({"fps": 61}, "exceeds the motion's frame rate"),
        ({"fps": 55}, "above 50"),
        ({"frame_range": (5, 5)}, "frame_range"),
        ({"frame_range": (-1, 10)}, "frame_range"),
        ({"frame_range": (0, 99)}, "frame_range"),
        ({"frame_range": (0.5, 10)}, "frame_range"),
        ({"size": (0, 5)}, "size"),
        ({"dpi": 0}, "dpi"),
    ],
)
def test_bad_gif_arguments(dance, tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        render_gif(dance, tmp_path / "x.gif", **kwargs)
    assert not (tmp_path / "x.gif").exists()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n_frames": 0}, "n_frames"),
        ({"n_frames": 2.5}, "n_frames"),
        ({"frames": []}, "empty"),
        ({"frames": [0, 98]}, "98"),
        ({"frames": [-1]}, "-1"),
        ({"frames": [1.5]}, "1.5"),
        ({"frames": "0,1"}, "sequence"),
        ({"height": -1.0}, "height"),
    ],
)
def test_bad_filmstrip_arguments(dance, tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        render_filmstrip(dance, tmp_path / "x.png", **kwargs)


def test_output_folder_must_exist(dance, tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        render_gif(dance, tmp_path / "nope" / "x.gif")
    with pytest.raises(ValueError, match="does not exist"):
        render_filmstrip(dance, tmp_path / "nope" / "x.png")
    with pytest.raises(ValueError, match="directory"):
        render_gif(dance, tmp_path)


def test_non_finite_positions_name_the_first_bad_frame(dance, tmp_path):
    """A motion with a non-finite root position or rotation cannot be made (the error names
    the first bad frame), so the renderers never see one."""
    root = np.array(dance.root_positions, copy=True)
    root[7, 1] = np.nan
    root[40, 0] = np.inf
    with pytest.raises(ValueError, match="frame 7"):
        mj.Motion(dance.skeleton, dance.fps, root, dance.rotations)
    q = np.array(dance.rotations, copy=True)
    q[12, 4] = np.nan
    with pytest.raises(ValueError, match="frame 12"):
        mj.Motion(dance.skeleton, dance.fps, dance.root_positions, q)
    # the good frames before it render
    good = mj.Motion(dance.skeleton, dance.fps, root[:7], dance.rotations[:7])
    render_gif(good, tmp_path / "ok.gif", size=(2, 2), dpi=30)


def test_missing_matplotlib_gives_install_hint(dance, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # makes `import matplotlib` fail
    with pytest.raises(ImportError, match=r'pip install "mtex_jax\[plot\]"'):
        render_gif(dance, tmp_path / "x.gif")


# ---------------------------------------------------------------------------------------------
# Real mocap: a CMU clip (120 Hz, y up, metres, 43 joints, fingers)
# ---------------------------------------------------------------------------------------------
def test_cmu_clip(tmp_path, cmu_files):
    clip = mj.read_bvh(cmu_files[0])[:60]
    frames, durations, _ = gif_frames(
        render_gif(clip, tmp_path / "cmu.gif", trajectories=["lFoot", "rFoot"])
    )
    assert len(frames) == 15  # 60 frames at 120 Hz shown at 30 fps: every fourth
    assert sum(durations) == 500
    assert colour_count(frames[-1], LEFT_RGB) > 100 and colour_count(frames[-1], RIGHT_RGB) > 100
    out = render_filmstrip(clip, tmp_path / "cmu.png", n_frames=4, height=2.0, dpi=50)
    with Image.open(out) as im:
        img = np.asarray(im.convert("RGB"))
    assert img.shape[:2] == (115, 400)
    assert all(c > 50 for c in panel_contents(img, 4, label_px=15))
