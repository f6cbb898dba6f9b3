"""Per-texton synthesis: noise-driven and constrained (design §5; MT §5.4, Eq. 6–9, Fig. 4, 10, 11).

For a texton (design §2) and a length ``l``, the states ``x_0 … x_{l−1}`` (0-based) obey the
``l − 2`` dynamics equations

.. code-block:: text

    e_j(x) = x_j − A1 x_{j−1} − A2 x_{j−2} − d = B v_j,     j = 2 … l−1,   v_j ~ N(0, I_k).

Constrained synthesis holds a set ``F`` of frames (the first two, the last two, and any edited
frames) at given states and solves the over-determined system in the free states in the
least-squares sense

.. code-block:: text

    min_{x_free}  Σ_j ‖ W (e_j(x) − B v_j) ‖²,     W = B⁻¹ ("whitened") or I ("paper").

With ``W = B⁻¹`` the objective is ``Σ_j ‖B⁻¹ e_j − v_j‖²``; with ``v = 0`` its minimiser is the
mean of the LDS conditioned on ``x_F`` and with ``v ~ N(0, I)`` it is an exact sample of that
conditional (perturb-and-MAP: the minimiser is ``J⁻¹ Gᵀ(c + v)``, whose covariance is
``J⁻¹ Gᵀ G J⁻¹ = J⁻¹``, the conditional covariance). The normal matrix ``J = Σ_j G_jᵀ G_j``
is block pentadiagonal in frames; fixed frames are eliminated by masks (their rows and columns
replaced by the identity, their contribution moved to the right-hand side) so that every edit
has the same static shapes, and the system is solved by :mod:`mtex_jax.linalg` in
``O(l·k³)``.

With both ends held and no edits (the case of a texton between two key poses) the same
solution comes from the dynamics recursion itself (:func:`solve_bridge`): the free motion from the
start frames plus the control, found from a ``2k × 2k`` system, that brings it to the end
frames; ``O(l·k²)`` per sample, 3–4× faster than the banded solve for one texton.
"""

from __future__ import annotations

from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Bool, Float

from ...core import (
    MAX_GENERATED_FRAMES,
    as_array,
    check_count,
    check_key,
    cut_frames,
    pad_frames,
)
from .._noise.draws import independent_innovations
from .._noise.innovation_process import InnovationProcess, draw_innovations
from .._texton.texton import Texton
from .._texton.validate import check_finite_output
from .bridge import bridge_usable, solve_bridge
from .normal import constrained_equations, observe, solve_constrained
from .texton_buckets import bucket_noise, held_end, texton_bucket

Weighting = Literal["whitened", "paper"]


def _check_frames(name: str, y: Any, shape: tuple[int, ...]) -> Array:
    if y is None:
        raise ValueError(f"{name} must be an array of shape {shape}, got None")
    y = as_array(y)  # jnp.asarray of a host array would compile a copy per shape
    if tuple(y.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(y.shape)}")
    if not jnp.issubdtype(y.dtype, jnp.floating):
        y = y.astype(jnp.result_type(float))
    if not isinstance(y, Tracer) and not np.isfinite(np.asarray(y)).all():
        raise ValueError(f"{name} contains NaN or inf")
    return y


def synthesize_texton(
    key: Array | None,
    texton: Texton,
    length: int,
    start: Float[ArrayLike, "2 D"],
    end: Float[ArrayLike, "2 D"] | None = None,
    fixed: tuple[Bool[ArrayLike, " l"], Float[ArrayLike, "l D"]] | None = None,
    weighting: Weighting = "whitened",
    innovations: InnovationProcess | None = None,
) -> Float[Array, "l D"]:
    """Synthesise ``length`` frames from one texton, noise-driven or constrained (MT §5.4).

    Key poses are projected to states with ``x = Cᵀ(y − μ)``; the result is ``μ + C x_t``.

    * ``end is None and fixed is None``: noise-driven (MT Fig. 4):
      ``x_t = A1 x_{t−1} + A2 x_{t−2} + d + B v_t`` from the two start states.
    * otherwise constrained (MT Eq. 6–9): the first two frames, the last two (if ``end`` is
      given) and every frame with ``fixed[0][t]`` true (MT Fig. 11, editing; pose
      ``fixed[1][t]``) are held; the free states minimise
      ``Σ_{j=2}^{l−1} ‖W(x_j − A1 x_{j−1} − A2 x_{j−2} − d − B v_j)‖²`` with ``W = B⁻¹``
      (``weighting="whitened"``, an exact sample of the LDS conditioned on the held states,
      or its mean when ``key is None``) or ``W = I`` (``weighting="paper"``, MT Eq. 9). With
      ``end=None`` the frames after the last held one follow the dynamics with the same
      noise, i.e. noise-driven continuation (computed by the recursion: they and their
      equations are not part of the least squares, which for an unstable texton would be
      as ill-conditioned as ``ρ^(2·tail)``).

    How the key is used: in every mode it gives the noise of the dynamics equations (with
    ``innovations``, a texture's :class:`~mtex_jax.texture.InnovationProcess`, drawn from it
    by :func:`~mtex_jax.texture.draw_innovations` instead, as :func:`synthesize` does; else),
    ``v`` ``(l−2, k)`` standard normal, by the Box–Muller transform of
    ``jax.random.uniform(key, (2, ⌈(l−2)k/2⌉))`` (cheaper than ``jax.random.normal`` in
    float64 on CPU; cosines first, then sines, in row-major order). The
    constrained sample is the perturb-and-MAP solution of the equations with that noise: with
    ``W = B⁻¹`` an exact sample of the LDS conditioned on the held frames (the mean when
    ``key is None``), and with the same key the noise-driven motion and the constrained one
    share their noise (the constrained motion is the noise-driven one plus the control that
    brings it to the end frames, see :func:`solve_bridge`).

    How it is computed. Both ends held and no edits (the usual constrained case,
    ``length ≥ 6``): from the dynamics recursion and a ``2k × 2k`` system (:func:`solve_bridge`,
    ``O(l·k²)`` per sample after ``O(log l)`` products of ``2k × 2k`` matrices), unless the
    texton amplifies over the segment so much that the recursion would lose accuracy; then,
    and with edits or an open end, the masked normal equations and the banded solver
    (``O(l·k³)``). Both give the same least-squares solution (to rounding; tested against
    dense least squares at 1e-9 relative). Under
    ``vmap`` over keys everything that does not depend on the noise is computed once.

    One program serves a shape bucket of lengths (design §11: multiples of 64 frames up to
    192, of 1,024 above; the noise is the draw for ``length``, the rows past it are cut), and
    the mask and poses are arrays, so neither a new length in a bucket nor a new edit
    recompiles (with ``innovations``, a small draw program per length).
    Any ``length ≥ 4`` (``≥ 2`` without ``end``) works: the same texton extrapolates (MT Fig. 10).
    ``vmap`` over ``key`` (or over the poses) works.

    Args:
        texton: a single :class:`~mtex_jax.texture.Texton` (``D``, ``k``).
        key: JAX PRNG key (see above); ``None`` for zero noise (the conditional mean).
        length: number of frames ``l``.
        start: ``(2, D)`` first two frames.
        end: ``(2, D)`` last two frames, or ``None``.
        fixed: ``(mask (l,) bool, poses (l, D))`` extra held frames, or ``None``.
        weighting: ``"whitened"`` (default) or ``"paper"``.
        innovations: ``None`` (default: independent innovations) or the
            :class:`~mtex_jax.texture.InnovationProcess` to draw them from (e.g.
            ``texture.innovations``).

    Returns:
        ``(l, D)`` observations ``μ + C x_t``; held frames equal ``μ + C Cᵀ(y − μ)`` of the
        given poses (the poses themselves when they lie in the texton's subspace).

    Raises:
        ValueError: bad shapes, non-finite poses, unknown weighting, too short or too long
            ``length`` (``MAX_GENERATED_FRAMES``), or a result that overflows (an unstable
            texton, spectral radius > 1, run noise-driven for too long: the message names
            the radius; learn with ``LearnConfig(rho_max=0.999)``, the default).
        TypeError: ``key`` is not a PRNG key (nor ``None``).
    """
    check_key(key, "synthesize_texton", allow_none=True)
    if not isinstance(texton, Texton) or texton.is_stacked:
        raise ValueError("texton must be a single (unstacked) Texton")
    if weighting not in ("whitened", "paper"):
        raise ValueError(f"weighting must be 'whitened' or 'paper', got {weighting!r}")
    if isinstance(length, bool) or not isinstance(length, int | np.integer):
        raise ValueError(f"length must be an int, got {length!r}")
    length = int(length)
    min_len = 2 if end is None else 4
    if length < min_len:
        raise ValueError(f"length must be >= {min_len}, got {length}")
    check_count(length, "length", MAX_GENERATED_FRAMES)
    D = texton.obs_dim
    start_a = _check_frames("start", start, (2, D))
    end_a = None if end is None else _check_frames("end", end, (2, D))
    fixed_a: tuple[Array, Array] | None = None
    if fixed is not None:
        if not isinstance(fixed, tuple | list) or len(fixed) != 2:
            raise ValueError("fixed must be a pair (mask (length,) bool, poses (length, D))")
        mask = as_array(fixed[0])
        if tuple(mask.shape) != (length,) or mask.dtype != jnp.bool_:
            raise ValueError(
                f"fixed mask must be bool of shape ({length},), got {mask.dtype}"
                f" {tuple(mask.shape)}"
            )
        poses = _check_frames("fixed poses", fixed[1], (length, D))
        fixed_a = (mask, poses)
    if innovations is not None and not isinstance(innovations, InnovationProcess):
        raise TypeError(
            f"innovations must be an InnovationProcess or None, got {type(innovations).__name__}"
        )
    # one program per shape bucket of lengths (design §11): the rows past ``length`` pad the
    # bucket and are cut; the noise is drawn inside the program for the bucket
    rows = texton_bucket(length)
    n_valid = jax.device_put(np.asarray(length, np.int32))
    if fixed_a is not None:  # the padding rows are free (past the end pair, or an open tail)
        fixed_a = (_pad_mask(fixed_a[0], rows), pad_frames(fixed_a[1], rows, axis=0))
    v = None
    if innovations is not None and key is not None:
        # the process's draws are not prefix-stable: drawn for the length (a small program
        # per length), zero-padded to the bucket
        v = _process_draws(key, innovations, (length - 2, texton.C.shape[-1]), rows - 2, texton)
    bridge = end_a is not None and fixed_a is None and length >= 6
    if end_a is None and fixed_a is None:
        out = _noise_driven_key_jit(texton, key, v, n_valid, rows, start_a)
    else:
        # concrete inputs: the solve's failure is checked on the host (NaN frames), so that
        # the program has no host callback and the persistent compilation cache keeps it
        # (design §11); traced ones (under jit, vmap, grad): checked in the program
        traced = any(
            isinstance(a, Tracer)
            for a in jax.tree.leaves((key, texton, start_a, end_a, fixed_a, innovations))
        )
        out = _constrained_key_jit(
            texton, key, v, n_valid, rows, start_a, end_a, fixed_a, weighting, bridge, traced
        )
        if not traced and not np.isfinite(np.asarray(out)[:length]).all():
            raise ValueError(
                "synthesize_texton: normal matrix not positive definite or non-finite states"
                " (non-finite or singular texton parameters?)"
            )
    out = cut_frames(out, length)
    check_finite_output(out, texton, "synthesize_texton")
    return out


def _pad_mask(mask: Array, rows: int) -> Array:
    """A held mask ``(l,)`` padded with ``False`` to ``rows`` (on the host when concrete)."""
    try:
        m = np.asarray(mask)
    except jax.errors.TracerArrayConversionError:
        return jnp.pad(mask, (0, rows - mask.shape[0]))
    return jax.device_put(np.pad(m, (0, rows - m.shape[0])))


@eqx.filter_jit
def _process_draws(
    key: Array, process: InnovationProcess, shape: tuple[int, int], rows: int, tex: Texton
) -> Array:
    v = draw_innovations(key, process, shape, tex.mu.dtype, tex.dof)
    return jnp.pad(v, ((0, rows - shape[0]), (0, 0)))


def draw_noise(
    tex: Texton, key: Array | None, length: int, process: InnovationProcess | None = None
) -> Array:
    """``v_j``, ``j = 2 … l−1``: ``(l−2, k)`` from :func:`independent_innovations`
    (``N(0, I_k)`` for Gaussian textons), or from ``process`` (:func:`draw_innovations`); 0 if
    no key."""
    shape = (length - 2, tex.C.shape[-1])
    if key is None:
        return jnp.zeros(shape, tex.mu.dtype)
    if process is not None:
        return draw_innovations(key, process, shape, tex.mu.dtype, tex.dof)
    return independent_innovations(key, shape, tex.mu.dtype, tex.dof)


# --------------------------------------------------------------------------------------------
# noise-driven
# --------------------------------------------------------------------------------------------


def _noise_driven(tex: Texton, v: Array, start: Array, n_valid: Array | None = None) -> Array:
    """``(l, D)`` from the recursion; ``n_valid``: ``v`` pads a shape bucket, and the states
    of the frames from ``n_valid`` on are zero (no overflow past the segment)."""
    dt = tex.mu.dtype
    x01 = (start.astype(dt) - tex.mu) @ tex.C

    def step(carry: tuple[Array, Array], vj: Array) -> tuple[tuple[Array, Array], Array]:
        xm1, xm2 = carry
        x = tex.A1 @ xm1 + tex.A2 @ xm2 + tex.d + tex.B @ vj
        return (x, xm1), x

    def masked(carry: tuple[Array, Array], inp: tuple[Array, Array]) -> Any:
        vj, on = inp
        (x, xm1), _ = step(carry, vj)
        x = jnp.where(on, x, 0.0)
        return (x, xm1), x

    if n_valid is None:
        _, rest = lax.scan(step, (x01[1], x01[0]), v)
    else:
        on = jnp.arange(2, v.shape[0] + 2) < n_valid
        _, rest = lax.scan(masked, (x01[1], x01[0]), (v, on))
    states = jnp.concatenate([x01, rest], axis=0)
    return tex.mu + states @ tex.C.T


def _noise_driven_key(
    tex: Texton, key: Array | None, v: Array | None, n_valid: Array, rows: int, start: Array
) -> Array:
    if v is None:
        v = bucket_noise(tex, key, n_valid, rows)
    return _noise_driven(tex, v, start, n_valid)


_noise_driven_key_jit = eqx.filter_jit(_noise_driven_key)


def constrained_texton(
    tex: Texton,
    v: Array,
    start: Array,
    end: Array | None,
    fixed: tuple[Array, Array] | None,
    weighting: str,
    check: bool = True,
    n_valid: Array | None = None,
    bridge: bool = True,
    eq_weight: Array | None = None,
) -> Array:
    """Constrained synthesis by perturb-and-MAP with the equation noise ``v`` ``(l−2, k)``.

    ``check=False``: a failed solve gives NaN frames instead of raising in the program
    (:func:`~.normal.observe`), for a caller that checks the result on the host.

    Both ends held and no edits (``l ≥ 6``): :func:`solve_bridge`, unless the texton amplifies
    over the segment so much (:func:`bridge_usable`) that the recursion would lose
    accuracy; then, and in every other case, the masked normal
    equations and the banded solve (:func:`solve_constrained`; the pair blocks of the
    block-tridiagonal form are built directly from the Gram matrix and the held mask, an
    odd length padded with one held frame). Under ``vmap`` over ``v`` alone (many samples of
    one texton) the factorisations and propagators are shared and the samples become the
    rows of GEMMs. Returns ``(l, D)``: one GEMM ``[x, 1] [Cᵀ; μ]``.

    ``n_valid`` (traced): a segment of ``n_valid`` frames in a shape bucket of ``l`` rows
    (design §11); ``fixed`` is then ``(l,)`` (its padding free) and ``bridge`` (static) says
    whether the segment may take the bridge (``n_valid ≥ 6``, no edits). The end pair sits at
    rows ``n_valid − 2, n_valid − 1`` and the rows after it are held there (banded) or zero
    (bridge, open tail), so no free state follows the segment and the solution of its frames
    is that of the segment alone.

    ``eq_weight`` ``(l,)``: weights of the least-squares equations (the transition bend,
    design §10.11; :func:`~.normal.transition_weights`), solved by the banded path; ``None``:
    all 1.
    """
    length = v.shape[0] + 2
    dt = tex.mu.dtype
    w = v.astype(dt) @ tex.B.T  # the noise in state units, w_j = B v_j (the one reader of v)
    short = length < 6 if n_valid is None else not bridge
    if end is None or fixed is not None or short or eq_weight is not None:
        if n_valid is not None and end is not None:  # the end pair at its rows of the bucket
            fixed, end = held_end(length, n_valid, end, fixed), None
        eqs = constrained_equations(tex, length, w, start, end, fixed, weighting, eq_weight)
        if n_valid is not None and eqs.tail is not None:  # an open tail stops at the segment
            eqs = eqx.tree_at(lambda e: e.tail, eqs, eqs.tail & (jnp.arange(length) < n_valid))
        return observe(tex, *solve_constrained(tex, eqs, w), check=check)
    proj = lambda y: (y.astype(dt) - tex.mu) @ tex.C
    x01, xe = proj(start), proj(end)
    # the bridge where the texton does not amplify too much over the segment (decided from
    # the dynamics alone, so unbatched under vmap over keys or poses); an amplifying texton
    # enters the bridge as A1 = A2 = 0, so that its unused result stays finite (for
    # derivatives under a batched lax.cond too), and is solved banded
    free = length - 4 if n_valid is None else n_valid - 4
    usable = bridge_usable(tex.A1, tex.A2, free, length - 4)
    safe = eqx.tree_at(
        lambda t: (t.A1, t.A2),
        tex,
        (jnp.where(usable, tex.A1, 0.0), jnp.where(usable, tex.A2, 0.0)),
    )
    x, ok = solve_bridge(safe, w, x01, xe, weighting, n_valid)

    def banded(_: Any) -> tuple[Array, Array]:
        if n_valid is None:
            eqs = constrained_equations(tex, length, w, start, end, None, weighting)
        else:
            held = held_end(length, n_valid, end, None)
            eqs = constrained_equations(tex, length, w, start, None, held, weighting)
        return solve_constrained(tex, eqs, w)

    x, ok = lax.cond(usable, lambda _: (x, ok), banded, None)
    return observe(tex, x, ok, check=check)


def _constrained_key(
    tex: Texton,
    key: Array | None,
    v: Array | None,
    n_valid: Array,
    rows: int,
    start: Array,
    end: Array | None,
    fixed: tuple[Array, Array] | None,
    weighting: str,
    bridge: bool,
    check: bool,
) -> Array:
    if v is None:
        v = bucket_noise(tex, key, n_valid, rows)
    return constrained_texton(tex, v, start, end, fixed, weighting, check, n_valid, bridge)


_constrained_key_jit = eqx.filter_jit(_constrained_key)
