"""Per-frame Jacobians of joint positions by coloured Jacobian-vector products (design §6.5).

With the root's horizontal trajectory held (the channels ``root.d*``, whose running sums place
every later frame), a joint's world position at frame ``t`` depends on ``y_t`` only. A tangent
that moves one channel in every frame at once therefore gives that channel's Jacobian column
at every frame in one Jacobian-vector product of the whole decode and forward kinematics.
Channels that move disjoint joints (the left knee and the right elbow) share a tangent: the
joint positions it moves split by joint into the channels' columns (:func:`channel_colouring`),
so the 54 channels of the salsa skeleton need 21 products. The Gauss–Newton steps of
:mod:`~mtex_jax.edit._banded` gather from them only the rows they use.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float

from ..motion import FeatureMap, Skeleton
from ._fk import fk_positions

__all__ = [
    "Colouring",
    "FrameColumns",
    "channel_colouring",
    "frame_columns",
    "frame_jacobians",
    "kept_positions",
    "root_free_channels",
]


def kept_positions(
    fm: FeatureMap, sub: Skeleton, keep: tuple[int, ...], Y: Array, sp: Array, sh: Array
) -> Array:
    """World positions ``(T, K, 3)`` of the kept joints (decode + forward kinematics)."""
    m = fm.decode(Y, sp, sh)
    k = list(keep)
    lp = None if m.local_positions is None else m.local_positions[:, k]
    return fk_positions(sub, m.root_positions, m.rotations[:, k], lp)


class Colouring(eqx.Module):
    """Channels grouped so that one tangent carries several Jacobian columns (static).

    Two channels may share a tangent when no kept joint's position depends on both (say the
    left knee and the right elbow): the joint positions a tangent moves then split by joint
    into the channels' columns.

    Attributes:
        colour: ``(D,)`` the tangent of each channel.
        support: ``(D, K)`` 1 where the channel may move the kept joint (its descendants).
        n_colours: number of tangents.
    """

    colour: tuple[int, ...] = eqx.field(static=True)
    support: tuple[tuple[bool, ...], ...] = eqx.field(static=True)
    n_colours: int = eqx.field(static=True)


def channel_colouring(fm: FeatureMap, keep: tuple[int, ...]) -> Colouring:
    """Greedy colouring of the observation channels for :func:`frame_jacobians`.

    A channel named ``joint.*`` rotates that joint, so it moves the kept joints below it (and,
    to be safe, the joint itself); any other channel (``root.*``, or a name that is not a
    joint's) is taken to move every kept joint and gets a tangent of its own. Channels are
    placed, most far-reaching first, in the first colour none of whose channels moves a joint
    they move.

    Args:
        fm: the feature map (its skeleton and channel names).
        keep: the kept joints (skeleton indices, in the order of the positions' axis 1).

    Returns:
        :class:`Colouring`.
    """
    sk = fm.skeleton
    parents = list(sk.parents)
    K = len(keep)

    def below(j: int) -> np.ndarray:
        out = np.zeros(K, bool)
        for i, k in enumerate(keep):
            a = k
            while a >= 0 and a != j:
                a = parents[a]
            out[i] = a == j
        return out

    names = fm.active_names
    support = np.ones((len(names), K), bool)
    for c, n in enumerate(names):
        joint = n.split(".", 1)[0]
        if joint != "root" and joint in sk.names and sk.index(joint) != 0:
            support[c] = below(sk.index(joint))
    colour = np.zeros(len(names), np.int32)
    used: list[np.ndarray] = []
    for c in np.argsort(-support.sum(axis=1), kind="stable"):
        for i, u in enumerate(used):
            if not np.any(u & support[c]):
                colour[c] = i
                used[i] = u | support[c]
                break
        else:
            colour[c] = len(used)
            used.append(support[c].copy())
    return Colouring(
        colour=tuple(int(c) for c in colour),
        support=tuple(tuple(bool(b) for b in row) for row in support),
        n_colours=len(used),
    )


class FrameColumns(eqx.Module):
    """Joint positions and their per-frame Jacobian columns, as tangents (module notes).

    The Jacobian of joint ``k``'s position at frame ``t`` with respect to channel ``d`` is
    ``cols[colour[d], t, k] · support[d, k]``; :meth:`rows` gathers the rows a step needs
    without forming the whole ``(T, K, 3, D)`` array.

    Attributes:
        P: ``(T, K, 3)`` the positions.
        cols: ``(C, T, K, 3)`` one Jacobian-vector product per tangent.
        colour: ``(D,)`` the tangent of each channel (static).
        support: ``(D, K)`` 1 where channel ``d`` moves joint ``k`` and is free.
    """

    P: Float[Array, "T K 3"]
    cols: Float[Array, "C T K 3"]
    colour: tuple[int, ...] = eqx.field(static=True)
    support: Float[Array, "D K"]

    def rows(self, frame: Array, slot: Array) -> Array:
        """``(P, 3, D)`` the Jacobians of the positions of joints ``slot`` at ``frame``."""
        c = self.cols[:, frame, slot][np.asarray(self.colour)]  # (D, P, 3)
        return jnp.moveaxis(c * self.support[:, slot][..., None], 0, -1)

    def axis(self, a: int) -> Array:
        """``(T, K, D)`` the Jacobians of every joint's coordinate ``a``."""
        c = self.cols[..., a][np.asarray(self.colour)]  # (D, T, K)
        return jnp.moveaxis(c * self.support[:, None, :], 0, -1)


def frame_columns(fn, Y: Array, free_ch: Array, colouring: Colouring | None = None) -> FrameColumns:
    """``fn(Y)`` ``(T, K, 3)`` and its Jacobian-vector products, one per colour.

    Valid when frames do not interact through the free channels (module notes). With a
    ``colouring`` one product serves every channel of a colour; without, one per channel.
    The products run one after the other on one linearisation (``lax.map``): measured on
    a 1,280-frame edit, ``vmap`` over the 21 tangents took 1.7 times as long.
    """
    D = Y.shape[1]
    colour = tuple(range(D)) if colouring is None else colouring.colour
    n_col = D if colouring is None else colouring.n_colours
    groups = jnp.asarray(np.eye(n_col)[np.asarray(colour)].T, Y.dtype)  # (C, D)
    P, lin = jax.linearize(fn, Y)
    cols = lax.map(lambda e: lin(jnp.broadcast_to(e * free_ch, Y.shape)), groups)
    # without a colouring every channel may move every joint
    allowed = np.ones((D, P.shape[1])) if colouring is None else np.asarray(colouring.support)
    support = jnp.asarray(allowed, Y.dtype) * free_ch[:, None]
    return FrameColumns(P=P, cols=cols, colour=tuple(int(c) for c in colour), support=support)


def frame_jacobians(
    fn, Y: Array, free_ch: Array, colouring: Colouring | None = None
) -> tuple[Array, Array]:
    """``P = fn(Y)`` ``(T, K, 3)`` and its per-frame Jacobians ``(T, K, 3, D)`` with respect
    to the free channels (held channels' columns are zero).

    Valid when frames do not interact through the free channels (module notes). With a
    ``colouring`` one Jacobian-vector product serves every channel of a colour, and each
    channel's column is its colour's tangent restricted to the joints it moves
    (:func:`frame_columns`).
    """
    fc = frame_columns(fn, Y, free_ch, colouring)
    J = fc.cols[np.asarray(fc.colour)] * fc.support[:, None, :, None]  # (D, T, K, 3)
    return fc.P, jnp.moveaxis(J, 0, -1)


def root_free_channels(fm: FeatureMap) -> np.ndarray:
    """``(D,)`` 1 for every channel but the root's integrated ones (``root.d*``)."""
    return np.array([0.0 if n.startswith("root.d") else 1.0 for n in fm.active_names])
