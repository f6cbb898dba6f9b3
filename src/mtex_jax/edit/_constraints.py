"""Edit constraints as fixed-shape arrays (so edits of equal size share one compilation and
batch with ``vmap``), and the weights of the objective.

Which constraints are exact and which are penalties:

* **whole pose at a frame** — exact: the frame's observation vector is not a variable, it is
  replaced by the given pose (a linear equality on the variables is eliminated, not weighted);
* **joint world position at a frame** — a penalty ``w_p ‖p_j(m) − (x + s)‖`` whose target is
  shifted by the method of multipliers (``s ← s + (x − p_j(m))`` between rounds), so it is met
  to solver precision where it is reachable, without the ill-conditioning of a huge weight;
  an unreachable target (a hand 5 m from the shoulder) stays a finite least-squares compromise
  and is reported as not met. Joint positions are nonlinear in ``Y`` (decode + forward
  kinematics), so elimination is not available;
* **foot planted over a frame range** — a penalty on the foot's horizontal displacement per
  step and on its height minus the plant height (both nonlinear in ``Y``);
* **the floor** — a one-sided penalty ``w_f max(0, h_floor − h_j)`` on every joint and frame
  (an inequality: only violations cost anything);
* **joint velocity at a frame** — a penalty on ``(p_j(m+1) − p_j(m)) f − v``.

Penalties are soft by design: with a weight of ``10³`` per metre a 1 mm error costs as much as
one standard deviation of a texton's innovation, so they hold to millimetres while the solver
stays well conditioned; :class:`~mtex_jax.edit.EditResult` reports every constraint's error.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..core import as_array
from ..motion import Skeleton

__all__ = ["Constraints", "EditWeights", "make_constraints"]


class EditWeights(eqx.Module):
    """Weights of the edit objective (array leaves: changing them does not recompile).

    Attributes:
        prior: multiplies the texture prior's whitened residuals.
        anchor: on the change of the observation vectors (z-scored units), every frame: a
            diagonal term added to the prior's curvature (``0`` turns it off).
        root: extra anchor on the channels the root trajectory integrates (``root.d*``: the
            heading-frame displacement and the yaw change): the world trajectory is their
            running sum, so a change there would shift every later frame; a large weight keeps
            edits local in time (added in quadrature to ``anchor``).
        smooth: on the second difference of the change, ``‖Δ_t − 2Δ_{t−1} + Δ_{t−2}‖``
            (z-scored units). The textons model the part of ``y`` outside their subspace as
            white noise, so the prior alone prices a one-frame spike there as cheaply as a
            smooth change; this term makes edits smooth in time.
        position: per metre, joint world position targets.
        velocity: per m/s, joint velocity targets.
        plant: per metre, planted-foot horizontal steps and height.
        floor: per metre, depth of any joint below the floor.
    """

    prior: Float[Array, ""] = eqx.field(default=1.0, converter=jnp.asarray)
    anchor: Float[Array, ""] = eqx.field(default=5.0, converter=jnp.asarray)
    root: Float[Array, ""] = eqx.field(default=1e4, converter=jnp.asarray)
    smooth: Float[Array, ""] = eqx.field(default=10.0, converter=jnp.asarray)
    position: Float[Array, ""] = eqx.field(default=1e3, converter=jnp.asarray)
    velocity: Float[Array, ""] = eqx.field(default=10.0, converter=jnp.asarray)
    plant: Float[Array, ""] = eqx.field(default=1e3, converter=jnp.asarray)
    floor: Float[Array, ""] = eqx.field(default=1e3, converter=jnp.asarray)

    def __check_init__(self) -> None:
        for name in ("prior", "anchor", "root", "smooth", "position", "velocity", "plant", "floor"):
            v = np.asarray(getattr(self, name))
            if v.shape != () or not np.isfinite(v) or v < 0:
                raise ValueError(f"EditWeights.{name} must be a finite scalar >= 0, got {v}")


class Constraints(eqx.Module):
    """The constraints of one edit (or of a batch, with a leading axis on every array).

    Attributes:
        joints: ``(P,)`` joint of each position target; frames: ``(P,)``; targets: ``(P, 3)``
            world positions (metres); active: ``(P,)`` (padding slots are inactive).
        vel_joints, vel_frames: ``(V,)``; vel_targets: ``(V, 3)`` m/s; vel_active: ``(V,)``.
        pose_mask: ``(T,)`` frames held exactly; poses: ``(T, D)`` their observation vectors.
        plant: ``(T − 1, F)`` steps ``t → t+1`` during which foot ``f`` is planted;
            plant_height: ``(T − 1, F)`` its height there (NaN: the original's mean over the
            run, filled in by :func:`~mtex_jax.edit.edit`).
        floor: scalar floor height (up axis); floor_on: whether the floor applies.
        lift: ``(T, F)`` lowest allowed height of each foot per frame (``-inf``: none), a
            one-sided penalty like the floor (keeps swing feet off the ground when cleaning).
        feet: the foot joints of the plant columns (static).
    """

    joints: Int[Array, " P"]
    frames: Int[Array, " P"]
    targets: Float[Array, "P 3"]
    active: Bool[Array, " P"]
    vel_joints: Int[Array, " V"]
    vel_frames: Int[Array, " V"]
    vel_targets: Float[Array, "V 3"]
    vel_active: Bool[Array, " V"]
    pose_mask: Bool[Array, " T"]
    poses: Float[Array, "T D"]
    plant: Bool[Array, "T1 F"]
    plant_height: Float[Array, "T1 F"]
    floor: Float[Array, ""]
    floor_on: Bool[Array, ""]
    lift: Float[Array, "T F"]
    feet: tuple[int, ...] = eqx.field(static=True)

    def __check_init__(self) -> None:
        p = np.shape(self.joints)[-1:]
        for name in ("frames", "active"):
            if np.shape(getattr(self, name))[-1:] != p:
                raise ValueError(f"Constraints.{name} must have as many entries as joints")
        if np.shape(self.targets)[-2:] != (*p, 3):
            raise ValueError("Constraints.targets must have shape (P, 3)")
        if np.shape(self.vel_targets)[-1:] != (3,):
            raise ValueError("Constraints.vel_targets must have shape (V, 3)")
        t = np.shape(self.pose_mask)[-1]
        if np.shape(self.poses)[-2] != t or np.shape(self.plant)[-2] != max(t - 1, 0):
            raise ValueError("Constraints: pose_mask, poses and plant disagree on T")
        if np.shape(self.plant)[-1] != len(self.feet):
            raise ValueError("Constraints.plant must have one column per foot")


def _joint(skeleton: Skeleton, j: Any, where: str) -> int:
    if isinstance(j, str):
        try:
            return skeleton.index(j)
        except (KeyError, ValueError):
            raise ValueError(f"{where}: unknown joint {j!r}") from None
    if isinstance(j, bool) or not isinstance(j, int | np.integer):
        raise TypeError(f"{where}: a joint is a name or an index, got {j!r}")
    if not 0 <= int(j) < skeleton.n_joints:
        raise ValueError(f"{where}: joint index {j} outside 0..{skeleton.n_joints - 1}")
    return int(j)


def _frame(f: Any, n: int, where: str, last: int = 0) -> int:
    if isinstance(f, bool) or not isinstance(f, int | np.integer):
        raise TypeError(f"{where}: a frame is an integer, got {f!r}")
    if not 0 <= int(f) < n - last:
        raise ValueError(f"{where}: frame {f} outside 0..{n - 1 - last}")
    return int(f)


def _vec3(v: Any, where: str) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{where}: expected 3 numbers, got {v!r}") from None
    if a.shape != (3,) or not np.isfinite(a).all():
        raise ValueError(f"{where}: expected 3 finite numbers, got {v!r}")
    return a


def make_constraints(
    skeleton: Skeleton,
    n_frames: int,
    dim: int,
    *,
    positions: Sequence[tuple[Any, int, Any]] = (),
    velocities: Sequence[tuple[Any, int, Any]] = (),
    poses: Sequence[tuple[int, Any]] = (),
    plants: Sequence[tuple[Any, int, int, float | None]] = (),
    floor: float | None = None,
    feet: Sequence[Any] | None = None,
    lift: Any = None,
    pad_to: int | None = None,
) -> Constraints:
    """Constraints of one edit, checked and packed into arrays.

    Args:
        skeleton: the figure (joint names are resolved here).
        n_frames: ``T`` of the motion to edit.
        dim: ``D`` of its observation vectors.
        positions: ``(joint, frame, (x, y, z))``: the joint's world position at the frame.
        velocities: ``(joint, frame, (vx, vy, vz))``: ``(p(m+1) − p(m))·fps`` in m/s.
        poses: ``(frame, y)``: the frame's whole observation vector ``y (D,)``, held exactly.
        plants: ``(foot, first, last, height)``: the foot does not move horizontally from
            frame ``first`` to ``last`` (inclusive) and stays at ``height`` (``None``: its mean
            height there in the original motion).
        floor: no joint below this height (``None``: no floor).
        feet: the joints that may be planted (default: those named in ``plants``).
        lift: ``(T, F)`` lowest allowed height per frame of each foot of ``feet`` (``-inf``
            where free; default free).
        pad_to: pad the position targets to this many slots (equal shapes for ``vmap``).

    Returns:
        :class:`Constraints`.
    """
    where = "make_constraints"
    T = int(n_frames)
    if T < 3:
        raise ValueError(f"{where}: n_frames must be >= 3, got {n_frames}")
    pj, pf, pt = [], [], []
    for item in positions:
        j, f, x = item
        pj.append(_joint(skeleton, j, f"{where}: positions"))
        pf.append(_frame(f, T, f"{where}: positions"))
        pt.append(_vec3(x, f"{where}: positions target"))
    n_pos = len(pj) if pad_to is None else int(pad_to)
    if n_pos < len(pj):
        raise ValueError(f"{where}: pad_to={pad_to} is smaller than {len(pj)} position targets")
    pad = n_pos - len(pj)
    vj, vf, vt = [], [], []
    for j, f, v in velocities:
        vj.append(_joint(skeleton, j, f"{where}: velocities"))
        vf.append(_frame(f, T, f"{where}: velocities", last=1))
        vt.append(_vec3(v, f"{where}: velocities target"))
    mask = np.zeros(T, bool)
    pose_arr = np.zeros((T, dim))
    for f, y in poses:
        f = _frame(f, T, f"{where}: poses")
        ya = np.asarray(y, dtype=np.float64)
        if ya.shape != (dim,) or not np.isfinite(ya).all():
            raise ValueError(f"{where}: a pose must be {dim} finite numbers, got shape {ya.shape}")
        mask[f], pose_arr[f] = True, ya
    foot_idx = [_joint(skeleton, j, f"{where}: feet") for j in (feet or ())]
    for foot, *_ in plants:
        j = _joint(skeleton, foot, f"{where}: plants")
        if j not in foot_idx:
            foot_idx.append(j)
    plant = np.zeros((T - 1, len(foot_idx)), bool)
    height = np.full((T - 1, len(foot_idx)), np.nan)
    for foot, first, last, h in plants:
        c = foot_idx.index(_joint(skeleton, foot, f"{where}: plants"))
        a, b = _frame(first, T, f"{where}: plants"), _frame(last, T, f"{where}: plants")
        if b <= a:
            raise ValueError(f"{where}: a plant needs last > first, got {first}..{last}")
        plant[a:b, c] = True
        height[a:b, c] = np.nan if h is None else float(h)
    lift_arr = np.full((T, len(foot_idx)), -np.inf)
    if lift is not None:
        la = np.asarray(lift, dtype=np.float64)
        if la.shape != lift_arr.shape or np.isnan(la).any() or (la == np.inf).any():
            raise ValueError(
                f"{where}: lift must be {lift_arr.shape} heights or -inf, got {la.shape}"
            )
        lift_arr = la
    if floor is not None and not np.isfinite(float(floor)):
        raise ValueError(f"{where}: floor must be finite, got {floor}")
    # the per-frame arrays with as_array: jnp.asarray of a NumPy array compiles a copy per length
    return Constraints(
        joints=jnp.asarray(np.array(pj + [0] * pad, np.int32)),
        frames=jnp.asarray(np.array(pf + [0] * pad, np.int32)),
        targets=jnp.asarray(np.array(pt + [np.zeros(3)] * pad).reshape(n_pos, 3)),
        active=jnp.asarray(np.array([True] * len(pj) + [False] * pad, bool)),
        vel_joints=jnp.asarray(np.array(vj, np.int32).reshape(-1)),
        vel_frames=jnp.asarray(np.array(vf, np.int32).reshape(-1)),
        vel_targets=jnp.asarray(np.array(vt).reshape(len(vj), 3)),
        vel_active=jnp.ones(len(vj), bool),
        pose_mask=as_array(mask),
        poses=as_array(pose_arr),
        plant=as_array(plant),
        plant_height=as_array(height),
        floor=jnp.asarray(0.0 if floor is None else float(floor)),
        floor_on=jnp.asarray(floor is not None),
        lift=as_array(lift_arr),
        feet=tuple(foot_idx),
    )
