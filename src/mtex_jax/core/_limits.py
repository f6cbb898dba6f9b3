"""Resource limits of the readers, the model files and the generators (one place for all).

Every limit is a module constant; a reader or generator that exceeds one raises a
``ValueError`` naming the file (and line, for text formats) or the argument, the value and the
limit. The frame limit of the readers and of :meth:`Motion.resample` is also a keyword
argument (``max_frames=``) of those functions, for a caller that needs longer clips.

The checks of :func:`check_count` and :func:`check_size` read a limit by its name at call
time, so :func:`set_limit` (``mtex_jax.core.set_limit("MAX_TEXTONS", 5000)``) raises it for
every later check; their errors name the limit and this way of raising it.

Each limit's comment states the memory and time of a call at its value: bytes above the
process's baseline after ``import jax`` (its address-space peak), on two cores, measured by
``tests/test_limits_at_value.py``, which runs every such call under ``RLIMIT_AS`` = baseline +
2 GiB (and marks ``xfail`` the calls that need more, naming the allocation).
"""

from __future__ import annotations

import math
from typing import Any

__all__ = [
    "MAX_ABS_VALUE",
    "MAX_CANDIDATES",
    "MAX_COMPONENTS",
    "MAX_DEPTH",
    "MAX_FRAMES",
    "MAX_FRAME_TIME",
    "MAX_GENERATED_FRAMES",
    "MAX_INPUT_BYTES",
    "MAX_ITERATIONS",
    "MAX_JOINTS",
    "MAX_MEMBER_BYTES",
    "MAX_MIN_SEGMENTS",
    "MAX_MODEL_BYTES",
    "MAX_PARTICLES",
    "MAX_PATH_TEXTONS",
    "MAX_SEGMENT_FRAMES",
    "MAX_STATE_DIM",
    "MAX_TEXTONS",
    "MIN_FRAME_TIME",
    "check_count",
    "check_frame_time",
    "check_json_depth",
    "check_real",
    "check_size",
    "json_depth",
    "limit",
    "set_limit",
]

#: Frames of a clip after reading or resampling (BVH ``Frames:``, DeepMimic keyframes resampled
#: to a uniform grid, :meth:`Motion.resample`): about 2.3 hours at 120 Hz. Memory at the limit
#: is linear in frames × joints: resampling to 1,000,000 frames (slerp in blocks of frames,
#: also of DeepMimic keyframes) holds the new clip and one block, 0.6 GiB above the baseline
#: and 7 s for the walk's 13 joints; a BVH file of 1,000,000 frames of one joint (44 MB) reads
#: in 4 s with 0.9 GiB; longer files are bounded by :data:`MAX_INPUT_BYTES` first.
MAX_FRAMES = 1_000_000
#: Frames one call may generate (texture and implicit synthesis, choreography, tracking).
#: At the limit the texture's ``synthesize`` (the default model: full-dimension textons,
#: float32) holds one block of textons and one decoded piece at a time and its result (the
#: observations, quaternions and root): 1.12 GiB above the baseline, 367 s; ``mtex synth
#: --frames 1000000`` streams the pieces to the BVH file within the same bound (739 s in
#: float64; design §5.11). The implicit ``synthesize``: 1.6 GiB
#: above the baseline and 16 s for the walk (13 joints); 4.2 GiB and 98 s for the salsa
#: skeleton (43 joints: the decoding of all frames at once; the Motion alone holds 1.4 GB).
#: Tracking 1,000,000 frames: the particle filter with 10 particles needs 3.3 GiB and 78 s
#: (300 particles: about 12 minutes); the MAP smoother's rigid start asks for 57 GB.
MAX_GENERATED_FRAMES = 1_000_000
#: Joints of a skeleton (a BVH hierarchy). At the limit a BVH file of 1,000 joints reads in
#: 0.2 s; forward kinematics of 100 frames takes 5 s and 0.3 GiB. A clip holds 32 bytes a
#: joint and frame of rotations (32 KB a frame here): its frames are bounded by
#: :data:`MAX_INPUT_BYTES` and :data:`MAX_FRAMES`, not by this limit.
MAX_JOINTS = 1_000
#: Nesting depth of a BVH hierarchy and of a JSON document (both parsed without recursion).
#: At the limit both read at once (0.0 s); forward kinematics of a chain 256 joints deep takes
#: 15 s and 1.4 GiB above the baseline (one step per level, each compiled).
MAX_DEPTH = 256
#: Frame time range in seconds (1/10,000 s to 10 s, i.e. 0.1 to 10,000 frames per second);
#: also the range of one DeepMimic keyframe's duration. A range of values, with no memory of
#: its own: a BVH file at 1/10,000 s reads at once; the frames a resampling makes are bounded
#: by :data:`MAX_FRAMES`.
MIN_FRAME_TIME = 1e-4
#: The longest frame time (and DeepMimic keyframe) in seconds, see :data:`MIN_FRAME_TIME`. No
#: memory of its own: a BVH file at 10 s reads at once, a DeepMimic keyframe of 10 s is
#: resampled to 300 frames at 30 fps (0.0 s).
MAX_FRAME_TIME = 10.0
#: Largest magnitude of a number in a motion file (angles in degrees, positions in file units).
#: A bound of values, with no memory of its own: a BVH at ±1e7 reads, and its forward
#: kinematics are finite.
MAX_ABS_VALUE = 1e7
#: Bytes of one array of a model file, from its ``.npy`` header, before it is read. At the
#: limit a keypoint array (658,000 frames) reads in 3 s with 1.0 GiB above the baseline; a
#: texture of 10,000 textons does not fit (its ``M`` alone is 800 MB: 5,792 textons at most).
MAX_MEMBER_BYTES = 256 << 20
#: Bytes of all arrays of one model file together (also of the implicit model's window
#: database). At the limit a texture file loads in 1 s with 1.3 GiB above the baseline;
#: ``implicit.learn`` of a 512 MiB window database needs 3.7 GiB and 213 s (the SVD's copies),
#: more than a 2 GiB budget.
MAX_MODEL_BYTES = 512 << 20
#: Particles of one tracking run. Memory: linear in the particles (about 3.4 KB a particle for
#: the walk clip's implicit model with 5-frame windows: 3.2 GiB at the limit, measured by XLA's
#: memory analysis); from 100,000 particles ``track`` estimates the program's memory before it
#: runs and refuses, naming both figures, what the process cannot allocate
#: (:func:`~mtex_jax.core.check_memory`).
MAX_PARTICLES = 1_000_000
#: Bytes of one motion file (BVH or DeepMimic JSON) read into memory (the salsa clips are
#: about 1 MB each). Parsing holds 18 to 34 bytes a byte of the file (Python lists of tokens
#: or numbers): at the limit a salsa BVH file (210,000 frames) needs 4.5 GiB above the
#: baseline and 19 s, a 208 MB DeepMimic file more than 2 GiB (its JSON lists of numbers), more
#: than a 2 GiB budget.
MAX_INPUT_BYTES = 256 << 20
#: Frames of one texton segment (``LearnConfig.tmax``, ``tmin``, ``chunk_frames``, segment
#: lengths of a model file): the segment scores take ``T × tmax`` entries. At the limit
#: ``learn(tmax=2000)`` of two salsa clips (2,172 frames) takes 8 s and 0.3 GiB above the
#: baseline, of the ten training clips (9,725 frames) 65 s and 0.4 GiB; ``tmin=2000`` is
#: refused by any clip shorter than that.
MAX_SEGMENT_FRAMES = 2_000
#: Textons of a model (``LearnConfig.n_textons``, ``min_segments``, the ``M`` of a model file).
#: At the limit ``learn(n_textons=10000)`` of two salsa clips runs (5 s, 0.4 GiB): the initial
#: textons are at most the clips' chunks; a model file of 10,000 textons is refused by
#: :data:`MAX_MODEL_BYTES` (its ``M`` alone is 800 MB).
MAX_TEXTONS = 10_000
#: Textons on one synthesised path (``path_of_length``, ``synthesize(lengths=...)``). At the
#: limit ``path_of_length`` takes 0.1 s (10 textons; with more, ``L × N_t`` exceeds
#: :data:`MAX_GENERATED_FRAMES` and is refused); ``synthesize`` of the path with lengths of
#: 10 frames (1,000,000 frames) 19 to 36 s and 0.8 GiB above the baseline; with the key
#: poses' lengths, the planned frames are checked against :data:`MAX_GENERATED_FRAMES`
#: before any array of them is made.
MAX_PATH_TEXTONS = 100_000
#: ``LearnConfig.min_segments`` (training segments a texton needs to be kept). At the limit
#: ``learn`` of two salsa clips runs and keeps one texton (5 s, 0.4 GiB).
MAX_MIN_SEGMENTS = 10_000
#: Texton state dimension (``LearnConfig.state_dim``). At the limit ``learn`` of motions is
#: refused by their observation dimension (54 for the salsa clips); of 4,096-dimensional arrays
#: its M-step asks for 19.9 GB (``k = 512``: 65 s and 0.7 GiB; 1,024: more than 5 minutes).
MAX_STATE_DIM = 4_096
#: Iterations of a learning loop (``LearnConfig.max_iter``). At the limit EM stops at
#: convergence as before (two salsa clips: 5 s, 0.4 GiB); the history holds 16 bytes an
#: iteration.
MAX_ITERATIONS = 100_000
#: Tree walks per search of the implicit model's sampler (``SynthesisConfig.candidates``,
#: default 16): each walk holds ``leaf_cap × d × P`` numbers of the database (276 KB for the
#: salsa model, ``d = 10``, leaves capped at 32). At the limit 100 frames of the salsa model
#: take 38 s and 0.39 GiB above the baseline, of the walk's 5 s and 0.06 GiB (at 10,000 walks
#: the salsa model asked for one buffer of 2.8 GB and took 237 s).
MAX_CANDIDATES = 1_000
#: Principal components of the implicit model's tree (``n_components``). At the limit
#: ``implicit.learn`` of the walk takes 1.6 s and 0.11 GiB above the baseline (the leaves are
#: counted from the sorted codes, not in an array of ``2**30`` counts).
MAX_COMPONENTS = 30


_NAMES = (
    "MAX_FRAMES",
    "MAX_GENERATED_FRAMES",
    "MAX_JOINTS",
    "MAX_DEPTH",
    "MAX_ABS_VALUE",
    "MAX_MEMBER_BYTES",
    "MAX_MODEL_BYTES",
    "MAX_PARTICLES",
    "MAX_INPUT_BYTES",
    "MAX_SEGMENT_FRAMES",
    "MAX_TEXTONS",
    "MAX_PATH_TEXTONS",
    "MAX_STATE_DIM",
    "MAX_ITERATIONS",
    "MAX_COMPONENTS",
    "MAX_MIN_SEGMENTS",
    "MAX_CANDIDATES",
)


def limit(name: str) -> int | float:
    """The current value of the limit ``name`` (e.g. ``"MAX_TEXTONS"``)."""
    if name not in _NAMES:
        raise KeyError(f"unknown limit {name!r}; the limits are {', '.join(_NAMES)}")
    return globals()[name]


def set_limit(name: str, value: int) -> int | float:
    """Set the limit ``name`` to ``value`` for every later check; returns the old value.

    Functions that take a limit as a keyword default (``max_frames=MAX_FRAMES`` of the
    readers) keep the value they were defined with; pass the keyword there.
    """
    old = limit(name)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"set_limit: {name} must be a positive int, got {value!r}")
    globals()[name] = value
    return old


def _over(name: str, v: Any, lim: str | int) -> str:
    if isinstance(lim, str):
        return (
            f"{name} = {v:,} exceeds the limit {lim} = {limit(lim):,} (raise it with "
            f"mtex_jax.core.set_limit({lim!r}, N))"
        )
    return f"{name} = {v:,} exceeds the limit of {lim:,} (mtex_jax.core limits)"


def check_count(
    value: Any, name: str, limit: int | str, *, low: int = 1, exc: type = ValueError
) -> int:
    """``value`` as an int if ``low <= value <= limit``; ``TypeError`` if it is not an integer
    (a bool is not), else ``exc`` naming ``name``, the value and the limit.

    ``limit`` is a number or the name of a limit of this module (read when called, so that
    :func:`set_limit` applies).
    """
    import numpy as np

    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(f"{name} must be an int, got {value!r}")
    v = int(value)
    if v < low:
        raise exc(f"{name} must be >= {low}, got {v}")
    lim = globals()[limit] if isinstance(limit, str) else limit
    if v > lim:
        raise exc(_over(name, v, limit))
    return v


def check_size(value: Any, name: str, limit: str) -> None:
    """``ValueError`` naming ``name`` and the limit ``limit`` (a name of this module) if the
    number ``value`` (a size computed before an allocation) exceeds that limit."""
    lim = globals()[limit]
    if value > lim:
        raise ValueError(_over(name, int(value), limit))


def check_real(
    value: Any,
    name: str,
    *,
    low: float | None = None,
    high: float | None = None,
    open_low: bool = False,
) -> float:
    """``value`` as a float if it is a finite real number in range, else ``ValueError`` (or
    ``TypeError`` for a non-number) naming ``name``.

    Args:
        value: the number (a bool is refused).
        name: what to call it in the error.
        low: the smallest value allowed (``None``: no bound); excluded when ``open_low``.
        high: the largest value allowed (``None``: no bound).
    """
    import numpy as np

    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise TypeError(f"{name} must be a real number, got {value!r}")
    try:
        v = float(value)
    except OverflowError:
        raise ValueError(f"{name} is too large: {value}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    if low is not None and (v < low or (open_low and v == low)):
        raise ValueError(f"{name} must be {'>' if open_low else '>='} {low:g}, got {v:g}")
    if high is not None and v > high:
        raise ValueError(f"{name} must be <= {high:g}, got {v:g}")
    return v


def check_frame_time(seconds: float, where: str) -> float:
    """``seconds`` if it lies in ``[MIN_FRAME_TIME, MAX_FRAME_TIME]``, else ``ValueError``
    prefixed with ``where`` (e.g. ``"file.bvh:12"``)."""
    if not (math.isfinite(seconds) and MIN_FRAME_TIME <= seconds <= MAX_FRAME_TIME):
        raise ValueError(
            f"{where}: frame time {seconds:g} s is outside [{MIN_FRAME_TIME:g}, "
            f"{MAX_FRAME_TIME:g}] s (0.1 to 10,000 frames per second)"
        )
    return seconds


_JSON_STRING = None
_DEPTH_BLOCK = 1 << 22  # bytes of JSON text per block of json_depth


def json_depth(text: str) -> int:
    """The largest nesting depth of ``[`` and ``{`` in JSON text (strings skipped), computed
    without recursion, so that a deeply nested document can be refused before
    :func:`json.loads` (which recurses) sees it."""
    global _JSON_STRING
    import re

    import numpy as np

    if _JSON_STRING is None:
        _JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"', re.DOTALL)
    b = np.frombuffer(_JSON_STRING.sub('""', text).encode("utf-8", "replace"), np.uint8)
    # in blocks of bytes, the depth carried from block to block: the temporaries of one block
    # (16 bytes a byte of text for the whole document otherwise: 3.1 GiB for a 208 MB file)
    deepest, depth = 0, 0
    for a in range(0, b.size, _DEPTH_BLOCK):
        part = b[a : a + _DEPTH_BLOCK]
        step = np.isin(part, (ord("["), ord("{"))).astype(np.int64)
        step -= np.isin(part, (ord("]"), ord("}")))
        run = depth + np.cumsum(step)
        deepest, depth = max(deepest, int(run.max())), int(run[-1])
    return deepest


def check_json_depth(text: str, where: str) -> None:
    """``ValueError`` prefixed with ``where`` if ``text`` nests deeper than :data:`MAX_DEPTH`."""
    depth = json_depth(text)
    if depth > MAX_DEPTH:
        raise ValueError(f"{where}: JSON nested {depth} levels deep (limit {MAX_DEPTH})")
