"""Value checks of a loaded motion texture (the door of :func:`load_texture`), and the finite
output check of noise-driven synthesis."""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from jax.core import Tracer

from ...core import check_count, check_real
from .._observation import MEMBER_FIELDS
from .texton import TEXTON_FIELDS, Texton, spectral_radius

__all__ = [
    "TEXTURE_MEMBERS",
    "check_config_limits",
    "check_finite_output",
    "check_texture_arrays",
]

#: The members a motion-texture file may hold besides the required ones (fnmatch patterns);
#: any other member is rejected before it is decompressed.
TEXTURE_MEMBERS = (
    *(f"texton.{f}" for f in (*TEXTON_FIELDS, *MEMBER_FIELDS)),
    "feature_map.offset",
    "feature_map.scale",
    "log_durations",
    "innovations.acf",
    "innovations.persistence",
    "residuals.rows",
    "residuals.starts",
    "residuals.lengths",
    "residuals.labels",
    "residuals.segments",
)

_STOCHASTIC_TOL = 1e-6
_MAX_BIC_THRESHOLDS = 1_000


def check_config_limits(cfg: Any) -> None:
    """Raise ``ValueError`` (or ``TypeError``) unless every size of a ``LearnConfig`` lies
    within the limits of :mod:`mtex_jax.core` and every real field is finite and in range.

    Sizes: ``tmin``, ``tmax`` and ``chunk_frames`` at most ``MAX_SEGMENT_FRAMES`` (the
    segment scores hold ``T × tmax`` entries), ``n_textons`` at most ``MAX_TEXTONS``,
    ``min_segments`` at most ``MAX_MIN_SEGMENTS``, ``state_dim`` at most ``MAX_STATE_DIM``,
    ``max_iter`` at most ``MAX_ITERATIONS``. Reals: ``threshold`` and every entry of
    ``bic_thresholds`` finite and positive, ``pseudo_count`` finite and positive, the floors,
    ``ridge`` and ``init_prior_weight`` finite and non-negative, ``rho_max`` finite and
    positive, ``fps`` in ``(0, 10000]``. The errors name the field (``LearnConfig.tmax``).
    """

    def name(field: str) -> str:
        return f"LearnConfig.{field}"

    check_count(cfg.tmin, name("tmin"), "MAX_SEGMENT_FRAMES", low=3)
    if cfg.tmax is not None:
        check_count(cfg.tmax, name("tmax"), "MAX_SEGMENT_FRAMES", low=cfg.tmin)
    check_count(cfg.chunk_frames, name("chunk_frames"), "MAX_SEGMENT_FRAMES", low=1)
    if cfg.n_textons is not None:
        check_count(cfg.n_textons, name("n_textons"), "MAX_TEXTONS")
    check_count(cfg.min_segments, name("min_segments"), "MAX_MIN_SEGMENTS")
    if cfg.state_dim is not None:
        check_count(cfg.state_dim, name("state_dim"), "MAX_STATE_DIM")
    check_count(cfg.max_iter, name("max_iter"), "MAX_ITERATIONS", low=0)
    if cfg.threshold is not None:
        check_real(cfg.threshold, name("threshold"), low=0.0, open_low=True)
    if cfg.bic_thresholds is not None:
        th = cfg.bic_thresholds
        if not isinstance(th, tuple | list) or not 1 <= len(th) <= _MAX_BIC_THRESHOLDS:
            raise ValueError(
                f"{name('bic_thresholds')} must be a tuple of 1 to {_MAX_BIC_THRESHOLDS} "
                f"positive numbers, got {th!r}"[:200]
            )
        for i, t in enumerate(th):
            check_real(t, f"{name('bic_thresholds')}[{i}]", low=0.0, open_low=True)
    check_real(cfg.pseudo_count, name("pseudo_count"), low=0.0, open_low=True)
    for f in ("ridge", "q_floor", "sigma2_floor", "init_prior_weight", "tol"):
        check_real(getattr(cfg, f), name(f), low=0.0)
    if cfg.rho_max is not None:
        check_real(cfg.rho_max, name("rho_max"), low=0.0, open_low=True)
    if cfg.fps is not None:
        check_real(cfg.fps, name("fps"), low=0.0, high=10_000.0, open_low=True)


def check_texture_arrays(path: str | os.PathLike[str], arrays: dict[str, np.ndarray]) -> None:
    """Raise ``ValueError`` naming ``path`` unless the arrays of a texture file hold sane values.

    Every floating array finite; the transition matrix ``M`` square with non-negative rows
    summing to 1 and ``pi`` a non-negative vector summing to 1; texton noise variances
    ``sigma2`` positive; key-pose labels within ``[0, N_t)``; segment lengths positive. Then
    what a learned texture has: floating arrays where the model has reals and integer arrays
    for labels and lengths (a boolean ``M`` is refused); at most ``MAX_TEXTONS`` textons and
    segments of at most ``MAX_SEGMENT_FRAMES`` frames; texton fields with ``N_t`` textons and
    key poses of the textons' dimension ``D``; orthonormal ``C``; ``B`` a Cholesky factor
    with a positive diagonal; ``S0`` symmetric positive definite; dynamics of spectral radius
    at most :data:`MAX_LOADED_RADIUS`; segment and residual labels within ``[0, N_t)``.
    """

    def fail(msg: str) -> ValueError:
        return ValueError(f"{path}: invalid motion texture file: {msg}")

    for k, a in arrays.items():
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise fail(f"array {k!r} contains NaN or inf")
    m = arrays.get("M")
    pi = arrays.get("pi")
    if m is None or pi is None:
        return  # reported as missing arrays by the caller
    if m.ndim != 2 or m.shape[0] != m.shape[1] or pi.shape != (m.shape[0],):
        raise fail(f"M has shape {m.shape} and pi {pi.shape}; expected (n, n) and (n,)")
    for name, a, rows in (("M", m, m), ("pi", pi, pi[None])):
        if (a < 0).any():
            raise fail(f"{name} has negative entries (minimum {float(a.min()):.3g})")
        err = np.abs(rows.sum(axis=-1) - 1.0)
        if a.size and err.max() > _STOCHASTIC_TOL:
            i = int(np.argmax(err))
            what = f"row {i} of M sums" if name == "M" else "pi sums"
            raise fail(f"{what} to {float(rows[i].sum()):.6g}, not 1 (not stochastic)")
    scale = arrays.get("feature_map.scale")
    if scale is not None and (scale <= 0).any():
        raise fail("feature_map.scale must be positive")
    s2 = arrays.get("texton.sigma2")
    if s2 is not None and (s2 <= 0).any():
        raise fail("texton.sigma2 (observation noise variance) must be positive")
    labels = arrays.get("key_pose_labels")
    if labels is not None and labels.size and (labels.min() < 0 or labels.max() >= m.shape[0]):
        raise fail(f"key_pose_labels outside [0, {m.shape[0]})")
    lengths = arrays.get("segment_lengths")
    if lengths is not None and lengths.size and lengths.min() < 1:
        raise fail("segment_lengths must be positive")
    try:
        _check_structure(arrays, m.shape[0])
    except ValueError as e:
        raise fail(str(e)) from None


# the dtype kind every member must have: "f" floating, "i" integer (signed or unsigned)
_INTEGER_MEMBERS = (
    "key_pose_labels",
    "segment_lengths",
    "segments",
    "residuals.starts",
    "residuals.lengths",
    "residuals.labels",
    "residuals.segments",
)
_ORTHONORMAL_TOL = 1e-4
#: Largest spectral radius of a loaded texton's dynamics (a learned texton with
#: ``rho_max=None`` stays near 1; ``A1 = 10⁶ I`` makes every likelihood −inf).
MAX_LOADED_RADIUS = 10.0


def _check_structure(arrays: dict[str, np.ndarray], n: int) -> None:
    """The dtypes, shapes, sizes and matrix properties of a texture file's arrays, as a
    learned texture has them (``ValueError`` naming the array)."""
    check_count(n, "number of textons (M)", "MAX_TEXTONS")
    for k, a in arrays.items():
        want = "iu" if k in _INTEGER_MEMBERS else "f"
        if a.dtype.kind not in want:
            kind = "an integer" if want == "iu" else "a floating-point"
            raise ValueError(f"array {k!r} has dtype {a.dtype}; expected {kind} array")
    tf = {k.split(".", 1)[1]: a for k, a in arrays.items() if k.startswith("texton.")}
    mu = tf.get("mu")
    if mu is None or mu.ndim != 2 or mu.shape[0] != n:
        got = None if mu is None else mu.shape
        raise ValueError(f"texton.mu must have shape ({n}, D), got {got}")
    D = mu.shape[1]
    for name, a in tf.items():
        if a.ndim < 1 or a.shape[0] != n:
            raise ValueError(
                f"texton.{name} must have {n} textons on its first axis, got {a.shape}"
            )
    _check_dynamics(tf)
    kp = arrays.get("key_poses")
    labels = arrays.get("key_pose_labels")
    if labels is not None and labels.ndim != 1:
        raise ValueError(f"key_pose_labels must have shape (n_segments,), got {labels.shape}")
    if kp is not None and labels is not None and kp.shape != (labels.shape[0], 2, D):
        raise ValueError(f"key_poses must have shape ({labels.shape[0]}, 2, {D}), got {kp.shape}")
    lengths = arrays.get("segment_lengths")
    if lengths is not None and lengths.size:
        check_count(int(lengths.max()), "longest segment_lengths", "MAX_SEGMENT_FRAMES")
    seg = arrays.get("segments")
    if seg is not None and seg.ndim == 2 and seg.shape[1] == 4 and seg.size:
        if seg[:, 3].min() < 0 or seg[:, 3].max() >= n:
            raise ValueError(f"segments hold labels outside [0, {n})")
        if seg[:, :3].min() < 0:
            raise ValueError("segments hold negative clip indices, starts or lengths")
        check_count(int(seg[:, 2].max()), "longest segment", "MAX_SEGMENT_FRAMES")
    hist = arrays.get("history")
    if hist is not None and (hist.ndim != 2 or hist.shape[1] != 2):
        raise ValueError(f"history must have shape (n_iter, 2), got {hist.shape}")
    _check_noise_members(arrays, n)


def _check_dynamics(tf: dict[str, np.ndarray]) -> None:
    """Orthonormal ``C``, a Cholesky factor ``B`` with a positive diagonal, a positive
    definite ``S0``, positive ``res_s2`` and dynamics of spectral radius at most
    :data:`MAX_LOADED_RADIUS`."""
    C, B, S0 = tf.get("C"), tf.get("B"), tf.get("S0")
    A1, A2 = tf.get("A1"), tf.get("A2")
    if C is not None and C.ndim == 3:
        gram = np.einsum("ndk,ndl->nkl", C, C)
        err = np.abs(gram - np.eye(C.shape[2])).max() if C.size else 0.0
        if err > _ORTHONORMAL_TOL:
            raise ValueError(f"texton.C must have orthonormal columns (CᵀC deviates by {err:.3g})")
    if B is not None and B.ndim == 3:
        diag = np.diagonal(B, axis1=1, axis2=2)
        if diag.size and not (diag > 0).all():
            i = int(np.nonzero((diag <= 0).any(axis=1))[0][0])
            raise ValueError(
                f"texton.B of texton {i} is not a Cholesky factor (a diagonal entry <= 0): the "
                "dynamics noise covariance Q = B Bᵀ must be positive definite"
            )
    if S0 is not None and S0.ndim == 3:
        for i, s in enumerate(S0):
            if np.abs(s - s.T).max() > 1e-6 * max(1.0, float(np.abs(s).max())):
                raise ValueError(f"texton.S0 of texton {i} is not symmetric")
            try:
                np.linalg.cholesky(s)
            except np.linalg.LinAlgError:
                raise ValueError(f"texton.S0 of texton {i} is not positive definite") from None
    r2 = tf.get("res_s2")
    if r2 is not None and (r2 <= 0).any():
        raise ValueError("texton.res_s2 (residual variance) must be positive")
    if A1 is not None and A2 is not None and A1.ndim == 3 and A1.shape == A2.shape:
        k = A1.shape[-1]
        top = np.concatenate([A1, A2], axis=2)
        bottom = np.concatenate([np.broadcast_to(np.eye(k), A1.shape), np.zeros_like(A1)], axis=2)
        rho = np.abs(np.linalg.eigvals(np.concatenate([top, bottom], axis=1))).max(axis=-1)
        if rho.size and rho.max() > MAX_LOADED_RADIUS:
            i = int(np.argmax(rho))
            raise ValueError(
                f"texton {i} has dynamics of spectral radius {float(rho[i]):.3g} (limit "
                f"{MAX_LOADED_RADIUS:g}): they grow without bound"
            )


def _check_noise_members(arrays: dict[str, np.ndarray], n: int) -> None:
    """The innovation process and the residual bank of a texture file."""
    acf = arrays.get("innovations.acf")
    if acf is not None and acf.size and np.abs(acf).max() > 1:
        raise ValueError("innovations.acf must lie in [-1, 1] (autocorrelations)")
    per = arrays.get("innovations.persistence")
    if per is not None and per.size and (per.min() < 0 or per.max() > 1):
        raise ValueError("innovations.persistence must lie in [0, 1]")
    rows = arrays.get("residuals.rows")
    if rows is None:
        return
    starts = arrays.get("residuals.starts")
    lens = arrays.get("residuals.lengths")
    labels = arrays.get("residuals.labels")
    if starts is None or lens is None or labels is None:
        return  # reported by the loader (the arrays come together)
    if not (starts.shape == lens.shape == labels.shape and starts.ndim == 1):
        raise ValueError("residuals.starts, lengths and labels must be equal-length vectors")
    if labels.size and (labels.min() < 0 or labels.max() >= n):
        raise ValueError(f"residuals.labels outside [0, {n})")
    if starts.size and (
        starts.min() < 0 or lens.min() < 0 or (starts + lens).max() > rows.shape[0]
    ):
        raise ValueError("residuals.starts and lengths point outside residuals.rows")
    seg = arrays.get("residuals.segments")
    if seg is not None:
        n_seg = np.shape(arrays["segments"])[0] if "segments" in arrays else 0
        if seg.shape != starts.shape:
            raise ValueError("residuals.segments must have the shape of residuals.starts")
        if seg.size and (seg.min() < 0 or seg.max() >= n_seg):
            raise ValueError(f"residuals.segments outside the {n_seg} training segments")


def check_finite_output(out: Any, texton: Texton, where: str) -> None:
    """Raise ``ValueError`` if a concrete synthesis result holds NaN or inf (finite input).

    Noise-driven synthesis of a texton whose dynamics have spectral radius ``ρ > 1`` grows
    like ``ρ^t`` and overflows after some hundred frames; the error names ``ρ`` and the cure.
    Traced results (under ``jit``/``vmap``) are not checked.
    """
    if isinstance(out, Tracer) or np.isfinite(np.asarray(out)).all():
        return
    rho = np.asarray(spectral_radius(texton))
    rho_s = ", ".join(f"{float(r):.3g}" for r in np.atleast_1d(rho)[:5])
    raise ValueError(
        f"{where}: the result overflows (NaN/inf): the texton's dynamics are unstable "
        f"(spectral radius {rho_s} > 1) and grow without bound over {np.shape(out)[-2]} frames; "
        "hold the end (end=...), synthesise fewer frames, or learn with "
        "LearnConfig(rho_max=0.999) (the default)"
    )
