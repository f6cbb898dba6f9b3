"""Refinement of a texton beyond the closed form: maximum exact likelihood (design §6).

The closed-form fit (:func:`mtex_jax.texture.fit_texton`) regresses the *projected* states
``x_t = Cᵀ(y_t − μ)``, which contain the observation noise ``Cᵀ w_t``. With noticeable noise
the regression is biased (errors in variables: ``A1, A2`` shrink towards 0, ``Q`` is inflated).
:func:`refine_texton` removes that bias by maximising the exact marginal likelihood of the full
LDS (Kalman filter, design §3) over ``(A1, A2, d, B, σ²)`` with ``optimistix.BFGS``, in an
unconstrained parameterisation:

.. code-block:: text

    A1, A2, d           free
    B = tril(L, −1) + diag(exp(ℓ))        (lower-triangular, positive diagonal ⇒ Q ≻ 0)
    σ² = exp(s)

``μ``, ``C`` (orthonormal, so the ``D``-dimensional likelihood reduces to ``k`` dimensions) and
the initial-state Gaussian ``(m0, S0)`` are kept. The result never has a lower exact
log-likelihood than the input (if the optimiser fails to improve, the input is returned) and a
:class:`RefineReport` says what changed.
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .checks import (
    check_positive,
    float_dtype,
)
from .likelihood import check_segments_inputs, kalman_log_likelihood
from .texton import Texton

__all__ = ["RefineReport", "refine_texton"]

LOG_2PI = math.log(2.0 * math.pi)


# --------------------------------------------------------------------------------------------
# Refinement
# --------------------------------------------------------------------------------------------


class RefineReport(eqx.Module):
    """What :func:`refine_texton` did, measured.

    Attributes:
        log_likelihood_before: exact log-likelihood of the input texton on the data.
        log_likelihood_after: exact log-likelihood of the returned texton (``>=`` before).
        n_frames: number of frames used (for per-frame comparisons).
        num_steps: BFGS iterations taken.
        converged: whether optimistix reported success (tolerances met within
            ``max_steps``).
        accepted: whether the optimised parameters were kept (``False`` only if they did not
            improve the likelihood, in which case the input is returned unchanged).
    """

    log_likelihood_before: Float[Array, ""]
    log_likelihood_after: Float[Array, ""]
    n_frames: Float[Array, ""]
    num_steps: Int[Array, ""]
    converged: Bool[Array, ""]
    accepted: Bool[Array, ""]

    @property
    def improvement_per_frame(self) -> Float[Array, ""]:
        """``(after − before) / n_frames`` (nats per frame)."""
        return (self.log_likelihood_after - self.log_likelihood_before) / jnp.maximum(
            self.n_frames, 1.0
        )


def _pack(tex: Texton) -> dict[str, Array]:
    diag = jnp.diagonal(tex.B)
    return dict(
        A1=tex.A1,
        A2=tex.A2,
        d=tex.d,
        L=jnp.tril(tex.B, -1),
        log_diag=jnp.log(jnp.maximum(diag, jnp.finfo(diag.dtype).tiny)),
        log_sigma2=jnp.log(tex.sigma2),
    )


def _unpack(theta: dict[str, Array], tex: Texton) -> Texton:
    B = jnp.tril(theta["L"], -1) + jnp.diag(jnp.exp(theta["log_diag"]))
    return eqx.tree_at(
        lambda t: (t.A1, t.A2, t.d, t.B, t.sigma2),
        tex,
        (theta["A1"], theta["A2"], theta["d"], B, jnp.exp(theta["log_sigma2"])),
    )


def refine_texton(
    texton: Texton,
    Y: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    max_steps: int = 200,
    rtol: float = 1e-8,
    atol: float = 1e-8,
) -> tuple[Texton, RefineReport]:
    """Maximise the exact LDS log-likelihood over ``(A1, A2, d, B, σ²)`` with BFGS (design §6).

    Objective: ``−exact_log_likelihood_segments(texton, Y, mask) / n_frames``, minimised with
    ``optimistix.BFGS(rtol, atol)`` in the unconstrained parameterisation of the module
    docstring, starting from ``texton`` (typically the closed-form fit). ``μ``, ``C``, ``m0``
    and ``S0`` are kept fixed. No stability constraint is imposed during refinement.

    Args:
        texton: a single texton (the starting point).
        Y: ``(T, D)`` or ``(S, T, D)`` observations.
        mask: segment ids (``-1`` = unused), as for :func:`mtex_jax.texture.fit_texton`.
        max_steps: maximum BFGS iterations (static).
        rtol: BFGS relative tolerance.
        atol: BFGS absolute tolerance.

    Returns:
        ``(refined texton, RefineReport)``. The refined texton's exact log-likelihood is never
        below the input's: if the optimiser does not improve it, the input is returned and
        ``report.accepted`` is ``False``.

    Raises:
        ValueError: for a texton whose likelihood is not the Kalman one (Student-t
            innovations, or an observation model without that form such as the residual
            AR(2)): the refinement would maximise another model's likelihood.
    """
    texton, Y, mask = check_segments_inputs(texton, Y, mask)
    if isinstance(max_steps, bool) or not isinstance(max_steps, int | np.integer) or max_steps < 1:
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}")
    rtol = check_positive("rtol", rtol)
    atol = check_positive("atol", atol)
    return _refine_jit(texton, Y, mask, int(max_steps), rtol, atol)


def _refine_impl(
    tex: Texton, Y: Array, mask: Array, max_steps: int, rtol: float, atol: float
) -> tuple[Texton, RefineReport]:
    dtype = float_dtype(Y, tex.mu)
    Y = Y.astype(dtype)
    tex = jax.tree.map(lambda a: a.astype(dtype), tex)
    n_frames = jnp.sum(mask >= 0).astype(dtype)
    scale = jnp.maximum(n_frames, 1.0)

    def loss(theta: dict[str, Array], _: Any) -> Array:
        return -kalman_log_likelihood(_unpack(theta, tex), Y, mask) / scale

    theta0 = _pack(tex)
    solver = optx.BFGS(rtol=rtol, atol=atol)
    sol = optx.minimise(loss, solver, theta0, max_steps=max_steps, throw=False)
    new = _unpack(sol.value, tex)
    ll_before = kalman_log_likelihood(tex, Y, mask)
    ll_after = kalman_log_likelihood(new, Y, mask)
    accept = jnp.isfinite(ll_after) & (ll_after >= ll_before)
    out = jax.tree.map(lambda a, b: jnp.where(accept, a, b), new, tex)
    report = RefineReport(
        log_likelihood_before=ll_before,
        log_likelihood_after=jnp.where(accept, ll_after, ll_before),
        n_frames=n_frames,
        num_steps=jnp.asarray(sol.stats["num_steps"]),
        converged=sol.result == optx.RESULTS.successful,
        accepted=accept,
    )
    return out, report


_refine_jit = eqx.filter_jit(_refine_impl)
