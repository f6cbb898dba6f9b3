"""Real keypoint files and camera files in (design §12.1): round trips of every format made by
projecting shipped clips, the COCO-17 joint maps of both skeletons, and every refusal."""

from __future__ import annotations

import dataclasses
import json

import jax.numpy as jnp
import numpy as np
import pytest

import mtex_jax.io as mio
from mtex_jax import forward_kinematics
from mtex_jax.core import save_arrays_json
from mtex_jax.motion import ground_axes
from mtex_jax.tracking import (
    COCO17_NAMES,
    Camera,
    Keypoints,
    TrackingProblem,
    coco_joint_map,
    problem_from_keypoints,
    read_camera,
    read_keypoints,
    write_keypoints,
)

# written out by hand (not derived from the module's tables): COCO name -> joint
SALSA = {
    "nose": "head",
    "left_shoulder": "lShldr",
    "right_shoulder": "rShldr",
    "left_elbow": "lForeArm",
    "right_elbow": "rForeArm",
    "left_wrist": "lHand",
    "right_wrist": "rHand",
    "left_hip": "lThigh",
    "right_hip": "rThigh",
    "left_knee": "lShin",
    "right_knee": "rShin",
    "left_ankle": "lFoot",
    "right_ankle": "rFoot",
}
DEEPMIMIC = {
    "nose": "neck",
    "left_shoulder": "left_shoulder",
    "right_shoulder": "right_shoulder",
    "left_elbow": "left_elbow",
    "right_elbow": "right_elbow",
    "left_hip": "left_hip",
    "right_hip": "right_hip",
    "left_knee": "left_knee",
    "right_knee": "right_knee",
    "left_ankle": "left_ankle",
    "right_ankle": "right_ankle",
}
# rest-pose facing direction and left side: salsa (CMU) faces +z with its left at +x; the
# DeepMimic humanoid faces +x with its left at -z
LEFT = {"salsa": np.array([1.0, 0, 0]), "deepmimic": np.array([0, 0, -1.0])}


def _clip(kind: str):
    if kind == "salsa":
        return mio.load_salsa("60_01")[:12], SALSA
    return mio.load_example("walk")[:12], DEEPMIMIC


def _camera_for(motion) -> Camera:
    """A camera 4 m along the second horizontal axis from the clip's mean root, looking at it."""
    u, _, h1 = ground_axes(motion.skeleton.up_axis)
    target = np.asarray(motion.root_positions).mean(axis=0)
    eye = target.copy()
    eye[h1] += 4.0
    return Camera.look_at(eye, target, np.eye(3)[u], focal=900.0, center=(640.0, 360.0))


@pytest.fixture(scope="module", params=["salsa", "deepmimic"])
def scene(request):
    """``(kind, skeleton, expected map, camera, coco (T, 17, 3) of projected joints)``."""
    motion, expected = _clip(request.param)
    cam = _camera_for(motion)
    px = np.asarray(cam.project(forward_kinematics(motion)))  # (T, J, 2)
    T = px.shape[0]
    coco = np.zeros((T, 17, 3))
    rng = np.random.default_rng(0)
    for c, name in enumerate(COCO17_NAMES):
        if name in expected:
            coco[:, c, :2] = px[:, motion.skeleton.index(expected[name])]
            coco[:, c, 2] = rng.uniform(0.3, 1.0, T)
        else:  # eyes and ears: detected, but no joint lies there
            coco[:, c] = [123.0, 45.0, 0.9]
    coco[3, 0, 2] = 2.0  # COCO's visibility flag 2: clipped to 1
    coco[5, 7] = [np.nan, np.nan, 0.0]  # a missing left elbow, NaN declared missing
    return request.param, motion.skeleton, expected, cam, coco, px


def _check(kp: Keypoints, skeleton, expected, coco, px) -> None:
    names = [n for n in COCO17_NAMES if n in expected]
    assert kp.names == tuple(names)
    assert kp.joints == tuple(skeleton.index(expected[n]) for n in names)
    cols = [COCO17_NAMES.index(n) for n in names]
    conf = np.minimum(coco[:, cols, 2], 1.0)
    np.testing.assert_allclose(np.asarray(kp.confidence), conf, rtol=0, atol=1e-12)
    seen = conf > 0
    # the mapped positions are the projections of the right skeleton joints
    np.testing.assert_allclose(np.asarray(kp.pixels)[seen], px[:, list(kp.joints)][seen], atol=1e-9)
    assert np.all(np.asarray(kp.pixels)[~seen] == 0)  # missing pixels are set to 0, not NaN
    assert float(kp.confidence[3, 0]) == 1.0 and float(kp.confidence[5, 3]) == 0.0


def _coco_results(coco: np.ndarray) -> list[dict]:
    return [
        {"image_id": t, "category_id": 1, "keypoints": coco[t].ravel().tolist(), "score": 0.9}
        for t in range(len(coco))
    ]


def _dump(path, doc) -> str:
    path.write_text(json.dumps(doc))
    return str(path)


# --------------------------------------------------------------------------- round trips
def test_coco_results_json(scene, tmp_path):
    _, sk, expected, _, coco, px = scene
    kp = read_keypoints(_dump(tmp_path / "det.json", _coco_results(coco)), sk, fps=30)
    _check(kp, sk, expected, coco, px)
    assert kp.fps == 30.0 and kp.n_frames == len(coco)
    # written back by write_keypoints and read again: the same keypoints
    write_keypoints(tmp_path / "out.json", kp)
    again = read_keypoints(tmp_path / "out.json", sk)
    assert again.joints == kp.joints and again.names == kp.names and again.fps is None
    np.testing.assert_array_equal(np.asarray(again.pixels), np.asarray(kp.pixels))
    np.testing.assert_array_equal(np.asarray(again.confidence), np.asarray(kp.confidence))


def test_coco_npz(scene, tmp_path):
    _, sk, expected, _, coco, px = scene
    np.savez(tmp_path / "kp.npz", keypoints=coco, fps=np.float64(60.0))
    kp = read_keypoints(tmp_path / "kp.npz", sk)
    _check(kp, sk, expected, coco, px)
    assert kp.fps == 60.0


def test_own_joints_npz_and_mtex_json(scene, tmp_path):
    _, sk, _, _, coco, px = scene
    joints = ["lShin", "rHand", "head"] if "head" in sk.names else ["left_knee", "neck", "chest"]
    idx = [sk.index(j) for j in joints]
    vals = np.concatenate([px[:, idx], np.full((len(px), 3, 1), 0.8)], axis=-1)
    vals[2, 1] = [np.nan, np.nan, 0.0]
    np.savez(tmp_path / "own.npz", keypoints=vals, names=np.array(joints), fps=np.int64(25))
    kp = read_keypoints(tmp_path / "own.npz", sk)
    assert kp.joints == tuple(idx) and kp.names == tuple(joints) and kp.fps == 25.0
    assert float(kp.confidence[2, 1]) == 0.0
    np.testing.assert_allclose(np.asarray(kp.pixels)[3], px[3, idx], atol=1e-12)
    write_keypoints(tmp_path / "own.json", kp, format="mtex-keypoints")
    doc = json.loads((tmp_path / "own.json").read_text())
    assert doc["format"] == "mtex-keypoints" and doc["fps"] == 25.0 and doc["names"] == joints
    again = read_keypoints(tmp_path / "own.json", sk)
    assert again.joints == kp.joints and again.fps == 25.0
    np.testing.assert_array_equal(np.asarray(again.pixels), np.asarray(kp.pixels))
    # COCO names in an mtex-keypoints file are mapped on a known skeleton
    coco_kp = read_keypoints(_dump(tmp_path / "d.json", _coco_results(coco)), sk)
    write_keypoints(tmp_path / "named.json", coco_kp, format="mtex-keypoints")
    assert read_keypoints(tmp_path / "named.json", sk).joints == coco_kp.joints


# --------------------------------------------------------------------------- joint maps
@pytest.mark.parametrize("kind", ["salsa", "deepmimic"])
def test_coco_joint_map_names_the_right_joints(kind):
    motion, expected = _clip(kind)
    sk = motion.skeleton
    assert coco_joint_map(sk) == expected
    # an independent look at the skeleton: the rest pose (offsets summed down the tree)
    rest = np.zeros((sk.n_joints, 3))
    for j, p in enumerate(sk.parents):
        rest[j] = (rest[p] if p >= 0 else 0) + np.asarray(sk.offsets[j])
    pos = {c: rest[sk.index(j)] for c, j in expected.items()}
    up = np.eye(3)[sk.up_axis]
    for part in ("shoulder", "elbow", "hip", "knee", "ankle"):
        assert (pos[f"left_{part}"] - pos[f"right_{part}"]) @ LEFT[kind] > 0.05, part
    for side in ("left", "right"):
        # each limb hangs from the one above it in the tree, top to bottom
        for a, b in (("shoulder", "elbow"), ("elbow", "wrist"), ("hip", "knee"), ("knee", "ankle")):
            if f"{side}_{b}" in expected:
                parent = sk.parents[sk.index(expected[f"{side}_{b}"])]
                assert sk.names[parent] == expected[f"{side}_{a}"]
        # the head's joint is at the shoulders' height or above (DeepMimic's neck: 2 cm below)
        assert pos["nose"] @ up > pos[f"{side}_shoulder"] @ up - 0.05
        assert pos[f"{side}_shoulder"] @ up > pos[f"{side}_hip"] @ up
        assert pos[f"{side}_hip"] @ up > pos[f"{side}_knee"] @ up > pos[f"{side}_ankle"] @ up


def test_unknown_skeleton_needs_a_mapping(tmp_path):
    motion, _ = _clip("salsa")
    sk = motion.skeleton
    renamed = dataclasses.replace(sk, names=tuple(f"j{i}" for i in range(sk.n_joints)))
    with pytest.raises(ValueError, match=r"not a CMU salsa .* or DeepMimic .*its joints: j0, j1"):
        coco_joint_map(renamed)
    coco = np.zeros((4, 17, 3))
    coco[:, 5] = [10.0, 20.0, 0.7]
    path = _dump(tmp_path / "d.json", _coco_results(coco))
    with pytest.raises(ValueError, match=r"d\.json: coco_joint_map: not a .*its joints: j0"):
        read_keypoints(path, renamed)
    kp = read_keypoints(path, renamed, mapping={"left_shoulder": "j22"})
    assert kp.joints == (22,) and kp.names == ("left_shoulder",)
    np.testing.assert_allclose(np.asarray(kp.pixels)[:, 0], [[10.0, 20.0]] * 4)
    # a user's mapping replaces the default one (here: the eyes too, the nose to the neck)
    mine = {**coco_joint_map(sk), "nose": "neck", "left_eye": "leftEye"}
    kp = read_keypoints(path, sk, mapping=mine)
    assert kp.names[:2] == ("nose", "left_eye")
    assert kp.joints[:2] == (sk.index("neck"), sk.index("leftEye"))
    with pytest.raises(ValueError, match=r"mapping names \['wing'\], not joints"):
        read_keypoints(path, sk, mapping={"nose": "wing"})
    with pytest.raises(ValueError, match=r"mapping's keys \['snout'\] are not COCO-17"):
        read_keypoints(path, sk, mapping={"snout": "head"})
    with pytest.raises(ValueError, match="both name the joint 'head'"):
        read_keypoints(path, sk, mapping={"nose": "head", "left_eye": "head"})


# --------------------------------------------------------------------------- COCO details
def test_coco_picks_the_best_detection_and_orders_frames(tmp_path):
    sk = _clip("salsa")[0].skeleton

    def det(image_id, x, score, **kw):
        kp = np.zeros((17, 3))
        kp[5] = [x, 2 * x, 1.0]
        return {
            "image_id": image_id,
            "category_id": 1,
            "keypoints": kp.ravel().tolist(),
            "score": score,
            **kw,
        }

    dets = [
        det("frame_10", 10.0, 0.9),
        det("frame_2", 2.0, 0.5),
        det("frame_2", 3.0, 0.8),  # the better of image frame_2's two detections
        det("frame_2", 4.0, 0.7),
        det("frame_9", 9.0, 0.9, category_id=2),  # not a person: frame_9 has no detection
        {"image_id": "frame_3", "keypoints": [], "score": 0.0},  # no one found
    ]
    kp = read_keypoints(_dump(tmp_path / "d.json", dets), sk)
    j = kp.names.index("left_shoulder")
    # natural order: frame_2, frame_3, frame_9, frame_10
    np.testing.assert_allclose(np.asarray(kp.pixels)[:, j], [[3, 6], [0, 0], [0, 0], [10, 20]])
    np.testing.assert_allclose(np.asarray(kp.confidence)[:, j], [1, 0, 0, 1])
    assert not np.asarray(kp.confidence)[1:3].any()  # frames without detection: all missing
    with pytest.raises(ValueError, match="mix integers and strings"):
        read_keypoints(_dump(tmp_path / "m.json", [*dets, det(4, 1.0, 0.5)]), sk)


# --------------------------------------------------------------------------- refusals
@pytest.fixture(scope="module")
def salsa_sk():
    return _clip("salsa")[0].skeleton


def _one(kp17: np.ndarray) -> list[dict]:
    return [
        {"image_id": t, "category_id": 1, "keypoints": kp.ravel().tolist(), "score": 1.0}
        for t, kp in enumerate(kp17)
    ]


@pytest.mark.parametrize(
    ("where", "value", "match"),
    [
        (
            (2, 7),
            [np.nan, 10.0, 0.8],
            r"frame 2 \(image_id 2\), keypoint 'left_elbow': NaN/inf pixel",
        ),
        ((1, 9), [np.inf, 10.0, 1.0], r"frame 1\b.*keypoint 'left_wrist': NaN/inf pixel"),
        ((0, 5), [1.0, 2.0, np.nan], r"frame 0\b.*'left_shoulder': the score is not finite"),
        ((3, 6), [1.0, 2.0, -0.5], r"frame 3\b.*'right_shoulder': the score is negative"),
        ((1, 0), [1e12, 2.0, 0.5], r"frame 1\b.*'nose': a pixel beyond"),
    ],
)
def test_bad_values_name_frame_and_keypoint(tmp_path, salsa_sk, where, value, match):
    kp = np.ones((4, 17, 3))
    kp[where] = value
    path = tmp_path / "d.json"
    path.write_text(json.dumps(_one(kp)))  # json writes NaN and Infinity literals
    with pytest.raises(ValueError, match=match):
        read_keypoints(path, salsa_sk)
    np.savez(tmp_path / "d.npz", keypoints=kp)
    with pytest.raises(ValueError, match=match.replace(r" \(image_id 2\)", "")):
        read_keypoints(tmp_path / "d.npz", salsa_sk)


def test_a_missing_keypoint_may_hold_nan(tmp_path, salsa_sk):
    kp = np.ones((3, 17, 3))
    kp[1, 7] = [np.nan, np.nan, 0.0]
    doc = _one(kp)
    doc[2]["keypoints"][21:24] = [None, None, 0]  # null pixels, declared missing
    out = read_keypoints(_dump(tmp_path / "d.json", doc), salsa_sk)
    j = out.names.index("left_elbow")
    assert np.isfinite(np.asarray(out.pixels)).all()
    np.testing.assert_array_equal(np.asarray(out.confidence)[:, j], [1, 0, 0])


def test_files_of_another_kind_and_broken_files(tmp_path, salsa_sk):
    def refused(name, content, match):
        p = tmp_path / name
        p.write_bytes(content if isinstance(content, bytes) else content.encode())
        with pytest.raises(ValueError, match=match) as e:
            read_keypoints(p, salsa_sk)
        assert str(p) in str(e.value)  # the file is named

    refused("empty.json", "", "empty file")
    refused("blank.json", "  \n ", "empty file")
    refused("clip.bvh", "HIERARCHY\nROOT hip\n{\n OFFSET 0 0 0\n}\nMOTION\n", "BVH motion file")
    refused("clip.json", '{"Loop": "wrap", "Frames": [[0.1]]}', "DeepMimic motion file, not")
    refused("other.json", '{"foo": 1, "bar": [2]}', r"JSON with keys 'foo', 'bar', not a keypoint")
    refused("num.json", "3", "a JSON int, not a keypoint file")
    refused("broken.json", '[{"image_id": 1', "invalid JSON")
    refused("pic.png", b"\x89PNG\r\n\x1a\n\xff\xfe", "PNG picture, not a keypoint file")
    refused("bad.npz", b"PK\x03\x04garbage", "unreadable NumPy archive")
    refused("deep.json", "[" * 5000 + "]" * 5000, "nested 5000 levels")
    refused("count.json", json.dumps(_one(np.ones((2, 18, 3)))), r"detection 0 .*has 18 keypoints")
    big = '[{"image_id": 1, "keypoints": [' + "9" * 400 + ", 0, 1" + ", 0" * 48 + "]}]"
    refused("big.json", big, r":1: \[0\]\.keypoints\[0\]: a 400-digit integer is too large for")
    refused("huge.json", big.replace("9" * 400, "9" * 5000), ":1: .*5000-digit integer is too")
    text = json.dumps(_one(np.ones((1, 17, 3)))).replace("1.0", '"1.0"', 1)
    refused("str.json", text, "'1.0' is not a number")
    refused("bool.json", text.replace('"1.0"', "true", 1), "True is not a number")
    refused("nolist.json", "[]", "no detections")
    refused("noid.json", '[{"keypoints": []}]', "detection 0 is not an object with image_id")
    refused(
        "own.json",
        json.dumps(
            {
                "format": "mtex-keypoints",
                "names": ["lShin", "wing"],
                "frames": [[[1, 2, 1], [3, 4, 1]]],
            }
        ),
        r"unknown joint name 'wing'; its joints: hip",
    )
    refused(
        "rag.json",
        json.dumps(
            {"format": "mtex-keypoints", "names": ["lShin"], "frames": [[[1, 2, 1]], [[1, 2]]]}
        ),
        r"frame 1 has 1 keypoints",
    )
    refused(
        "fps.json",
        json.dumps(
            {"format": "mtex-keypoints", "names": ["lShin"], "fps": -3, "frames": [[[1, 2, 1]]]}
        ),
        "fps must be positive",
    )
    with pytest.raises(ValueError, match="is a directory"):
        read_keypoints(tmp_path, salsa_sk)


def test_npz_of_another_kind(tmp_path, salsa_sk):
    np.savez(tmp_path / "k18.npz", keypoints=np.ones((3, 18, 3)))
    with pytest.raises(ValueError, match="18 keypoints per frame; COCO-17 has 17"):
        read_keypoints(tmp_path / "k18.npz", salsa_sk)
    save_arrays_json(
        tmp_path / "model.npz",
        {"keypoints": np.ones((3, 17, 3))},
        {"kind": "mtex_jax.MotionTexture"},
    )
    with pytest.raises(ValueError, match=r"motion texture model .*not a keypoint file"):
        read_keypoints(tmp_path / "model.npz", salsa_sk)
    np.savez(tmp_path / "other.npz", poses=np.ones(3))
    with pytest.raises(ValueError, match="NumPy archive of poses, not a keypoint file"):
        read_keypoints(tmp_path / "other.npz", salsa_sk)
    np.savez(tmp_path / "obj.npz", keypoints=np.array([[[1, 2, None]]], dtype=object))
    with pytest.raises(ValueError, match=r"unreadable NumPy archive.*allow_pickle"):
        read_keypoints(tmp_path / "obj.npz", salsa_sk)
    np.savez(tmp_path / "shape.npz", keypoints=np.ones((3, 17)))
    with pytest.raises(ValueError, match=r"must be numbers \(T, K, 3\)"):
        read_keypoints(tmp_path / "shape.npz", salsa_sk)
    np.savez(tmp_path / "names.npz", keypoints=np.ones((3, 2, 3)), names=np.array(["lShin"]))
    with pytest.raises(ValueError, match="'names' must be 2 strings"):
        read_keypoints(tmp_path / "names.npz", salsa_sk)


# --------------------------------------------------------------------------- camera files
@pytest.mark.parametrize("up_axis", [1, 2])
@pytest.mark.parametrize(
    "fields",
    [{"focal": 800, "center": [320, 240]}, {"fx": 798, "fy": 802, "cx": 320, "cy": 240}],
)
def test_level_camera_without_extrinsics(tmp_path, up_axis, fields):
    cam, posed = read_camera(_dump(tmp_path / "cam.json", fields), up_axis)
    assert posed is False
    np.testing.assert_allclose(float(cam.focal), 800.0)
    u, h0, h1 = ground_axes(up_axis)
    e = np.eye(3)
    ahead = 3.0 * e[h1]  # straight ahead of a level camera at the origin
    np.testing.assert_allclose(np.asarray(cam.project(ahead)), [320, 240], atol=1e-9)
    higher = np.asarray(cam.project(ahead + 0.5 * e[u]))
    assert higher[1] < 240 and abs(higher[0] - 320) < 1e-9  # up in the world is up in the image
    np.testing.assert_allclose(higher[1], 240 - 800 * 0.5 / 3.0)
    right = np.asarray(cam.project(ahead + 0.5 * e[h0]))
    assert right[0] > 320 and abs(right[1] - 240) < 1e-9


def test_camera_with_extrinsics(tmp_path):
    ref = Camera.look_at([1.0, 1.5, 5.0], [0.0, 1.0, 0.0], [0, 1, 0], focal=1000.0)
    rot = np.round(np.asarray(ref.rotation), 6)  # the few digits of a file
    doc = {
        "focal": 1000.0,
        "center": [500, 500],
        "rotation": rot.tolist(),
        "translation": np.asarray(ref.translation).tolist(),
        "width": 1000,
        "height": 1000,
    }
    cam, posed = read_camera(_dump(tmp_path / "cam.json", doc))
    assert posed is True
    r = np.asarray(cam.rotation)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)  # made exactly orthonormal
    pts = jnp.asarray([[0.0, 1.0, 0.0], [0.3, 0.2, -0.4]])
    np.testing.assert_allclose(
        np.asarray(cam.project(pts)), np.asarray(ref.project(pts)), atol=1e-2
    )


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ({"focal": 0, "center": [1, 2]}, "focal length must be positive"),
        ({"focal": -5, "center": [1, 2]}, "focal length must be positive"),
        ({"focal": float("nan"), "center": [1, 2]}, "cam.json:1: focal: non-finite value NaN"),
        ({"focal": "800", "center": [1, 2]}, "focal' must be a number"),
        ({"fx": 1000, "fy": 1020, "center": [1, 2]}, "only square pixels are modelled"),
        ({"fx": 1000, "center": [1, 2]}, "fy"),
        ({"center": [1, 2]}, "give the focal length once"),
        ({"focal": 800, "fx": 800, "fy": 800, "center": [1, 2]}, "give the focal length once"),
        ({"focal": 800}, "give the principal point once"),
        ({"focal": 800, "cx": 3}, "center"),
        ({"focal": 800, "center": [1, 2, 3]}, r"'center' must be \(2,\) numbers"),
        (
            {"focal": 800, "center": [1, 2], "rotaton": [[1, 0, 0]]},
            r"unknown camera fields \['rotaton'\]",
        ),
        ({"focal": 800, "center": [1, 2], "rotation": np.eye(3).tolist()}, "given together"),
        (
            {
                "focal": 800,
                "center": [1, 2],
                "rotation": np.diag([1.0, 1, -1]).tolist(),
                "translation": [0, 0, 0],
            },
            "not a rotation matrix",
        ),
        (
            {
                "focal": 800,
                "center": [1, 2],
                "rotation": (2 * np.eye(3)).tolist(),
                "translation": [0, 0, 0],
            },
            "not a rotation matrix",
        ),
        (
            {
                "focal": 800,
                "center": [1, 2],
                "rotation": [[1, 0], [0, 1]],
                "translation": [0, 0, 0],
            },
            r"'rotation' must be \(3, 3\)",
        ),
        ([800, [1, 2]], "expected a JSON object"),
    ],
)
def test_camera_refusals(tmp_path, doc, match):
    path = _dump(tmp_path / "cam.json", doc)
    with pytest.raises(ValueError, match=match) as e:
        read_camera(path)
    assert "cam.json" in str(e.value)


def test_camera_file_broken(tmp_path):
    (tmp_path / "cam.json").write_text('{"focal": 800,')
    with pytest.raises(ValueError, match="invalid JSON"):
        read_camera(tmp_path / "cam.json")
    with pytest.raises(ValueError, match="up_axis must be 0, 1 or 2"):
        read_camera(tmp_path / "cam.json", up_axis=3)


# --------------------------------------------------------------------------- the problem
def test_problem_from_keypoints(scene, tmp_path):
    _, sk, _, cam, coco, _ = scene
    kp = read_keypoints(_dump(tmp_path / "d.json", _coco_results(coco)), sk)
    prob = problem_from_keypoints(kp, cam, pixel_noise=3.0)
    assert isinstance(prob, TrackingProblem)
    assert prob.frames == tuple(range(len(coco))) and prob.joints == kp.joints
    assert prob.init_window is None and prob.truth is None and not prob.has_init
    assert float(prob.pixel_noise) == 3.0
    np.testing.assert_array_equal(np.asarray(prob.observations), np.asarray(kp.pixels))
    np.testing.assert_array_equal(np.asarray(prob.confidence), np.asarray(kp.confidence))
    with pytest.raises(ValueError, match="pixel_noise must be > 0"):
        problem_from_keypoints(kp, cam, pixel_noise=0.0)
    with pytest.raises(TypeError, match="expected Keypoints and a Camera"):
        problem_from_keypoints(prob, cam)  # type: ignore[arg-type]


def test_keypoints_checks_and_writer_refusals(tmp_path):
    ok = {"joints": (0, 3), "pixels": np.zeros((2, 2, 2)), "confidence": np.ones((2, 2))}
    Keypoints(**ok, names=("a", "b"))
    with pytest.raises(ValueError, match="pixels"):
        Keypoints(**{**ok, "pixels": np.zeros((2, 3, 2))}, names=("a", "b"))
    with pytest.raises(ValueError, match="distinct joints"):
        Keypoints(**{**ok, "joints": (1, 1)}, names=("a", "b"))
    with pytest.raises(ValueError, match=r"confidence must be finite and in \[0, 1\]"):
        Keypoints(**{**ok, "confidence": np.full((2, 2), 1.5)}, names=("a", "b"))
    with pytest.raises(ValueError, match="fps"):
        Keypoints(**ok, names=("a", "b"), fps=-1.0)
    kp = Keypoints(**ok, names=("a", "b"))
    with pytest.raises(ValueError, match=r"\['a', 'b'\] are not COCO keypoints"):
        write_keypoints(tmp_path / "k.json", kp)
    with pytest.raises(ValueError, match="format must be"):
        write_keypoints(tmp_path / "k.json", kp, format="openpose")
    nan = Keypoints(**{**ok, "pixels": np.full((2, 2, 2), np.nan)}, names=("nose", "left_eye"))
    with pytest.raises(ValueError, match="positive confidence is not finite"):
        write_keypoints(tmp_path / "k.json", nan)
    assert not (tmp_path / "k.json").exists()


# --------------------------------------------------------------------------- hostile numbers
# issue 57: a ValueError naming the file and the line, never an OverflowError or a NaN passed on
def _with_token(path, doc, where, token: str) -> tuple[str, int]:
    """``doc`` written one value a line, the value at the path ``where`` as ``token``; the
    file and the token's 1-based line."""
    d = json.loads(json.dumps(doc))
    inner = d
    for k in where[:-1]:
        inner = inner[k]
    inner[where[-1]] = "@@"
    text = json.dumps(d, indent=1)
    line = text[: text.index('"@@"')].count("\n") + 1
    path.write_text(text.replace('"@@"', token))
    return str(path), line


_TOO_LARGE = [
    ("9" * 401, "a 401-digit integer is too large for a float"),
    ("-" + "9" * 5000, "a 5000-digit integer is too large for a float"),
    ("1e400", "the number '1e400' is too large for a float"),
]
_NOT_JSON = [("nan", "'nan' is not a JSON number"), ("-INF", "'-INF' is not a JSON number")]


@pytest.mark.parametrize(("token", "frag"), _TOO_LARGE + _NOT_JSON)
@pytest.mark.parametrize("score", [1.0, 0.0])  # a missing keypoint's pixel too
def test_keypoint_numbers_no_float_holds_name_the_line(tmp_path, salsa_sk, token, frag, score):
    kp = np.ones((3, 17, 3))
    kp[2, 5, 2] = score
    p, line = _with_token(tmp_path / "k.json", _one(kp), (2, "keypoints", 15), token)
    with pytest.raises(ValueError) as e:
        read_keypoints(p, salsa_sk)
    msg = str(e.value)
    assert msg.startswith(f"{p}:{line}: ") and frag in msg, msg
    if "JSON" not in frag:
        assert f"{p}:{line}: [2].keypoints[15]: " in msg, msg


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
def test_keypoint_nan_and_infinity_only_as_a_missing_pixel(tmp_path, salsa_sk, token):
    """NaN and Infinity may be a missing keypoint's pixel (score 0, the documented format);
    as a score, a detection score, the pixel of a seen keypoint, ``category_id`` or ``fps``
    they are refused with the line."""
    kp = np.ones((3, 17, 3))
    kp[2, 5, 2] = 0.0
    p, _ = _with_token(tmp_path / "ok.json", _one(kp), (2, "keypoints", 15), token)
    out = read_keypoints(p, salsa_sk)
    assert np.isfinite(np.asarray(out.pixels)).all()
    cases = [
        ((2, "keypoints", 16), np.ones((3, 17, 3)), "keypoint 'left_shoulder': NaN/inf pixel"),
        ((1, "keypoints", 17), np.ones((3, 17, 3)), "'left_shoulder': the score is not finite"),
        ((0, "score"), np.ones((3, 17, 3)), "detection 0 (image_id 0): the detection score"),
        ((1, "category_id"), np.ones((3, 17, 3)), "category_id is not finite"),
    ]
    for where, kp, frag in cases:
        p, line = _with_token(tmp_path / "bad.json", _one(kp), where, token)
        with pytest.raises(ValueError) as e:
            read_keypoints(p, salsa_sk)
        msg = str(e.value)
        assert msg.startswith(f"{p}:{line}: ") and frag in msg, (where, msg)
    own = {"format": "mtex-keypoints", "names": ["lShin"], "fps": 30, "frames": [[[1, 2, 1]]]}
    for where, frag in [(("fps",), "fps must be finite"), (("frames", 0, 0, 1), "NaN/inf pixel")]:
        p, line = _with_token(tmp_path / "own.json", own, where, token)
        with pytest.raises(ValueError) as e:
            read_keypoints(p, salsa_sk)
        msg = str(e.value)
        assert msg.startswith(f"{p}:{line}: ") and frag in msg, (where, msg)


def test_keypoint_denormals_and_negative_zero_are_numbers(tmp_path, salsa_sk):
    kp = np.ones((3, 17, 3))
    ref = read_keypoints(_dump(tmp_path / "ref.json", _one(kp)), salsa_sk)
    j = ref.names.index("left_shoulder")
    for token, value in [("4e-320", 4e-320), ("-0.0", -0.0)]:
        p, _ = _with_token(tmp_path / "k.json", _one(kp), (2, "keypoints", 15), token)
        x = np.asarray(read_keypoints(p, salsa_sk).pixels)[2, j, 0]
        assert x == value and np.signbit(x) == np.signbit(value), (token, x)
        p, _ = _with_token(tmp_path / "s.json", _one(kp), (2, "keypoints", 17), token)
        c = np.asarray(read_keypoints(p, salsa_sk).confidence)[2, j]  # a score of 4e-320
        assert c == abs(value), (token, c)


@pytest.mark.parametrize(
    ("token", "frag"),
    [*_TOO_LARGE, *_NOT_JSON, ("NaN", "non-finite value NaN"), ("-Infinity", "non-finite")],
)
@pytest.mark.parametrize(
    "where", [("focal",), ("center", 1), ("rotation", 2, 0), ("translation", 2)]
)
def test_camera_hostile_numbers_name_the_line(tmp_path, token, frag, where):
    doc = {"focal": 800, "center": [1, 2], "rotation": np.eye(3).tolist(), "translation": [0] * 3}
    p, line = _with_token(tmp_path / "cam.json", doc, where, token)
    with pytest.raises(ValueError) as e:
        read_camera(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}:{line}: ") and frag in msg, msg
    if "JSON" not in frag:
        path = where[0] + "".join(f"[{i}]" for i in where[1:])
        assert f"{p}:{line}: {path}: " in msg, msg


def test_camera_denormals_and_negative_zero_are_numbers(tmp_path):
    doc = {"focal": 800, "center": [1, 2], "rotation": np.eye(3).tolist(), "translation": [0] * 3}
    for token, value in [("4e-320", 4e-320), ("-0.0", -0.0)]:
        p, _ = _with_token(tmp_path / "cam.json", doc, ("translation", 2), token)
        cam, posed = read_camera(p)
        z = float(np.asarray(cam.translation)[2])
        assert posed and z == value and np.signbit(z) == np.signbit(value), (token, z)
