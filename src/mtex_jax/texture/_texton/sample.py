"""Noise-driven sampling of a texton (MT Fig. 4)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Float

from ...core import MAX_GENERATED_FRAMES, check_count, check_key
from .checks import as_float_array, check_finite, psd_cholesky
from .texton import Texton, check_texton
from .validate import check_finite_output

# --------------------------------------------------------------------------------------------
# Sampling (MT Fig. 4)
# --------------------------------------------------------------------------------------------


def sample_texton(
    key: Array,
    texton: Texton,
    length: int,
    x1: ArrayLike | None = None,
    x2: ArrayLike | None = None,
    *,
    observation_noise: bool = True,
) -> tuple[Float[Array, "L k"], Float[Array, "L D"]]:
    """Noise-driven synthesis from one texton (MT Fig. 4).

    ``x_t = A1 x_{t−1} + A2 x_{t−2} + d + B v_t`` with ``v_t ~ N(0, I)`` for ``t = 3..L``
    (``lax.scan``), starting from the two given states; ``y_t = μ + C x_t (+ σ w_t)``.

    Args:
        texton: a single texton.
        key: a JAX PRNG key.
        length: number of frames ``L >= 2`` (static).
        x1: ``(k,)`` first state (e.g. a key pose reprojected, ``Cᵀ(y − μ)``). If ``x1``
            and ``x2`` are ``None`` both are drawn from ``N(m0, S0)``; give both or neither.
        x2: ``(k,)`` second state, as ``x1``.
        observation_noise: add ``w_t ~ N(0, σ² I_D)`` to the observations. MT Fig. 4 shows
            the noise-free projection ``μ + C x_t``; ``True`` samples the full generative model.

    Returns:
        ``(states (L, k), observations (L, D))``; ``states[0] = x1``, ``states[1] = x2``.

    Raises:
        ValueError: bad arguments, or a result that overflows (an unstable texton, spectral
            radius > 1, sampled for too long; the message names the radius).
    """
    check_key(key, "sample_texton")
    texton = check_texton("texton", texton, stacked=False)
    if isinstance(length, bool) or not isinstance(length, int | np.integer) or length < 2:
        raise ValueError(f"length must be an int >= 2, got {length!r}")
    check_count(length, "length", MAX_GENERATED_FRAMES)
    k = texton.state_dim
    if (x1 is None) != (x2 is None):
        raise ValueError("give both x1 and x2, or neither (then they are sampled from m0, S0)")
    xs: tuple[Array, Array] | None = None
    if x1 is not None and x2 is not None:
        a = as_float_array("x1", x1, (1,), f"({k},)")
        b = as_float_array("x2", x2, (1,), f"({k},)")
        for name, v in (("x1", a), ("x2", b)):
            if v.shape != (k,):
                raise ValueError(f"{name} must have shape ({k},), got {tuple(v.shape)}")
            check_finite(name, v)
        xs = (a, b)
    states, obs = _sample_jit(texton, key, int(length), xs, bool(observation_noise))
    check_finite_output(obs, texton, "sample_texton")
    return states, obs


def _sample_impl(
    tex: Texton,
    key: Array,
    length: int,
    xs: tuple[Array, Array] | None,
    observation_noise: bool,
) -> tuple[Array, Array]:
    dtype = tex.mu.dtype
    k = tex.C.shape[-1]
    D = tex.C.shape[0]
    k_init, k_dyn, k_obs = jax.random.split(key, 3)
    if xs is None:
        L0 = psd_cholesky(tex.S0, jnp.zeros((), dtype))
        s = tex.m0 + L0 @ jax.random.normal(k_init, (2 * k,), dtype)
        x1, x2 = s[:k], s[k:]
    else:
        x1, x2 = xs[0].astype(dtype), xs[1].astype(dtype)
    V = jax.random.normal(k_dyn, (length - 2, k), dtype)
    if tex.dof is not None:  # Student-t innovations: B v / √g, g ~ Gamma(ν/2, rate ν/2)
        g = jax.random.gamma(jax.random.fold_in(k_dyn, 1), tex.dof / 2, (length - 2,), dtype)
        V = V / jnp.sqrt(g / (tex.dof / 2))[:, None]

    def step(carry: tuple[Array, Array], v: Array) -> tuple[tuple[Array, Array], Array]:
        xm1, xm2 = carry
        x = tex.A1 @ xm1 + tex.A2 @ xm2 + tex.d + tex.B @ v
        return (x, xm1), x

    _, rest = lax.scan(step, (x2, x1), V)
    states = jnp.concatenate([x1[None], x2[None], rest], axis=0)
    obs = tex.mu + states @ tex.C.T
    if observation_noise:
        obs = obs + jnp.sqrt(tex.sigma2) * jax.random.normal(k_obs, (length, D), dtype)
    return states, obs


_sample_jit = eqx.filter_jit(_sample_impl)
