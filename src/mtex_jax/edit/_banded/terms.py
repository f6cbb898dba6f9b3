"""Residual terms of the banded solve (design §6.5, §12.2): a family with one small protocol.

The banded objective is a block-banded quadratic (the prior, smoothness and anchor) plus a sum
of *terms*, each a function of the kept joints' world positions ``P (T, K, 3)``. A term is a
:class:`ResidualTerm`: it prices positions (:meth:`~ResidualTerm.cost`), gives the rows of its
Gauss–Newton model ``½ Σ w (r + J δ)²`` at a step (:meth:`~ResidualTerm.rows`, from the step's
per-frame Jacobians :class:`Columns`), and may hold a multiplier *shift* that the solver's
rounds move (:meth:`~ResidualTerm.next_round`: an augmented Lagrangian, so that a constraint is
met rather than balanced against the prior). Each member owns its parameters:

- :class:`PointTargets`: joint positions wanted at frames (an edit's targets, clean's plants
  and swing guidance), met exactly by the rounds where marked ``exact``;
- :class:`HeightBounds`: one-sided lower heights (clean's floor and lifts), met by the rounds
  where marked;
- :class:`FrameResidual`: any per-frame residual ``r_t = f_t(P_t)`` with a robust loss, its rows
  from forward-mode products of ``f`` (the tracker's 2-D reprojection and floor contact,
  :mod:`mtex_jax.tracking`).

The solver (:class:`~mtex_jax.edit.BandedGaussNewton`) is chosen apart from the terms: it adds
the rows of every term to the normal equations, frame-wise rows as a batched product and rows
of sparse frames scattered to their frames.
"""

from __future__ import annotations

import abc
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._jacobians import FrameColumns

__all__ = [
    "Columns",
    "FrameResidual",
    "HeightBounds",
    "PointTargets",
    "ResidualTerm",
    "RootOffset",
    "Rows",
    "residual_rows",
]


class RootOffset(eqx.Module):
    """Let the root move horizontally in a banded solve, as a smooth world offset per frame.

    Columns ``channels`` of the displacement ``z`` (two held channels, e.g. ``root.d*``) then
    carry a world offset (metres) of the whole figure along the world axes ``axes`` at each
    frame, priced by ``smooth`` per metre of its second difference over the first ``n_valid``
    frames (plus the solve's anchor ridge). Frames stay independent: the offset moves every
    joint of its frame alike. The caller turns it into root channels
    (:func:`mtex_jax.edit._gn.apply_shift`).

    Attributes:
        channels: the two columns of ``z`` (static).
        axes: their world axes (static).
        smooth: weight of the offset's second difference.
        n_valid: the motion's own frames (``None``: all).
    """

    channels: tuple[int, int] = eqx.field(static=True)
    axes: tuple[int, int] = eqx.field(static=True)
    smooth: Float[Array, ""] | float = 0.0
    n_valid: Int[Array, ""] | int | None = None


class Columns(eqx.Module):
    """The positions at a step and their per-frame Jacobians with respect to the channels.

    Attributes:
        P: ``(T, K, 3)`` kept joint positions, with the root offset (if any).
        fc: the Jacobian-vector products of the decode and forward kinematics.
        root: the root offset, whose columns move every joint of a frame alike.
    """

    P: Float[Array, "T K 3"]
    fc: FrameColumns
    root: RootOffset | None = None

    def _with_root(self, J: Array, a: int) -> Array:
        """``J`` (of world coordinate ``a``) with the root offset's column of that axis set."""
        if self.root is None or a not in self.root.axes:
            return J
        c = self.root.channels[self.root.axes.index(a)]
        return J.at[..., c].set(1.0)

    def rows(self, frame: Int[Array, " N"], slot: Int[Array, " N"]) -> Float[Array, "N 3 D"]:
        """The Jacobians of the positions of joints ``slot`` at frames ``frame``."""
        J = self.fc.rows(frame, slot)
        if self.root is not None:
            for a, c in zip(self.root.axes, self.root.channels, strict=True):
                J = J.at[:, a, c].set(1.0)
        return J

    def axis(self, a: int) -> Float[Array, "T K D"]:
        """The Jacobians of every kept joint's world coordinate ``a``."""
        return self._with_root(self.fc.axis(a), a)

    def all(self) -> Float[Array, "T K 3 D"]:
        """The Jacobians of every kept joint's position."""
        return jnp.stack([self.axis(a) for a in range(3)], axis=2)


class Rows(eqx.Module):
    """A term's rows of the Gauss–Newton model ``½ Σ w (r + J δ)²``.

    Frame-wise rows (``frame is None``) come weighted (``√w ⊙ J``, ``√w ⊙ r``), ``N = T``, one
    block per frame. Rows at sparse frames (``frame``: ``(N,)``) come with their weights ``w``
    and are scattered to their frames.

    Attributes:
        J: ``(N, R, D)`` rows.
        r: ``(N, R)`` residuals.
        w: ``(N, R)`` weights (sparse rows only).
        frame: ``(N,)`` the frame of each block of sparse rows (``None``: frame-wise).
    """

    J: Float[Array, "N R D"]
    r: Float[Array, "N R"]
    w: Float[Array, "N R"] | None = None
    frame: Int[Array, " N"] | None = None


class ResidualTerm(eqx.Module):
    """A term of the banded objective (module notes): a function of the kept positions.

    A member prices positions, gives its Gauss–Newton rows at a step and, optionally, keeps a
    multiplier shift that the solver's rounds move. ``shift`` is whatever :meth:`start`
    returns (``()`` for a term without one).
    """

    def start(self) -> Any:
        """The shift before the first round (``()``: the term has none)."""
        return ()

    @abc.abstractmethod
    def cost(self, P: Float[Array, "T K 3"], shift: Any) -> Float[Array, ""]:
        """The term's cost at positions ``P``."""

    @abc.abstractmethod
    def rows(self, P: Float[Array, "T K 3"], cols: Columns, shift: Any) -> tuple[Rows, ...]:
        """The rows of the term's Gauss–Newton model at ``P`` (``cols``: the Jacobians)."""

    def next_round(self, P: Float[Array, "T K 3"], shift: Any) -> tuple[Any, Bool[Array, ""]]:
        """The shift for the next round at positions ``P``, and whether that round is needed
        for this term (the rounds end early when no term needs one)."""
        return shift, jnp.asarray(False)


class PointTargets(ResidualTerm):
    """Joint world positions wanted at frames, with per-coordinate weights.

    The cost is ``½ Σ w² (P[frame, slot] − target − shift)²``. The first ``n_sparse`` targets
    may sit at any frames. The rest, if ``per_frame > 0``, are *frame-major*: ``per_frame``
    targets at each frame ``0, 1, …`` in order (clean's planted and swing feet: one per foot and
    frame), so a step assembles their normal equations per frame, without one ``D × D`` matrix
    per target. With ``shifted``, the rounds shift the targets marked ``exact`` by their
    remaining error, so that they are met.

    Attributes:
        slot: ``(P,)`` index of the joint among the solve's kept joints.
        frame: ``(P,)`` frame of each target.
        target: ``(P, 3)`` world positions (metres).
        weight: ``(P, 3)`` per metre (0: that coordinate is free; an inactive slot is all 0).
        exact: ``(P,)`` whether multiplier rounds shift this target (meet it exactly).
        n_sparse: the leading targets at any frames (``None``: all of them).
        per_frame: the frame-major targets per frame (``0``: none).
        shifted: the rounds shift the ``exact`` targets (``False``: all stay penalties).
    """

    slot: Int[Array, " P"]
    frame: Int[Array, " P"]
    target: Float[Array, "P 3"]
    weight: Float[Array, "P 3"]
    exact: Bool[Array, " P"]
    n_sparse: int | None = eqx.field(static=True, default=None)
    per_frame: int = eqx.field(static=True, default=0)
    shifted: bool = eqx.field(static=True, default=True)

    def __check_init__(self) -> None:
        P = int(jnp.shape(self.frame)[-1])
        s = self.sparse_count
        if not 0 <= s <= P:
            raise ValueError(f"PointTargets: n_sparse={s} is not in [0, {P}]")
        if self.per_frame < 0 or (self.per_frame == 0 and s != P):
            raise ValueError("PointTargets: targets past n_sparse need per_frame > 0")
        if self.per_frame > 0 and (P - s) % self.per_frame:
            raise ValueError(
                f"PointTargets: {P - s} frame-major targets are not a multiple of "
                f"per_frame={self.per_frame}"
            )

    @property
    def sparse_count(self) -> int:
        """The number of leading targets at any frames."""
        return int(jnp.shape(self.frame)[-1]) if self.n_sparse is None else self.n_sparse

    def start(self) -> Float[Array, "P 3"]:
        return jnp.zeros_like(self.target)

    def _res(self, P: Array, shift: Array) -> Array:
        return P[self.frame, self.slot] - self.target - shift  # (P, 3)

    def cost(self, P: Float[Array, "T K 3"], shift: Float[Array, "P 3"]) -> Float[Array, ""]:
        r = self._res(P, shift)
        return 0.5 * jnp.sum(self.weight**2 * r * r)

    def rows(self, P: Float[Array, "T K 3"], cols: Columns, shift: Any) -> tuple[Rows, ...]:
        T, D = P.shape[0], cols.fc.support.shape[0]
        r = self._res(P, shift)
        J = cols.rows(self.frame, self.slot)  # (P, 3, D)
        ns, out = self.sparse_count, []
        if self.per_frame:
            F = self.per_frame
            wd = self.weight[ns:].reshape(T, F, 3)
            Jf = (J[ns:].reshape(T, F, 3, D) * wd[..., None]).reshape(T, 3 * F, D)
            out.append(Rows(J=Jf, r=(r[ns:].reshape(T, F, 3) * wd).reshape(T, 3 * F)))
        if ns:
            out.append(Rows(J=J[:ns], r=r[:ns], w=self.weight[:ns] ** 2, frame=self.frame[:ns]))
        return tuple(out)

    def next_round(self, P: Float[Array, "T K 3"], shift: Array) -> tuple[Array, Array]:
        err = P[self.frame, self.slot] - self.target
        new = shift - jnp.where(self.exact[:, None] & self.shifted, err, 0.0)
        return new, jnp.asarray(self.shifted)


class HeightBounds(ResidualTerm):
    """Lowest allowed heights of the kept joints: ``½ Σ (weight · max(lower + s − h, 0))²``.

    One-sided, so its Gauss–Newton model at a step holds the bounds active there. With
    ``exact``, the rounds shift the marked bounds (``s ← max(0, s + lower − h)``, an augmented
    Lagrangian of ``h ≥ lower``), so they are met instead of balanced against the prior; no
    further round is needed for this term once no marked bound is violated by more than
    ``tol``.

    Attributes:
        lower: ``(T, K)`` lowest heights (``-inf``: none).
        weight: per metre.
        up: the up axis (static).
        exact: ``(T, K)`` the bounds the rounds meet (``None``: all stay penalties).
        tol: metres (static).
    """

    lower: Float[Array, "T K"]
    weight: Float[Array, ""]
    up: int = eqx.field(static=True)
    exact: Bool[Array, "T K"] | None = None
    tol: float = eqx.field(static=True, default=0.0)

    def start(self) -> Float[Array, "T K"]:
        return jnp.zeros_like(self.lower)

    def cost(self, P: Float[Array, "T K 3"], shift: Array) -> Float[Array, ""]:
        low = jnp.maximum(self.lower + shift - P[..., self.up], 0.0)
        return 0.5 * jnp.sum((self.weight * low) ** 2)

    def rows(self, P: Float[Array, "T K 3"], cols: Columns, shift: Any) -> tuple[Rows, ...]:
        h, low = P[..., self.up], self.lower + shift
        act = (h < low).astype(P.dtype)  # the active set at P
        lw = self.weight.astype(P.dtype)
        J = cols.axis(self.up) * (lw * act)[..., None]
        return (Rows(J=J, r=lw * act * (h - jnp.where(act > 0, low, h))),)

    def next_round(self, P: Float[Array, "T K 3"], shift: Array) -> tuple[Array, Array]:
        if self.exact is None:
            return shift, jnp.asarray(False)
        gap = self.lower - P[..., self.up]  # > 0: a bound violated
        return jnp.maximum(shift + gap, 0.0), jnp.any(self.exact & (gap > self.tol))


class FrameResidual(ResidualTerm):
    """A per-frame residual ``r_t = f_t(P_t)`` priced by a loss ``Σ_t ρ(r_t)`` (robust allowed).

    Its Gauss–Newton model is the iteratively reweighted ``½ Σ w (r + J δ)²``: the rows
    ``J_t = ∂f_t/∂P_t · ∂P_t/∂y_t`` come from forward-mode products of the residual (one per
    joint coordinate, every frame at once, because ``f`` is separable over frames) and the
    step's per-frame Jacobians (:func:`residual_rows`).
    """

    @abc.abstractmethod
    def residual(self, P: Float[Array, "T K 3"]) -> Float[Array, "T R"]:
        """``(T, R)`` residuals, frame ``t``'s a function of ``P[t]`` alone."""

    @abc.abstractmethod
    def loss(self, r: Float[Array, "T R"]) -> Float[Array, ""]:
        """The term's cost ``Σ ρ`` at residuals ``r`` (``½ Σ w r²`` for a least-squares term)."""

    @abc.abstractmethod
    def weights(self, r: Float[Array, "T R"]) -> Float[Array, "T R"]:
        """Non-negative weights ``w`` of the reweighted model ``½ Σ w r²`` at ``r`` (IRLS:
        ``ρ'(r) / r`` per residual for a loss of ``r`` alone; constant for least squares)."""

    def cost(self, P: Float[Array, "T K 3"], shift: Any = ()) -> Float[Array, ""]:
        return self.loss(self.residual(P))

    def rows(self, P: Float[Array, "T K 3"], cols: Columns, shift: Any = ()) -> tuple[Rows, ...]:
        J, r = residual_rows(self, P, cols.all())
        return (Rows(J=J, r=r),)


def residual_rows(
    term: FrameResidual, P: Float[Array, "T K 3"], Jp: Float[Array, "T K 3 D"]
) -> tuple[Float[Array, "T R D"], Float[Array, "T R"]]:
    """The weighted rows ``√w ⊙ J_t`` and residuals ``√w ⊙ r_t`` of a term at ``P``.

    ``Jp`` holds the per-frame Jacobians of the positions with respect to the channels.
    """
    T, K = P.shape[:2]
    r, lin = jax.linearize(term.residual, P)
    eye = jnp.eye(3 * K, dtype=P.dtype).reshape(3 * K, 1, K, 3)
    dr = jax.lax.map(lambda e: lin(jnp.broadcast_to(e, P.shape)), eye)  # (3K, T, R)
    dr = jnp.moveaxis(dr.reshape(K, 3, T, -1), (0, 1), (2, 3))  # (T, R, K, 3)
    sw = jnp.sqrt(jnp.maximum(term.weights(r), 0.0))
    rows = jnp.einsum("trka,tkad->trd", dr, Jp) * sw[..., None]
    return rows, r * sw
