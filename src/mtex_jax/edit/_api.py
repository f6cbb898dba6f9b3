"""The public verbs: :func:`edit` (one motion) and :func:`edit_many` (a ``vmap`` batch)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from ..motion import FeatureMap, Motion
from ..texture import MotionTexture, Synthesis
from ._bucket import solve_gn_bucketed
from ._constraints import Constraints, EditWeights
from ._gn import solve_edit_gn
from ._prior import FrameSegments, WhitenedTextons, frame_segments
from ._solve import EditResult, bfgs_polish, problem, solve_edit

__all__ = ["edit", "edit_many", "edit_residuals", "segments_of"]

_solve_jit = eqx.filter_jit(solve_edit)
_bfgs_jit = eqx.filter_jit(bfgs_polish)


@eqx.filter_jit
def _solve_many(fm, tx, seg, Y0, sp, sh, cons, w, *, solver: str, mesh: Any = None, **kw):
    # vmap over the motions (the forward kinematics of ._fk batch without the dot_general
    # that XLA's HLO verifier rejected under vmap); with a mesh, each device runs the vmap of
    # its share of the motions (shard_map), the shared arguments replicated
    core = solve_edit_gn if solver == "gn" else solve_edit
    shared, static = eqx.partition((fm, tx, w), eqx.is_array)

    def batch(shared, s, y, a, b, c):
        f, t, ww = eqx.combine(shared, static)
        return jax.vmap(lambda s, y, a, b, c: core(f, t, s, y, a, b, c, ww, **kw))(s, y, a, b, c)

    if mesh is None:
        return batch(shared, seg, Y0, sp, sh, cons)
    rep, split = PartitionSpec(), PartitionSpec(mesh.axis_names[0])
    sharded = jax.shard_map(
        batch,
        mesh=mesh,
        in_specs=(rep, split, split, split, split, split),
        out_specs=split,
        check_vma=False,
    )
    return sharded(shared, seg, Y0, sp, sh, cons)


def _batch_mesh(devices: Sequence[Any] | None, n: int) -> Mesh | None:
    """The mesh that splits a batch of ``n`` motions over ``devices`` (``None``: one device,
    or a batch of one)."""
    devs = list(jax.devices() if devices is None else devices)
    if not devs:
        raise ValueError("edit_many: devices is empty")
    bad = [d for d in devs if not isinstance(d, jax.Device)]
    if bad:
        raise TypeError(f"edit_many: devices must be JAX devices, got {type(bad[0]).__name__}")
    if len(devs) == 1 or n == 1:
        return None
    return Mesh(np.asarray(devs[: min(len(devs), n)]), ("motions",))


def _solver(solver: str, cons: Constraints) -> str:
    if solver not in ("auto", "gn", "lm"):
        raise ValueError(f"solver must be 'auto', 'gn' or 'lm', got {solver!r}")
    has_vel = bool(np.shape(cons.vel_joints)[-1])
    if solver == "gn" and has_vel:
        raise ValueError("solver='gn' does not take velocity targets (use 'lm' or 'auto')")
    return ("lm" if has_vel else "gn") if solver == "auto" else solver


def feature_map_of(texture: Any) -> FeatureMap:
    if not isinstance(texture, MotionTexture):
        raise TypeError(f"texture must be a MotionTexture, got {type(texture).__name__}")
    if texture.feature_map is None:
        raise ValueError("texture: learned from arrays (no feature map); editing needs one")
    return texture.feature_map


def segments_of(texture: MotionTexture, motion: Motion | Synthesis | Any) -> FrameSegments:
    """Per-frame texton labels of a motion: carried from a :class:`Synthesis` (its path and
    lengths), otherwise the texture's optimal segmentation (semi-Markov Viterbi)."""
    if isinstance(motion, Synthesis):
        return frame_segments(np.asarray(motion.lengths), np.asarray(motion.path))
    seg = texture.segment(motion)
    rows = seg.to_list()
    if not rows:
        raise ValueError("segments_of: the texture found no segmentation of this motion")
    return frame_segments(np.array([r[1] for r in rows]), np.array([r[2] for r in rows]))


def observations_of(
    texture: MotionTexture, motion: Any, start_position: Any, start_heading: Any
) -> tuple[jax.Array, jax.Array, jax.Array]:
    fm = feature_map_of(texture)
    if isinstance(motion, Synthesis):
        if motion.motion is not None and start_position is None and start_heading is None:
            sp, sh = fm.start_of(motion.motion)
        else:
            sp, sh = start_position, start_heading
        Y = jnp.asarray(motion.Y)
    elif isinstance(motion, Motion):
        Y = fm.encode(motion)
        sp, sh = fm.start_of(motion) if start_position is None else (start_position, start_heading)
    else:
        Y = texture.observations(motion)
        sp, sh = start_position, start_heading
    if not jnp.issubdtype(Y.dtype, jnp.floating):
        Y = Y.astype(jnp.result_type(float))
    if not np.isfinite(np.asarray(Y)).all():  # on the host: no program per length
        raise ValueError("motion: observation vectors contain NaN or inf")
    sp = jnp.zeros(3, Y.dtype) if sp is None else jnp.asarray(sp, Y.dtype)
    sh = jnp.zeros((), Y.dtype) if sh is None else jnp.asarray(sh, Y.dtype)
    if sp.shape != (3,) or sh.shape != ():
        raise ValueError("start_position must have shape (3,) and start_heading be a scalar")
    return Y, sp, sh


def check_constraints(cons: Any, Y: jax.Array, fm: FeatureMap) -> Constraints:
    if not isinstance(cons, Constraints):
        raise TypeError(f"constraints must be made by make_constraints, got {type(cons).__name__}")
    T, D = Y.shape
    if np.shape(cons.poses) != (T, D):
        raise ValueError(
            f"constraints were made for {np.shape(cons.poses)} frames x dims, the motion is "
            f"({T}, {D}); make them with n_frames={T}, dim={D}"
        )
    J = fm.skeleton.n_joints
    for name, idx in (("joints", cons.joints), ("vel_joints", cons.vel_joints)):
        if np.size(idx) and (np.min(idx) < 0 or np.max(idx) >= J):
            raise ValueError(f"constraints.{name}: joint index outside the skeleton")
    return jax.tree.map(
        lambda a: a.astype(Y.dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, cons
    )


def kept_channels(
    cons: Constraints, fm: FeatureMap, floor_joints: Sequence[int] | None
) -> tuple[int, ...]:
    """Joints whose positions the solve computes: constrained joints, feet, floor joints
    (default: every joint with a moving rotation channel)."""
    js = {int(j) for j in np.asarray(cons.joints).reshape(-1)}
    js |= {int(j) for j in np.asarray(cons.vel_joints).reshape(-1)}
    js |= set(cons.feet)
    if floor_joints is None:
        names = fm.active_names
        sk = fm.skeleton
        js |= {
            j for j in range(1, sk.n_joints) if any(n.startswith(f"{sk.names[j]}.") for n in names)
        }
    else:
        js |= {int(j) for j in floor_joints}
    return tuple(sorted(js))


def edit(
    texture: MotionTexture,
    motion: Motion | Synthesis | Any,
    constraints: Constraints,
    *,
    weights: EditWeights | None = None,
    segments: FrameSegments | None = None,
    start_position: Any = None,
    start_heading: Any = None,
    floor_joints: Sequence[int] | None = None,
    relative: bool = True,
    rounds: int = 3,
    max_steps: int = 60,
    fallback: bool = True,
    cg_steps: int = 100,
    cg_rtol: float = 1e-6,
    solver: str = "auto",
) -> EditResult:
    """Edit a motion: meet the constraints, otherwise stay statistically like the texture.

    Minimises ``½‖prior‖² + ½ Σ ‖constraint residuals‖²`` over the observation vectors
    ``Y (T, D)`` (see :mod:`mtex_jax.edit` for the objective and which constraints are exact).
    Two solvers: ``"gn"``, Gauss–Newton with the banded normal equations (root trajectory
    held; :mod:`mtex_jax.edit._gn`), fast and the default; ``"lm"``, Levenberg–Marquardt
    (optimistix) in whitened variables with conjugate gradients, BFGS run from where it
    stopped if it did not converge (``fallback``); ``"auto"`` takes ``"gn"`` unless there are
    velocity targets. The Gauss–Newton solve is jit-compiled once per bucket of lengths
    (:func:`~mtex_jax.edit._bucket.edit_length`), Levenberg–Marquardt once per shape.

    Args:
        texture: the motion texture (its textons are the prior; its feature map decodes).
        motion: a :class:`Synthesis` (its texton segments are used), a :class:`Motion`
            (segmented by the texture) or observation vectors ``(T, D)``.
        constraints: from :func:`make_constraints` for this motion's ``T`` and ``D``.
        weights: :class:`EditWeights` (default weights when ``None``).
        segments: per-frame segmentation (default: :func:`segments_of`).
        start_position: root position ``(3,)`` of frame 0 (default: the motion's own; the
            origin for raw observation vectors).
        start_heading: root yaw of frame 0 (default: the motion's own; 0 for raw observation
            vectors).
        floor_joints: joints the floor applies to (default: every joint with a moving
            rotation channel, and the feet).
        relative: prior on the change (default) or the plain negative log-likelihood.
        rounds: multiplier rounds for position targets.
        max_steps: Levenberg–Marquardt steps per round.
        fallback: run L-BFGS if Levenberg–Marquardt did not converge (not for float32
            variables while x64 is enabled, where optimistix 0.1.0 mixes dtypes).
        cg_steps: conjugate-gradient iterations of each Levenberg–Marquardt step.
        cg_rtol: conjugate-gradient relative tolerance of each Levenberg–Marquardt step.
        solver: ``"auto"``, ``"gn"`` or ``"lm"`` (above); ``max_steps`` applies to either.

    Returns:
        :class:`EditResult` (check ``converged`` and ``met``; ``report()`` says it in words).
    """
    fm = feature_map_of(texture)
    Y, sp, sh = observations_of(texture, motion, start_position, start_heading)
    cons = check_constraints(constraints, Y, fm)
    seg = segments if segments is not None else segments_of(texture, motion)
    if seg.n_frames != Y.shape[0]:
        raise ValueError(f"segments cover {seg.n_frames} frames, the motion has {Y.shape[0]}")
    w = EditWeights() if weights is None else weights
    if not isinstance(w, EditWeights):
        raise TypeError(f"weights must be EditWeights, got {type(w).__name__}")
    for name, v, lo in (("rounds", rounds, 1), ("max_steps", max_steps, 1)):
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
    tx = WhitenedTextons.of(texture.textons, Y.dtype)
    keep = kept_channels(cons, fm, floor_joints)
    if _solver(solver, cons) == "gn":
        if not relative:
            raise ValueError("relative=False needs solver='lm'")
        return solve_gn_bucketed(
            fm, tx, seg, Y, sp, sh, cons, w, keep=keep, rounds=rounds, max_steps=max_steps
        )
    kw: dict[str, Any] = dict(keep=keep, relative=bool(relative))
    res = _solve_jit(
        fm,
        tx,
        seg,
        Y,
        sp,
        sh,
        cons,
        w,
        rounds=rounds,
        max_steps=max_steps,
        cg_steps=cg_steps,
        cg_rtol=cg_rtol,
        **kw,
    )
    # (optimistix 0.1.0's L-BFGS also keeps a default-float carry: no fallback for float32
    # variables while x64 is enabled)
    default_float = jnp.dtype(Y.dtype) == jnp.dtype(jnp.result_type(float))
    if fallback and default_float and not bool(res.converged):
        res = _bfgs_jit(fm, tx, seg, Y, sp, sh, cons, w, res, **kw)
    return res


def edit_many(
    texture: MotionTexture,
    motions: Sequence[Any],
    constraints: Sequence[Constraints],
    *,
    weights: EditWeights | None = None,
    segments: Sequence[FrameSegments] | None = None,
    floor_joints: Sequence[int] | None = None,
    relative: bool = True,
    rounds: int = 3,
    max_steps: int = 60,
    solver: str = "auto",
    devices: Sequence[Any] | None = None,
) -> EditResult:
    """Edit several motions of equal length in one jit-compiled program (``vmap``).

    The motions must have the same number of frames and their constraints the same shapes
    (use ``pad_to`` of :func:`make_constraints`; plant feet in the same order). No BFGS
    fallback: check ``converged`` per motion (and :func:`edit` those that did not). The
    solver is chosen as by :func:`edit`; under ``vmap`` a Gauss–Newton loop runs until every
    motion has stopped (each keeps its own result and ``converged``).

    With several devices a Gauss–Newton batch is split between them (``shard_map``: each device
    runs the ``vmap`` of its share, padded with copies of the first motion to a multiple of the
    device count); a Levenberg–Marquardt batch (velocity targets) runs as one ``vmap``. One
    edit's solve is a chain of small dependent kernels that keeps a CPU's cores only partly
    busy, so on a CPU give JAX one device per core before it starts
    (``jax.config.update("jax_num_cpu_devices", os.cpu_count())``, or ``XLA_FLAGS=
    --xla_force_host_platform_device_count=N``); the library never sets this itself.

    Args:
        texture: the motion texture.
        motions: the motions to edit.
        constraints: one constraints object per motion.
        weights: as for :func:`edit`.
        segments: as for :func:`edit`.
        floor_joints: as for :func:`edit`.
        relative: as for :func:`edit`.
        rounds: as for :func:`edit`.
        max_steps: as for :func:`edit`.
        solver: as for :func:`edit`.
        devices: the devices to split the batch over (default: ``jax.devices()``; one
            device: a plain ``vmap``).

    Returns:
        :class:`EditResult` with a leading batch axis on every field (on the default device).
    """
    fm = feature_map_of(texture)
    if len(motions) == 0 or len(motions) != len(constraints):
        raise ValueError("edit_many: give one constraints object per motion (at least one)")
    obs = [observations_of(texture, m, None, None) for m in motions]
    if len({o[0].shape for o in obs}) != 1:
        raise ValueError("edit_many: every motion must have the same (T, D)")
    cons = [check_constraints(c, o[0], fm) for c, o in zip(constraints, obs, strict=True)]
    if len({c.feet for c in cons}) != 1:
        raise ValueError("edit_many: every motion's constraints must plant the same feet")
    segs = list(segments) if segments is not None else [segments_of(texture, m) for m in motions]
    stack = lambda xs: jax.tree.map(lambda *a: jnp.stack(a), *xs)
    try:
        C = stack(cons)
    except ValueError:
        raise ValueError("edit_many: the constraints differ in shape (use pad_to)") from None
    Y = jnp.stack([o[0] for o in obs])
    tx = WhitenedTextons.of(texture.textons, Y.dtype)
    keep = tuple(sorted(set().union(*(kept_channels(c, fm, floor_joints) for c in cons))))
    w = EditWeights() if weights is None else weights
    which = _solver(solver, C)
    kw: dict[str, Any] = dict(keep=keep, rounds=rounds, max_steps=max_steps)
    if which == "lm":
        kw["relative"] = bool(relative)
    elif not relative:
        raise ValueError("relative=False needs solver='lm'")
    args = (stack(segs), Y, jnp.stack([o[1] for o in obs]), jnp.stack([o[2] for o in obs]), C)
    n = len(motions)
    # Levenberg–Marquardt: one vmap (equinox's closure conversion inside optimistix rejects
    # the per-device types of shard_map: 'called with different dynamic arguments')
    mesh = _batch_mesh(devices, n) if which == "gn" else None
    if mesh is not None:
        pad = -n % mesh.devices.size
        args = jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[:1], pad, 0)]), args)
    out = _solve_many(
        fm, tx, args[0], args[1], args[2], args[3], args[4], w, solver=which, mesh=mesh, **kw
    )
    if mesh is None:
        return out
    first = mesh.devices.flat[0]
    return jax.tree.map(lambda a: jax.device_put(a[:n], first), out)


def edit_residuals(
    texture: MotionTexture,
    motion: Motion | Synthesis | Any,
    constraints: Constraints,
    *,
    weights: EditWeights | None = None,
    segments: FrameSegments | None = None,
    start_position: Any = None,
    start_heading: Any = None,
    floor_joints: Sequence[int] | None = None,
    relative: bool = True,
) -> tuple[Any, jax.Array, Any]:
    """The residual form :func:`edit` solves, for other solvers and for checking gradients.

    Returns:
        ``(fn, u0, to_Y)``: ``fn(u)`` is the tuple of residual arrays (whitened prior, position,
        velocity, plant slide, plant height, floor) of the whitened variables ``u (T, D)``;
        ``u0`` is zero (the start of the solve); ``to_Y(u)`` the observation vectors.
    """
    fm = feature_map_of(texture)
    Y, sp, sh = observations_of(texture, motion, start_position, start_heading)
    cons = check_constraints(constraints, Y, fm)
    seg = segments if segments is not None else segments_of(texture, motion)
    w = EditWeights() if weights is None else weights
    tx = WhitenedTextons.of(texture.textons, Y.dtype)
    prob = problem(
        fm, tx, seg, Y, sp, sh, cons, w, bool(relative), kept_channels(cons, fm, floor_joints)
    )
    zero = jnp.zeros_like(cons.targets)
    return (lambda u: prob.residuals(u, zero)), jnp.zeros_like(Y), prob.edited
