"""The tracker's observation model (IP §6): a pinhole camera and the 2-D joint positions it sees
of a pose decoded from the model's pose vector."""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..motion import (
    FeatureMap,
    expmap_to_quat,
    ground_axes,
    quat_mul,
    quat_rotate,
    yaw_quat,
)


# --------------------------------------------------------------------------- camera
class Camera(eqx.Module):
    """Pin-hole camera: ``x_c = R x + t``, pixel ``= (f x_c[0] / x_c[2], f x_c[1] / x_c[2]) + c``.

    Camera axes: ``x_c[0]`` right, ``x_c[1]`` down, ``x_c[2]`` forward (viewing direction).

    Attributes:
        rotation: ``(3, 3)`` world-to-camera rotation.
        translation: ``(3,)``.
        focal: focal length in pixels.
        center: ``(2,)`` principal point in pixels.
    """

    rotation: Float[Array, "3 3"]
    translation: Float[Array, " 3"]
    focal: Float[Array, ""]
    center: Float[Array, " 2"]

    def __check_init__(self) -> None:
        for name, shape in (
            ("rotation", (3, 3)),
            ("translation", (3,)),
            ("focal", ()),
            ("center", (2,)),
        ):
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(f"Camera.{name} must have shape {shape}")

    @classmethod
    def look_at(
        cls,
        eye: Float[ArrayLike, " 3"] | Sequence[float],
        target: Float[ArrayLike, " 3"] | Sequence[float],
        up: Float[ArrayLike, " 3"] | Sequence[float],
        *,
        focal: float = 1000.0,
        center: tuple[float, float] = (500.0, 500.0),
    ) -> Camera:
        """Camera at ``eye`` looking at ``target`` with ``up`` pointing up in the image."""
        eye = np.asarray(eye, dtype=np.float64)
        fwd = np.asarray(target, dtype=np.float64) - eye
        if np.linalg.norm(fwd) <= 0:
            raise ValueError("Camera.look_at: eye and target coincide")
        fwd = fwd / np.linalg.norm(fwd)
        right = np.cross(fwd, np.asarray(up, dtype=np.float64))
        if np.linalg.norm(right) < 1e-9:
            raise ValueError("Camera.look_at: viewing direction parallel to up")
        right = right / np.linalg.norm(right)
        down = np.cross(fwd, right)
        rot = np.stack([right, down, fwd])
        return cls(
            rotation=jnp.asarray(rot),
            translation=jnp.asarray(-rot @ eye),
            focal=jnp.asarray(float(focal)),
            center=jnp.asarray(center, dtype=float),
        )

    def project(self, points: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 2"]:
        """Pixel coordinates of world points (any batch shape; pure JAX)."""
        x = jnp.asarray(points)
        xc = x @ self.rotation.astype(x.dtype).T + self.translation.astype(x.dtype)
        z = xc[..., 2:3]
        return self.focal.astype(x.dtype) * xc[..., :2] / z + self.center.astype(x.dtype)


# --------------------------------------------------------------------------- decoding
def decode_frame(
    fm: FeatureMap,
    y: Float[Array, " D"],
    position: Float[Array, " 3"],
    heading: Float[Array, ""],
) -> tuple[Array, Array, Array, Array | None]:
    """One step of :meth:`FeatureMap.decode`: frame ``t`` from ``y_t`` and frame ``t−1``'s root.

    The displacement of ``y_t`` (heading frame of ``t−1``) is rotated by ``heading`` and added
    to ``position``; the new heading is ``heading + Δyaw_t``; the height is absolute.

    Args:
        fm: the feature map.
        y: ``(D,)`` observation vector of frame ``t``.
        position: ``(3,)`` root position at ``t − 1``.
        heading: root yaw at ``t − 1`` (radians).

    Returns:
        root position ``(3,)``, heading ``()``, local rotations ``(J, 4)`` and local positions
        ``(J, 3)`` (``None`` unless the map has position channels) of frame ``t``.
    """
    dt = y.dtype
    act = np.asarray(fm.active, dtype=np.int64)
    off = jnp.asarray(fm.offset, dt)
    sc = jnp.asarray(fm.scale, dt)
    raw = off.at[act].set(y * sc[act] + off[act])
    sk = fm.skeleton
    j = sk.n_joints
    u, h0, h1 = ground_axes(sk.up_axis)
    up = jnp.zeros(3, dt).at[u].set(1.0)
    local = jnp.zeros(3, dt).at[h0].set(raw[0]).at[h1].set(raw[1])
    pos = position + quat_rotate(yaw_quat(heading, up), local)
    pos = pos.at[u].set(raw[2])
    new_heading = heading + raw[3]
    q = expmap_to_quat(raw[4 : 4 + 3 * j].reshape(j, 3))
    q = q.at[0].set(quat_mul(yaw_quat(new_heading, up), q[0]))
    lp = None
    if fm.has_local_positions:
        lp = jnp.concatenate([pos[None], raw[4 + 3 * j :].reshape(j - 1, 3)], axis=0)
    return pos, new_heading, q, lp


def default_joints(fm: FeatureMap) -> tuple[int, ...]:
    """The root and every joint with a moving rotation channel (the observed joints)."""
    moving = {name.rsplit(".", 1)[0] for name in fm.active_names}
    sk = fm.skeleton
    return tuple(i for i in range(sk.n_joints) if i == 0 or sk.names[i] in moving)
