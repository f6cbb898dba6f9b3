"""Synthesis with the implicit model (IP §5, §7): the paper's frame-by-frame sampler and the
extensions that make its motion smooth and new — velocity form, leaf choice by exact distance,
blended transitions, dead-end look-ahead, multi-frame continuation and a cap on verbatim runs.

State of the generator after frame ``t``: the history window (``d`` pose vectors), the database
example ``e_t`` whose successor gave frame ``t``, a pose offset ``o`` and its age ``a`` (frames
since the last transition). One step:

1. **Continue or search.** If ``e_t`` has a successor example in its clip and fewer than
   ``continuation`` frames have passed since the last search, ``e_{t+1} = e_t + 1`` (the next
   window of the same clip). Otherwise search (tree, IP Eq. 7–8, or exact, IP Eq. 3) with the
   history as probe; the leaf (or the exact kernel) only admits examples with at least
   ``lookahead`` further frames in their clip (dead ends), and, once a verbatim run has lasted
   ``max_run`` frames, none within ``d`` frames of ``e_t + 1`` in the same clip. The exact
   kernel (leaf choice, choice among the candidate walks, exact sampler) scores an example by
   ``‖Ψ_i − Φ‖² − h r_i`` (hubness correction, :mod:`._hubness`): in ``W ≈ 10³`` dimensions
   slow near-mean windows are the nearest neighbours of most probes, and without it the
   motion is slower than the real motion.
2. **Transition.** If ``e_{t+1} ≠ e_t + 1``: in the velocity form the offset becomes
   ``o = ŷ_t − y(e_{t+1})``, the current pose minus the example's own current pose, and
   ``a = 0``; in the paper's form ``o = 0``.
3. **Pose.** ``ŷ_{t+1} = y(e_{t+1} + 1) + w(a + 1) ⊙ o`` (``y(e + 1)`` is the example's
   successor pose), ``a ← a + 1``. With ``blend = B > 0`` the offset fades out smoothly,
   ``w(a) = 1 − S(min(a / (B + 1), 1))`` with ``S(x) = 3x² − 2x³``: the change of pose of the
   example is applied at the transition and the motion rejoins the example's absolute poses
   after ``B`` frames with continuous velocity. With ``B = 0`` the offset is kept
   (``w = 1``): the pure velocity form ``ŷ_{t+1} = ŷ_t + Δy(e_{t+1})``. Root displacement and
   yaw change already are velocities: their offset fades over its own (shorter)
   ``B_r = root_blend`` frames, ``w_r(a) = 1 − S(min(a / (B_r + 1), 1))`` (``B_r = 0``: none;
   none either when ``B = 0``). The example's joint motion fits its own root velocity: while
   the root keeps the old velocity and the limbs already follow the new example, the feet
   slide, so a long root fade makes the extremities too fast.
4. **Foot lock** (``foot_lock > 0``, :mod:`._feet`): the root's horizontal displacement of
   the new frame is corrected so that the feet the example keeps planted move as in the
   example, not as the fading offset drags them.

After the scan, the output frames around each transition are low-passed (``seam_smoothing``,
:mod:`._seams`); the generator's history is the unsmoothed motion.
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float, Int, PRNGKeyArray

from ..core import check_count
from ..motion import FeatureMap
from ._database import MotionDatabase
from ._feet import lock_root, root_channels
from ._seams import smooth_seams
from ._tree import descend
from ._windows import velocity_channels

SynthLeafRule = Literal["uniform", "weighted", "exact"]
_LEAVES = ("uniform", "weighted", "exact")


def _check_int(value: object, name: str, low: int, high: str = "MAX_GENERATED_FRAMES") -> int:
    """``value`` if it is an integer in ``[low, limit(high)]`` (a limit of
    :mod:`mtex_jax.core`), else ``ValueError`` naming ``SynthesisConfig.name``."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
        raise ValueError(f"SynthesisConfig.{name} must be an integer ≥ {low}, got {value!r}")
    return check_count(value, f"SynthesisConfig.{name}", high, low=low)


class SynthesisConfig(eqx.Module):
    """How :meth:`ImplicitModel.synthesize` turns sampled examples into motion (all static).

    The defaults were chosen on validation splits of the training clips only (``blend``,
    ``hubness``, ``root_blend``, ``foot_lock``, ``lock_smoothing`` and ``seam_smoothing`` by
    the worst case over three folds; design §7.5); :meth:`paper` gives the published sampler
    (IP §5).

    Attributes:
        velocity: apply the chosen example's change of pose to the current pose (``True``)
            instead of jumping to its absolute pose (``False``, the paper).
        blend: frames over which a transition's pose offset fades out (``0``: never, the pure
            velocity form). Needs ``velocity=True`` when ``> 0``.
        leaf: choice within the tree's leaf: ``"uniform"``, ``"weighted"`` by ``p(c_i | c_t)``
            (the paper, IP Eq. 8) or ``"exact"`` by the exact kernel of IP Eq. 3 on the leaf's
            few members.
        lookahead: a searched example needs at least this many further frames in its clip
            (``0``: no check). Avoids dead ends.
        continuation: frames played from one example before the next search (``1``: a search
            per frame, the paper).
        max_run: after this many verbatim frames (continuing the previous database frame),
            the next search excludes the neighbourhood of the continuation (``0``: no cap).
        candidates: tree walks per search; the exact kernel picks among them (``1``: one walk).
        leaf_cap: leaf members examined per walk (``0``: the whole leaf). A larger leaf
            contributes a random block of ``leaf_cap`` consecutive members (cyclic), so the
            cost per walk is ``O(b log n + leaf_cap · W)`` whatever the leaf sizes.
        hubness: weight ``h`` of the hubness correction of the exact kernel (leaf choice,
            candidate choice and the exact sampler): an example scores
            ``‖Ψ_i − Φ‖² − h · r_i`` instead of ``‖Ψ_i − Φ‖²``, where ``r_i`` is its mean
            squared distance to its nearest database windows
            (``ImplicitModel.neighbour_radius``). ``0.5`` is CSLS (Conneau et al. 2018);
            ``0`` is the paper's kernel (IP Eq. 3). Without it, slow near-mean windows are
            the nearest neighbours of most probes and the motion slows down.
        root_blend: frames ``B_r`` over which the offset of the root-velocity channels (root
            displacement and yaw change, :func:`velocity_channels`) fades,
            ``w_r(a) = 1 − S(min(a / (B_r + 1), 1))``; ``0``: the root takes the example's
            velocity at once; ``-1``: the same as ``blend``. Used only when ``blend > 0``.
            The default ``1`` keeps the root's velocity consistent with the example's limbs,
            so planted feet slide less during a transition; the root's quicker change of
            velocity costs some acceleration and jerk.
        foot_lock: strength in ``[0, 1]`` of the foot lock (:mod:`~mtex_jax.implicit._feet`):
            the root's horizontal displacement is corrected so that planted feet move as in
            the example (``0``: off, the paper). It lowers foot skating and the speed
            distance, and raises acceleration and jerk a little (design §7.5).
        lock_smoothing: ``λ ∈ [0, 1)``: the foot lock's correction is smoothed over frames,
            ``δ̄_t = λ δ̄_{t−1} + (1 − λ) δ_t`` (a quicker correction shakes the body). The
            default 0.5 was chosen with seam smoothing on, on the validation folds.
        seam_smoothing: ``S``: the output frames within ``S − 1`` frames of a transition are
            blended with their ``[1, 2, 1] / 4`` average, fully at the transition and less
            with distance (:mod:`~mtex_jax.implicit._seams`; ``0``: off, the paper). It
            removes the jerk spike of the velocity step at each transition. ``S = 2`` was
            chosen on the validation folds; ``S = 3`` smooths more but slows the motion.
    """

    velocity: bool = eqx.field(static=True, default=True)
    blend: int = eqx.field(static=True, default=6)
    leaf: str = eqx.field(static=True, default="exact")
    lookahead: int = eqx.field(static=True, default=8)
    continuation: int = eqx.field(static=True, default=6)
    max_run: int = eqx.field(static=True, default=12)
    candidates: int = eqx.field(static=True, default=16)
    leaf_cap: int = eqx.field(static=True, default=32)
    hubness: float = eqx.field(static=True, default=0.2)
    root_blend: int = eqx.field(static=True, default=1)
    foot_lock: float = eqx.field(static=True, default=1.0)
    lock_smoothing: float = eqx.field(static=True, default=0.5)
    seam_smoothing: int = eqx.field(static=True, default=2)

    def __check_init__(self) -> None:
        if not isinstance(self.velocity, bool):
            raise ValueError(f"SynthesisConfig.velocity must be a bool, got {self.velocity!r}")
        _check_int(self.blend, "blend", 0)
        _check_int(self.lookahead, "lookahead", 0)
        _check_int(self.continuation, "continuation", 1)
        _check_int(self.max_run, "max_run", 0)
        _check_int(self.candidates, "candidates", 1, "MAX_CANDIDATES")
        _check_int(self.leaf_cap, "leaf_cap", 0)
        _check_int(self.root_blend, "root_blend", -1)
        _check_int(self.seam_smoothing, "seam_smoothing", 0)
        h = self.hubness
        if isinstance(h, bool) or not isinstance(h, int | float) or not 0 <= h < np.inf:
            raise ValueError(f"SynthesisConfig.hubness must be a finite number ≥ 0, got {h!r}")
        for name, hi, closed in (("foot_lock", 1.0, True), ("lock_smoothing", 1.0, False)):
            v = getattr(self, name)
            ok = isinstance(v, int | float) and not isinstance(v, bool)
            if not ok or not (0 <= v <= hi if closed else 0 <= v < hi):
                rng = f"[0, {hi:g}]" if closed else f"[0, {hi:g})"
                raise ValueError(f"SynthesisConfig.{name} must be a number in {rng}, got {v!r}")
        if self.leaf not in _LEAVES:
            raise ValueError(
                f"SynthesisConfig.leaf must be one of {', '.join(_LEAVES)}, got {self.leaf!r}"
            )
        if self.blend > 0 and not self.velocity:
            raise ValueError(
                "SynthesisConfig.blend > 0 needs velocity=True (it fades the velocity form's "
                "pose offset)"
            )

    @classmethod
    def paper(cls) -> SynthesisConfig:
        """The published sampler (IP §5, Eq. 7–8): absolute poses, a search every frame,
        ``p(c_i | c_t)`` in the leaf, no blending, no look-ahead, no run cap, no hubness
        correction."""
        return cls(
            velocity=False,
            blend=0,
            leaf="weighted",
            lookahead=0,
            continuation=1,
            max_run=0,
            hubness=0.0,
            foot_lock=0.0,
            seam_smoothing=0,
        )


def _remaining(db: MotionDatabase) -> np.ndarray:
    """Further examples after each example in its clip, ``(n,)`` (static, from clip sizes)."""
    return np.concatenate([np.arange(s - 1, -1, -1) for s in db.clip_sizes]).astype(np.int32)


def _pick(key: PRNGKeyArray, logw: Array, ok: Array, valid: Array) -> Array:
    """Categorical pick over ``logw`` restricted to ``ok``, or to ``valid`` if none is ok."""
    masked = jnp.where(ok, logw, -jnp.inf)
    fallback = jnp.where(valid, logw, -jnp.inf)
    return jax.random.categorical(key, jnp.where(jnp.any(ok), masked, fallback))


def _kernel(
    db: MotionDatabase, cfg: SynthesisConfig, ex: Array, probe: Array, beta: Array
) -> Array:
    """Log weight of the exact kernel of examples ``ex`` for ``probe``, hubness-corrected:
    ``−(‖Ψ_i − Φ‖² − h r_i) / (2β)``."""
    diff = db.windows[ex].astype(probe.dtype) - probe
    d2 = jnp.sum(diff * diff, axis=-1)
    if cfg.hubness > 0:
        d2 = d2 - cfg.hubness * db.neighbour_radius[ex].astype(probe.dtype)
    return -0.5 * d2 / beta


def _admissible(
    db: MotionDatabase, cfg: SynthesisConfig, ex: Array, cur: Array, run: Array, rem: Array
) -> Array:
    """Which examples ``ex`` a search may return (look-ahead and run cap)."""
    ok = rem[ex] >= cfg.lookahead
    if cfg.max_run > 0:
        same = db.clip_index[ex] == db.clip_index[jnp.maximum(cur, 0)]
        near = jnp.abs(db.frame_index[ex] - db.frame_index[jnp.maximum(cur, 0)] - 1)
        banned = (cur >= 0) & (run >= cfg.max_run) & same & (near <= db.window)
        ok = ok & ~banned
    return ok


def _search_tree(
    db: MotionDatabase,
    cfg: SynthesisConfig,
    key: PRNGKeyArray,
    probe: Float[Array, " W"],
    beta: Array,
    cur: Array,
    run: Array,
    rem: Array,
) -> Int[Array, ""]:
    """Tree search (IP Eq. 7–8) with the configured leaf rule and admissibility mask."""
    c = db.coefficients(probe)
    scale = jnp.sqrt(beta) * db.sigma.astype(c.dtype)
    n = db.n_examples

    def walk(k: PRNGKeyArray) -> tuple[Array, Array]:
        k_walk, k_leaf, k_block = jax.random.split(k, 3)
        u = jax.random.uniform(k_walk, (db.n_components,), dtype=c.dtype)
        lo, hi, _ = descend(db.sorted_codes, c / scale, u)
        width = db.leaf_max if cfg.leaf_cap == 0 else min(cfg.leaf_cap, db.leaf_max)
        j = jnp.arange(width, dtype=jnp.int32)
        size = hi - lo
        if width < db.leaf_max:  # a random cyclic block of `width` members
            first = jax.random.randint(k_block, (), 0, jnp.maximum(size, 1))
            first = jnp.where(size > width, first, 0)
            pos = lo + (first + j) % jnp.maximum(size, 1)
        else:
            pos = lo + j
        valid = j < size
        ex = db.order[jnp.minimum(pos, n - 1)]
        if cfg.leaf == "uniform":
            logw = jnp.zeros(pos.shape, c.dtype)
        elif cfg.leaf == "weighted":
            z = (db.sorted_coeffs[jnp.minimum(pos, n - 1)].astype(c.dtype) - c) / scale
            logw = -0.5 * jnp.sum(z * z, axis=-1)
        else:
            logw = _kernel(db, cfg, ex, probe, beta)
        ok = valid & _admissible(db, cfg, ex, cur, run, rem)
        j = _pick(k_leaf, logw, ok, valid)
        return ex[j], ok[j]

    if cfg.candidates == 1:
        return walk(key)[0]
    k_walks, k_pick = jax.random.split(key)
    idx, ok = jax.vmap(walk)(jax.random.split(k_walks, cfg.candidates))
    logp = _kernel(db, cfg, idx, probe, beta)
    return idx[_pick(k_pick, logp, ok, jnp.ones_like(ok))]


def _search_exact(
    db: MotionDatabase,
    cfg: SynthesisConfig,
    key: PRNGKeyArray,
    probe: Float[Array, " W"],
    beta: Array,
    cur: Array,
    run: Array,
    rem: Array,
) -> Int[Array, ""]:
    """Exact sampler (IP Eq. 3) over all admissible examples, ``O(n·W)``."""
    ex = jnp.arange(db.n_examples, dtype=jnp.int32)
    logw = _kernel(db, cfg, ex, probe, beta)
    ok = _admissible(db, cfg, ex, cur, run, rem)
    return _pick(key, logw, ok, jnp.ones_like(ok)).astype(jnp.int32)


def fade_weight(age: Array, blend: int) -> Array:
    """``w(a) = 1 − S(min(a / (B + 1), 1))``, ``S(x) = 3x² − 2x³`` (``B = blend > 0``)."""
    x = jnp.clip(age / (blend + 1.0), 0.0, 1.0)
    return 1.0 - x * x * (3.0 - 2.0 * x)


def synthesize_scan(
    db: MotionDatabase,
    fm: FeatureMap,
    key: PRNGKeyArray,
    win0: Float[Array, "d P"],
    n_frames: int,
    beta: Array,
    noise: Array,
    sampler: str,
    cfg: SynthesisConfig,
    n_valid: Array | None = None,
) -> tuple[Float[Array, "n_frames D"], Int[Array, " n_frames"]]:
    """The generator of the module docstring as one ``lax.scan``: poses and examples.

    ``n_valid``: the first ``n_valid`` frames are the motion asked for, the rest a shape
    bucket's padding (the seam smoothing then ends at frame ``n_valid − 1``), so that they
    equal those of a scan of ``n_valid`` frames."""
    dim = fm.dim
    dt = win0.dtype
    std = db.pose_std.astype(dt)[:dim]
    succ_y = db.successors[:, :dim].astype(dt)
    succ_v = db.successors[:, dim:].astype(dt)
    rem = jnp.asarray(_remaining(db))
    vel = np.zeros(dim, dtype=bool)
    vel[np.asarray(velocity_channels(fm), dtype=np.int64)] = True
    vel_a = jnp.asarray(vel)
    search = _search_tree if sampler == "tree" else _search_exact
    chans = root_channels(fm)
    lock = cfg.foot_lock > 0 and len(db.feet) > 0 and chans is not None
    contact = db.foot_contact.astype(dt)

    def step(carry, k):
        win, cur, off, age, run, since, delta = carry
        k_s, k_n = jax.random.split(k)
        has_next = (cur >= 0) & (rem[jnp.maximum(cur, 0)] >= 1)
        do_search = (~has_next) | (since >= cfg.continuation)
        probe = db.scale_windows(win)
        idx = lax.cond(
            do_search,
            lambda: search(db, cfg, k_s, probe, beta, cur, run, rem).astype(jnp.int32),
            lambda: (cur + 1).astype(jnp.int32),
        )
        cont = has_next & (idx == cur + 1)
        last = win[-1, :dim]
        if cfg.velocity:
            start = last - (succ_y[idx] - succ_v[idx])  # current pose − example's current pose
        else:
            start = jnp.zeros((dim,), dt)
        off = jnp.where(cont, off, start)
        age = jnp.where(cont, age, 0) + 1
        if cfg.blend > 0:
            w = fade_weight(age.astype(dt), cfg.blend)
            w_pose = jnp.broadcast_to(w, (dim,))
            if cfg.root_blend >= 0 and cfg.root_blend != cfg.blend:
                w_root = (
                    fade_weight(age.astype(dt), cfg.root_blend)
                    if cfg.root_blend > 0
                    else jnp.zeros((), dt)
                )
                w_pose = jnp.where(vel_a, w_root, w_pose)
        else:
            w_pose = jnp.where(vel_a, 0.0, 1.0).astype(dt)
        pose = succ_y[idx] + w_pose * off
        if lock:
            assert chans is not None
            ex_last = succ_y[idx] - succ_v[idx]
            pose, delta = lock_root(
                fm, db.feet, chans, last, pose, ex_last, succ_y[idx],
                contact[idx], delta, cfg.foot_lock, cfg.lock_smoothing,
            )  # fmt: skip
        pose = pose + noise * std * jax.random.normal(k_n, (dim,), dt)
        psi = jnp.concatenate([pose, pose - last])
        win = jnp.concatenate([win[1:], psi[None]], axis=0)
        run = jnp.where(cont, run + 1, 1)
        since = jnp.where(do_search, 1, since + 1)
        return (win, idx, off, age, run, since, delta), (pose, idx, ~cont)

    init = (
        win0,
        jnp.int32(-1),
        jnp.zeros((dim,), dt),
        jnp.int32(0),
        jnp.int32(0),
        jnp.int32(0),
        jnp.zeros((3,), dt),
    )
    _, (poses, idx, seam) = lax.scan(step, init, jax.random.split(key, n_frames))
    if cfg.seam_smoothing > 0:
        poses = smooth_seams(poses, win0[-1, :dim], seam, cfg.seam_smoothing, ~vel, n_valid)
    return poses, idx


synthesize_jit = eqx.filter_jit(synthesize_scan)
