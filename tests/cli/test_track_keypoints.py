"""``mtex track MODEL --keypoints FILE``: real keypoints to a BVH, end to end.

A small texture is learned from two shipped salsa clips at 30 Hz (the shared
``salsa_tracking_texture`` of four clips tracks these keypoints 80 mm off); the keypoints are
the COCO joints of a held-out clip (``60_12``) projected through a camera 4 m away. With that
camera's file the tracked joints are within 60 mm of the truth; without a camera the command
still gives a finite motion; every bad input is one line and status 2 before any tracking."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import mtex_jax as mj
from mtex_jax.cli import main
from mtex_jax.motion import ground_axes
from mtex_jax.tracking import Camera, Keypoints, coco_joint_map, write_keypoints

FPS = 30.0
FRAMES = 60
FOCAL, CENTER = 1000.0, (640.0, 360.0)


def _camera(motion: mj.Motion, behind: bool = False) -> Camera:
    """4 m along the second horizontal axis from the clip's mean root, looking at it (or, with
    ``behind``, away from it: the subject is then behind the camera)."""
    u, _, h1 = ground_axes(motion.skeleton.up_axis)
    target = np.asarray(motion.root_positions).mean(axis=0)
    eye = target.copy()
    eye[h1] += 4.0
    look = 2 * eye - target if behind else target
    return Camera.look_at(eye, look, np.eye(3)[u], focal=FOCAL, center=CENTER)


def _camera_json(path, cam: Camera, **extra) -> str:
    doc = {"focal": float(cam.focal), "center": np.asarray(cam.center).tolist()}
    doc |= {"rotation": np.asarray(cam.rotation).tolist()}
    doc |= {"translation": np.asarray(cam.translation).tolist()} | extra
    path.write_text(json.dumps(doc))
    return str(path)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """``(folder, model file, keypoint file, camera file, truth (T, J, 3), coco joints)``."""
    import jax

    jax.config.update("jax_enable_x64", True)  # as the command line runs
    d = tmp_path_factory.mktemp("track_keypoints")
    clips = [mj.io.load_salsa(n).resample(FPS) for n in ("60_01", "60_02")]
    texture = mj.learn(clips, mj.LearnConfig(fps=FPS))
    assert texture.feature_map is not None and texture.feature_map.fps == FPS
    model = d / "texture.npz"
    texture.save(model)
    clip = mj.io.load_salsa("60_12").resample(FPS)[:FRAMES]
    sk = clip.skeleton
    truth = np.asarray(mj.forward_kinematics(clip), dtype=np.float64)
    table = coco_joint_map(sk)
    names = list(table)
    joints = [sk.names.index(table[n]) for n in names]
    cam = _camera(clip)
    px = np.asarray(cam.project(truth[:, joints]))
    kp = Keypoints(joints=joints, pixels=px, confidence=np.ones(px.shape[:2]), names=names)
    write_keypoints(d / "kp.json", kp)  # COCO results: no frame rate (the model's is taken)
    return d, str(model), str(d / "kp.json"), _camera_json(d / "cam.json", cam), truth, joints


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("mtex: error: "), err
    assert "Traceback" not in err
    return err


def test_track_keypoints_with_a_camera(scene, capsys):
    d, model, kp, cam, truth, joints = scene
    bvh, js, page, png = (d / n for n in ("out.bvh", "out.json", "view.html", "ov.png"))
    argv = ["track", model, "--keypoints", kp, "--camera", cam, "-o", str(bvh)]
    rc = main([*argv, "--json", str(js), "--html", str(page), "--overlay", str(png)])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert f"frames: {FRAMES}" in out and "joints seen: 13 of 13" in out
    reproj = float(out.split("mean reprojection error: ")[1].split(" px")[0])
    assert reproj < 10.0
    assert "textons used: " in out

    motion = mj.read_bvh(bvh)
    assert motion.n_frames == FRAMES and motion.fps == FPS
    world = np.asarray(mj.forward_kinematics(motion), dtype=np.float64)
    error = np.linalg.norm(world[:, joints] - truth[:, joints], axis=-1).mean()
    assert error < 0.060, f"tracked joints {1000 * error:.0f} mm from the truth"

    doc = json.loads(js.read_text())
    assert doc["fps"] == FPS and doc["joints"] == list(motion.skeleton.names)
    assert len(doc["frames"]) == FRAMES
    n_textons = mj.load_texture(model).n_textons
    for t, fr in enumerate(doc["frames"]):
        assert fr["frame"] == t and 0 <= fr["texton"] < n_textons
        assert np.abs(np.asarray(fr["joints"]) - world[t]).max() < 1e-4  # the BVH's joints
    text = page.read_text()
    assert 'id="mtex-data"' in text and 'id="keypoint-overlay"' in text
    assert png.read_bytes().startswith(b"\x89PNG")


def test_track_keypoints_without_a_camera(scene, capsys):
    d, model, kp, _, _, _ = scene
    bvh = d / "level.bvh"
    assert main(["track", model, "--keypoints", kp, "-o", str(bvh)]) == 0
    out = capsys.readouterr().out
    assert "a level camera, focal 1000 px" in out and "floor estimated" in out
    motion = mj.read_bvh(bvh)
    assert motion.n_frames == FRAMES
    assert np.isfinite(np.asarray(mj.forward_kinematics(motion))).all()


def _coco(path, frames: list[list[float]]) -> str:
    dets = [{"image_id": t, "category_id": 1, "keypoints": k} for t, k in enumerate(frames)]
    path.write_text(json.dumps(dets))  # NaN is written as NaN (Python's JSON)
    return str(path)


def test_track_keypoints_refuses_bad_input(scene, capsys):
    d, model, kp, _, truth, joints = scene
    clip = mj.io.load_salsa("60_12").resample(FPS)[:FRAMES]
    mj.write_bvh(d / "clip.bvh", clip)
    good = json.loads((d / "kp.json").read_text())
    nan = [list(det["keypoints"]) for det in good]
    nan[7][3 * 5] = math.nan  # left shoulder x, score 1
    names = list(coco_joint_map(clip.skeleton))
    px = np.asarray(_camera(clip).project(truth[:, joints]))
    fast = Keypoints(joints, px, np.ones(px.shape[:2]), names, fps=60.0)
    write_keypoints(d / "kp60.json", fast, format="mtex-keypoints")
    behind = _camera(clip, behind=True)  # the keypoints a camera facing away would "see"
    upside = Keypoints(
        joints, np.asarray(behind.project(truth[:, joints])), np.ones(px.shape[:2]), names
    )
    write_keypoints(d / "behind_kp.json", upside)
    out = str(d / "bad.bvh")
    base = ["track", model, "-o", out]
    cases = [
        ([*base, "--keypoints", str(d / "clip.bvh")], "a BVH motion file, not a keypoint file"),
        (
            [*base, "--keypoints", _coco(d / "k16.json", [[0.0] * 48] * 3)],
            "has 16 keypoints (48 values); COCO-17 has 17",
        ),
        (
            [*base, "--keypoints", _coco(d / "none.json", [[0.0] * 51] * 3)],
            "no keypoint has a positive score",
        ),
        ([*base, "--keypoints", kp, "--focal", "0"], "--focal must be a positive number"),
        (
            [*base, "--keypoints", kp, "--camera", _camera_json(d / "f0.json", behind, focal=0)],
            "the focal length must be positive",
        ),
        (
            [
                *base,
                "--keypoints",
                str(d / "behind_kp.json"),
                "--camera",
                _camera_json(d / "behind.json", behind),
            ],
            "upside down in 60 of 60 frames: the subject is behind the camera",
        ),
        (
            [*base, "--keypoints", _coco(d / "nan.json", nan)],
            "frame 7 (image_id 7), keypoint 'left_shoulder': NaN/inf pixel with a positive score",
        ),
        (
            [*base, "--keypoints", str(d / "kp60.json")],
            f"the keypoints are at 60 Hz but the texture model {model} is at 30 Hz",
        ),
        (["track", kp, "--keypoints", kp, "-o", out], "not a model file"),
        (["track", model, model, "--keypoints", kp, "-o", out], "give one texture model"),
        ([*base, "--keypoints", kp, "--particles", "5"], "--particles belongs to the particle"),
        (["track", model, "--keypoints", kp], "-o/--output is required with --keypoints"),
        ([*base[:2], "-o", out, "--test", "example:walk"], "-o/--output belongs to the keypoint"),
        (["track", "example:walk"], "give --test CLIP"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = _one_line_error(capsys)
        assert message in err, (argv, err)
    assert not (d / "bad.bvh").exists()
