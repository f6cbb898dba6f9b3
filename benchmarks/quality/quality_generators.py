"""Generators of the quality benchmark that the library does not provide as one call: the
paper's noise-driven synthesis along a texton path (MT Fig. 7b) and samples of the AR(2)
baseline (see ``bench_quality.py``)."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import mtex_jax as mj
from mtex_jax import metrics
from mtex_jax.texture import random_path, synthesize_texton


def noise_driven(key: jax.Array, tex: mj.MotionTexture, n_frames: int) -> tuple[Any, np.ndarray]:
    """MT Fig. 7b: a random texton path; each texton is run by its dynamics with sampled noise
    (from the texture's innovation process, if it has one) from the last two frames so far (no
    end constraint), for a length drawn from its training segments. Returns (Y, boundaries)."""
    kp, kl, kn = jax.random.split(key, 3)
    path = np.asarray(random_path(kp, tex, max(4, n_frames // tex.config.tmin + 2)))
    lab = np.asarray(tex.key_pose_labels)
    lens = np.asarray(tex.segment_lengths)
    kpose = np.asarray(tex.key_poses)
    rng = np.random.default_rng(int(jax.random.randint(kl, (), 0, 2**31 - 1)))
    first = rng.choice(np.flatnonzero(lab == path[0]))
    Y = [kpose[first]]
    total, bounds = 2, []
    for j, i in enumerate(path):
        L = int(rng.choice(lens[lab == i]))
        start = np.concatenate(Y)[-2:]
        k = jax.random.fold_in(kn, j)
        out = synthesize_texton(k, tex.textons[int(i)], L, start, innovations=tex.innovations)
        Y.append(np.asarray(out)[2:])
        bounds.append(total)
        total += L - 2
        if total >= n_frames:
            break
    return np.concatenate(Y)[:n_frames], np.asarray(bounds[1:])


def ar2_samples(key: jax.Array, model: metrics.GaussianAR2, start: np.ndarray, n: int) -> Any:
    A1, A2, c, L = (np.asarray(a) for a in (model.A1, model.A2, model.c, model.chol))
    e = np.asarray(jax.random.normal(key, (n, c.shape[0]), jnp.float64)) @ L.T
    Y = np.zeros((n, c.shape[0]))
    Y[:2] = start
    for t in range(2, n):
        Y[t] = A1 @ Y[t - 1] + A2 @ Y[t - 2] + c + e[t]
        if not np.all(np.isfinite(Y[t])) or np.abs(Y[t]).max() > 1e6:
            raise FloatingPointError(f"AR(2) sample diverged at frame {t}")
    return Y
