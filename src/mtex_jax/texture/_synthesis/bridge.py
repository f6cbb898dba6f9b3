"""The bridge recursion for constrained synthesis: the noise-driven motion from the start frames
plus the control that brings it to the end frames, from a ``2k × 2k`` system (the fast path of
:func:`~mtex_jax.texture.synthesize_texton` when both ends are held and the texton does not
amplify too much over the segment)."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jax import lax
from jaxtyping import Array

from ...linalg import sym
from .._texton.texton import Texton

# --------------------------------------------------------------------------------------------
# constrained, both ends held, no edits: the bridge recursion
# --------------------------------------------------------------------------------------------

# frames per step of the blocked forward recursion of the batched bridge
_BRIDGE_BLOCK = 4
# Largest entry of the propagators [I 0] F̃^p (p = 1, 2, 4, …, n) for which the bridge is
# used, by floating-point item size; beyond it (a texton that amplifies over the segment) the
# banded solve is used instead (the same least-squares solution). The bridge's relative error
# grows roughly like eps·growth²: float64 (length 172, k = 15) 1e-13 or less for contracting
# textons, 1.5e-11 at growth 20, 8.6e-8 at 2,600; float32 2.6e-5 at growth 7.7 (the banded
# solve: 7e-6), 8.4e-4 at 40. The textons learned from the CMU salsa clips have growth 4–8 over
# their longest segments (one 31, one 160: that one is solved banded).
_BRIDGE_MAX_GROWTH = {8: 100.0, 4: 10.0}


def _adjoint_rows(Fa: Array, k: int, n: int) -> Array:
    """``V_m = [I_k 0] F̃ᵐ`` for ``m = 1 … n`` ``(n, k, 2k)`` by doubling: one GEMM per round.

    ``V_{m+p} = V_m F̃ᵖ``: with ``V_1 … V_p`` known, ``V_{p+1} … V_{2p}`` is one product of
    the stack with ``F̃ᵖ`` (``⌈log₂ n⌉`` rounds instead of ``n`` dependent products).
    """
    V = Fa[None, :k, :]
    P = Fa
    while V.shape[0] < n:
        c = min(V.shape[0], n - V.shape[0])
        V = jnp.concatenate([V, V[:c] @ P], axis=0)
        if V.shape[0] < n:
            P = P @ P
    return V


def _bit_plan(n: int | Array, n_max: int) -> list[tuple[Any, Any]]:
    """``(bit b of n, n ≥ 2^{b+1})`` for the binary powering loops: Python bools for a static
    ``n`` (the loop of a fixed length), traced ones for a traced ``n ≤ n_max`` (a length in a
    shape bucket, design §11: the loop runs over every bit of ``n_max``)."""
    if isinstance(n, int):
        return [(bool(n >> b & 1), n >> (b + 1) > 0) for b in range(max(n.bit_length(), 1))]
    return [((n >> b) & 1 == 1, n >> (b + 1) > 0) for b in range(max(n_max.bit_length(), 1))]


def _sel(c: Any, a: Array, b: Array) -> Array:
    """``a if c else b``: in Python for a static ``c`` (the same operations as a plain loop),
    ``jnp.where`` for a traced one."""
    if isinstance(c, bool):
        return a if c else b
    return jnp.where(c, a, b)


def _gramian(Fa: Array, Pm: Array, n: int | Array, n_max: int) -> Array:
    """``X_n = Σ_{m=1}^n (F̃ᵐ)ᵀ Pm F̃ᵐ`` by doubling (``n`` static, or traced ``≤ n_max``).

    ``X_{a+b} = X_a + (F̃ᵃ)ᵀ X_b F̃ᵃ``: ``O(log n)`` products of ``2k × 2k`` matrices. For a
    traced ``n`` the same products are selected (``jnp.where``) and the powers past the
    highest bit of ``n`` are zero (no overflow, so no NaN in derivatives).
    """
    PF, PX = Fa, Fa.T @ Pm @ Fa  # F̃¹, X_1
    RF, RX, started = PF, PX, False  # placeholders until the first set bit
    for b, (bit, more) in enumerate(_bit_plan(n, n_max)):
        if b:
            acc = bit & started
            RX, RF = (
                _sel(acc, RX + RF.T @ PX @ RF, _sel(bit, PX, RX)),
                _sel(acc, PF @ RF, _sel(bit, PF, RF)),
            )
        started = started | bit
        if more is not False:
            zero = jnp.zeros_like(PF)
            PX = _sel(more, PX + PF.T @ PX @ PF, zero)
            PF = _sel(more, PF @ PF, zero)
    return RX


def bridge_usable(A1: Array, A2: Array, n: int | Array, n_max: int = 0) -> Array:
    """Whether the bridge recursion is accurate for this texton over ``n`` free frames.

    The growth ``max |[I 0] F̃ᵖ|`` over ``p = 1, 2, 4, … ≤ n`` and ``p = n`` (a proxy for
    the largest propagator over the segment, from ``O(log n)`` squarings of
    ``F̃ = [[A1ᵀ, A2ᵀ], [I, 0]]``, no derivatives) must be finite and at most
    ``_BRIDGE_MAX_GROWTH`` for the dtype. ``n`` is static, or traced and at most ``n_max``
    (a length in a shape bucket, design §11).
    """
    A1, A2 = lax.stop_gradient(A1), lax.stop_gradient(A2)
    k = A1.shape[0]
    eye, zero = jnp.eye(k, dtype=A1.dtype), jnp.zeros((k, k), A1.dtype)
    PF = jnp.block([[A1.T, A2.T], [eye, zero]])
    growth = jnp.max(jnp.abs(PF[:k]))
    RF, started = PF, False
    for b, (bit, more) in enumerate(_bit_plan(n, n_max)):
        if b:
            RF = _sel(bit & started, PF @ RF, _sel(bit, PF, RF))
        started = started | bit
        if more is not False:
            PF = _sel(more, PF @ PF, jnp.zeros_like(PF))
            growth = _sel(more, jnp.maximum(growth, jnp.max(jnp.abs(PF[:k]))), growth)
    growth = jnp.maximum(growth, jnp.max(jnp.abs(RF[:k])))
    limit = _BRIDGE_MAX_GROWTH.get(jnp.dtype(A1.dtype).itemsize, 10.0)
    return jnp.isfinite(growth) & (growth <= limit)


def _recursion(
    A1: Array, A2: Array, u: Array, reverse: bool = False, n: Array | None = None
) -> Array:
    """``x_j = A1 x_{j−1} + A2 x_{j−2} + u_j`` from zeros, ``(n, k)`` (one ``lax.scan``).

    ``reverse``: the adjoint direction, ``x_j = A1 x_{j+1} + A2 x_{j+2} + u_j`` from the end.
    ``n`` (traced, forward only): rows ``j ≥ n`` pad a shape bucket and are set to zero, so
    that the recursion past the segment cannot overflow.
    """
    A = jnp.concatenate([A1, A2], axis=1).T  # row form: x = [x_{j−1}, x_{j−2}] Aᵀ + u

    def step(c: Array, uj: Array) -> tuple[Array, Array]:
        x = c @ A + uj
        return jnp.concatenate([x, c[: x.shape[0]]]), x

    def masked(c: Array, inp: tuple[Array, Array]) -> tuple[Array, Array]:
        uj, on = inp
        x = jnp.where(on, c @ A + uj, 0.0)
        return jnp.concatenate([x, c[: x.shape[0]]]), x

    k = u.shape[1]
    c0 = jnp.zeros(2 * k, u.dtype)
    if n is None:
        return lax.scan(step, c0, u, reverse=reverse)[1]
    return lax.scan(masked, c0, (u, jnp.arange(u.shape[0]) < n), reverse=reverse)[1]


class _BridgeInputs(eqx.Module):
    """The arrays of :func:`solve_bridge` (a pytree, so that ``custom_vmap`` sees what is
    batched)."""

    A1: Array
    A2: Array
    B: Array
    d: Array
    w: Array
    x01: Array
    xe: Array
    n: Array | None = None  # free frames when w pads a shape bucket (traced), else None


def _bridge_parts(p: _BridgeInputs, whitened: bool) -> tuple[Array, Array, Array, Array]:
    """``Wᵀ``, ``M = (WᵀW)⁻¹``, ``F̃`` and ``S`` of :func:`solve_bridge`."""
    k = p.A1.shape[0]
    dt = p.A1.dtype
    eye, zero = jnp.eye(k, dtype=dt), jnp.zeros((k, k), dt)
    Wt = jsl.solve_triangular(p.B, eye, lower=True).T if whitened else eye
    M = p.B @ p.B.T if whitened else eye
    Fa = jnp.block([[p.A1.T, p.A2.T], [eye, zero]])
    S = -jnp.block([[Wt, zero], [zero, Wt]])
    return Wt, M, Fa, S


def _start_terms(A1: Array, A2: Array, x01: Array, n: int) -> Array:
    """``(n, k)``: the held start states moved right in equations 2 and 3 (``n ≥ 2``)."""
    st = jnp.stack([A1 @ x01[1] + A2 @ x01[0], A2 @ x01[1]])
    return jnp.pad(st, ((0, n - 2), (0, 0)))


def _free_frames(p: _BridgeInputs) -> tuple[int, int | Array, Array | None]:
    """``(N, n, mask)``: the rows of free frames in ``p.w`` (``N = l − 4``), the free frames
    ``n`` (``N``, or the traced ``p.n`` of a shape bucket) and ``n`` again for the masks of
    :func:`_recursion` (``None`` without a bucket)."""
    N = p.w.shape[-2] - 2
    return (N, N, None) if p.n is None else (N, p.n, p.n)


def _rows(a: Array, i: int | Array, size: int, axis: int = 0) -> Array:
    """``size`` rows of ``a`` from row ``i`` (static or traced) along ``axis``."""
    if isinstance(i, int):
        return lax.slice_in_dim(a, i, i + size, axis=axis)
    return lax.dynamic_slice_in_dim(a, i, size, axis=axis)


def _place_end(x: Array, xe: Array, n: int | Array) -> Array:
    """The states ``(…, N + 4, k)`` with the end pair at rows ``n + 2, n + 3`` and zeros after
    them (a shape bucket's padding; nothing to do without one)."""
    if isinstance(n, int):
        return x
    x = lax.dynamic_update_slice_in_dim(x, xe, n + 2, axis=-2)
    keep = (jnp.arange(x.shape[-2]) < n + 4)[:, None]
    return jnp.where(keep, x, 0.0)


def _bridge_single(p: _BridgeInputs, whitened: bool) -> tuple[Array, Array]:
    """:func:`solve_bridge` for one sample: ``O(log n)`` small products and three vector scans.

    ``ZᵀZ = Sᵀ X_n S`` with the Gramian ``X_n = Σ_m (F̃ᵐ)ᵀ [[M, 0], [0, 0]] F̃ᵐ``
    (:func:`_gramian`); ``Zᵀ c_a = G_b G_a⁻¹ c_a`` from the free motion ``x_u = G_a⁻¹ c_a``
    (the noise-driven recursion, forward scan); ``U_i α`` by the adjoint recursion (backward
    scan); the correction ``G_a⁻¹ (Z α)`` by a third scan. In a shape bucket (``p.n``) the
    scans run over the bucket (the forward ones causal and zero past the segment, the
    backward one zero until it reaches the end of the segment).
    """
    dt = p.A1.dtype
    k = p.A1.shape[0]
    N, n, mask = _free_frames(p)
    Wt, M, Fa, S = _bridge_parts(p, whitened)
    Pm = jnp.zeros((2 * k, 2 * k), dt).at[:k, :k].set(M)
    X = _gramian(Fa, Pm, n, N)
    Lc = jnp.linalg.cholesky(jnp.eye(2 * k, dtype=dt) + sym(S.T @ X @ S))
    f = p.d + p.w  # (l−2, k): f_j = d + B v_j, row j−2
    fa = f[:N] + _start_terms(p.A1, p.A2, p.x01, N)
    xu = _recursion(p.A1, p.A2, fa, n=mask)  # the free (noise-driven) motion, frames 2 … l−3
    xl4, xl3 = _rows(xu, n - 2, 2)
    fn, fn1 = _rows(f, n, 2)
    xe = p.xe
    # c_b − G_b x_u: the two end equations' residuals at the free motion (units of W·)
    e = jnp.concatenate(
        [
            (fn - xe[0] + p.A1 @ xl3 + p.A2 @ xl4) @ Wt,
            (fn1 - xe[1] + p.A1 @ xe[0] + p.A2 @ xl3) @ Wt,
        ]
    )
    alpha = jsl.cho_solve((Lc, True), e)
    Sa = S @ alpha  # [U_{l−2} α; U_{l−1} α]
    # U_i α for i = l−3 … 2: the adjoint recursion u_i = A1ᵀ u_{i+1} + A2ᵀ u_{i+2} from
    # the two end values, entered as inputs of its first two steps
    ua, ub = Sa[:k], Sa[k:]
    seed = jnp.zeros((N, k), dt).at[n - 1].set(p.A1.T @ ua + p.A2.T @ ub)
    seed = seed.at[n - 2].add(p.A2.T @ ua)
    u = _recursion(p.A1.T, p.A2.T, seed, reverse=True)
    x = xu + _recursion(p.A1, p.A2, u @ M.T, n=mask)
    x = jnp.concatenate([p.x01, x, p.xe], axis=0)
    return _place_end(x, xe, n), _chol_ok(Lc)


def _chol_ok(Lc: Array) -> Array:
    diag = jnp.diagonal(Lc)
    return jnp.all(jnp.isfinite(diag) & (diag > 0))


def _block_propagators(A1: Array, A2: Array, m: int) -> tuple[Array, Array]:
    """Propagators of ``m`` frames of ``x_j = A1 x_{j−1} + A2 x_{j−2} + u_j``.

    With ``Φ_0 = I``, ``Φ_1 = A1``, ``Φ_s = A1 Φ_{s−1} + A2 Φ_{s−2}``, the frames of a block
    are ``X = T c + H u`` for ``c = [x_{−1}; x_{−2}]`` the two frames before it:
    ``T`` ``(mk, 2k)`` and ``H`` ``(mk, mk)``, block lower-triangular Toeplitz in ``Φ``.
    """
    k = A1.shape[0]
    dt = A1.dtype
    eye, zero = jnp.eye(k, dtype=dt), jnp.zeros((k, k), dt)
    p1, p2 = jnp.concatenate([eye, zero], 1), jnp.concatenate([zero, eye], 1)
    rows = []
    for _ in range(m):
        p1, p2 = A1 @ p1 + A2 @ p2, p1
        rows.append(p1)
    phi = [eye, A1]
    while len(phi) < m:
        phi.append(A1 @ phi[-1] + A2 @ phi[-2])
    H = jnp.block([[phi[r - c] if r >= c else zero for c in range(m)] for r in range(m)])
    return jnp.concatenate(rows, axis=0), H


def _bridge_batched(
    p: _BridgeInputs, whitened: bool, w_b: bool, poses_b: bool, N: int
) -> tuple[Array, Array]:
    """:func:`solve_bridge` for a batch of ``N`` noises and/or key poses of one texton.

    ``p.w`` is ``(N, l−2, k)`` if ``w_b`` (else ``(l−2, k)``, shared), ``p.x01`` and ``p.xe``
    ``(N, 2, k)`` if ``poses_b``. The parts that depend only on the texton are built once,
    with ``U_i`` explicit (:func:`_adjoint_rows`); every sample is then linear in its noise
    and poses: ``α`` from one GEMM with ``Zᵀ`` (the rows ``U_i``), the right-hand sides of
    the recursion blocked by ``m`` frames (:func:`_block_propagators`)
    ``R = w Hᵀ + α P + R₀`` from two GEMMs, and ``⌈n/m⌉`` sequential GEMMs
    ``X_b = c_b Tᵀ + R_b`` over the batch, in place in ``R`` (batch-major, so that no
    transposed copy of the batch is made).

    In a shape bucket (``p.n``, traced) the rows ``U_i`` past the segment are zero and the
    recursion is zero past it.

    Returns:
        states ``(N, l, k)`` and ``ok`` (unbatched).
    """
    w = p.w
    dt = w.dtype
    k = p.A1.shape[0]
    n, nv, mask = _free_frames(p)  # n rows of free frames, nv of them real
    m = _BRIDGE_BLOCK
    nb = -(-n // m)
    Wt, M, Fa, S = _bridge_parts(p, whitened)
    V = _adjoint_rows(Fa, k, n)  # V_m, m = 1 … n
    if mask is None:
        U = (V.reshape(n * k, 2 * k) @ S).reshape(n, k, 2 * k)[::-1]  # U_i, i = 2 … l−3
    else:  # U_i = V_{nv+1−i}, zero past the segment
        j = jnp.arange(n)
        Vr = jnp.take(V, jnp.clip(nv - 1 - j, 0, n - 1), axis=0)
        Vr = jnp.where((j < nv)[:, None, None], Vr, 0.0)
        U = (Vr.reshape(n * k, 2 * k) @ S).reshape(n, k, 2 * k)
    Uf = U.reshape(n * k, 2 * k)
    MU = jnp.einsum("ab,ibc->iac", M, U)
    Lc = jnp.linalg.cholesky(jnp.eye(2 * k, dtype=dt) + sym(Uf.T @ MU.reshape(n * k, 2 * k)))
    T, H = _block_propagators(p.A1, p.A2, m)
    blocks = lambda a: jnp.pad(a, ((0, nb * m - n), (0, 0), *[(0, 0)] * (a.ndim - 2)))
    P = jnp.moveaxis(H @ blocks(MU).reshape(nb, m * k, 2 * k), 2, 0).reshape(2 * k, -1)

    def pose_terms(x01: Array, xe: Array) -> tuple[Array, Array]:
        # without noise: f⁰_j = d, the held states moved right
        fa0 = p.d + _start_terms(p.A1, p.A2, x01, n)
        cb0 = jnp.concatenate([(p.d - xe[0]) @ Wt, (p.d - xe[1] + p.A1 @ xe[0]) @ Wt])
        e0 = cb0 - fa0.reshape(n * k) @ Uf  # c_b − Zᵀ c_a  (Z_iᵀ c_a,i = U_iᵀ W⁻¹ c_a,i)
        return e0, blocks(fa0).reshape(nb, m * k) @ H.T

    e0, R0 = (jax.vmap(pose_terms) if poses_b else pose_terms)(p.x01, p.xe)
    # per sample: the noise w_j = B v_j
    if not w_b:
        w = jnp.broadcast_to(w, (N, *w.shape))
    wa = w[:, :n]
    wn, wn1 = jnp.moveaxis(_rows(w, nv, 2, axis=1), 1, 0)
    e = e0 - wa.reshape(N, n * k) @ Uf + jnp.concatenate([wn @ Wt, wn1 @ Wt], 1)
    # (I + ZᵀZ)⁻¹ explicitly (2k × 2k, ≥ I so well conditioned): one GEMM for the batch
    # instead of two triangular solves with N right-hand sides
    Ginv = jsl.cho_solve((Lc, True), jnp.eye(2 * k, dtype=dt))
    alpha = e @ sym(Ginv)  # (N, 2k)
    wb = jnp.pad(wa, ((0, 0), (0, nb * m - n), (0, 0))).reshape(N, nb, m * k)
    R = wb @ H.T + (alpha @ P).reshape(N, nb, m * k) + R0
    # X_b = c_b Tᵀ + R_b with c_b = [x_last, x_before_last] of block b−1: the last 2k
    # columns of X_{b−1} times Tᵀ with its two row blocks swapped
    Ts = jnp.concatenate([T[:, k:], T[:, :k]], axis=1).T  # (2k, mk)

    def body(b: Array, carry: tuple[Array, Array]) -> tuple[Array, Array]:
        X_prev, R = carry
        X = X_prev[:, -2 * k :] @ Ts + lax.dynamic_index_in_dim(R, b, axis=1, keepdims=False)
        if mask is not None:  # zero past the segment: no overflow in a bucket's padding
            X = jnp.where(jnp.repeat(b * m + jnp.arange(m), k) < mask, X, 0.0)
        return X, lax.dynamic_update_index_in_dim(R, X, b, axis=1)

    _, R = lax.fori_loop(0, nb, body, (jnp.zeros((N, m * k), dt), R))
    ends = lambda a: a if poses_b else jnp.broadcast_to(a, (N, 2, k))
    x = jnp.concatenate([ends(p.x01), R.reshape(N, nb * m, k)[:, :n], ends(p.xe)], axis=1)
    return _place_end(x, ends(p.xe), nv), _chol_ok(Lc)


def _make_bridge(whitened: bool) -> Any:
    """:func:`solve_bridge` for one weighting: ``custom_vmap`` picks the batched form when the
    texton is shared (only noises and/or key poses batched); derivatives (``custom_jvp``) are
    those of the single form."""
    single = lambda p: _bridge_single(p, whitened)

    @jax.custom_batching.custom_vmap
    def vmappable(p: _BridgeInputs) -> tuple[Array, Array]:
        return single(p)

    @vmappable.def_vmap
    def rule(axis_size: int, in_batched: list[Any], p: _BridgeInputs) -> Any:
        f = in_batched[0]
        if not (f.A1 or f.A2 or f.B or f.d or f.n):
            poses_b = bool(f.x01 or f.xe)
            if poses_b:  # both poses batched (or broadcast) together
                bc = lambda a, b: a if b else jnp.broadcast_to(a, (axis_size, *a.shape))
                p = eqx.tree_at(lambda q: (q.x01, q.xe), p, (bc(p.x01, f.x01), bc(p.xe, f.xe)))
            return _bridge_batched(p, whitened, bool(f.w), poses_b, axis_size), (True, False)
        bcast = lambda a, b: a if b else jnp.broadcast_to(a, (axis_size, *a.shape))
        out = jax.vmap(single)(jax.tree_util.tree_map(bcast, p, f))
        return out, (True, True)

    @jax.custom_jvp
    def bridge(p: _BridgeInputs) -> tuple[Array, Array]:
        return vmappable(p)

    @bridge.defjvp
    def _jvp(primals: tuple[_BridgeInputs], tangents: tuple[_BridgeInputs]) -> Any:
        return jax.jvp(single, primals, tangents)

    return bridge


_BRIDGES = {True: _make_bridge(True), False: _make_bridge(False)}


def solve_bridge(
    tex: Texton, w: Array, x01: Array, xe: Array, weighting: str, n_valid: Array | None = None
) -> tuple[Array, Array]:
    """Constrained synthesis with both ends held and no edits, without the banded solve.

    The same least-squares solution as :func:`solve_constrained`, computed from the
    recursion. Free frames ``i = 2 … l−3`` (``n = l − 4``); split the equations into the
    ``n`` square ones ``G_a`` (``j = 2 … l−3``, block lower triangular: the dynamics) and the
    two of the end, ``G_b`` (``j = l−2, l−1``). With ``c`` the right-hand sides (noise, ``d``
    and the held states moved right) and ``Z = G_a⁻ᵀ G_bᵀ`` (``(nk, 2k)``), ``y = G_a x``
    turns ``min ‖G_a x − c_a‖² + ‖G_b x − c_b‖²`` into ``min ‖y − c_a‖² + ‖Zᵀ y − c_b‖²``,
    whose solution (Woodbury) is

    .. code-block:: text

        y = c_a + Z α,   (I + ZᵀZ) α = c_b − Zᵀ c_a,   x = G_a⁻¹ y.

    ``G_a⁻¹`` is the dynamics recursion, so ``x`` is the noise-driven motion from the start
    frames with the extra input ``W⁻¹ Z_i α = M U_i α`` (``M = (WᵀW)⁻¹``: ``B Bᵀ`` whitened,
    ``I`` paper), the control that brings it to the end frames. ``U_i = Wᵀ Z_i`` obey the
    adjoint recursion ``U_i = A1ᵀ U_{i+1} + A2ᵀ U_{i+2}`` from ``U_{l−2} = −[Wᵀ, 0]``,
    ``U_{l−1} = −[0, Wᵀ]``, i.e. ``U_i = [I 0] F̃^{l−2−i} S`` with ``F̃ = [[A1ᵀ, A2ᵀ], [I, 0]]``
    and ``S = −diag(Wᵀ, Wᵀ)``. One sample: :func:`_bridge_single`; a batch for one texton
    (``vmap`` over keys and/or key poses): :func:`_bridge_batched`. Accurate only for a
    texton that does not amplify much over the segment (:func:`bridge_usable`): the caller
    checks that first.

    ``n_valid`` (traced): a segment of ``l = n_valid`` frames in a shape bucket of ``l_b``
    rows (design §11): ``w`` is ``(l_b − 2, k)`` (rows past ``l − 2`` unused) and the states
    ``(l_b, k)`` hold the end pair at rows ``l − 2, l − 1`` and zeros after it. The products
    and scans run for the bucket with the segment's bits and rows selected, so the states are
    those of the segment alone (the same operations; the batched form sums zeros past the
    segment into its ``2k × 2k`` system, a difference of rounding).

    Returns:
        states ``(l, k)`` and ``ok`` (the ``2k × 2k`` factorisation is finite).
    """
    n = None if n_valid is None else jnp.asarray(n_valid, jnp.int32) - 4
    p = _BridgeInputs(A1=tex.A1, A2=tex.A2, B=tex.B, d=tex.d, w=w, x01=x01, xe=xe, n=n)
    return _BRIDGES[weighting == "whitened"](p)
