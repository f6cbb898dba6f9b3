"""Resource limits of the readers, the model files and the generators (one place for all).

Every limit is a module constant; a reader or generator that exceeds one raises a
``ValueError`` naming the file (and line, for text formats) or the argument, the value and the
limit. The frame limit of the readers and of :meth:`Motion.resample` is also a keyword
argument (``max_frames=``) of those functions, for a caller that needs longer clips.
"""

from __future__ import annotations

import math
from typing import Any

__all__ = [
    "MAX_ABS_VALUE",
    "MAX_DEPTH",
    "MAX_FRAMES",
    "MAX_FRAME_TIME",
    "MAX_GENERATED_FRAMES",
    "MAX_JOINTS",
    "MAX_MEMBER_BYTES",
    "MAX_MODEL_BYTES",
    "MAX_PARTICLES",
    "MIN_FRAME_TIME",
    "check_count",
    "check_frame_time",
    "check_json_depth",
    "json_depth",
]

#: Frames of a clip after reading or resampling (BVH ``Frames:``, DeepMimic keyframes resampled
#: to a uniform grid, :meth:`Motion.resample`): about 2.3 hours at 120 Hz.
MAX_FRAMES = 1_000_000
#: Frames one call may generate (texture and implicit synthesis, choreography, tracking).
MAX_GENERATED_FRAMES = 1_000_000
#: Joints of a skeleton (a BVH hierarchy).
MAX_JOINTS = 1_000
#: Nesting depth of a BVH hierarchy and of a JSON document (both parsed without recursion).
MAX_DEPTH = 256
#: Frame time range in seconds (1/10,000 s to 10 s, i.e. 0.1 to 10,000 frames per second);
#: also the range of one DeepMimic keyframe's duration.
MIN_FRAME_TIME = 1e-4
MAX_FRAME_TIME = 10.0
#: Largest magnitude of a number in a motion file (angles in degrees, positions in file units).
MAX_ABS_VALUE = 1e7
#: Bytes of one array of a model file, from its ``.npy`` header, before it is read.
MAX_MEMBER_BYTES = 256 << 20
#: Bytes of all arrays of one model file together.
MAX_MODEL_BYTES = 1 << 30
#: Particles of one tracking run.
MAX_PARTICLES = 1_000_000


def check_count(value: Any, name: str, limit: int, *, low: int = 1, exc: type = ValueError) -> int:
    """``value`` as an int if ``low <= value <= limit``; ``TypeError`` if it is not an integer
    (a bool is not), else ``exc`` naming ``name``, the value and the limit."""
    import numpy as np

    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(f"{name} must be an int, got {value!r}")
    v = int(value)
    if v < low:
        raise exc(f"{name} must be >= {low}, got {v}")
    if v > limit:
        raise exc(f"{name} = {v:,} exceeds the limit of {limit:,} (mtex_jax.core limits)")
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
    step = np.isin(b, (ord("["), ord("{"))).astype(np.int64) - np.isin(b, (ord("]"), ord("}")))
    return int(np.cumsum(step).max()) if step.size else 0


def check_json_depth(text: str, where: str) -> None:
    """``ValueError`` prefixed with ``where`` if ``text`` nests deeper than :data:`MAX_DEPTH`."""
    depth = json_depth(text)
    if depth > MAX_DEPTH:
        raise ValueError(f"{where}: JSON nested {depth} levels deep (limit {MAX_DEPTH})")
