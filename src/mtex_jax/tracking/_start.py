"""Where a smoother starts without a known initial state: a per-frame rigid fit (design §12.3).

The texture's mean pose (every z-scored channel 0) is placed at every frame under ``H``
headings ``θ_j = 2πj/H``. For each frame and heading, the root's translation ``p`` that best
reprojects the pose onto the observations is found by Gauss–Newton on the robust reprojection
cost (IRLS, from the depth at which the pose's spread matches the pixels' spread); left and
right keypoints tell the headings apart. The headings over frames are then chosen jointly by
Viterbi, with a Gaussian cost on each frame's turn, and unwrapped; frames with no observed
joint take their neighbours' translation. The result is the smoother's first estimate ``X``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..motion import ground_axes
from ._body import Body
from ._camera import Camera
from ._reprojection import PixelLoss, project

__all__ = ["rigid_start"]


def _translations(
    body: Body,
    X_pose: Array,
    camera: Camera,
    obs: Array,
    conf: Array,
    sigma: Array,
    loss: PixelLoss,
    n_headings: int,
    up_sd: Array,
    bone_scale: Array | None = None,
    steps: int = 10,
) -> tuple[Array, Array]:
    """``(p (T, H, 3), cost (T, H))``: the best root translation and its cost per frame and
    heading."""
    dt = obs.dtype
    D = X_pose.shape[0]
    _, _, cy = body.root_cols
    up = body.feature_map.skeleton.up_axis
    theta = jnp.arange(n_headings, dtype=dt) * (2 * np.pi / n_headings)
    Xh = jnp.broadcast_to(X_pose, (n_headings, D)).at[:, cy].set(theta)
    c0, c1, _ = body.root_cols
    Xh = Xh.at[:, c0].set(0.0).at[:, c1].set(0.0)
    poses = body.observed(Xh, bone_scale)  # (H, K, 3)
    R = camera.rotation.astype(dt)
    centre = -R.T @ camera.translation.astype(dt)
    f = camera.focal.astype(dt)
    e_up = jnp.zeros(3, dt).at[up].set(1.0)

    def one(o: Array, c: Array, pose: Array) -> tuple[Array, Array]:
        cw = c / jnp.maximum(jnp.sum(c), 1e-12)
        o_bar = cw @ o
        s2 = jnp.sqrt(jnp.sum(cw * jnp.sum((o - o_bar) ** 2, axis=-1)) + 1e-12)
        x_bar = cw @ pose
        s3 = jnp.sqrt(jnp.sum(cw * jnp.sum((pose - x_bar) ** 2, axis=-1)) + 1e-12)
        depth = jnp.clip(f * s3 / s2, 0.3, 1e3)
        ray = R.T @ jnp.concatenate([(o_bar - camera.center.astype(dt)) / f, jnp.ones(1, dt)])
        p0 = centre + depth * ray - x_bar

        def cost(p: Array) -> Array:
            r = project(camera, pose + p) - o
            u = jnp.sum(r * r, axis=-1) / sigma**2
            return jnp.sum(c * loss.rho(u)) + 0.5 * (jnp.dot(p, e_up) / up_sd) ** 2

        res = lambda q: project(camera, pose + q) - o

        def step(p: Array, _) -> tuple[Array, None]:
            r, J = res(p), jax.jacfwd(res)(p)  # (K, 2), (K, 2, 3)
            u = jnp.sum(r * r, axis=-1) / sigma**2
            w = 2 * c * loss.drho(u) / sigma**2
            A = jnp.einsum("k,kai,kaj->ij", w, J, J) + jnp.outer(e_up, e_up) / up_sd**2
            A = A + 1e-9 * jnp.eye(3, dtype=dt)
            g = jnp.einsum("k,kai,ka->i", w, J, r) + e_up * jnp.dot(p, e_up) / up_sd**2
            dp = -jnp.linalg.solve(A, g)
            # halve a step that raises the cost (at most four times)
            c_old = cost(p)

            def body_fn(i, q):
                return jnp.where(cost(q) <= c_old, q, p + 0.5 ** (i + 1) * dp)

            q = jax.lax.fori_loop(0, 4, body_fn, p + dp)
            return jnp.where(cost(q) <= c_old, q, p), None

        p, _ = jax.lax.scan(step, p0, None, length=steps)
        return p, cost(p)

    per_heading = jax.vmap(one, in_axes=(None, None, 0))
    return jax.vmap(per_heading, in_axes=(0, 0, None))(obs, conf, poses)


_translations_jit = eqx.filter_jit(_translations)


def _viterbi_headings(cost: np.ndarray, turn_sd: float) -> np.ndarray:
    """The heading bin of every frame minimising ``Σ cost + Σ ½ (turn / turn_sd)²``."""
    T, H = cost.shape
    th = np.arange(H) * 2 * np.pi / H
    d = np.angle(np.exp(1j * (th[None, :] - th[:, None])))
    trans = 0.5 * (d / turn_sd) ** 2  # (from, to)
    V = cost[0].copy()
    back = np.zeros((T, H), np.int64)
    for t in range(1, T):
        tot = V[:, None] + trans
        back[t] = np.argmin(tot, axis=0)
        V = tot[back[t], np.arange(H)] + cost[t]
    path = np.zeros(T, np.int64)
    path[-1] = int(np.argmin(V))
    for t in range(T - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path


def rigid_start(
    body: Body,
    camera: Camera,
    obs: Float[Array, "T K 2"],
    conf: Float[Array, "T K"],
    sigma: float,
    loss: PixelLoss,
    *,
    fps: float,
    n_headings: int = 16,
    floor_known: bool = True,
    turn_rate: float = 6.0,
    bone_scale: Float[Array, " J"] | None = None,
) -> tuple[np.ndarray, float]:
    """The first estimate ``X (T, D)`` and the floor height (module notes).

    Args:
        body: the tracked body's coordinates.
        camera: the camera.
        obs, conf: the observations and their confidences.
        sigma: the pixel noise.
        loss: the robust loss of the reprojection.
        fps: the frame rate (for the turn prior).
        n_headings: headings tried per frame.
        floor_known: the world's floor is the skeleton's (the root's height then has a
            prior around the mean pose's, ``0.15`` m); otherwise the root's height is free and
            the floor is estimated as the median lift.
        turn_rate: standard deviation of the heading's rate of change, radians per second.
        bone_scale: the person's bones (``None``: the skeleton's).

    Returns:
        ``(X, floor)``.
    """
    fm = body.feature_map
    dt = jnp.asarray(obs).dtype
    D = fm.dim
    X_pose = jnp.zeros((D,), dt)
    up_sd = jnp.asarray(0.15 if floor_known else 1e3, dt)
    p, cost = _translations_jit(
        body,
        X_pose,
        camera,
        jnp.asarray(obs),
        jnp.asarray(conf),
        jnp.asarray(sigma, dt),
        loss,
        n_headings,
        up_sd,
        bone_scale,
    )
    p, cost = np.asarray(p), np.asarray(cost)
    seen = np.asarray(conf).sum(axis=1) > 0
    cost = np.where(seen[:, None], cost, 0.0)
    path = _viterbi_headings(cost, turn_rate / fps)
    th_bins = np.arange(n_headings) * 2 * np.pi / n_headings
    T = cost.shape[0]
    heading = np.zeros(T)
    heading[0] = th_bins[path[0]]
    for t in range(1, T):
        heading[t] = heading[t - 1] + np.angle(np.exp(1j * (th_bins[path[t]] - heading[t - 1])))
    trans = p[np.arange(T), path]  # (T, 3)
    if seen.any() and not seen.all():  # frames with nothing seen: the nearest seen frame's
        idx = np.flatnonzero(seen)
        near = idx[np.argmin(np.abs(np.arange(T)[:, None] - idx[None, :]), axis=1)]
        trans = trans[near]
    up, h0, h1 = ground_axes(fm.skeleton.up_axis)
    c0, c1, cy = body.root_cols
    X = np.zeros((T, D))
    X[:, c0], X[:, c1], X[:, cy] = trans[:, h0], trans[:, h1], heading
    floor = 0.0
    if floor_known:
        sc = float(np.asarray(fm.scale)[np.asarray(fm.active)][2])
        X[:, 2] = trans[:, up] / sc
    else:
        floor = float(np.median(trans[:, up]))
    return X, floor
