"""The whitening change of variables that makes the edit's least squares well conditioned.

The quadratic part of the objective (texture prior + anchor) in the displacement ``z`` of the
free frames is ``½ zᵀ H z + bᵀ z`` with ``H = w_prior² RᵀR + w_anchor² I`` block-banded
(:func:`~mtex_jax.edit._prior.prior_hessian`). With the block Cholesky factor ``H = L Lᵀ``
(two frames per block, so the band is block-tridiagonal) and

.. code-block:: text

    z = z* + L⁻ᵀ u,    z* = −H⁻¹ (b + H_{free,held} δ_held)

the quadratic part is ``½‖u‖² + const``: its residual *is* ``u``. ``z*`` is the motion the
prior wants given the held frames (a pose constraint's displacement ``δ``), the texture's own
constrained synthesis around an exact pose. Levenberg–Marquardt then solves in ``u``, where
the prior's Hessian is the identity and only the constraint residuals curve the problem, so
the conjugate-gradient solves of its damped normal equations take few iterations.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Float

from ..linalg import BlockTridiagCholesky, block_tridiag_cholesky, block_tridiag_solve

__all__ = ["Whitening", "band_matvec", "band_quad", "whitening", "whitening_each"]


class Whitening(eqx.Module):
    """``z = z* + L⁻ᵀ u`` for a motion of ``T`` frames (padded to an even number).

    Attributes:
        factor: block Cholesky factor of ``H`` (blocks of two frames).
        z_star: ``(T, D)`` the prior's optimum given the held frames.
        free: ``(T, D)`` 1 where a variable is free, 0 at held frames.
    """

    factor: BlockTridiagCholesky
    z_star: Float[Array, "T D"]
    free: Float[Array, "T D"]

    def displacement(self, u: Float[Array, "T D"]) -> Float[Array, "T D"]:
        """``z* + L⁻ᵀ u`` (zero at held frames besides ``z*``)."""
        T, D = u.shape
        n = self.factor.Linv.shape[0]
        v = jnp.zeros((2 * n, D), u.dtype).at[:T].set(u).reshape(n, 2 * D)
        x = _back_substitute(self.factor, v).reshape(2 * n, D)[:T]
        return self.z_star + x * self.free


def _back_substitute(f: BlockTridiagCholesky, u: Array) -> Array:
    """``x`` with ``Lᵀ x = u``: ``x_I = L_I⁻ᵀ (u_I − M_Iᵀ x_{I+1})``, from the last block."""
    b = u.shape[-1]
    M_next = jnp.concatenate([f.M, jnp.zeros((1, b, b), u.dtype)], axis=0)

    def step(x_next: Array, blk: tuple[Array, Array, Array]) -> tuple[Array, Array]:
        Li, Mi, ui = blk
        x = Li.T @ (ui - Mi.T @ x_next)
        return x, x

    _, xs = lax.scan(step, jnp.zeros((b,), u.dtype), (f.Linv, M_next, u), reverse=True)
    return xs


def whitening(
    bands: tuple[Array, Array, Array],
    anchor: Float[Array, " D"],
    held: Array,
    delta: Float[Array, "T D"],
    linear: Float[Array, "T D"],
) -> Whitening:
    """Factor ``H`` over the free frames and the prior's optimum ``z*``.

    Args:
        bands: ``(H0, H1, H2)`` of the (weighted) prior Hessian, each ``(T, D, D)``.
        anchor: ``(D,)`` per-channel anchor weights (added as ``diag(anchor²)``).
        held: ``(T,)`` bool, frames held exactly.
        delta: ``(T, D)`` displacement of the held frames (zero elsewhere).
        linear: ``(T, D)`` the linear term ``b`` (zero for the relative prior).

    Returns:
        :class:`Whitening`.
    """
    H0, H1, H2 = bands
    T, D, _ = H0.shape
    dt = H0.dtype
    eye = jnp.eye(D, dtype=dt)
    f = (~held).astype(dt)
    b = linear + band_matvec(bands, delta)
    H0 = jnp.where(held[:, None, None], eye, H0 + jnp.diag(anchor**2))
    H1 = H1 * (f * jnp.concatenate([jnp.zeros((1,), dt), f[:-1]]))[:, None, None]
    H2 = H2 * (f * jnp.concatenate([jnp.zeros((2,), dt), f[:-2]]))[:, None, None]
    if T % 2:  # pad with one independent frame
        H0 = jnp.concatenate([H0, eye[None]], axis=0)
        H1 = jnp.concatenate([H1, jnp.zeros((1, D, D), dt)], axis=0)
        H2 = jnp.concatenate([H2, jnp.zeros((1, D, D), dt)], axis=0)
    n = H0.shape[0] // 2
    ev, od = slice(0, 2 * n, 2), slice(1, 2 * n, 2)
    top = jnp.concatenate([H0[ev], jnp.swapaxes(H1[od], -1, -2)], axis=-1)
    bot = jnp.concatenate([H1[od], H0[od]], axis=-1)
    diag = jnp.concatenate([top, bot], axis=-2)  # (n, 2D, 2D)
    s_top = jnp.concatenate([H2[ev][1:], H1[ev][1:]], axis=-1)
    s_bot = jnp.concatenate([jnp.zeros_like(H2[od][1:]), H2[od][1:]], axis=-1)
    sub = jnp.concatenate([s_top, s_bot], axis=-2)  # (n − 1, 2D, 2D)
    factor = block_tridiag_cholesky(diag, sub)
    rhs = jnp.zeros((2 * n, D), dt).at[:T].set(-b * f[:, None]).reshape(n, 2 * D, 1)
    z_star = block_tridiag_solve(factor, rhs).reshape(2 * n, D)[:T] * f[:, None]
    return Whitening(
        factor=factor, z_star=z_star + delta, free=jnp.broadcast_to(f[:, None], (T, D))
    )


def _down(v: Array, n: int) -> Array:
    """``v`` moved ``n`` rows later (``out[t] = v[t − n]``, zero rows first)."""
    return jnp.concatenate([jnp.zeros((n, *v.shape[1:]), v.dtype), v[:-n]], axis=0)


def _up(v: Array, n: int) -> Array:
    """``v`` moved ``n`` rows earlier (``out[t] = v[t + n]``, zero rows last)."""
    return jnp.concatenate([v[n:], jnp.zeros((n, *v.shape[1:]), v.dtype)], axis=0)


def band_matvec(bands: tuple[Array, Array, Array], v: Float[Array, "T D"]) -> Float[Array, "T D"]:
    """``H v`` for the symmetric block band ``(H0, H1, H2)`` (see ``prior_hessian``; the
    blocks ``H1[0]``, ``H2[0]``, ``H2[1]`` must be zero, as there). The vectors are shifted,
    not the ``(T, D, D)`` bands, so no copy of a band is made."""
    H0, H1, H2 = bands
    mv = lambda A, x: jnp.einsum("tde,te->td", A, x)
    mtv = lambda A, x: jnp.einsum("ted,te->td", A, x)
    out = mv(H0, v) + mv(H1, _down(v, 1)) + mv(H2, _down(v, 2))
    return out + _up(mtv(H1, v), 1) + _up(mtv(H2, v), 2)


def band_quad(bands: tuple[Array, Array, Array], v: Float[Array, "T D"]) -> Float[Array, ""]:
    """``vᵀ H v`` for the symmetric block band ``(H0, H1, H2)`` (as :func:`band_matvec`)."""
    H0, H1, H2 = bands
    q = jnp.einsum("td,tde,te->", v, H0, v)
    q = q + 2.0 * jnp.einsum("td,tde,te->", v, H1, _down(v, 1))
    return q + 2.0 * jnp.einsum("td,tde,te->", v, H2, _down(v, 2))


# :func:`whitening`, factorised one motion after the other under ``vmap`` (``lax.map``): XLA's
# CPU backend runs the batched triangular solves of a batched block Cholesky about 60× slower
# per matrix than single ones (a vmap of three 120-frame motions did not finish in 5 minutes)
whitening_each = jax.custom_batching.custom_vmap(whitening)


@whitening_each.def_vmap
def _whitening_each_vmap(axis_size: int, in_batched, *args):
    full = jax.tree.map(
        lambda a, b: a if b else jnp.broadcast_to(a, (axis_size, *jnp.shape(a))),
        args,
        tuple(in_batched),
    )
    out = lax.map(lambda xs: whitening(*xs), full)
    return out, jax.tree.map(lambda _: True, out)
