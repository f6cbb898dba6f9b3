"""The camera of the trackers (IP §6, design §12.1): a pin-hole camera that projects world
points to pixels."""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float


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
