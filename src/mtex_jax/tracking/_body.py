"""The smoothers' coordinates of a tracked body: world root per frame, the texture's channels
otherwise (design §12.2).

A texture's observation vector ``y_t`` places the root by its displacement and yaw change
since frame ``t − 1``: running sums, so a change at one frame moves every later one. A tracker
needs every frame's joints to depend on that frame's variables alone (the banded solve's
condition). Its coordinates ``x_t`` therefore replace the three integrated channels
(``root.d{h0}``, ``root.d{h1}``, ``root.dyaw``) by the root's world position on the two ground
axes (metres) and its heading (radians), and keep every other channel of ``y_t`` (z-scored):
the root height, the root tilt and every joint rotation. :meth:`Body.observations` turns
``X`` back into ``Y`` (differences of the world root in the previous frame's heading frame),
:meth:`Body.coordinates` the other way.

The person's bones: each joint's offset from its parent is scaled by ``b_j`` (``1``: the
skeleton's own), and the whole figure is lifted by ``floor`` (the world height of the
skeleton's ground plane, ``0`` when the camera's extrinsics are known).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..motion import (
    FeatureMap,
    Skeleton,
    expmap_to_quat,
    forward_kinematics_arrays,
    ground_axes,
    quat_conj,
    quat_mul,
    quat_rotate,
    sub_skeleton,
    yaw_quat,
)

__all__ = ["Body"]


class Body(eqx.Module):
    """The coordinates of one tracked body (module notes).

    Attributes:
        feature_map: the texture's feature map.
        joints: the observed joints (skeleton indices, static).
        sub: the observed joints and their ancestors, as a skeleton (static).
        order: the skeleton index of each joint of ``sub`` (static).
        slots: the index in ``sub`` of each observed joint (static).
        root_cols: the columns of ``root.d{h0}``, ``root.d{h1}``, ``root.dyaw`` (static).
    """

    feature_map: FeatureMap
    joints: tuple[int, ...] = eqx.field(static=True)
    sub: Skeleton = eqx.field(static=True)
    order: tuple[int, ...] = eqx.field(static=True)
    slots: tuple[int, ...] = eqx.field(static=True)
    root_cols: tuple[int, int, int] = eqx.field(static=True)

    @classmethod
    def of(cls, fm: FeatureMap, joints: tuple[int, ...]) -> Body:
        """The body of a feature map and its observed joints."""
        sk = fm.skeleton
        _, h0, h1 = ground_axes(sk.up_axis)
        ax = "xyz"
        names = fm.active_names
        want = (f"root.d{ax[h0]}", f"root.d{ax[h1]}", "root.dyaw")
        missing = [n for n in want if n not in names]
        if missing:
            raise ValueError(
                f"track: the texture's feature map has no channel {missing[0]!r} (a constant "
                "root); a smoother needs the root's displacement and turn channels"
            )
        if names[:4] != (want[0], want[1], f"root.{ax[sk.up_axis]}", "root.dyaw"):
            raise ValueError("track: the feature map's first channels are not the root's")
        sub, order = sub_skeleton(sk, tuple(joints))
        slots = tuple(order.index(j) for j in joints)
        cols = (names.index(want[0]), names.index(want[1]), names.index(want[2]))
        return cls(
            feature_map=fm, joints=tuple(joints), sub=sub, order=order, slots=slots, root_cols=cols
        )

    @property
    def dim(self) -> int:
        return self.feature_map.dim

    def _raw(self, X: Array) -> Array:
        fm = self.feature_map
        act = np.asarray(fm.active, dtype=np.int64)
        off = jnp.asarray(fm.offset, X.dtype)
        sc = jnp.asarray(fm.scale, X.dtype)
        raw = jnp.broadcast_to(off, (X.shape[0], off.shape[0]))
        return raw.at[:, act].set(X * sc[act] + off[act])

    def bone_offsets(self, bone_scale: Float[Array, " J"] | None, dtype) -> Array:
        """``(J_sub, 3)`` the offsets of the sub-skeleton's joints, scaled."""
        off = jnp.asarray(np.asarray(self.sub.offsets), dtype)
        if bone_scale is None:
            return off
        return off * jnp.asarray(bone_scale, dtype)[np.asarray(self.order)][:, None]

    def positions(
        self,
        X: Float[Array, "T D"],
        bone_scale: Float[Array, " J"] | None = None,
        floor: Float[Array, ""] | float = 0.0,
    ) -> Float[Array, "T Ks 3"]:
        """World positions of the sub-skeleton's joints (every frame from its own row)."""
        fm = self.feature_map
        sk = fm.skeleton
        J = sk.n_joints
        up, h0, h1 = ground_axes(sk.up_axis)
        c0, c1, cy = self.root_cols
        raw = self._raw(X)
        T = X.shape[0]
        root = jnp.zeros((T, 3), X.dtype)
        root = root.at[:, h0].set(X[:, c0]).at[:, h1].set(X[:, c1]).at[:, up].set(raw[:, 2] + floor)
        e_up = jnp.zeros(3, X.dtype).at[up].set(1.0)
        q = expmap_to_quat(raw[:, 4 : 4 + 3 * J].reshape(T, J, 3))
        q = q.at[:, 0].set(quat_mul(yaw_quat(X[:, cy], e_up), q[:, 0]))
        order = np.asarray(self.order)
        lp = jnp.broadcast_to(self.bone_offsets(bone_scale, X.dtype), (T, len(order), 3))
        if fm.has_local_positions:
            own = raw[:, 4 + 3 * J :].reshape(T, J - 1, 3)
            own = jnp.concatenate([jnp.zeros((T, 1, 3), X.dtype), own], axis=1)[:, order]
            scale = 1.0 if bone_scale is None else jnp.asarray(bone_scale, X.dtype)[order][:, None]
            lp = own * scale
        return forward_kinematics_arrays(self.sub, root, q[:, order], lp)

    def observed(
        self,
        X: Float[Array, "T D"],
        bone_scale: Float[Array, " J"] | None = None,
        floor: Float[Array, ""] | float = 0.0,
    ) -> Float[Array, "T K 3"]:
        """World positions of the observed joints."""
        return self.positions(X, bone_scale, floor)[:, np.asarray(self.slots)]

    def observations(
        self,
        X: Float[Array, "T D"],
        prev_position: Float[Array, " 3"] | None = None,
        prev_heading: Float[Array, ""] | None = None,
    ) -> Float[Array, "T D"]:
        """The texture's observation vectors ``Y`` of ``X`` (module notes).

        Frame 0's displacement and turn are taken from ``prev_position`` and ``prev_heading``
        (the frame before), or, without them, repeat frame 1's (decoding ignores them).
        """
        fm = self.feature_map
        up, h0, h1 = ground_axes(fm.skeleton.up_axis)
        c0, c1, cy = self.root_cols
        dt = X.dtype
        act = np.asarray(fm.active, dtype=np.int64)
        off = jnp.asarray(fm.offset, dt)[act]
        sc = jnp.asarray(fm.scale, dt)[act]
        p = jnp.zeros((X.shape[0], 3), dt).at[:, h0].set(X[:, c0]).at[:, h1].set(X[:, c1])
        psi = X[:, cy]
        if prev_position is not None and prev_heading is not None:
            p0 = (
                jnp.zeros((1, 3), dt)
                .at[0, h0]
                .set(prev_position[h0])
                .at[0, h1]
                .set(prev_position[h1])
            )
            p_prev = jnp.concatenate([p0, p[:-1]])
            psi_prev = jnp.concatenate([jnp.asarray(prev_heading, dt)[None], psi[:-1]])
        else:
            p_prev = jnp.concatenate([p[:1] - (p[1:2] - p[:1]), p[:-1]]) if X.shape[0] > 1 else p
            psi_prev = (
                jnp.concatenate([psi[:1] - (psi[1:2] - psi[:1]), psi[:-1]])
                if X.shape[0] > 1
                else psi
            )
        e_up = jnp.zeros(3, dt).at[up].set(1.0)
        local = quat_rotate(quat_conj(yaw_quat(psi_prev, e_up)), p - p_prev)
        Y = X.at[:, c0].set((local[:, h0] - off[c0]) / sc[c0])
        Y = Y.at[:, c1].set((local[:, h1] - off[c1]) / sc[c1])
        return Y.at[:, cy].set((psi - psi_prev - off[cy]) / sc[cy])

    def coordinates(
        self, Y: Float[Array, "T D"], start_position: Array, start_heading: Array
    ) -> Float[Array, "T D"]:
        """``X`` of observation vectors ``Y`` whose frame 0 is at ``start_position`` and
        ``start_heading`` (:meth:`FeatureMap.decode`'s convention)."""
        fm = self.feature_map
        _, h0, h1 = ground_axes(fm.skeleton.up_axis)
        c0, c1, cy = self.root_cols
        m = fm.decode(Y, start_position, start_heading)
        dt = Y.dtype
        act = np.asarray(fm.active, dtype=np.int64)
        dyaw = Y[:, cy] * jnp.asarray(fm.scale, dt)[act[cy]] + jnp.asarray(fm.offset, dt)[act[cy]]
        psi = jnp.asarray(start_heading, dt) + jnp.concatenate(
            [jnp.zeros((1,), dt), jnp.cumsum(dyaw[1:])]
        )
        rp = jnp.asarray(m.root_positions, dt)
        return Y.at[:, c0].set(rp[:, h0]).at[:, c1].set(rp[:, h1]).at[:, cy].set(psi)
