"""The case tables of the hostile-input suite (``tests/test_hostile.py``, issue 43).

Each table is a list of :class:`Case`: an id, what to build or call, and the expected
outcome (an exception type and a regular expression its message must match, or ``None`` for
a correct result). ``default=True`` marks the representative cases of the default run; the
others run with ``-m slow``.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
from typing import Any

import numpy as np


@dataclasses.dataclass(frozen=True)
class Case:
    """One hostile input and what must come of it."""

    id: str
    make: Any  # what the family's test builds or calls (see each table)
    error: Any  # an exception type (or a tuple of them), or None: a correct result
    match: str = ""  # regular expression the message must match
    default: bool = False  # part of the default (fast) run


def params(cases: list[Case]) -> list[Any]:
    """``pytest.param`` of every case: the default ones as they are, the others ``slow``."""
    import pytest

    return [pytest.param(c, id=c.id, marks=() if c.default else pytest.mark.slow) for c in cases]


# --------------------------------------------------------------------------------------------
# 1. file kinds: every reader on every kind of file that is not what it expects
# --------------------------------------------------------------------------------------------
#: readers by name: (function path in mtex_jax, file suffix)
READERS = {
    "read_motion": ("io.read_motion", ".bvh"),
    "read_bvh": ("io.read_bvh", ".bvh"),
    "read_deepmimic": ("io.read_deepmimic", ".txt"),
    "load_texture": ("texture.load_texture", ".npz"),
    "load_contacts": ("edit.load_contacts", ".npz"),
    "load_feature_map": ("motion.load_feature_map", ".npz"),
}
_NOT_REGULAR = r"not a regular file"
#: hostile file kinds: name -> (expected message, regular expression)
FILE_KINDS = {
    "missing": r"no such file|does not exist",
    "directory": r"directory",
    "dev_null": _NOT_REGULAR,
    "dev_zero": _NOT_REGULAR,
    "dev_urandom": _NOT_REGULAR,
    "fifo": _NOT_REGULAR,
    "symlink_to_dev_zero": _NOT_REGULAR,
    "empty": r".",
    "text": r".",
    "binary": r".",
    "sparse_3gb": r"MAX_INPUT_BYTES|not a model file|not an \.npz|unknown motion format",
    "truncated_zip": r".",
}
_DEFAULT_FILE_CASES = {
    ("read_motion", "dev_zero"),
    ("read_motion", "fifo"),
    ("read_bvh", "sparse_3gb"),
    ("read_deepmimic", "dev_urandom"),
    ("load_texture", "fifo"),
    ("load_texture", "truncated_zip"),
    ("load_contacts", "directory"),
    ("load_feature_map", "missing"),
}
FILE_CASES = [
    Case(f"{r}-{k}", (r, k), ValueError, m, (r, k) in _DEFAULT_FILE_CASES)
    for r in READERS
    for k, m in FILE_KINDS.items()
]


# --------------------------------------------------------------------------------------------
# 2. sizes: configuration fields and generator arguments beyond the limits
# --------------------------------------------------------------------------------------------
_INF, _NAN = math.inf, math.nan
_LIMIT = r"exceeds the limit \w+ = [\d,]+ \(raise it with mtex_jax.core.set_limit"
#: LearnConfig(**kw): kw, error type, regular expression
_CONFIG = [
    ({"tmax": 10**9}, ValueError, r"LearnConfig.tmax = 1,000,000,000 " + _LIMIT, True),
    ({"tmax": 10**5}, ValueError, r"LearnConfig.tmax .*MAX_SEGMENT_FRAMES", False),
    ({"tmin": 10**7, "tmax": None}, ValueError, r"LearnConfig.tmin .*MAX_SEGMENT_FRAMES", False),
    ({"tmin": 2}, ValueError, r"LearnConfig.tmin", False),
    ({"tmin": -1}, ValueError, r"LearnConfig.tmin", False),
    ({"tmin": 3.5}, ValueError, r"LearnConfig.tmin", False),
    ({"n_textons": 10**6}, ValueError, r"LearnConfig.n_textons .*MAX_TEXTONS", True),
    ({"n_textons": 0}, ValueError, r"LearnConfig.n_textons", False),
    ({"n_textons": -3}, ValueError, r"LearnConfig.n_textons", False),
    ({"min_segments": 10**6}, ValueError, r"LearnConfig.min_segments .*MAX_MIN_SEGMENTS", True),
    ({"min_segments": 0}, ValueError, r"LearnConfig.min_segments", False),
    ({"state_dim": 10**6}, ValueError, r"LearnConfig.state_dim .*MAX_STATE_DIM", False),
    ({"state_dim": 0}, ValueError, r"LearnConfig.state_dim", False),
    ({"max_iter": 10**9}, ValueError, r"LearnConfig.max_iter .*MAX_ITERATIONS", False),
    ({"max_iter": -1}, ValueError, r"LearnConfig.max_iter", False),
    ({"chunk_frames": 10**9}, ValueError, r"LearnConfig.chunk_frames .*MAX_SEGMENT_FRAMES", False),
    ({"threshold": _INF}, ValueError, r"LearnConfig.threshold must be finite", True),
    ({"threshold": _NAN}, ValueError, r"LearnConfig.threshold", False),
    ({"threshold": -1.0}, ValueError, r"LearnConfig.threshold", False),
    ({"threshold": 0.0}, ValueError, r"LearnConfig.threshold", False),
    (
        {"bic_thresholds": (_NAN,)},
        ValueError,
        r"LearnConfig.bic_thresholds\[0\] must be finite",
        True,
    ),
    ({"bic_thresholds": (0.1, _INF)}, ValueError, r"LearnConfig.bic_thresholds\[1\]", False),
    ({"bic_thresholds": ()}, ValueError, r"LearnConfig.bic_thresholds", False),
    ({"bic_thresholds": (-0.1,)}, ValueError, r"LearnConfig.bic_thresholds\[0\]", False),
    ({"bic_thresholds": (0.1,) * 5000}, ValueError, r"LearnConfig.bic_thresholds", False),
    ({"bic_thresholds": ("a",)}, TypeError, r"LearnConfig.bic_thresholds\[0\]", False),
    ({"pseudo_count": _INF}, ValueError, r"LearnConfig.pseudo_count must be finite", True),
    ({"pseudo_count": _NAN}, ValueError, r"LearnConfig.pseudo_count", False),
    ({"pseudo_count": 0.0}, ValueError, r"LearnConfig.pseudo_count", False),
    ({"fps": _INF}, ValueError, r"LearnConfig.fps", False),
    ({"fps": _NAN}, ValueError, r"LearnConfig.fps", False),
    ({"fps": 0.0}, ValueError, r"LearnConfig.fps", False),
    ({"fps": 1e9}, ValueError, r"LearnConfig.fps must be <= 10000", False),
    ({"ridge": _NAN}, ValueError, r"LearnConfig.ridge", False),
    ({"ridge": -1.0}, ValueError, r"LearnConfig.ridge", False),
    ({"q_floor": _INF}, ValueError, r"LearnConfig.q_floor", False),
    ({"sigma2_floor": -1e-3}, ValueError, r"LearnConfig.sigma2_floor", False),
    ({"init_prior_weight": _INF}, ValueError, r"LearnConfig.init_prior_weight", False),
    ({"tol": _INF}, ValueError, r"LearnConfig.tol", False),
    ({"tol": _NAN}, ValueError, r"LearnConfig.tol", False),
    ({"rho_max": _INF}, ValueError, r"LearnConfig.rho_max", False),
    ({"rho_max": 0.0}, ValueError, r"LearnConfig.rho_max", False),
    ({"relabel_tol": _NAN}, ValueError, r"LearnConfig.relabel_tol", False),
]
CONFIG_CASES = [
    Case("config-" + "-".join(f"{k}={str(v)[:12]}" for k, v in kw.items()), kw, e, m, d)
    for kw, e, m, d in _CONFIG
]

#: generator calls beyond the limits: name -> (call(tex, key) -> Any, error, match, default)
_GEN: list[tuple[Any, ...]] = [
    (
        "synthesize-lengths-1e8",
        lambda mj, tex, key: mj.synthesize(key, tex, path=[0], lengths=[10**8]),
        ValueError,
        r"MAX_GENERATED_FRAMES",
        True,
    ),
    (
        "synthesize-lengths-sum",
        lambda mj, tex, key: mj.synthesize(key, tex, path=[0, 0], lengths=[600_000, 600_000]),
        ValueError,
        r"sum of lengths .*MAX_GENERATED_FRAMES",
        False,
    ),
    (
        "synthesize-lengths-1",
        lambda mj, tex, key: mj.synthesize(key, tex, path=[0], lengths=[1]),
        ValueError,
        r"every texton needs >= 2 frames",
        False,
    ),
    (
        "synthesize-lengths-negative",
        lambda mj, tex, key: mj.synthesize(key, tex, path=[0], lengths=[-5]),
        ValueError,
        r"every texton needs >= 2 frames",
        False,
    ),
    (
        "synthesize-path-1e6",
        lambda mj, tex, key: mj.synthesize(key, tex, path=np.zeros(10**6, np.int64)),
        ValueError,
        r"MAX_PATH_TEXTONS",
        False,
    ),
    (
        "synthesize-n_frames-1e9",
        lambda mj, tex, key: mj.synthesize(key, tex, n_frames=10**9),
        ValueError,
        r"n_frames = 1,000,000,000 exceeds",
        True,
    ),
    (
        "synthesize-n_frames-3",
        lambda mj, tex, key: mj.synthesize(key, tex, n_frames=3),
        ValueError,
        r"n_frames must be >= 4",
        False,
    ),
    (
        "synthesize-n_frames-float",
        lambda mj, tex, key: mj.synthesize(key, tex, n_frames=100.0),
        TypeError,
        r"n_frames must be an int",
        False,
    ),
    (
        "path_of_length-1e7",
        lambda mj, tex, key: mj.texture.path_of_length(tex, 0, 0, 10**7),
        ValueError,
        r"path_of_length: L = 10,000,000 exceeds the limit MAX_PATH_TEXTONS",
        True,
    ),
    (
        "path_of_length-1e6",
        lambda mj, tex, key: mj.texture.path_of_length(tex, 0, 0, 10**6),
        ValueError,
        r"MAX_PATH_TEXTONS|MAX_GENERATED_FRAMES",
        False,
    ),
    (
        "path_of_length-0",
        lambda mj, tex, key: mj.texture.path_of_length(tex, 0, 0, 0),
        ValueError,
        r"L must be >= 1",
        False,
    ),
    (
        "random_path-1e9",
        lambda mj, tex, key: mj.texture.random_path(key, tex, 10**9),
        ValueError,
        r"n_textons = 1,000,000,000 exceeds",
        False,
    ),
    (
        "choreograph-n_frames-1e9",
        lambda mj, tex, key: mj.choreograph(
            key, tex, np.asarray(tex.key_poses[0]), np.asarray(tex.key_poses[1]), 10**9
        ),
        ValueError,
        r"n_frames = 1,000,000,000 exceeds",
        False,
    ),
    (
        "resample-1e9-fps",
        lambda mj, tex, key: mj.load_example("dance_a").resample(1e9),
        ValueError,
        r"limit",
        False,
    ),
    (
        "resample-inf-fps",
        lambda mj, tex, key: mj.load_example("dance_a").resample(math.inf),
        ValueError,
        r"fps must be positive and finite",
        False,
    ),
    (
        "resample-nan-fps",
        lambda mj, tex, key: mj.load_example("dance_a").resample(math.nan),
        ValueError,
        r"fps must be positive and finite",
        False,
    ),
]
GENERATOR_CASES = [Case(n, f, e, m, d) for n, f, e, m, d in _GEN]

#: the implicit model: (call(mj, model, motion, key), error, match, default)
_IMPLICIT: list[tuple[Any, ...]] = [
    (
        "implicit-n_components-1e6",
        lambda mj, model, m, key: mj.implicit.learn([m], 5, n_components=10**6),
        ValueError,
        r"n_components = 1,000,000 exceeds the limit MAX_COMPONENTS",
        True,
    ),
    (
        "implicit-max_components-1e9",
        lambda mj, model, m, key: mj.implicit.learn([m], 5, max_components=10**9),
        ValueError,
        r"max_components .*MAX_COMPONENTS",
        False,
    ),
    (
        "implicit-window-1e9",
        lambda mj, model, m, key: mj.implicit.learn([m], 10**9),
        ValueError,
        r"window",
        False,
    ),
    (
        "implicit-window-0",
        lambda mj, model, m, key: mj.implicit.learn([m], 0),
        ValueError,
        r"window must be an integer",
        False,
    ),
    (
        "implicit-synthesize-1e9",
        lambda mj, model, m, key: model.synthesize(key, m, 10**9, 0.1, 0.0),
        ValueError,
        r"n_frames = 1,000,000,000 exceeds",
        False,
    ),
    (
        "implicit-track-particles-1e6",
        lambda mj, model, m, key: mj.tracking.track(
            key, model, mj.tracking.make_problem(key, model, m, n_frames=5), n_particles=10**7
        ),
        ValueError,
        r"n_particles = 10,000,000 exceeds",
        True,
    ),
    (
        "implicit-track-particles-0",
        lambda mj, model, m, key: mj.tracking.track(
            key, model, mj.tracking.make_problem(key, model, m, n_frames=5), n_particles=0
        ),
        ValueError,
        r"n_particles must be (>=|≥) 1",
        False,
    ),
]
IMPLICIT_CASES = [Case(n, f, e, m, d) for n, f, e, m, d in _IMPLICIT]


# --------------------------------------------------------------------------------------------
# 3. values: model files, motions, numbers in motion files
# --------------------------------------------------------------------------------------------
def _eye_like(a: np.ndarray, scale: float) -> np.ndarray:
    return scale * np.broadcast_to(np.eye(a.shape[-1]), a.shape).copy()


def _neg_def(a: np.ndarray) -> np.ndarray:
    return -_eye_like(a, 1.0)


def _swap_first_column(a: np.ndarray) -> np.ndarray:
    b = a.copy()
    b[..., 0] *= 3.0
    return b


#: texture-file mutations: id -> (arrays changes: name -> fn(arrays) -> array | None,
#: meta change: fn(meta) -> meta | None, match, default). ``None`` drops the member.
_TEX: list[tuple[Any, ...]] = [
    (
        "A1-1e6",
        {"texton.A1": lambda a: _eye_like(a["texton.A1"], 1e6)},
        None,
        r"spectral radius",
        True,
    ),
    (
        "B-zero",
        {"texton.B": lambda a: np.zeros_like(a["texton.B"])},
        None,
        r"texton.B .*Cholesky",
        True,
    ),
    (
        "A1-1e6-B-zero",
        {
            "texton.A1": lambda a: _eye_like(a["texton.A1"], 1e6),
            "texton.B": lambda a: np.zeros_like(a["texton.B"]),
        },
        None,
        r"Cholesky|spectral",
        False,
    ),
    (
        "S0-negative-definite",
        {"texton.S0": lambda a: _neg_def(a["texton.S0"])},
        None,
        r"S0 .*not positive definite",
        True,
    ),
    (
        "S0-asymmetric",
        {"texton.S0": lambda a: a["texton.S0"] + np.triu(np.ones(a["texton.S0"].shape[-2:]), 1)},
        None,
        r"S0 .*not symmetric",
        False,
    ),
    (
        "S0-zero",
        {"texton.S0": lambda a: np.zeros_like(a["texton.S0"])},
        None,
        r"S0 .*not positive definite",
        False,
    ),
    (
        "C-not-orthonormal",
        {"texton.C": lambda a: _swap_first_column(a["texton.C"])},
        None,
        r"orthonormal",
        False,
    ),
    (
        "sigma2-zero",
        {"texton.sigma2": lambda a: np.zeros_like(a["texton.sigma2"])},
        None,
        r"sigma2",
        False,
    ),
    (
        "sigma2-negative",
        {"texton.sigma2": lambda a: -np.ones_like(a["texton.sigma2"])},
        None,
        r"sigma2",
        False,
    ),
    (
        "mu-nan",
        {"texton.mu": lambda a: np.full_like(a["texton.mu"], np.nan)},
        None,
        r"NaN or inf",
        False,
    ),
    (
        "A2-inf",
        {"texton.A2": lambda a: np.full_like(a["texton.A2"], np.inf)},
        None,
        r"NaN or inf",
        False,
    ),
    (
        "M-bool",
        {"M": lambda a: np.eye(a["M"].shape[0], dtype=bool)},
        None,
        r"'M' has dtype bool",
        True,
    ),
    (
        "M-int",
        {"M": lambda a: np.eye(a["M"].shape[0], dtype=np.int64)},
        None,
        r"'M' has dtype int64",
        False,
    ),
    ("M-not-stochastic", {"M": lambda a: 2 * a["M"]}, None, r"not stochastic", False),
    ("M-negative", {"M": lambda a: a["M"] - 1}, None, r"negative entries", False),
    ("M-nan", {"M": lambda a: np.full_like(a["M"], np.nan)}, None, r"NaN or inf", False),
    ("M-not-square", {"M": lambda a: a["M"][:, :-1]}, None, r"M has shape", False),
    ("pi-sums-2", {"pi": lambda a: 2 * a["pi"]}, None, r"pi sums", False),
    ("pi-negative", {"pi": lambda a: -a["pi"]}, None, r"pi has negative", False),
    (
        "key_poses-wrong-D",
        {"key_poses": lambda a: a["key_poses"][..., :-1]},
        None,
        r"key_poses must have shape",
        True,
    ),
    (
        "key_poses-3-frames",
        {"key_poses": lambda a: np.concatenate([a["key_poses"], a["key_poses"][:, :1]], 1)},
        None,
        r"key_poses must have shape",
        False,
    ),
    (
        "key_pose_labels-1e6",
        {"key_pose_labels": lambda a: np.full_like(a["key_pose_labels"], 10**6)},
        None,
        r"key_pose_labels outside",
        True,
    ),
    (
        "key_pose_labels-scalar",  # found by the fuzz: an IndexError before
        {"key_pose_labels": lambda a: np.asarray(0, dtype=a["key_pose_labels"].dtype)},
        None,
        r"key_pose_labels must have shape \(n_segments,\)",
        True,
    ),
    (
        "key_pose_labels-negative",
        {"key_pose_labels": lambda a: -np.ones_like(a["key_pose_labels"])},
        None,
        r"key_pose_labels outside",
        False,
    ),
    (
        "key_pose_labels-float",
        {"key_pose_labels": lambda a: a["key_pose_labels"].astype(float)},
        None,
        r"key_pose_labels' has dtype float64",
        False,
    ),
    (
        "segments-label-1e6",
        {
            "segments": lambda a: np.concatenate(
                [a["segments"][:, :3], np.full_like(a["segments"][:, 3:], 10**6)], 1
            )
        },
        None,
        r"segments hold labels outside",
        False,
    ),
    (
        "segments-negative-start",
        {"segments": lambda a: a["segments"] * np.array([1, -1, 1, 1]) - np.array([0, 1, 0, 0])},
        None,
        r"negative",
        False,
    ),
    (
        "segment_lengths-huge",
        {"segment_lengths": lambda a: np.full_like(a["segment_lengths"], 10**12)},
        None,
        r"segment_lengths = 1,000,000,000,000 exceeds the limit MAX_SEGMENT_FRAMES",
        True,
    ),
    (
        "segment_lengths-zero",
        {"segment_lengths": lambda a: np.zeros_like(a["segment_lengths"])},
        None,
        r"segment_lengths must be positive",
        False,
    ),
    (
        "segments-length-huge",
        {
            "segments": lambda a: np.concatenate(
                [
                    a["segments"][:, :2],
                    np.full_like(a["segments"][:, 2:3], 10**12),
                    a["segments"][:, 3:],
                ],
                1,
            )
        },
        None,
        r"longest segment = .* exceeds",
        False,
    ),
    (
        "history-wrong-shape",
        {"history": lambda a: a["history"].reshape(-1)},
        None,
        r"history must have shape",
        False,
    ),
    (
        "texton-field-int",
        {"texton.d": lambda a: a["texton.d"].astype(np.int64)},
        None,
        r"'texton.d' has dtype int64",
        False,
    ),
    (
        "texton-count-mismatch",
        {"texton.d": lambda a: a["texton.d"][:-1]},
        None,
        r"texton.d must have",
        False,
    ),
    (
        "mu-wrong-rank",
        {"texton.mu": lambda a: a["texton.mu"][0]},
        None,
        r"texton.mu must have shape",
        False,
    ),
    ("missing-M", {"M": lambda a: None}, None, r"missing arrays \['M'\]", False),
    ("missing-texton-B", {"texton.B": lambda a: None}, None, r"missing arrays", False),
    (
        "unknown-member",
        {"payload": lambda a: np.zeros(3)},
        None,
        r"unknown arrays \['payload'\]",
        False,
    ),
    (
        "object-member",
        {"M": lambda a: np.array([{"x": 1}], dtype=object)},
        None,
        r"pickled or non-numeric",
        True,
    ),
    (
        "complex-member",
        {"M": lambda a: a["M"].astype(complex)},
        None,
        r"pickled or non-numeric|dtype complex",
        False,
    ),
    ("meta-fps-0", {}, lambda m: _set(m, ("feature_map", "fps"), 0.0), r"fps", True),
    ("meta-fps-nan", {}, lambda m: _set(m, ("feature_map", "fps"), math.nan), r"fps", False),
    ("meta-fps-negative", {}, lambda m: _set(m, ("feature_map", "fps"), -30.0), r"fps", False),
    (
        "meta-threshold-nan",
        {},
        lambda m: _set(m, ("threshold",), math.nan),
        r"threshold must be finite",
        True,
    ),
    (
        "meta-threshold-inf",
        {},
        lambda m: _set(m, ("threshold",), math.inf),
        r"threshold must be finite",
        False,
    ),
    (
        "meta-threshold-negative",
        {},
        lambda m: _set(m, ("threshold",), -1.0),
        r"threshold must be >=? 0",
        False,
    ),
    (
        "meta-threshold-string",
        {},
        lambda m: _set(m, ("threshold",), "x"),
        r"threshold must be a real number",
        False,
    ),
    (
        "meta-tmax-1e9",
        {},
        lambda m: _set(m, ("config", "tmax"), 10**9),
        r"LearnConfig.tmax .*MAX_SEGMENT_FRAMES",
        False,
    ),
    (
        "meta-pseudo_count-inf",
        {},
        lambda m: _set(m, ("config", "pseudo_count"), math.inf),
        r"pseudo_count",
        False,
    ),
    ("meta-config-unknown-field", {}, lambda m: _set(m, ("config", "bogus"), 1), r"bogus", False),
    # integers too large for a float (a 401-digit JSON number) where numbers are read
    (
        "meta-fps-401-digits",
        {},
        lambda m: _set(m, ("feature_map", "fps"), 10**400),
        r"fps",
        True,
    ),
    (
        "meta-tmax-401-digits",
        {},
        lambda m: _set(m, ("config", "tmax"), 10**400),
        r"tmax",
        False,
    ),
    (
        "meta-threshold-401-digits",
        {},
        lambda m: _set(m, ("threshold",), -(10**400)),
        r"threshold",
        False,
    ),
    (
        "meta-dof-401-digits",
        {},
        lambda m: _set(m, ("dof",), 10**400),
        r"dof",
        False,
    ),
    (
        "meta-kind-other",
        {},
        lambda m: _set(m, ("kind",), "mtex_jax.ContactModel"),
        r"expected a 'mtex_jax.MotionTexture' file",
        False,
    ),
    (
        "meta-version-99",
        {},
        lambda m: _set(m, ("format_version",), 99),
        r"format version 99",
        False,
    ),
    (
        "meta-observation-unknown",
        {},
        lambda m: _set(m, ("observation",), "evil"),
        r"evil|observation",
        False,
    ),
    ("meta-dof-negative", {}, lambda m: _set(m, ("dof",), -1.0), r"dof", False),
]


def _set(meta: dict[str, Any], keys: tuple[str, ...], value: Any) -> dict[str, Any]:
    """``meta`` with ``meta[k0][k1]... = value``."""
    m = json.loads(json.dumps(meta))
    d = m
    for k in keys[:-1]:
        d = d[k]
    d[keys[-1]] = value
    return m


TEXTURE_FILE_CASES = [
    Case(f"texture-{n}", (arrays, meta), ValueError, m, d) for n, arrays, meta, m, d in _TEX
]


def rewrite_npz(src: Any, dst: Any, arrays: dict[str, Any], meta: Any) -> None:
    """Copy a model file with members changed (``fn(arrays) -> array``, ``None`` drops it)
    and the metadata changed by ``meta(meta) -> meta`` (NaN allowed, as a hostile writer
    would)."""
    with np.load(src) as z:
        old = {k: z[k] for k in z.files}
    out = dict(old)
    for k, fn in arrays.items():
        v = fn(old)
        if v is None:
            out.pop(k, None)
        else:
            out[k] = v
    if meta is not None:
        m = json.loads(out["__meta_json__"].tobytes().decode("utf-8"))
        out["__meta_json__"] = np.frombuffer(json.dumps(meta(m)).encode("utf-8"), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **out)  # type: ignore[arg-type]
    with open(dst, "wb") as fh:
        fh.write(buf.getvalue())


#: Motion(...) built from a valid clip with one change: id -> (change(m) -> kwargs, error,
#: match, default)
def _motion_kw(m: Any, **changes: Any) -> dict[str, Any]:
    kw = dict(
        skeleton=m.skeleton,
        fps=m.fps,
        root_positions=np.array(m.root_positions),
        rotations=np.array(m.rotations),
        local_positions=None,
    )
    kw.update(changes)
    return kw


def _with(a: np.ndarray, index: Any, value: Any) -> np.ndarray:
    b = np.array(a, dtype=np.result_type(a, type(value)))
    b[index] = value
    return b


_MOTION: list[tuple[Any, ...]] = [
    (
        "root-nan",
        lambda m: _motion_kw(m, root_positions=_with(m.root_positions, (3, 1), np.nan)),
        ValueError,
        r"root_positions: frame 3 holds NaN or inf",
        True,
    ),
    (
        "root-inf",
        lambda m: _motion_kw(m, root_positions=_with(m.root_positions, (0, 0), np.inf)),
        ValueError,
        r"root_positions: frame 0",
        False,
    ),
    (
        "quat-int-norm-2",
        lambda m: _motion_kw(
            m, rotations=np.tile(np.array([2, 0, 0, 0]), (*m.rotations.shape[:2], 1))
        ),
        ValueError,
        r"norm 2, not a unit quaternion",
        True,
    ),
    (
        "quat-int-unit",
        lambda m: _motion_kw(
            m, rotations=np.tile(np.array([1, 0, 0, 0]), (*m.rotations.shape[:2], 1))
        ),
        None,
        r"",
        True,
    ),
    (
        "quat-bool",
        lambda m: _motion_kw(
            m,
            rotations=np.tile(np.array([True, False, False, False]), (*m.rotations.shape[:2], 1)),
        ),
        None,
        r"",
        False,
    ),
    (
        "quat-zero",
        lambda m: _motion_kw(m, rotations=_with(m.rotations, (1, 2), 0.0)),
        ValueError,
        r"zero quaternion",
        False,
    ),
    (
        "quat-nan",
        lambda m: _motion_kw(m, rotations=_with(m.rotations, (2, 0, 1), np.nan)),
        ValueError,
        r"NaN or inf",
        False,
    ),
    (
        "quat-norm-1.5",
        lambda m: _motion_kw(m, rotations=1.5 * np.asarray(m.rotations)),
        ValueError,
        r"norm 1.5",
        False,
    ),
    (
        "quat-near-unit",
        lambda m: _motion_kw(m, rotations=(1 + 1e-5) * np.asarray(m.rotations)),
        None,
        r"",
        False,
    ),
    (
        "root-int",
        lambda m: _motion_kw(m, root_positions=np.zeros(m.root_positions.shape, np.int64)),
        None,
        r"",
        False,
    ),
    (
        "root-string",
        lambda m: _motion_kw(m, root_positions=np.full(m.root_positions.shape, "a")),
        (TypeError, ValueError),
        r".",
        False,
    ),  # type: ignore[list-item]
    (
        "local-nan",
        lambda m: _motion_kw(m, local_positions=np.full((m.n_frames, m.n_joints, 3), np.nan)),
        ValueError,
        r"local_positions: frame 0",
        False,
    ),
    ("fps-0", lambda m: _motion_kw(m, fps=0.0), ValueError, r"Motion.fps", False),
    ("fps-nan", lambda m: _motion_kw(m, fps=math.nan), ValueError, r"Motion.fps", False),
    ("fps-inf", lambda m: _motion_kw(m, fps=math.inf), ValueError, r"Motion.fps", False),
    (
        "rotations-wrong-shape",
        lambda m: _motion_kw(m, rotations=np.asarray(m.rotations)[:, :-1]),
        ValueError,
        r"rotations must have shape",
        False,
    ),
    (
        "frames-disagree",
        lambda m: _motion_kw(m, rotations=np.asarray(m.rotations)[:-1]),
        ValueError,
        r"frames",
        False,
    ),
]
MOTION_CASES = [Case(f"motion-{n}", f, e, m, d) for n, f, e, m, d in _MOTION]

#: BVH text with one token replaced: id -> (where: "frame" | "offset" | "frames" | "time",
#: token, error, match, default)
_BVH: list[tuple[Any, ...]] = [
    ("frame-1_0", "frame", "1_0", ValueError, r":\d+: non-numeric token '1_0' in frame 0", True),
    ("frame-inf", "frame", "inf", ValueError, r"non-finite value 'inf'", False),
    ("frame-nan", "frame", "nan", ValueError, r"non-finite value 'nan'", False),
    ("frame-NaN", "frame", "NaN", ValueError, r"non-finite value 'NaN'", False),
    ("frame-infinity", "frame", "-Infinity", ValueError, r"non-finite value", False),
    ("frame-hex", "frame", "0x10", ValueError, r"non-numeric token '0x10'", False),
    ("frame-comma", "frame", "1,5", ValueError, r"non-numeric token '1,5'", False),
    ("frame-exp-only", "frame", "1e", ValueError, r"non-numeric token '1e'", False),
    ("frame-double-sign", "frame", "--1", ValueError, r"non-numeric token '--1'", False),
    ("frame-1e999", "frame", "1e999", ValueError, r"'1e999' in frame 0 is too large for a", False),
    ("frame-1e8", "frame", "1e8", ValueError, r"exceeds 1e\+07 in magnitude", False),
    ("frame-unicode-digit", "frame", "١", ValueError, r"non-numeric token", False),
    ("frame-fullwidth", "frame", "１", ValueError, r"non-numeric token", False),
    ("offset-1_0", "offset", "1_0", ValueError, r"non-numeric token '1_0'", True),
    ("offset-inf", "offset", "inf", ValueError, r"non-finite value 'inf'", False),
    ("offset-nan", "offset", "nan", ValueError, r"non-finite value 'nan'", False),
    # issue 57: numbers no float holds, NaN / Infinity in any case, denormals and -0.0
    ("frame-int-401", "frame", "9" * 401, ValueError, r":\d+: a 401-digit integer in", True),
    ("frame-int-5000", "frame", "9" * 5000, ValueError, r"a 5000-digit integer in frame 0", False),
    ("frame-NAN", "frame", "NAN", ValueError, r":\d+: non-finite value 'NAN' in frame 0", False),
    ("frame-INF", "frame", "-INF", ValueError, r"non-finite value '-INF' in frame 0", False),
    ("offset-int-401", "offset", "9" * 401, ValueError, r":\d+: a 401-digit integer for", True),
    ("offset-1e400", "offset", "1e400", ValueError, r"'1e400' for OFFSET x is too large", False),
    ("offset-Infinity", "offset", "Infinity", ValueError, r"non-finite value 'Infinity'", False),
    ("offset-denormal", "offset", "4e-320", None, r"", False),  # read as its value
    ("offset-negative-zero", "offset", "-0.0", None, r"", False),
    ("frames-int-401", "frames", "9" * 401, ValueError, r":\d+: invalid value .* 401-digit", True),
    ("time-int-401", "time", "9" * 401, ValueError, r"'Frame Time:': a 401-digit integer", False),
    ("time-1e400", "time", "1e400", ValueError, r"'1e400' is too large for a float", False),
    ("time-denormal", "time", "4e-320", ValueError, r"frame time", False),  # out of range
    ("frames-1_0", "frames", "1_0", ValueError, r"invalid value '1_0' for 'Frames:'", False),
    ("frames-1e15", "frames", "1e15", ValueError, r"exceeds the limit", False),
    ("frames-inf", "frames", "inf", ValueError, r"invalid value 'inf'", False),
    ("time-1_0", "time", "0.0_1", ValueError, r"invalid value '0.0_1' for 'Frame Time:'", False),
    ("time-nan", "time", "nan", ValueError, r"invalid value 'nan'", False),
    ("time-0", "time", "0", ValueError, r"Frame Time must be positive", False),
    ("time-1e6", "time", "1e6", ValueError, r"frame time", False),
    ("bom", "bom", "", None, r"", True),
    ("crlf", "crlf", "", None, r"", False),
]
BVH_CASES = [Case(f"bvh-{n}", (w, t), e, m, d) for n, w, t, e, m, d in _BVH]

#: DeepMimic JSON with a change: id -> (change(text) -> text, error, match, default)
_DM: list[tuple[Any, ...]] = [
    (
        "int-5000-digits",  # beyond Python's int() limit of 4300 digits
        lambda t: _dm_first_value(t, "9" * 5000),
        ValueError,
        r":1: Frames\[0\]\[0\]: a 5000-digit integer is too large for a float",
        True,
    ),
    (
        "int-401-digits",  # parses as a Python int, which no float holds
        lambda t: _dm_first_value(t, "9" * 401),
        ValueError,
        r":1: Frames\[0\]\[0\]: a 401-digit integer is too large for a float",
        True,
    ),
    (
        "int-401-digits-loop",  # a number anywhere, not only in a frame
        lambda t: t.replace('"wrap"', "-" + "1" * 401, 1),
        ValueError,
        r":\d+: Loop: a 401-digit integer is too large for a float",
        False,
    ),
    (
        "1e400",  # json.loads reads inf
        lambda t: _dm_first_value(t, "1e400"),
        ValueError,
        r":1: Frames\[0\]\[0\]: the number '1e400' is too large for a float",
        False,
    ),
    (
        "nan-lowercase",  # not JSON
        lambda t: _dm_first_value(t, "nan"),
        ValueError,
        r":1: invalid JSON: 'nan' is not a JSON number",
        False,
    ),
    ("INF", lambda t: _dm_first_value(t, "-INF"), ValueError, r"'-INF' is not a JSON", False),
    (
        "negative-zero-duration",
        lambda t: _dm_first_value(t, "-0.0"),
        ValueError,
        r"frame 0 lasts -0 s \(durations must be positive\)",
        False,
    ),
    ("NaN", lambda t: _dm_first_value(t, "NaN"), ValueError, r"non-finite|NaN", False),
    (
        "Infinity",
        lambda t: _dm_first_value(t, "Infinity"),
        ValueError,
        r"non-finite|Infinity|frame time",
        False,
    ),
    (
        "string-number",
        lambda t: _dm_first_value(t, '"1_0"'),
        ValueError,
        r"non-numeric|number",
        False,
    ),
    ("bom", lambda t: "\ufeff" + t, None, r"", True),
    ("bom-and-space", lambda t: "\ufeff  \n" + t, None, r"", False),
    ("truncated", lambda t: t[: len(t) // 2], ValueError, r"invalid JSON", False),
    ("not-a-motion", lambda t: '{"Loop": "wrap"}', ValueError, r"not a DeepMimic motion", False),
    (
        "deep-nesting",
        lambda t: '{"Frames": ' + "[" * 10_000 + "]" * 10_000 + "}",
        ValueError,
        r"nested",
        False,
    ),
    ("zero-frames", lambda t: '{"Frames": []}', ValueError, r"zero frames", False),
]


def _dm_first_value(text: str, token: str) -> str:
    """DeepMimic text whose first frame's first duration is ``token``."""
    doc = json.loads(text)
    frames = json.dumps(doc["Frames"][0][1:])[1:-1]
    rest = json.dumps(doc["Frames"][1:])[1:-1]
    return '{"Loop": "wrap", "Frames": [[' + token + ", " + frames + "], " + rest + "]}"


DEEPMIMIC_CASES = [Case(f"deepmimic-{n}", f, e, m, d) for n, f, e, m, d in _DM]


# --------------------------------------------------------------------------------------------
# 4. indexing
# --------------------------------------------------------------------------------------------
#: index of tex.textons: id -> (index(n) -> index, error, default)
_TEXTON_INDEX: list[tuple[Any, ...]] = [
    ("n", lambda n: n, IndexError, True),
    ("n+5", lambda n: n + 5, IndexError, False),
    ("1e9", lambda n: 10**9, IndexError, False),
    ("minus-n-1", lambda n: -n - 1, IndexError, True),
    ("np-int64-n", lambda n: np.int64(n), IndexError, False),
    ("jnp-n", lambda n: __import__("jax.numpy").numpy.asarray(n), IndexError, False),
    ("array-with-n", lambda n: np.array([0, n]), IndexError, False),
    ("float", lambda n: 1.5, IndexError, False),
    ("bool-mask-short", lambda n: np.ones(n - 1, bool), IndexError, False),
    ("0", lambda n: 0, None, True),
    ("minus-1", lambda n: -1, None, False),
    ("slice", lambda n: slice(1, 3), None, False),
    ("array", lambda n: np.array([0, n - 1]), None, False),
    ("bool-mask", lambda n: np.arange(n) % 2 == 0, None, False),
]
TEXTON_INDEX_CASES = [
    Case(f"textons[{n}]", f, e, "out of range|index|mask", d) for n, f, e, d in _TEXTON_INDEX
]


# --------------------------------------------------------------------------------------------
# 5. CLI numbers: every numeric flag with a hostile value (exit 2, one line, no internal error)
# --------------------------------------------------------------------------------------------
#: command templates; ``{model}``, ``{clip}``, ``{out}`` are filled by the test
_CMDS = {
    "learn": ["learn", "{clip}", "-o", "{out}.npz", "--quiet"],
    "synth": ["synth", "{model}", "-o", "{out}.bvh"],
    "choreograph": [
        "choreograph",
        "{model}",
        "--start",
        "{clip}:0",
        "--end",
        "{clip}:5",
        "-o",
        "{out}.bvh",
    ],
    "implicit-synth": ["implicit-synth", "{clip}", "-o", "{out}.bvh"],
    "track": ["track", "{clip}", "--test", "{clip}"],
    "evaluate": ["evaluate", "{model}", "--test", "{clip}"],
    "edit": [
        "edit",
        "{model}",
        "{clip}",
        "--joint",
        "root",
        "--frame",
        "1",
        "--at",
        "0,1,0",
        "-o",
        "{out}.bvh",
    ],
    "contacts": ["contacts", "{clip}", "-o", "{out}.npz"],
    "render": ["render", "{clip}", "-o", "{out}.gif"],
}
_BIG = str(2**70)
_NUMBERS: list[tuple[Any, ...]] = [
    # (command, flag, values, expected message fragment, default for the first value)
    ("synth", "--seed", [_BIG, "-1", "1.5", "abc", "1e3"], "--seed", True),
    ("synth", "--frames", ["1" + "0" * 30, "-5", "0", "3", "nan", "1000000001"], "--frames", True),
    ("choreograph", "--seed", [_BIG, "-7"], "--seed", False),
    ("choreograph", "--frames", ["1" + "0" * 30, "-1", "inf"], "--frames", False),
    ("learn", "--fps", ["inf", "nan", "0", "-1", "1e308", "1e9", "-inf"], "--fps", True),
    ("learn", "--tmin", ["1e308", "inf", "nan", "-1", "0", "1e6"], "--tmin", True),
    ("learn", "--tmax", ["inf", "1e308", "nan", "0", "1e6"], "--tmax", True),
    ("learn", "--textons", ["1" + "0" * 30, "0", "-1", "10000000"], "textons", False),
    ("learn", "--threshold", ["inf", "nan", "-1", "0"], "threshold", False),
    ("learn", "--max-iter", ["1" + "0" * 30, "-1", "1000000000"], "max", False),
    ("learn", "--min-segments", ["10000000", "0", "-2"], "min", False),
    ("learn", "--state-dim", ["10000000", "0"], "state", False),
    ("learn", "--dof", ["inf", "nan", "0", "-3"], "--dof", False),
    ("implicit-synth", "--frames", ["1" + "0" * 30, "0", "1000000001"], "frames", False),
    ("implicit-synth", "--seed", [_BIG], "--seed", True),
    ("implicit-synth", "--fps", ["inf", "nan", "0", "-5"], "fps", False),
    ("implicit-synth", "--beta", ["inf", "nan", "0"], "beta", False),
    ("implicit-synth", "--noise", ["nan", "-1"], "noise", False),
    ("implicit-synth", "--window", ["1" + "0" * 30, "0", "1000000000"], "window", False),
    ("implicit-synth", "--start", ["-1", "1" + "0" * 30], "start", False),
    ("implicit-synth", "--candidates", [str(2**53), "0", "100000"], "candidates", False),
    ("implicit-synth", "--lookahead", [str(2**53), "-1"], "lookahead", False),
    ("implicit-synth", "--continuation", [str(2**53), "0"], "continuation", False),
    ("implicit-synth", "--blend", [str(2**53), "-1"], "blend", False),
    ("implicit-synth", "--max-run", [str(2**53), "-1"], "max", False),
    ("implicit-synth", "--leaf-cap", [str(2**53), "-1"], "leaf", False),
    ("implicit-synth", "--seam-smoothing", [str(2**53), "-1"], "seam", False),
    ("implicit-synth", "--root-blend", [str(2**53), "-2"], "root", False),
    ("implicit-synth", "--hubness", ["inf", "-1"], "hubness", False),
    ("implicit-synth", "--min-explained", ["0", "2", "nan"], "min-explained", False),
    ("implicit-synth", "--recent-weight", ["-1", "inf"], "recent-weight", False),
    ("implicit-synth", "--foot-lock", ["2", "-0.5", "nan"], "foot-lock", False),
    ("track", "--particles", ["1" + "0" * 30, "0", "100000000"], "particles", False),
    ("track", "--seed", [_BIG], "--seed", False),
    ("track", "--fps", ["inf", "nan"], "--fps", False),
    ("track", "--likelihood-sigma", ["nan", "0"], "likelihood-sigma", False),
    ("evaluate", "--synth", ["1" + "0" * 30, "0", "65"], "synth", False),
    ("evaluate", "--seconds", ["inf", "nan", "1e308", "0", "601"], "seconds", True),
    ("evaluate", "--seed", [_BIG], "--seed", False),
    ("edit", "--frame", ["1" + "0" * 30, "-1", "1000000"], "frame", False),
    ("edit", "--at", ["nan,0,0", "inf,0,0", "1,2", "a,b,c"], "--at", False),
    ("edit", "--tolerance", ["nan", "0", "-1"], "tolerance", False),
    ("contacts", "--fps", ["inf", "nan", "0", "-1"], "fps", False),
    ("render", "--fps", ["inf", "nan", "0", "1e308"], "fps", False),
]
CLI_NUMBER_CASES = [
    Case(
        f"{cmd}{flag}={v[:12]}",
        (_CMDS[cmd], flag, v),
        SystemExit,
        frag.lstrip("-"),
        default and i == 0,
    )
    for cmd, flag, values, frag, default in _NUMBERS
    for i, v in enumerate(values)
]


# --------------------------------------------------------------------------------------------
# 6. overwrite rules: per command, an output over an input, over a file of another kind, over
# what is not a regular file, in a missing folder
# --------------------------------------------------------------------------------------------
#: command -> (argv template: ``{in}`` is the input that ``-o`` may name, ``{out}`` the output;
#: the output's suffix; what ``{in}`` is ("clip", "bvh", "model"); a file of another kind to put
#: at ``{out}`` ("bvh", "texture", "deepmimic"))
OVERWRITE_CMDS = {
    "learn": (["learn", "{in}", "-o", "{out}", "--quiet"], ".npz", "clip", "bvh"),
    "synth": (["synth", "{in}", "-o", "{out}"], ".bvh", "model", "texture"),
    "choreograph": (
        ["choreograph", "{model}", "--start", "{in}:0", "--end", "{in}:3", "-o", "{out}"],
        ".bvh",
        "bvh",
        "texture",
    ),
    "implicit-synth": (["implicit-synth", "{in}", "-o", "{out}"], ".bvh", "bvh", "texture"),
    "contacts": (["contacts", "{in}", "-o", "{out}"], ".npz", "clip", "texture"),
    "edit": (
        [
            "edit",
            "{model}",
            "{in}",
            "--joint",
            "root",
            "--frame",
            "1",
            "--at",
            "0,1,0",
            "-o",
            "{out}",
        ],
        ".bvh",
        "bvh",
        "texture",
    ),
    "evaluate": (
        ["evaluate", "{model}", "--test", "{in}", "-o", "{out}"],
        ".json",
        "clip",
        "deepmimic",
    ),
    "render": (["render", "{in}", "-o", "{out}"], ".gif", "clip", "bvh"),
    "segment": (["segment", "{model}", "{in}", "-o", "{out}"], ".png", "clip", "bvh"),
    "track": (["track", "{in}", "--test", "{in}", "--plot", "{out}"], ".png", "bvh", "bvh"),
}
#: what is at the output path: id -> expected message
OVERWRITE_TARGETS = {
    "is-input": r"is also an input",
    "other-kind": r"needs --force",
    "fifo": r"FIFO|only regular files",
    "directory": r"directory|only regular files",
    "char-device": r"character device|only regular files",
    "missing-folder": r"output folder .* does not exist",
}
_DEFAULT_OVERWRITE = {
    ("learn", "is-input"),
    ("synth", "other-kind"),
    ("contacts", "other-kind"),
    ("edit", "is-input"),
    ("implicit-synth", "is-input"),
    ("evaluate", "other-kind"),
    ("render", "char-device"),
    ("segment", "missing-folder"),
}
OVERWRITE_CASES = [
    Case(f"{cmd}-{t}", (cmd, t), SystemExit, m, (cmd, t) in _DEFAULT_OVERWRITE)
    for cmd in OVERWRITE_CMDS
    for t, m in OVERWRITE_TARGETS.items()
]


# --------------------------------------------------------------------------------------------
# 7. the command line on hostile files: every reading command, every file kind
# --------------------------------------------------------------------------------------------
#: command -> argv template; ``{file}`` is the hostile file, ``{model}`` a valid model file
CLI_FILE_CMDS = {
    "info": (["info", "{file}"], ".bvh"),
    "render": (["render", "{file}", "-o", "{out}.gif"], ".txt"),
    "learn": (["learn", "{file}", "-o", "{out}.npz", "--quiet"], ".bvh"),
    "synth": (["synth", "{file}", "-o", "{out}.bvh"], ".npz"),
    "segment": (["segment", "{file}", "{clip}"], ".npz"),
    "segment-clip": (["segment", "{model}", "{file}"], ".bvh"),
    "contacts": (["contacts", "{file}", "-o", "{out}.npz"], ".txt"),
    "synth-contacts": (
        ["synth", "{model}", "-o", "{out}.bvh", "--clean", "--contacts", "{file}"],
        ".npz",
    ),
}
_DEFAULT_CLI_FILES = {("info", "dev_zero"), ("synth", "fifo"), ("learn", "sparse_3gb")}
CLI_FILE_CASES = [
    Case(f"cli-{cmd}-{k}", (cmd, k), SystemExit, m, (cmd, k) in _DEFAULT_CLI_FILES)
    for cmd in CLI_FILE_CMDS
    for k, m in FILE_KINDS.items()
]
