"""Whole-sequence synthesis and the virtual choreographer (design §5; MT §5, Fig. 1, 5, 8).

A texton path ``ℓ_1 … ℓ_n`` with segment lengths ``l_1 … l_n`` is synthesised as follows.

1. Key poses first: for every position ``m`` one training segment of texton ``ℓ_m`` (an
   *instance*); its first two frames ``K_m (2, D)`` are the key poses and, unless lengths are
   given, its length is ``l_m``. The instances are chosen together, as the chain whose
   transitions are closest to transitions seen in training (texton ``ℓ_m`` asked to reach
   ``K_{m+1}`` where, in its training clip, segment ``m`` reached ``K_next``; cost
   ``‖K_next − K_{m+1}‖²``, zero for a pair of segments that were adjacent in training),
   by dynamic programming over the path. Key poses whose two frames jump far more than the
   others' (box-plot outliers: capture glitches, cuts at abrupt events) are left out where
   the texton has other instances.
2. Texton ``m < n`` is synthesised for ``l_m + 2`` frames with its first two frames held at
   ``K_m`` (the given ``start`` pose for ``m = 1``) and its last two held at ``K_{m+1}``,
   reprojected into its own subspace, ``x = C_{ℓ_m}ᵀ(K_{m+1} − μ_{ℓ_m})`` (MT §5.4,
   :func:`~mtex_jax.texture.synthesize_texton`). The last two frames are dropped, because
   they are the first two frames of texton ``m + 1``: shared frames appear once. It bends
   towards ``K_{m+1}`` in about its last ``transition`` seconds (design §10.11). The
   innovations of each texton replay the training residuals of the segment whose key poses
   it starts from (the texture's :class:`~mtex_jax.texture.ResidualBank`, aligned replay;
   where the texton is longer than that segment's residuals, the rows past them come from
   the texture's :class:`~mtex_jax.texture.InnovationProcess`, not from the segment's start
   again; ``replay="shuffled"``: another segment of the texton, drawn at random and
   repeated cyclically), or are drawn from its :class:`~mtex_jax.texture.InnovationProcess`
   (autocorrelated, with a persistent Student-t scale), or independently when it has
   neither.
3. The last texton is held, the same way, at the key poses of a successor drawn from
   ``M[ℓ_n, ·]`` that is not output — or, for the choreographer, at the requested end pose in
   its own last two frames. No texton runs free, so an unstable texton (spectral radius > 1)
   cannot diverge.
4. The concatenated observations ``Y (Σ l_m, D)`` are decoded into a :class:`Motion` whose
   root trajectory is integrated continuously from a start position and heading.

All textons of a path (of a block of it, for a long path) are synthesised by one jit-compiled
``lax.map`` with a common padded length (the end constraint sits at a per-texton row of a
static-shaped mask).
Every synthesis of up to 4,096 frames is one size class (design §11): the path axis has the
rows of a random path of that many frames (padded textons skip their solve), the per-texton
length is a multiple of 64 frames and at least ``tmax + 2``, the random walk, the drawn
durations and the decoding are padded the same way. So syntheses of any such length share one
set of compiled programs, and the padding changes no result: the rows past a texton's end pair
are held, the draws are prefix-stable, the decoding is causal. (A texture without a residual
bank draws its innovations at the shapes they had before, to keep their values.)

*Long syntheses* (design §5.11). The path is planned whole (:class:`PathPlan`), then
synthesised in blocks of :func:`block_rows` textons, the rows of one size class, so that the
working memory does not grow with the path (:func:`path_blocks`; block 0 draws with the noise
key as before, block ``b`` with a key of its own); the observations are decoded in pieces of
:data:`CHUNK_FRAMES` frames, each continuing the last. :func:`synthesize_chunks` yields those
pieces instead of keeping them.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Float, Int

from ...core import (
    check_count,
    check_key,
    check_size,
)
from ...motion import Motion
from .._model import MotionTexture
from .._texton.texton import Texton
from .checks import (
    check_lengths,
    check_n_frames,
    check_options,
    check_pair,
    check_texture,
    scale_lengths,
    transition_decay,
)
from .keyposes import key_pose_instances, next_texton
from .normal import transition_weights
from .path_noise import path_innovations, round_up
from .paths import random_path
from .texton_synthesis import Weighting, constrained_texton

_PAD_TEXTONS = 16  # the path axis is padded to a multiple of this (compilation sharing)
_PAD_FRAMES = 64  # and the per-texton length to a multiple of this
# a synthesis of up to this many frames is one size class: its path, walk and decoding are
# padded as for this many frames (one set of programs; the padded textons skip their solve)
_CLASS_FRAMES = 4096
#: Frames per decoded piece of a long synthesis: a synthesis of up to this many frames is
#: decoded whole and held in JAX arrays, a longer one in pieces into host arrays
#: (:func:`synthesize_chunks` yields such pieces).
CHUNK_FRAMES = 16_384


def path_capacity(texture: MotionTexture, n: int) -> int:
    """Rows of the padded path axis for a path of ``n`` textons: those of a random path of
    ``_CLASS_FRAMES`` frames (at least), so that every synthesis of that size shares them."""
    shortest = int(max(2, np.asarray(texture.segment_lengths).min()))
    if texture.log_durations is not None:
        shortest = min(shortest, int(texture.config.tmin))
    return max(round_up(_CLASS_FRAMES // shortest + 2, _PAD_TEXTONS), round_up(n, _PAD_TEXTONS))


Residual = Literal["blend", "subspace"]
Replay = Literal["aligned", "shuffled"]


class Synthesis(eqx.Module):
    """A synthesised sequence.

    Attributes:
        Y: ``(T, D)`` observations (the texture's feature space).
        path: ``(n,)`` texton labels.
        lengths: ``(n,)`` frames contributed by each texton (``Σ = T``).
        starts: ``(n,)`` first output frame of each texton.
        key_segments: ``(n,)`` training segment whose key poses (and length, unless lengths
            were given) each texton used; ``-1`` where the start pose was given instead.
        motion: the decoded :class:`Motion` (``None`` if the texture has no feature map).
    """

    Y: Float[Array, "T D"]
    path: Int[Array, " n"]
    lengths: Int[Array, " n"]
    starts: Int[Array, " n"]
    key_segments: Int[Array, " n"]
    motion: Motion | None

    @property
    def n_frames(self) -> int:
        return int(np.shape(self.Y)[0])

    def frame_labels(self) -> np.ndarray:
        """``(T,)`` texton label of every frame."""
        return np.repeat(np.asarray(self.path), np.asarray(self.lengths))

    def boundaries(self) -> np.ndarray:
        """Output frames where a new texton starts (all but the first)."""
        return np.asarray(self.starts)[1:]


def _draw_durations(key: Array, texture: MotionTexture, path: np.ndarray) -> np.ndarray:
    """One length per texton of ``path`` from its fitted duration distribution on
    ``[tmin, tmax]`` (``texture.log_durations``)."""
    assert texture.log_durations is not None
    # the rows of a categorical draw are prefix-stable: drawn for a bucket of path entries
    n = path.size
    padded = np.concatenate([path, np.zeros(path_capacity(texture, n) - n, path.dtype)])
    log_d = np.asarray(texture.log_durations)[padded]
    idx = _categorical_rows(key, jnp.asarray(log_d))
    return np.asarray(idx)[:n].astype(np.int64) + int(texture.config.tmin)


@jax.jit
def _categorical_rows(key: Array, logits: Array) -> Array:
    return jax.random.categorical(key, logits, axis=-1)


# --------------------------------------------------------------------------------------------
# the jitted core: all textons of a path
# --------------------------------------------------------------------------------------------


def path_core(
    textons: Texton,
    labels: Int[Array, " n"],
    starts: Float[Array, "n 2 D"],
    ends: Float[Array, "n 2 D"],
    end_at: Int[Array, " n"],
    v: Float[Array, "n l2 k"],
    weighting: str,
    blend: bool,
    n_real: Int[Array, ""] | None = None,
    decay: Float[Array, ""] | None = None,
) -> Float[Array, "n l D"]:
    length = v.shape[1] + 2
    t = jnp.arange(length)
    n_path = labels.shape[0]
    real = jnp.arange(n_path) < (n_path if n_real is None else n_real)

    def one(args: tuple[Array, ...]) -> Array:
        ok, lab, s, e, at, vi = args
        return lax.cond(
            ok, solve, lambda *a: jnp.zeros((length, s.shape[-1]), s.dtype), lab, s, e, at, vi
        )

    def solve(lab: Array, s: Array, e: Array, at: Array, vi: Array) -> Array:
        tex = jax.tree.map(lambda a: a[lab], textons)

        # rows from ``at`` on are held (the end pair, then frames that are dropped), so no
        # free state follows the end constraint: a free tail would make the normal equations
        # of an unstable texton as ill-conditioned as ρ^(2·tail)
        poses = jnp.where((t == at)[:, None], e[0], e[1])
        # check=False: a failed solve gives NaN, which synthesize_path reports from the host
        # (an in-program check is a host callback: the program could not be cached)
        # the bend towards the end pair near the end (design §10.11), or spread (None)
        omega = None if decay is None else transition_weights(length, decay, at, tex.mu.dtype)
        fixed = (t >= at, poses)
        y = constrained_texton(tex, vi, s, None, fixed, weighting, check=False, eq_weight=omega)
        if not blend:
            return y
        # residual outside the subspace, r = y − μ − C Cᵀ(y − μ), at the held frames, blended
        # linearly from frame 1 to frame ``at`` so that held frames are the exact poses
        res = lambda z: (z - tex.mu) - ((z - tex.mu) @ tex.C) @ tex.C.T
        rs, re = res(s), res(e)
        span = jnp.maximum(at - 1, 1).astype(y.dtype)
        w = jnp.clip((t - 1) / span, 0.0, 1.0)[:, None]
        r = (1.0 - w) * rs[1] + w * re[0]
        r = jnp.where((t == 0)[:, None], rs[0], r)
        r = jnp.where((t == at + 1)[:, None], re[1], r)
        return y + r

    # lax.map (not vmap): one unbatched factorisation per texton (see _linalg's notes); the
    # padded entries past ``n_real`` skip it
    return lax.map(one, (real, labels, starts, ends, end_at, v))


_path_core_jit = eqx.filter_jit(path_core)


class PathPlan(eqx.Module):
    """A planned path, before its frames are synthesised (host arrays; see the module notes).

    Attributes:
        path: ``(n,)`` texton labels.
        lengths: ``(n,)`` frames each texton contributes.
        seg_idx: ``(n,)`` key-pose instances (rows of ``texture.segments``).
        start: ``(2, D)`` given first two frames, or ``None`` (the first instance's key poses).
        end: ``(2, D)`` the poses the last texton is held at.
        end_in_output: the last texton holds ``end`` in its own last two frames (the
            choreographer) instead of two dropped frames past its end.
    """

    path: np.ndarray
    lengths: np.ndarray
    seg_idx: np.ndarray
    start: np.ndarray | None
    end: np.ndarray
    end_in_output: bool = eqx.field(static=True)

    @property
    def n_frames(self) -> int:
        return int(self.lengths.sum())


def block_rows(texture: MotionTexture) -> int:
    """Textons per block of a path's synthesis: the padded path rows of a synthesis of
    ``_CLASS_FRAMES`` frames, so that every synthesis of that size is one block (as it
    always was) and a longer one is a sequence of such blocks (module notes)."""
    return path_capacity(texture, 1)


def path_blocks(
    texture: MotionTexture,
    key: Array | None,
    plan: PathPlan,
    weighting: str,
    residual: str,
    replay: str = "aligned",
    decay: float | None = None,
) -> Iterator[np.ndarray]:
    """The observations of a planned path, block by block: ``(frames of the block's
    textons, D)`` host arrays, in order (module notes, *long syntheses*).

    A block holds :func:`block_rows` textons; its working memory is that of one synthesis of
    ``_CLASS_FRAMES`` frames, whatever the path's length. Block ``0`` draws its innovations
    with ``key`` (so a synthesis of one block keeps the draws it always had), block ``b ≥ 1``
    with ``fold_in(fold_in(key, 2), b)``: a block's draws depend on the path and the key, not
    on how many blocks are synthesised at a time. With ``replay="aligned"`` each texton
    replays the residuals of its own instance (not the first one's when ``start`` replaces
    its key poses). ``decay``: ``1 / τ`` in frames of the bend towards the end poses
    (:func:`~.checks.transition_decay`), or ``None``.
    """
    path, lengths, seg_idx = plan.path, plan.lengths, plan.seg_idx
    n = path.size
    tex = texture.textons
    dt = tex.mu.dtype
    D, k = texture.obs_dim, int(tex.C.shape[-1])
    key_poses = np.asarray(texture.key_poses)
    # texton m is held at the next key poses in rows l_m, l_m + 1 (dropped from the output);
    # the last one at ``end`` there too, or in its own last two rows (``end_in_output``)
    end_at = lengths.copy()
    if plan.end_in_output:
        end_at[-1] -= 2
    longest = int(end_at.max()) + 2
    if texture.config.tmax is not None:  # every drawn length fits one bucket
        longest = max(longest, int(texture.config.tmax) + 2)
    l_pad = round_up(longest, _PAD_FRAMES)
    first = key_poses[seg_idx[0]] if plan.start is None else plan.start
    inst_all = None
    if key is not None and texture.residuals is not None and replay == "aligned":
        inst_all = seg_idx.astype(np.int32)
        if plan.start is not None:  # the given start is not the instance's state
            inst_all = inst_all.copy()
            inst_all[0] = -1
    dof = None if tex.dof is None else float(tex.dof)
    P = block_rows(texture)
    put = jax.device_put  # jnp.asarray of a host array compiles a copy per shape
    for b, a in enumerate(range(0, n, P)):
        e = min(n, a + P)
        nb = e - a
        lab_p = np.zeros(P, np.int32)
        lab_p[:nb] = path[a:e]
        st_p = np.repeat(np.asarray(first)[None], P, 0)
        st_p[:nb] = key_poses[seg_idx[a:e]]
        if a == 0:
            st_p[0] = first
        # each texton ends at the next one's key poses; the last one at ``plan.end``
        en_p = np.zeros((P, 2, D), st_p.dtype)
        nxt = seg_idx[a + 1 : min(e + 1, n)]
        en_p[: nxt.size] = key_poses[nxt]
        if e == n:
            en_p[nb - 1] = plan.end
        at_p = np.full(P, l_pad - 2, np.int32)
        at_p[:nb] = end_at[a:e]
        if key is None:
            v = jnp.zeros((P, l_pad - 2, k), dt)
        else:
            kb = key if b == 0 else jax.random.fold_in(jax.random.fold_in(key, 2), b)
            inst = None
            if inst_all is not None:
                inst = np.full(P, -1, np.int32)
                inst[:nb] = inst_all[a:e]
            v = path_innovations(
                kb, texture, lab_p, inst, nb, (P, l_pad - 2, k), int(end_at.max()), dt, dof
            )
        out = _path_core_jit(
            tex,
            put(lab_p),
            put(np.asarray(st_p, dt)),
            put(np.asarray(en_p, dt)),
            put(at_p),
            v,
            weighting,
            residual == "blend",
            jax.device_put(np.asarray(nb, np.int32)),
            None if decay is None else jax.device_put(np.asarray(decay, dt)),
        )
        lens = lengths[a:e]
        rows = np.repeat(np.arange(nb), lens)
        cols = np.arange(int(lens.sum())) - np.repeat(np.cumsum(lens) - lens, lens)
        Y = np.asarray(out)[rows, cols]  # on the host: no program per length
        if not np.isfinite(Y).all():
            bad = sorted({int(path[a + r]) for r in rows[~np.isfinite(Y).all(axis=1)]})
            raise ValueError(
                f"synthesize: the constrained solve of texton(s) {bad} failed (normal matrix "
                "not positive definite or non-finite states: non-finite or singular texton "
                "parameters?)"
            )
        yield Y


def frame_chunks(blocks: Iterator[np.ndarray], chunk_frames: int) -> Iterator[np.ndarray]:
    """The rows of ``blocks`` cut again into pieces of ``chunk_frames`` (the last shorter)."""
    held: list[np.ndarray] = []
    size = 0
    for Y in blocks:
        held.append(Y)
        size += Y.shape[0]
        while size >= chunk_frames:
            rows = np.concatenate(held) if len(held) > 1 else held[0]
            yield rows[:chunk_frames]
            held, size = [rows[chunk_frames:]], size - chunk_frames
    if size:
        yield np.concatenate(held) if len(held) > 1 else held[0]


def synthesize_path(
    texture: MotionTexture,
    key: Array | None,
    plan: PathPlan,
    weighting: str,
    residual: str,
    replay: str = "aligned",
    decay: float | None = None,
) -> np.ndarray:
    """Observations ``(Σ lengths, D)`` of a planned path, as one host array filled block by
    block (:func:`path_blocks`)."""
    dt = np.dtype(texture.textons.mu.dtype)
    Y = np.empty((plan.n_frames, texture.obs_dim), dt)
    at = 0
    for rows in path_blocks(texture, key, plan, weighting, residual, replay, decay):
        Y[at : at + rows.shape[0]] = rows
        at += rows.shape[0]
    return Y


def finish(
    texture: MotionTexture,
    Y: np.ndarray,
    plan: PathPlan,
    seg_out: np.ndarray,
    start_position: Any,
    start_heading: Any,
    decode: bool,
) -> Synthesis:
    """The :class:`Synthesis` of a planned path's observations ``Y``: decoded in pieces of
    :data:`CHUNK_FRAMES` (:meth:`~mtex_jax.motion.FeatureMap.decode_chunks`). A synthesis of
    one piece is held in JAX arrays, as it always was; a longer one in host NumPy arrays, so
    that no second copy is made (module notes, *long syntheses*)."""
    T = int(Y.shape[0])
    whole = T <= CHUNK_FRAMES
    fm = texture.feature_map
    motion = None
    if decode and fm is not None:
        if whole:
            motion = fm.decode(Y, start_position, start_heading)
        else:
            pieces = (Y[a : a + CHUNK_FRAMES] for a in range(0, T, CHUNK_FRAMES))
            motion = _collect(fm.decode_chunks(pieces, start_position, start_heading), T)
    lengths = plan.lengths
    return Synthesis(
        Y=jax.device_put(Y) if whole else Y,  # type: ignore[arg-type]  # host when long
        path=jax.device_put(np.asarray(plan.path)),
        lengths=jax.device_put(np.asarray(lengths)),
        starts=jax.device_put(np.cumsum(lengths) - lengths),
        key_segments=jax.device_put(np.asarray(seg_out)),
        motion=motion,
    )


def _collect(motions: Iterator[Motion], T: int) -> Motion:
    """One :class:`Motion` of ``T`` frames from consecutive pieces, filled in place."""
    first = next(motions)
    arrays = [first.root_positions, first.rotations, first.local_positions]
    out = [None if a is None else np.empty((T, *a.shape[1:]), a.dtype) for a in arrays]
    at = 0
    for m in itertools.chain([first], motions):
        t = m.n_frames
        for o, a in zip(out, (m.root_positions, m.rotations, m.local_positions), strict=True):
            if o is not None:
                o[at : at + t] = a
        at += t
    pos, rot, lp = out
    assert pos is not None and rot is not None
    return Motion(first.skeleton, first.fps, pos, rot, lp)


# --------------------------------------------------------------------------------------------
# public entry points
# --------------------------------------------------------------------------------------------


def synthesize(
    key: Array | None,
    texture: MotionTexture,
    path: ArrayLike | None = None,
    n_frames: int | None = None,
    *,
    lengths: ArrayLike | None = None,
    start: Float[ArrayLike, "2 D"] | None = None,
    start_texton: int | None = None,
    start_position: Float[ArrayLike, 3] | None = None,
    start_heading: float | None = None,
    weighting: Weighting = "whitened",
    residual: Residual = "blend",
    decode: bool = True,
    lengths_from: str = "durations",
    replay: Replay = "aligned",
    transition: float | str | None = "auto",
) -> Synthesis:
    """Synthesise a new motion from a motion texture (MT §5; design §5).

    Key poses are chosen for every texton on the path first; each texton is synthesised with
    the constrained least-squares solver of :func:`~mtex_jax.texture.synthesize_texton`,
    held at its own key poses and at the next texton's key poses (reprojected into its
    subspace); the shared frames appear once; the last texton ends at the key poses of a
    successor drawn from ``M``. See the module docstring for the frame layout.

    * ``path=None``: a random walk on ``M`` (first texton from ``π`` or ``start_texton``)
      until ``n_frames`` frames are covered; the last texton is shortened to fit.
    * ``path`` given, ``n_frames=None``: the lengths of the key poses' training segments (or
      ``lengths``).
    * ``path`` and ``n_frames`` given: those lengths are rescaled to sum to ``n_frames``
      (each texton extrapolated to its new length, MT Fig. 10).

    Args:
        texture: a learned :class:`~mtex_jax.texture.MotionTexture`.
        key: JAX PRNG key; ``None`` = deterministic: zero noise (conditional means), the most
            probable successor, and ties between equally good key-pose chains broken towards
            median segment lengths (a random path needs a key). With a given path the key
            poses and lengths depend on the key only through such ties and the successor.
        path: ``(n,)`` texton labels, or ``None``.
        n_frames: number of output frames.
        lengths: ``(n,)`` frames per texton (with ``path``), instead of drawn ones.
        start: ``(2, D)`` first two frames (held), instead of the first texton's key poses.
        start_texton: first texton of a random path.
        start_position: ``(3,)`` root position of frame 0 for decoding (default origin).
        start_heading: root yaw of frame 0 (radians, default 0).
        weighting: ``"whitened"`` (exact conditional samples) or ``"paper"`` (MT Eq. 9).
        residual: ``"blend"`` (default): the part of the held poses outside the texton's
            subspace is blended linearly across the texton, so held frames are the exact
            poses and boundaries are continuous; ``"subspace"``: plain ``μ + C x`` (the
            paper; boundaries then jump by the difference of two reprojections).
        decode: decode to a :class:`Motion` (if the texture has a feature map).
        lengths_from: where drawn texton lengths come from (when ``lengths`` is not given):
            ``"durations"`` (default): each texton's fitted duration distribution
            (``MotionTexture.log_durations``, ``LearnConfig.durations="lognormal"``), drawn
            with ``key``; ``"segments"``: the training segment of the texton's key poses
            (the paper). A texture with flat durations, or ``key=None``, uses the segments.
        replay: for a texture with a :class:`~mtex_jax.texture.ResidualBank` (the default
            innovations): ``"aligned"`` (default): each texton replays the residuals of the
            training segment whose key poses it starts from, in the state they were measured
            in (design §10.8), and past that segment's end draws from the texture's
            :class:`~mtex_jax.texture.InnovationProcess`; ``"shuffled"``: those of a
            segment of the texton drawn at random (the residual block bootstrap without
            alignment: faster motion, more foot skating, less copying). The first texton of
            a synthesis with a given ``start``, and a segment the bank left out, draw at
            random.
        transition: where a texton bends towards the next key poses (design §10.11): a time
            constant ``τ`` in seconds, the least-squares equation of frame ``j`` weighted
            ``exp((end − j) / τ)`` so that the correction concentrates in the last ``τ`` or so
            before the end and the rest of the texton keeps its replayed motion;
            ``"auto"`` (default): :data:`~mtex_jax.texture.DEFAULT_TRANSITION` s for a
            texture learned from motions (``None`` without a frame rate); ``None``: every
            equation weighted 1, the exact conditional sample (the correction spread over
            the whole texton, MT §5.4).

    Returns:
        a :class:`Synthesis` (observations, path, lengths, starts, decoded motion).

    Raises:
        ValueError / TypeError: bad path, lengths, poses or sizes.
    """
    plan, k_noise, decay, seg_out = _prepare(
        key,
        texture,
        path,
        n_frames,
        lengths=lengths,
        start=start,
        start_texton=start_texton,
        weighting=weighting,
        residual=residual,
        lengths_from=lengths_from,
        replay=replay,
        transition=transition,
    )
    Y = synthesize_path(texture, k_noise, plan, weighting, residual, replay, decay)
    return finish(texture, Y, plan, seg_out, start_position, start_heading, decode)


def _prepare(
    key: Array | None,
    texture: MotionTexture,
    path: ArrayLike | None,
    n_frames: int | None,
    *,
    lengths: ArrayLike | None,
    start: Any,
    start_texton: int | None,
    weighting: Any,
    residual: Any,
    lengths_from: str,
    replay: Any,
    transition: Any,
) -> tuple[PathPlan, Array | None, float | None, np.ndarray]:
    """The checked arguments of :func:`synthesize` as a planned path: the plan, the noise
    key, the transition decay and the key segments to report."""
    check_key(key, "synthesize", allow_none=True)
    check_texture(texture)
    check_options(weighting, residual, replay)
    decay = transition_decay(texture, transition)
    if lengths_from not in ("durations", "segments"):
        raise ValueError(f"lengths_from must be 'durations' or 'segments', got {lengths_from!r}")
    n_t = texture.n_textons
    D = texture.obs_dim
    start_np = None if start is None else check_pair("start", start, D)
    if n_frames is not None:
        n_frames = check_n_frames(n_frames)
    k_path, k_inst, k_noise, k_succ = jax.random.split(key, 4) if key is not None else (None,) * 4

    if path is None:
        if lengths is not None:
            raise ValueError("lengths need a path")
        if n_frames is None:
            raise ValueError("give a path or n_frames")
        if k_path is None:
            raise ValueError("a random path needs a key (key=None only with a given path)")
        fitted = lengths_from == "durations" and texture.log_durations is not None
        shortest = int(max(2, np.asarray(texture.segment_lengths).min()))
        if fitted:  # the shortest length the duration distributions allow
            shortest = min(shortest, int(texture.config.tmin))
        n_max = n_frames // shortest + 2
        # drawn for the size class (prefix-stable): no program per length
        walk = random_path(k_path, texture, path_capacity(texture, n_max), start=start_texton)
        walk = walk[:n_max]
        walk_seg = key_pose_instances(texture, k_inst, walk)
        drawn = np.asarray(texture.segment_lengths)[walk_seg]
        if fitted:
            drawn = _draw_durations(jax.random.fold_in(k_path, 1), texture, walk)
        n = int(np.searchsorted(np.cumsum(drawn), n_frames) + 1)
        lens = drawn[:n].copy()
        lens[-1] = n_frames - int(lens[:-1].sum())
        if lens[-1] < 2 and n > 1:  # fold a too-short tail into the previous texton
            lens[-2] += lens[-1]
            n, lens = n - 1, lens[:-1]
        # the walk goes on: its next texton and key poses are the successor (n < n_max)
        path_np, seg_idx = walk[:n], walk_seg[:n]
        succ_seg = int(walk_seg[n])
    else:
        if start_texton is not None:
            raise ValueError("start_texton is for random paths; the path's first label is given")
        path_np = np.asarray(path)
        if path_np.ndim != 1 or path_np.size < 1 or not np.issubdtype(path_np.dtype, np.integer):
            raise ValueError(f"path must be a non-empty 1-D integer array, got {path_np.shape}")
        check_size(path_np.size, "synthesize: textons on the path", "MAX_PATH_TEXTONS")
        if (path_np < 0).any() or (path_np >= n_t).any():
            raise ValueError(f"path has labels outside [0, {n_t})")
        path_np = path_np.astype(np.int64)
        # the last texton is held at the key poses of a successor drawn from M (not output),
        # chosen with the others
        succ = next_texton(texture, k_succ, int(path_np[-1]))
        chain = key_pose_instances(texture, k_inst, np.append(path_np, succ))
        seg_idx, succ_seg = chain[:-1], int(chain[-1])
        if lengths is not None:
            lens = check_lengths(lengths, path_np.size)
            if n_frames is not None and int(lens.sum()) != n_frames:
                raise ValueError(f"lengths sum to {int(lens.sum())}, not n_frames = {n_frames}")
        else:
            lens = np.asarray(texture.segment_lengths)[seg_idx].astype(np.int64)
            if (
                lengths_from == "durations"
                and texture.log_durations is not None
                and k_inst is not None
            ):
                lens = _draw_durations(jax.random.fold_in(k_inst, 1), texture, path_np)
            if n_frames is not None:
                lens = scale_lengths(lens, n_frames, np.full(lens.size, 2))
    if (lens < 2).any():
        raise ValueError(f"every texton needs >= 2 frames, got lengths {lens.tolist()}")
    # the frames the plan makes (the key poses' or drawn lengths of a given path), before any
    # array of them is allocated
    check_size(int(lens.sum()), "synthesize: frames of the planned path", "MAX_GENERATED_FRAMES")
    # every texton is constrained at both ends (the last one at its successor's key poses),
    # so none runs free (unstable textons diverge)
    end_np = np.asarray(texture.key_poses)[succ_seg]
    plan = PathPlan(path_np, lens.astype(np.int64), seg_idx, start_np, end_np, False)
    seg_out = seg_idx.copy()
    if start_np is not None:
        seg_out[0] = -1
    return plan, k_noise, decay, seg_out


class SynthesisChunk(eqx.Module):
    """One piece of a :class:`SynthesisStream`.

    Attributes:
        start: the piece's first frame in the whole synthesis.
        Y: ``(t, D)`` observations (host array).
        motion: the decoded piece (host arrays; ``None`` without a feature map), continuing
            the previous piece's root position and heading.
    """

    start: int = eqx.field(static=True)
    Y: Float[np.ndarray, "t D"]
    motion: Motion | None

    @property
    def n_frames(self) -> int:
        return int(self.Y.shape[0])


class SynthesisStream:
    """A synthesis planned whole and made in pieces (:func:`synthesize_chunks`).

    The path, its lengths and key poses are drawn when the stream is made; iterating it
    synthesises, decodes and yields :class:`SynthesisChunk` pieces of ``chunk_frames``
    frames (the last shorter), holding one piece at a time. It can be iterated once.

    Attributes:
        path: ``(n,)`` texton labels.
        lengths: ``(n,)`` frames per texton.
        starts: ``(n,)`` first frame of each texton.
        key_segments: ``(n,)`` training segment of each texton's key poses (``-1``: the given
            start pose).
        n_frames: frames of the whole synthesis.
        chunk_frames: frames per piece.
    """

    def __init__(
        self,
        texture: MotionTexture,
        pieces: Iterator[np.ndarray],
        plan: PathPlan,
        seg_out: np.ndarray,
        chunk_frames: int,
        start_position: Any,
        start_heading: Any,
        decode: bool,
    ) -> None:
        self.path = np.asarray(plan.path)
        self.lengths = np.asarray(plan.lengths)
        self.starts = np.cumsum(self.lengths) - self.lengths
        self.key_segments = np.asarray(seg_out)
        self.n_frames = plan.n_frames
        self.chunk_frames = chunk_frames
        self._texture = texture
        self._pieces = pieces
        self._decode = decode and texture.feature_map is not None
        self._start = (start_position, start_heading)
        self._used = False

    def __iter__(self) -> Iterator[SynthesisChunk]:
        if self._used:
            raise ValueError("a SynthesisStream can be iterated once; make another")
        self._used = True
        pieces = self._pieces
        if not self._decode:
            at = 0
            for Y in pieces:
                yield SynthesisChunk(at, Y, None)
                at += Y.shape[0]
            return
        fm = self._texture.feature_map
        assert fm is not None
        held: list[np.ndarray] = []

        def kept() -> Iterator[np.ndarray]:  # each piece's Y, kept for its chunk
            for Y in pieces:
                held.append(Y)
                yield Y

        at = 0
        for m in fm.decode_chunks(kept(), *self._start):
            Y = held.pop(0)
            yield SynthesisChunk(at, Y, m)
            at += Y.shape[0]


def synthesize_chunks(
    key: Array | None,
    texture: MotionTexture,
    path: ArrayLike | None = None,
    n_frames: int | None = None,
    *,
    chunk_frames: int = CHUNK_FRAMES,
    start_position: Float[ArrayLike, 3] | None = None,
    start_heading: float | None = None,
    decode: bool = True,
    **options: Any,
) -> SynthesisStream:
    """:func:`synthesize` as a stream of pieces, for syntheses longer than memory holds
    (design §5.11).

    The path, the lengths and the key poses are drawn whole, as :func:`synthesize` draws
    them; the frames are then synthesised block by block, decoded and yielded in pieces of
    ``chunk_frames`` frames, each continuing the last, so the memory is that of one piece
    whatever ``n_frames`` is (up to :data:`~mtex_jax.core.MAX_GENERATED_FRAMES`). The pieces'
    observations together are :func:`synthesize`'s, bit for bit; their decoded motion is
    its motion up to the rounding of the running root sums (within a piece the same).
    ``mtex synth`` writes long syntheses this way.

    Args:
        key, texture, path, n_frames: as :func:`synthesize`.
        chunk_frames: frames per piece (default :data:`CHUNK_FRAMES`).
        start_position, start_heading, decode: as :func:`synthesize`.
        **options: the other keyword arguments of :func:`synthesize` (``lengths``, ``start``,
            ``start_texton``, ``weighting``, ``residual``, ``lengths_from``, ``replay``,
            ``transition``).

    Returns:
        a :class:`SynthesisStream`: the plan, and the pieces when iterated.

    Raises:
        ValueError / TypeError: as :func:`synthesize`, or ``chunk_frames`` not a positive
            int, or an unknown option.
    """
    chunk_frames = check_count(
        chunk_frames, "synthesize_chunks: chunk_frames", "MAX_GENERATED_FRAMES"
    )
    unknown = sorted(set(options) - set(_OPTIONS))
    if unknown:
        raise TypeError(f"synthesize_chunks: unknown options {unknown}; known: {list(_OPTIONS)}")
    kw = {**_OPTIONS, **options}
    plan, k_noise, decay, seg_out = _prepare(key, texture, path, n_frames, **kw)
    blocks = path_blocks(
        texture, k_noise, plan, kw["weighting"], kw["residual"], kw["replay"], decay
    )
    return SynthesisStream(
        texture,
        frame_chunks(blocks, chunk_frames),
        plan,
        seg_out,
        chunk_frames,
        start_position,
        start_heading,
        decode,
    )


#: the keyword arguments of :func:`synthesize` that :func:`synthesize_chunks` passes on, with
#: their defaults
_OPTIONS: dict[str, Any] = {
    "lengths": None,
    "start": None,
    "start_texton": None,
    "weighting": "whitened",
    "residual": "blend",
    "lengths_from": "durations",
    "replay": "aligned",
    "transition": "auto",
}
