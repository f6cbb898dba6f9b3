"""The texture prior of an edit: texton dynamics residuals over a motion's segments.

A motion ``Y (T, D)`` with a segmentation (texton ``ℓ_t`` of every frame, position ``s_t`` of
the frame inside its segment) has the negative log-likelihood (design §3, up to constants)

.. code-block:: text

    −log p(Y) = ½ Σ_t ‖e_t‖² + ½ Σ_{s_t = 1} ‖g_t‖² + ½ Σ_t ‖o_t‖²

with, for the texton ``i = ℓ_t`` and ``x^i_s = C_iᵀ(y_s − μ_i)``,

.. code-block:: text

    e_t = B_j⁻¹ (x^j_t − A1_j x^j_{t−1} − A2_j x^j_{t−2} − d_j)      dynamics (k per frame)
    g_t = L0_i⁻¹ ([x^i_{t−1}; x^i_t] − m0_i),  L0 L0ᵀ = S0            initial pair (2k)
    o_t = ((y_t − μ_i) − C_i x^i_t) / σ_i                             outside the subspace (D)

where ``j = ℓ_t`` inside a segment (``s_t ≥ 2``). At the first two frames of a segment the
texture's own likelihood has only the broad initial-pair density, so an edit could open a jump
at a texton boundary for almost nothing; there ``j`` is the *previous* segment's texton (its
dynamics continued over the boundary), which keeps the motion continuous where the textons hand
over. Every term is affine in ``Y``: the whitened residuals are a linear map plus a constant.

The factors ``B⁻¹``, ``L0⁻¹`` and ``1/σ`` are computed once per texton, with floors (diagonal
of ``B`` at least ``1e-6`` of its largest, ``S0`` regularised before its Cholesky factor).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..core import as_array

__all__ = ["FrameSegments", "WhitenedTextons", "frame_segments", "prior_residuals"]

_REL_FLOOR = 1e-6  # relative floor of Cholesky diagonals (B, chol S0)


class FrameSegments(eqx.Module):
    """Per-frame segmentation of a motion, as the prior uses it.

    Attributes:
        labels: ``(T,)`` texton of every frame.
        dyn_labels: ``(T,)`` texton whose dynamics predict frame ``t`` (its own from the third
            frame of a segment on, the previous segment's at a segment's first two frames).
        position: ``(T,)`` index of the frame inside its segment.
    """

    labels: Int[Array, " T"]
    dyn_labels: Int[Array, " T"]
    position: Int[Array, " T"]

    def __check_init__(self) -> None:
        s = np.shape(self.labels)
        if np.shape(self.dyn_labels) != s or np.shape(self.position) != s:
            raise ValueError("FrameSegments: labels, dyn_labels and position must share a shape")

    @property
    def n_frames(self) -> int:
        return int(np.shape(self.labels)[-1])


def frame_segments(lengths: np.ndarray, labels: np.ndarray) -> FrameSegments:
    """Per-frame labels from segment lengths and labels (segments in time order).

    Args:
        lengths: ``(n,)`` positive segment lengths (their sum is ``T``).
        labels: ``(n,)`` texton of each segment.

    Returns:
        :class:`FrameSegments` of ``T = Σ lengths`` frames.
    """
    ln = np.asarray(lengths, dtype=np.int64).reshape(-1)
    lab = np.asarray(labels, dtype=np.int64).reshape(-1)
    if ln.shape != lab.shape or ln.size == 0 or (ln < 1).any():
        raise ValueError("segments: lengths must be positive and as many as labels")
    per = np.repeat(lab, ln)
    prev = np.repeat(np.concatenate([lab[:1], lab[:-1]]), ln)
    pos = np.concatenate([np.arange(n) for n in ln])
    dyn = np.where(pos >= 2, per, prev)
    # as_array: jnp.asarray with a dtype compiles a conversion for every new length
    return FrameSegments(
        labels=as_array(per.astype(np.int32)),
        dyn_labels=as_array(dyn.astype(np.int32)),
        position=as_array(pos.astype(np.int32)),
    )


class WhitenedTextons(eqx.Module):
    """The texton parameters the prior needs, with the whitening factors precomputed.

    Attributes:
        mu: ``(N, D)``; C: ``(N, D, k)``; A1, A2: ``(N, k, k)``; d: ``(N, k)``;
        B_inv: ``(N, k, k)`` ``B⁻¹``; L0_inv: ``(N, 2k, 2k)`` ``chol(S0)⁻¹``; m0: ``(N, 2k)``;
        inv_sigma: ``(N,)`` ``1/σ``.
    """

    mu: Float[Array, "N D"]
    C: Float[Array, "N D k"]
    A1: Float[Array, "N k k"]
    A2: Float[Array, "N k k"]
    d: Float[Array, "N k"]
    B_inv: Float[Array, "N k k"]
    L0_inv: Float[Array, "N k2 k2"]
    m0: Float[Array, "N k2"]
    inv_sigma: Float[Array, " N"]

    def __check_init__(self) -> None:
        n, D, k = np.shape(self.C)
        for name, shape in (
            ("mu", (n, D)),
            ("A1", (n, k, k)),
            ("A2", (n, k, k)),
            ("d", (n, k)),
            ("B_inv", (n, k, k)),
            ("L0_inv", (n, 2 * k, 2 * k)),
            ("m0", (n, 2 * k)),
            ("inv_sigma", (n,)),
        ):
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(f"WhitenedTextons.{name} must have shape {shape}")

    @classmethod
    def of(cls, textons, dtype, noise: float = 0.0) -> WhitenedTextons:
        """From a stacked :class:`~mtex_jax.texture.Texton` (its public fields), in ``dtype``.

        ``noise > 0`` adds ``noise²·I`` to every noise covariance (the innovations', the
        initial pairs' and the out-of-subspace variance ``σ²``): process-noise inflation, a
        prior that allows for motion a little off the textons' dynamics (a tracker's new
        dancer, design §12.2); ``0`` is the texture itself."""
        f = lambda a: jnp.asarray(a, dtype)
        B, S0 = f(textons.B), f(textons.S0)
        if B.ndim == 2:  # a single texton
            textons = jax.tree.map(lambda a: jnp.asarray(a)[None], textons)
            B, S0 = B[None], S0[None]
        k = B.shape[-1]
        eye = jnp.eye(k, dtype=dtype)
        if noise < 0 or not np.isfinite(noise):
            raise ValueError(f"WhitenedTextons.of: noise must be ≥ 0 and finite, got {noise}")
        if noise > 0:
            Q = jnp.einsum("nkl,nml->nkm", B, B) + noise**2 * eye
            B = jnp.linalg.cholesky(Q)
            S0 = S0 + noise**2 * jnp.eye(2 * k, dtype=dtype)
        diag = jnp.abs(jnp.diagonal(B, axis1=-2, axis2=-1))
        floor = _REL_FLOOR * jnp.maximum(diag.max(-1, keepdims=True), 1e-12)
        Bf = jnp.tril(B) + jnp.einsum("nk,kl->nkl", jnp.maximum(floor - diag, 0.0), eye)
        B_inv = jax.scipy.linalg.solve_triangular(Bf, jnp.broadcast_to(eye, Bf.shape), lower=True)
        S0s = 0.5 * (S0 + jnp.swapaxes(S0, -1, -2))
        scale = jnp.maximum(jnp.trace(S0s, axis1=-2, axis2=-1) / (2 * k), 1e-12)
        eye2 = jnp.eye(2 * k, dtype=dtype)
        L0 = jnp.linalg.cholesky(S0s + (_REL_FLOOR * scale)[:, None, None] * eye2)
        L0_inv = jax.scipy.linalg.solve_triangular(L0, jnp.broadcast_to(eye2, L0.shape), lower=True)
        s2 = jnp.maximum(f(textons.sigma2) + noise**2, 1e-12)
        return cls(
            mu=f(textons.mu),
            C=f(textons.C),
            A1=f(textons.A1),
            A2=f(textons.A2),
            d=f(textons.d),
            B_inv=B_inv,
            L0_inv=L0_inv,
            m0=f(textons.m0),
            inv_sigma=1.0 / jnp.sqrt(s2),
        )


def _shift(a: Array, n: int) -> Array:
    """``a`` delayed by ``n`` frames along axis 0 (the first ``n`` rows repeat row 0)."""
    return jnp.concatenate([jnp.broadcast_to(a[:1], (n, *a.shape[1:])), a[:-n]], axis=0)


def _valid(T: int, n_valid: Int[Array, ""] | int | None) -> Array:
    """``(T,)`` whether each frame is one of the first ``n_valid`` (all when ``None``)."""
    t = jnp.arange(T)
    return t < (T if n_valid is None else n_valid)


def prior_residuals(
    tx: WhitenedTextons,
    seg: FrameSegments,
    Y: Float[Array, "T D"],
    n_valid: Int[Array, ""] | int | None = None,
) -> tuple[Float[Array, "T k"], Float[Array, "T k2"], Float[Array, "T D"]]:
    """Whitened dynamics, initial-pair and out-of-subspace residuals ``(e, g, o)`` (module doc).

    Rows whose term does not exist (dynamics at ``t < 2``, initial pair where ``s_t ≠ 1``,
    every term of a padding frame ``t ≥ n_valid``) are zero.

    Args:
        tx: whitened textons.
        seg: per-frame segmentation of ``Y``.
        Y: ``(T, D)`` observations.
        n_valid: the motion's own frames, the first ``n_valid`` of ``Y`` (the rest pad it to a
            shape bucket, design §11); ``None``: all ``T``.

    Returns:
        ``e (T, k)``, ``g (T, 2k)``, ``o (T, D)``; ``½(‖e‖² + ‖g‖² + ‖o‖²)`` is the prior's
        negative log-likelihood up to a constant.
    """
    T = Y.shape[0]
    own, dyn = seg.labels, seg.dyn_labels
    # dynamics under texton j = dyn_labels[t], applied to frames t, t−1, t−2
    Cj, muj = tx.C[dyn], tx.mu[dyn]
    Y1, Y2 = _shift(Y, 1), _shift(Y, 2)
    proj = lambda Yv, C, mu: jnp.einsum("tdk,td->tk", C, Yv - mu)
    x0, x1, x2 = proj(Y, Cj, muj), proj(Y1, Cj, muj), proj(Y2, Cj, muj)
    inn = (
        x0
        - jnp.einsum("tkl,tl->tk", tx.A1[dyn], x1)
        - jnp.einsum("tkl,tl->tk", tx.A2[dyn], x2)
        - tx.d[dyn]
    )
    e = jnp.einsum("tkl,tl->tk", tx.B_inv[dyn], inn)
    ok = _valid(T, n_valid)
    e = jnp.where(((jnp.arange(T) >= 2) & ok)[:, None], e, 0.0)
    # own texton: initial pair and the part outside the subspace
    Ci, mui = tx.C[own], tx.mu[own]
    yc = Y - mui
    xi = jnp.einsum("tdk,td->tk", Ci, yc)
    xi_prev = proj(Y1, Ci, mui)
    pair = jnp.concatenate([xi_prev, xi], axis=1) - tx.m0[own]
    g = jnp.einsum("tkl,tl->tk", tx.L0_inv[own], pair)
    g = jnp.where(((seg.position == 1) & ok)[:, None], g, 0.0)
    o = (yc - jnp.einsum("tdk,tk->td", Ci, xi)) * tx.inv_sigma[own][:, None]
    return e, g, jnp.where(ok[:, None], o, 0.0)


def prior_hessian(
    tx: WhitenedTextons, seg: FrameSegments, dtype, n_valid: Int[Array, ""] | int | None = None
) -> tuple[Float[Array, "T D D"], Float[Array, "T D D"], Float[Array, "T D D"]]:
    """The prior's (constant) Hessian ``RᵀR`` as three bands of ``D × D`` blocks.

    The residuals of :func:`prior_residuals` are ``R y + const`` with per-frame coefficient
    blocks ``e_t = G0_t y_t + G1_t y_{t−1} + G2_t y_{t−2}``, ``g_t = K1_t y_{t−1} + K0_t y_t``,
    ``o_t = O_t y_t``; so ``RᵀR`` is block-banded with bandwidth two frames.

    With ``n_valid`` (a motion padded to a shape bucket), the padding frames' terms are left
    out, so the first ``n_valid`` frames do not interact with the padding.

    Returns:
        ``(H0, H1, H2)``: ``H0[t] = (RᵀR)[t, t]``, ``H1[t] = (RᵀR)[t, t−1]`` (row 0 zero),
        ``H2[t] = (RᵀR)[t, t−2]`` (rows 0, 1 zero).
    """
    T = seg.n_frames
    own, dyn = seg.labels, seg.dyn_labels
    k = tx.A1.shape[-1]
    Ct = jnp.swapaxes(tx.C, -1, -2).astype(dtype)  # (N, k, D)
    Bi = tx.B_inv.astype(dtype)
    G0 = Bi @ Ct
    G1 = -(Bi @ tx.A1.astype(dtype)) @ Ct
    G2 = -(Bi @ tx.A2.astype(dtype)) @ Ct
    ok = _valid(T, n_valid)
    has_dyn = ((jnp.arange(T) >= 2) & ok)[:, None, None]
    L0i = tx.L0_inv.astype(dtype)
    K1 = L0i[:, :, :k] @ Ct
    K0 = L0i[:, :, k:] @ Ct
    has_init = ((seg.position == 1) & ok)[:, None, None]
    D = Ct.shape[-1]
    C = tx.C.astype(dtype)
    proj = (jnp.eye(D, dtype=dtype) - C @ Ct) * (tx.inv_sigma.astype(dtype) ** 2)[:, None, None]
    # the per-frame blocks are per-texton products gathered by frame (N·k·D² work, not T·k·D²)
    tt = lambda a, b: jnp.einsum("nkd,nke->nde", a, b)
    nxt = lambda a, n: jnp.concatenate([a[n:], jnp.zeros((n, *a.shape[1:]), a.dtype)], axis=0)
    dyn_of = lambda a: jnp.where(has_dyn, a[dyn], 0.0)  # a texton product at each frame
    init_of = lambda a: jnp.where(has_init, a[own], 0.0)
    H0 = dyn_of(tt(G0, G0)) + nxt(dyn_of(tt(G1, G1)), 1) + nxt(dyn_of(tt(G2, G2)), 2)
    H0 = H0 + init_of(tt(K0, K0)) + nxt(init_of(tt(K1, K1)), 1)
    H0 = H0 + proj[own] * ok[:, None, None]  # (I − CCᵀ)ᵀ(I − CCᵀ)/σ² = (I − CCᵀ)/σ²
    H1 = dyn_of(tt(G0, G1)) + nxt(dyn_of(tt(G1, G2)), 1) + init_of(tt(K0, K1))
    H2 = dyn_of(tt(G0, G2))
    return H0, H1, H2


def smoothness_hessian(
    T: int, D: int, dtype, n_valid: Int[Array, ""] | int | None = None
) -> tuple[Array, Array, Array]:
    """Bands of ``ΔᵀΔ`` for the second difference ``(Δy)_t = y_t − 2 y_{t−1} + y_{t−2}``
    (``2 ≤ t < n_valid``, default ``T``), as multiples of ``I_D`` (same layout as
    :func:`prior_hessian`)."""
    t = jnp.arange(T)
    end = T if n_valid is None else n_valid
    has = lambda s: ((s >= 2) & (s < end)).astype(dtype)
    d0 = has(t) + 4.0 * has(t + 1) + has(t + 2)
    d1 = -2.0 * has(t) - 2.0 * has(t + 1)
    d2 = has(t)
    eye = jnp.eye(D, dtype=dtype)
    return d0[:, None, None] * eye, d1[:, None, None] * eye, d2[:, None, None] * eye
