"""The virtual choreographer (MT §5.3, Fig. 1): motion between two given key poses, through the
textons that match them."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ...core import check_key, limit
from .._model import MotionTexture
from .._scoring.frame_terms import frame_terms
from .._scoring.frame_terms_ref import init_terms
from .checks import (
    check_n_frames,
    check_options,
    check_pair,
    check_texture,
    scale_lengths,
    transition_decay,
)
from .keyposes import key_pose_instances
from .paths import path_of_length, shortest_path
from .sequence import PathPlan, Residual, Synthesis, finish, synthesize_path
from .texton_synthesis import Weighting


def match_texton(
    texture: MotionTexture, pose: Float[ArrayLike, "2 D"], *, role: str = "start"
) -> tuple[int, np.ndarray]:
    """The texton that best explains a pair of frames at the start or the end of a segment.

    ``role="start"``: the pair as the first two frames of a segment of texton ``i``, scored
    ``init_i(0) + obs_i(0) + obs_i(1)`` (initial two-state Gaussian plus the residual outside
    the subspace, design §3). ``role="end"``: the pair as the last two frames, scored by the
    residual ``obs_i(0) + obs_i(1)`` (a texton's end states have no stored distribution), so
    the chosen texton's subspace reproduces the pose best.

    Returns:
        ``(best texton, scores (N_t,))``.
    """
    check_texture(texture)
    if role not in ("start", "end"):
        raise ValueError(f"role must be 'start' or 'end', got {role!r}")
    p = check_pair("pose", pose, texture.obs_dim)
    y = jnp.asarray(p, texture.textons.mu.dtype)
    _, obs = frame_terms(texture.textons, y)
    score = obs.sum(axis=1)
    if role == "start":
        score = score + init_terms(texture.textons, y)[:, 0]
    score = np.asarray(score)
    return int(np.argmax(score)), score


def choreograph(
    key: Array | None,
    texture: MotionTexture,
    start_pose: Float[ArrayLike, "2 D"],
    end_pose: Float[ArrayLike, "2 D"],
    n_frames: int | None = None,
    *,
    start_position: Float[ArrayLike, 3] | None = None,
    start_heading: float | None = None,
    weighting: Weighting = "whitened",
    residual: Residual = "blend",
    decode: bool = True,
    transition: float | str | None = "auto",
) -> Synthesis:
    """Virtual choreographer (MT Fig. 1): a motion from a start pose to an end pose.

    The start pair is matched to texton ``u`` as the first frames of a segment and the end
    pair to texton ``v`` as the last frames of one (:func:`match_texton`). The path from ``u``
    to ``v`` is planned with :func:`path_of_length` when ``n_frames`` is given (``L ≈
    n_frames / mean segment length`` textons) or, by default, with :func:`shortest_path`
    without self-repeats: the most probable texton path, each texton as long as its key
    poses' training segment (sampled self-repeats made the default motion of a 53-texton
    model 142 s long; ask for more frames with ``n_frames``). Key poses are chosen for the
    textons in between as in :func:`synthesize`; the first texton starts at ``start_pose`` and
    the last one (``v``) is held at ``end_pose`` in its final two frames, so the motion begins
    and ends at the given poses (each reprojected into its texton's subspace,
    ``μ + C Cᵀ(y − μ)``). With ``n_frames`` the segment lengths are rescaled to fit exactly.

    Args:
        texture: a learned :class:`~mtex_jax.texture.MotionTexture`.
        key: JAX PRNG key, or ``None`` for the deterministic (mean) motion.
        start_pose: ``(2, D)`` first two frames.
        end_pose: ``(2, D)`` last two frames.
        n_frames: total frames, or ``None`` for the lengths that come with the key poses.
        start_position: ``(3,)`` root position of frame 0 for decoding (default origin).
        start_heading: root yaw of frame 0 (radians, default 0).
        weighting: ``"whitened"`` or ``"paper"``.
        residual: ``"blend"`` or ``"subspace"`` (see :func:`synthesize`).
        decode: decode to a :class:`Motion`.
        transition: where each texton bends towards the next key poses (see
            :func:`synthesize`; design §10.11).

    Returns:
        a :class:`Synthesis` whose first and last two frames are the given poses.
    """
    check_key(key, "choreograph", allow_none=True)
    check_texture(texture)
    check_options(weighting, residual)
    decay = transition_decay(texture, transition)
    D = texture.obs_dim
    s_np = check_pair("start_pose", start_pose, D)
    e_np = check_pair("end_pose", end_pose, D)
    u, _ = match_texton(texture, s_np, role="start")
    v, _ = match_texton(texture, e_np, role="end")
    _, k_inst, k_noise = jax.random.split(key, 3) if key is not None else (None,) * 3
    seg_len = np.asarray(texture.segment_lengths, dtype=np.float64)
    if n_frames is not None:
        n_frames = check_n_frames(n_frames)
        L = max(1, min(round(int(n_frames) / seg_len.mean()), (int(n_frames) - 2) // 2))
        L = min(L, int(limit("MAX_PATH_TEXTONS")))
        if u != v and L == 1:
            L = 2
        body, _ = path_of_length(texture, u, v, L)
    else:
        body = shortest_path(texture, u, v, key=None)
    seg_idx = key_pose_instances(texture, k_inst, body)
    lens = seg_len[seg_idx].astype(np.int64)
    mins = np.full(body.size, 2)
    mins[-1] = 4
    if n_frames is not None:
        lens = scale_lengths(lens.astype(np.float64), int(n_frames), mins)
    else:
        lens = np.maximum(lens, mins)
    plan = PathPlan(body, lens.astype(np.int64), seg_idx, s_np, e_np, True)
    Y = synthesize_path(texture, k_noise, plan, weighting, residual, decay=decay)
    seg_out = seg_idx.copy()
    seg_out[0] = -1
    return finish(texture, Y, plan, seg_out, start_position, start_heading, decode)
