"""M-step kernels: every texton fitted from summed statistics of its segments (design §2), in
one process (``fit_all``: per-texton chunks of segments) and as the passes of the
multi-process M-step (``frame_pass``, ``subspaces_from``, ``dynamics_pass``, ``solve_texton``:
per-segment statistics summed per texton, all-reduced between the passes by the caller)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._texton.fit import student_frame_weights, texton_from_stats_impl
from .._texton.options import SolveOptions
from .._texton.stats import (
    DynamicsStats,
    FrameStats,
    Subspace,
    dynamics_stats_impl,
    frame_stats_impl,
    subspace_impl,
)
from .._texton.texton import Texton


def _fit_all_impl(
    Y: Array,
    rows: Array,
    chunks: tuple[Array, Array],
    n_tex: int,
    width: int,
    k: int,
    floor: float,
    opts,
    prev: Texton | None = None,
    cold: Array | None = None,
) -> Texton:
    """M-step: fit every texton on all of its segments (design §2), from summed statistics.

    ``rows`` are segments ``(seq, start, length, label)`` of ``Y (S, T, D)``; ``chunks =
    (labels (C,), groups (C, G))`` groups them by texton (chunk ``c`` holds up to ``G`` row
    indices of texton ``labels[c]``, ``-1``: none; :func:`~._rows.row_chunks`). A chunk's
    segments are gathered into ``(width, D)`` slabs laid end to end (frame ids keep terms
    from reaching across two slabs) and its pass-1 statistics come from one ``(D, G·width)``
    GEMM; the subspaces are solved, then pass 2 of each chunk runs in its texton's subspace,
    again one GEMM per statistic. The chunks go one after the other (``lax.scan``), their sums
    added into their texton's: memory holds one chunk's slabs, and the work is
    ``O(total frames)``, not ``O(N_t × frames)``. (Per-segment GEMMs batched over the
    segments of mixed textons, the alternative, run at a fraction of the GEMM rate.)

    With Student-t textons (``opts.dof``) each frame's dynamics term is weighted by its t
    weight under a previous fit (IRLS, as in :func:`~._fit.fit_texton`). Without ``prev``:
    the Gaussian fit, then ``opts.irls_steps`` reweightings. With ``prev`` (the textons of the
    E-step that made the segments, stacked as the labels index them; EM's later iterations):
    one reweighting from ``prev``, the EM of the t as a scale mixture (its E-step: the weights;
    its M-step: the weighted closed form), so that EM's iterations carry the IRLS and an
    M-step costs one weighted pass, not ``opts.irls_steps``. With ``cold`` (a traced bool)
    as well, ``prev`` is used only where ``cold`` is false (else it is a placeholder of the
    same shapes, and the Gaussian fit and ``opts.irls_steps`` reweightings run): the cold and
    the warm M-step are then one compiled program.
    """
    T = Y.shape[1]
    D = Y.shape[2]
    labels, groups = chunks
    G = groups.shape[1]
    off = jnp.arange(width)

    def slab(g: Array) -> tuple[Array, Array]:
        """A chunk's slabs end to end ``(G·width, D)`` and their frame ids (``-1``: unused)."""
        r = rows[jnp.maximum(g, 0)]
        seq, start, length = r[:, 0], r[:, 1], r[:, 2]
        inside = (off[None, :] < length[:, None]) & (g >= 0)[:, None]
        frames = Y[seq[:, None], jnp.clip(start[:, None] + off[None, :], 0, T - 1)]
        ids = jnp.where(inside, jnp.arange(G)[:, None], -1)
        return frames.reshape(G * width, D), ids.reshape(G * width)

    def summed(stats: Callable[[Array, Array], Any]) -> Any:
        """``Σ`` of ``stats(texton, row group)`` over the chunks, per texton."""
        shapes = jax.eval_shape(stats, labels[0], groups[0])
        acc0 = jax.tree.map(lambda a: jnp.zeros((n_tex, *a.shape), a.dtype), shapes)
        none = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)

        def body(acc: Any, x: tuple[Array, Array]) -> tuple[Any, None]:
            # the padding chunks (no rows) are skipped, not computed on zeros
            part = jax.lax.cond(x[1][0] >= 0, lambda: stats(*x), lambda: none)
            return jax.tree.map(lambda a, b: a.at[x[0]].add(b), acc, part), None

        acc, _ = jax.lax.scan(body, acc0, (labels, groups))
        return acc

    # check=False: the clips were checked when learning began, and an in-program NaN check
    # (a host callback) would keep the M-step out of the persistent compilation cache
    fs = summed(lambda i, g: frame_stats_impl(*slab(g), check=False))
    # The eigen-decompositions and Cholesky factorisations run one texton at a time
    # (lax.map): batched LAPACK calls in jaxlib's CPU runtime split their batch over the
    # intra-op thread pool and two of them running concurrently can deadlock a 2-core pool.
    sub = jax.lax.map(lambda f: subspace_impl(f, k, floor), fs)

    def pass2(i: Array, g: Array) -> Any:
        frames, ids = slab(g)
        # one segment starts per slab
        return dynamics_stats_impl(frames, ids, jax.tree.map(lambda a: a[i], sub), G, check=False)

    def gaussian() -> Texton:
        ds = summed(pass2)
        return solve_stack(sub, ds, opts)

    dof = opts.dof
    steps: int | Array
    if dof is None:
        return gaussian()
    if prev is None:
        tex, steps = gaussian(), opts.irls_steps
    elif cold is None:
        tex, steps = prev, 1
    else:
        # one program for EM's first M-step (cold: ``prev`` is a placeholder) and the later
        # ones (warm), so that a learn compiles the M-step once per stack size, not twice
        tex = jax.lax.cond(cold, gaussian, lambda: prev)
        steps = jnp.where(cold, opts.irls_steps, 1)

    def irls(_: Array, tex: Texton) -> Texton:
        """One reweighting of the Student-t fit (``fit_texton``'s IRLS), every texton."""

        def pass2w(i: Array, g: Array) -> Any:
            frames, ids = slab(g)
            w = student_frame_weights(tex[i], frames, dof)
            sub_i = jax.tree.map(lambda a: a[i], sub)
            return dynamics_stats_impl(frames, ids, sub_i, G, weights=w, check=False)

        ds = summed(pass2w)
        return solve_stack(sub, ds, opts)

    return jax.lax.fori_loop(0, steps, irls, tex)


fit_all = eqx.filter_jit(_fit_all_impl)


def solve_stack(sub: Subspace, ds: DynamicsStats, opts: SolveOptions) -> Texton:
    """Every texton's closed form from its summed statistics, as the observation model of
    ``opts`` solves a stack (design §2.4–§2.6; tied models pool across textons)."""
    fit_one = functools.partial(texton_from_stats_impl, opts=opts)
    return opts.observation.solve(fit_one, Texton, sub, ds, opts)


# multi-process passes
def _slabs(Y: Array, rows: Array, valid: Array, width: int) -> tuple[Array, Array]:
    """Every segment row ``(seq, start, length, label)`` gathered into a ``(width, D)`` slab,
    with the per-frame segment ids (``-1`` outside the segment)."""
    T = Y.shape[1]
    start, length = rows[:, 1], rows[:, 2]
    off = jnp.arange(width)
    inside = (off[None, :] < length[:, None]) & valid[:, None]
    G = Y[rows[:, 0][:, None], jnp.clip(start[:, None] + off[None, :], 0, T - 1)]
    ids = jnp.where(inside, jnp.arange(rows.shape[0])[:, None], -1)
    return G, ids


def _per_texton(x: Array, rows: Array, valid: Array, n_tex: int) -> Array:
    bucket = jnp.where(valid, rows[:, 3], n_tex)  # invalid rows go to a discarded bucket
    return jax.ops.segment_sum(x, bucket, num_segments=n_tex + 1)[:n_tex]


@eqx.filter_jit
def frame_pass(Y: Array, rows: Array, valid: Array, n_tex: int, width: int) -> FrameStats:
    """Pass 1 on this process's segments: frame statistics summed per texton."""
    G, ids = _slabs(Y, rows, valid, width)
    fs = jax.vmap(frame_stats_impl)(G, ids)
    return jax.tree.map(lambda a: _per_texton(a, rows, valid, n_tex), fs)


@eqx.filter_jit
def subspaces_from(fs: FrameStats, k: int, floor: float) -> Subspace:
    """The subspaces of every texton from its summed (all-reduced) pass-1 statistics."""
    # one texton at a time (lax.map), as in the single-process M-step: batched LAPACK calls
    # can deadlock jaxlib's CPU thread pool on 2 cores
    return jax.lax.map(lambda f: subspace_impl(f, k, floor), fs)


@eqx.filter_jit
def dynamics_pass(
    Y: Array, rows: Array, valid: Array, sub: Subspace, width: int, tex: Texton | None = None
) -> DynamicsStats:
    """Pass 2 on this process's segments: dynamics statistics summed per texton. With
    Student-t textons ``tex`` (the current fit), one IRLS step: every frame's dynamics term
    weighted under ``tex`` (as in ``fit_all``)."""
    n_tex = sub.mu.shape[0]
    G, ids = _slabs(Y, rows, valid, width)
    lab = jnp.clip(rows[:, 3], 0, n_tex - 1)
    sub_seg = jax.tree.map(lambda a: a[lab], sub)
    if tex is None:
        ds = jax.vmap(dynamics_stats_impl)(G, ids, sub_seg)
    else:
        dof = tex.dof
        assert dof is not None
        w = jax.vmap(lambda t, g: student_frame_weights(t, g, dof))(tex[lab], G)
        ds = jax.vmap(lambda g, i, s, ww: dynamics_stats_impl(g, i, s, weights=ww))(
            G, ids, sub_seg, w
        )
    return jax.tree.map(lambda a: _per_texton(a, rows, valid, n_tex), ds)


@eqx.filter_jit
def solve_texton(sub: Subspace, ds: DynamicsStats, opts: SolveOptions) -> Texton:
    return solve_stack(sub, ds, opts)
