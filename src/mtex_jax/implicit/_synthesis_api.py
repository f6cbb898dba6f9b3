"""The public synthesis entry points of the implicit model (IP §5): argument checks, the start
window, and decoding to a :class:`Motion`; the generator itself is in ``_synthesis``.

:meth:`ImplicitModel.synthesize` and :meth:`ImplicitModel.synthesize_poses` *are* these
functions (``model.synthesize(key, ...)`` is ``synthesize(model, key, ...)``). They need only
a model's :class:`FeatureMap` and :class:`MotionDatabase` (:class:`SynthesisModel`), so this
module does not import ``_model``, which imports it.
"""

from __future__ import annotations

from typing import Any, Literal, Protocol

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from ..core import MAX_GENERATED_FRAMES, bucket_length, check_count, check_key
from ..motion import FeatureMap, Motion
from ._database import MotionDatabase
from ._synthesis import SynthesisConfig, SynthLeafRule, synthesize_jit
from ._windows import check_beta, check_candidates, is_concrete, pose_vectors

__all__ = ["SynthLeafRule", "SynthesisConfig", "SynthesisModel", "synthesize", "synthesize_poses"]


class SynthesisModel(Protocol):
    """What synthesis needs of a model: an :class:`~mtex_jax.implicit.ImplicitModel`."""

    @property
    def feature_map(self) -> FeatureMap: ...

    @property
    def database(self) -> MotionDatabase: ...


def _replace(config: SynthesisConfig, **changes: Any) -> SynthesisConfig:
    fields = {f: getattr(config, f) for f in SynthesisConfig.__dataclass_fields__}
    return SynthesisConfig(**(fields | changes))


def _config(config: SynthesisConfig | None, leaf: Any, candidates: Any, fn: str) -> SynthesisConfig:
    if config is None:
        config = SynthesisConfig()
    elif not isinstance(config, SynthesisConfig):
        raise ValueError(f"{fn}: config must be a SynthesisConfig, got {type(config).__name__}")
    if leaf is not None:
        if leaf not in ("uniform", "weighted", "exact"):
            raise ValueError(f"{fn}: leaf must be 'uniform', 'weighted' or 'exact', got {leaf!r}")
        config = _replace(config, leaf=leaf)
    if candidates is not None:
        check_candidates(candidates, fn)
        config = _replace(config, candidates=int(candidates))
    return config


def synthesize_poses(
    model: SynthesisModel,
    key: PRNGKeyArray,
    start_window: Motion | Float[ArrayLike, "d P"],
    n_frames: int,
    beta: float | Float[ArrayLike, ""],
    noise: float | Float[ArrayLike, ""] = 0.0,
    *,
    sampler: Literal["tree", "exact"] = "tree",
    config: SynthesisConfig | None = None,
    leaf: SynthLeafRule | None = None,
    candidates: int | None = None,
) -> tuple[Float[Array, "T D"], Int[Array, " n_frames"]]:
    """Like :func:`synthesize` but returns observation vectors instead of a :class:`Motion`.

    Returns:
        ``(d + n_frames, D)`` poses (seed then generated, FeatureMap units) and the database
        example ``(n_frames,)`` whose successor gave each generated frame.
    """
    check_key(key, "synthesize")
    check_beta(beta, "synthesize")
    if isinstance(n_frames, bool) or not isinstance(n_frames, int | np.integer):
        raise ValueError(f"synthesize: n_frames must be an integer, got {n_frames!r}")
    if n_frames < 1:
        raise ValueError(f"synthesize: n_frames must be ≥ 1, got {n_frames}")
    check_count(n_frames, "synthesize: n_frames", MAX_GENERATED_FRAMES)
    if sampler not in ("tree", "exact"):
        raise ValueError(f"synthesize: sampler must be 'tree' or 'exact', got {sampler!r}")
    cfg = _config(config, leaf, candidates, "synthesize")
    if is_concrete(noise):
        nz = np.asarray(noise)
        if nz.shape != () or not (np.isfinite(nz) and nz >= 0):
            raise ValueError(f"synthesize: noise must be a finite scalar ≥ 0, got {noise!r}")
    fm, db = model.feature_map, model.database
    if isinstance(start_window, Motion):
        fm._check_motion(start_window)
        if start_window.n_frames < db.window + 1:
            raise ValueError(
                f"synthesize: the start clip needs at least {db.window + 1} frames, "
                f"got {start_window.n_frames}"
            )
        win = jnp.asarray(pose_vectors(fm, start_window[: db.window + 1]))
    else:
        win = jnp.asarray(start_window)
        if win.shape != (db.window, db.pose_dim):
            raise ValueError(
                f"synthesize: start_window must be a Motion or a ({db.window}, "
                f"{db.pose_dim}) array of pose vectors, got shape {win.shape}"
            )
        if is_concrete(win) and not bool(jnp.all(jnp.isfinite(win))):
            raise ValueError("synthesize: start_window contains NaN or inf")
    dtype = db.windows.dtype
    win = win.astype(dtype)
    # the scan runs for a shape bucket of frames (design §11): its per-step keys are
    # prefix-stable, so the first n_frames are those of an n_frames scan
    gen, idx = synthesize_jit(
        db,
        fm,
        key,
        win,
        bucket_length(int(n_frames)),
        jnp.asarray(beta, dtype),
        jnp.asarray(noise, dtype),
        sampler,
        cfg,
        jax.device_put(np.asarray(n_frames)),
    )
    try:  # cut and joined on the host: eager slices would compile once per length
        head = np.concatenate([np.asarray(win[:, : fm.dim]), np.asarray(gen)[:n_frames]])
        return jax.device_put(head), jax.device_put(np.asarray(idx)[:n_frames])
    except jax.errors.TracerArrayConversionError:
        return jnp.concatenate([win[:, : fm.dim], gen[:n_frames]], axis=0), idx[:n_frames]


def synthesize(
    model: SynthesisModel,
    key: PRNGKeyArray,
    start_window: Motion | Float[ArrayLike, "d P"],
    n_frames: int,
    beta: float | Float[ArrayLike, ""],
    noise: float | Float[ArrayLike, ""] = 0.0,
    *,
    sampler: Literal["tree", "exact"] = "tree",
    config: SynthesisConfig | None = None,
    leaf: SynthLeafRule | None = None,
    candidates: int | None = None,
    start_position: Float[ArrayLike, " 3"] | None = None,
    start_heading: float | None = None,
) -> Motion:
    """Generate motion frame by frame (IP §5) and decode it to a :class:`Motion`.

    Each step either continues the current database example or searches a new one for the
    current ``d``-frame history (tree, IP Eq. 7–8, or exact, IP Eq. 3), and turns the
    example's successor into the next pose as set by ``config`` (velocity form, blending,
    look-ahead, continuation, run cap; ``SynthesisConfig.paper()`` is the published sampler).
    Gaussian noise of standard deviation ``noise · pose_std`` is added to each pose; the
    velocity half of each new pose vector is the frame difference of the generated poses, so
    the history always describes the generated motion. One ``lax.scan``.

    Args:
        model: the implicit model.
        key: PRNG key.
        start_window: a clip (its frames ``0 … d`` seed the history, and its frame 1 fixes
            the start position and heading) or a ``(d, P)`` array of pose vectors.
        n_frames: frames to generate after the ``d`` seed frames.
        beta: sampling temperature ``> 0`` (same meaning for both samplers, see ``_model``).
        noise: innovation scale ``≥ 0``.
        sampler: ``"tree"`` (IP Eq. 7–8) or ``"exact"`` (IP Eq. 3).
        config: synthesis options (default ``SynthesisConfig()``).
        leaf: overrides ``config.leaf``.
        candidates: overrides ``config.candidates``.
        start_position: root position of the first output frame (default: from
            ``start_window`` if it is a clip, else the origin).
        start_heading: root yaw of the first output frame (default: from ``start_window``
            if it is a clip, else 0).

    Returns:
        a clip of ``d + n_frames`` frames: the seed poses followed by the generated ones.
    """
    poses, _ = synthesize_poses(
        model,
        key,
        start_window,
        n_frames,
        beta,
        noise,
        sampler=sampler,
        config=config,
        leaf=leaf,
        candidates=candidates,
    )
    sp, sh = start_position, start_heading
    if isinstance(start_window, Motion):
        p0, h0 = model.feature_map.start_of(start_window[1:])
        sp = p0 if sp is None else sp
        sh = h0 if sh is None else sh
    return model.feature_map.decode(poses, sp, sh)
