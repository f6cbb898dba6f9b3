"""``synthesize_texton`` in shape buckets (design §11): the bucketed program gives the results
of the computation at the segment's own length (the kernels called unpadded, as before the
buckets). The states are computed by the same operations; the last step, the GEMM
``[x, 1] [Cᵀ; μ]`` over the rows, may take another CPU kernel for another number of rows
(seen at 6, 7 and 12 frames of a ``k = 3`` texton: 1 ulp), so the results are compared to
a few ulps (``1e-14`` of the largest entry; most lengths are bit for bit). The noise is
the draw for the length, bit for bit; the batched bridge (``vmap`` over keys) adds the zero
rows of the padding into a sum, equal to rounding."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mtex_jax.texture import Texton, synthesize_texton
from mtex_jax.texture._noise.draws import standard_normal
from mtex_jax.texture._synthesis import texton_buckets as tb, texton_synthesis as tts
from mtex_jax.texture._synthesis.bridge import bridge_usable


def make_texton(seed: int, D: int = 6, k: int = 3, gain: float = 0.9) -> Texton:
    rng = np.random.default_rng(seed)
    C = np.linalg.qr(rng.standard_normal((D, k)))[0]
    Bm = np.tril(0.3 * rng.standard_normal((k, k)))
    Bm[np.diag_indices(k)] = rng.uniform(0.2, 0.8, k)
    return Texton(
        mu=jnp.asarray(rng.standard_normal(D)),
        C=jnp.asarray(C),
        A1=jnp.asarray(gain * np.linalg.qr(rng.standard_normal((k, k)))[0]),
        A2=jnp.asarray(0.15 * rng.standard_normal((k, k))),
        d=jnp.asarray(0.1 * rng.standard_normal(k)),
        B=jnp.asarray(Bm),
        sigma2=jnp.asarray(0.01),
        m0=jnp.zeros(2 * k),
        S0=jnp.eye(2 * k),
    )


TEX = make_texton(7)
RNG = np.random.default_rng(3)
S0, E0 = RNG.standard_normal((2, 6)), RNG.standard_normal((2, 6))
POSES = RNG.standard_normal((1100, 6))


def assert_same(out: np.ndarray, ref: np.ndarray) -> None:
    assert out.shape == ref.shape
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-14 * max(1.0, np.abs(ref).max()))


@eqx.filter_jit
def _unpadded(tex, key, length, start, end, fixed, weighting):
    """The computation before the buckets: noise and solve at the segment's length."""
    v = tts.draw_noise(tex, key, length)
    if end is None and fixed is None:
        return tts._noise_driven(tex, v, start)
    return tts.constrained_texton(tex, v, start, end, fixed, weighting)


def test_bucket_sizes():
    assert [tb.texton_bucket(n) for n in (2, 64, 65, 192, 193, 1024, 1025, 3000)] == [
        64,
        64,
        128,
        192,
        1024,
        1024,
        2048,
        3072,
    ]


@pytest.mark.parametrize("n", [4, 6, 63, 64, 65, 192, 193, 1025])
def test_prefix_normal_is_the_draw_for_the_length(n):
    key = jax.random.key(11)
    k, rows = 3, tb.texton_bucket(n)
    z = np.asarray(tb.prefix_normal(key, jnp.asarray((n - 2) * k), rows - 2, k, jnp.float64))
    ref = np.asarray(standard_normal(key, (n - 2, k), jnp.float64))
    assert np.array_equal(z[: n - 2], ref)
    assert not z[n - 2 :].any()


@pytest.mark.parametrize("n", [6, 64, 65, 192, 193, 1024, 1025])
@pytest.mark.parametrize("weighting", ["whitened", "paper"])
def test_both_ends_bridge_equals_unpadded(n, weighting):
    key = jax.random.key(n)
    out = np.asarray(synthesize_texton(key, TEX, n, S0, E0, weighting=weighting))
    ref = np.asarray(_unpadded(TEX, key, n, S0, E0, None, weighting))
    assert out.shape == (n, 6)
    assert_same(out, ref)


@pytest.mark.parametrize("n", [4, 5, 65, 193])
def test_short_lengths_and_mean_equal_unpadded(n):
    out = np.asarray(synthesize_texton(None, TEX, n, S0, E0))
    assert_same(out, np.asarray(_unpadded(TEX, None, n, S0, E0, None, "whitened")))


@pytest.mark.parametrize("n", [2, 64, 193, 1025])
def test_noise_driven_equals_unpadded(n):
    key = jax.random.key(5)
    out = np.asarray(synthesize_texton(key, TEX, n, S0))
    assert_same(out, np.asarray(_unpadded(TEX, key, n, S0, None, None, "whitened")))


@pytest.mark.parametrize("n", [65, 193])
@pytest.mark.parametrize("with_end", [True, False])
def test_edits_equal_unpadded(n, with_end):
    """Held frames (and an open tail without an end): the banded solve in the bucket, its
    padding rows held after the end pair or left out of an open tail."""
    key = jax.random.key(2)
    mask = np.zeros(n, bool)
    mask[[20, 21, 40]] = True
    mask[n - 1] = with_end  # an edit on the end row: the end pair wins, as before
    fixed = (mask, POSES[:n])
    end = E0 if with_end else None
    out = np.asarray(synthesize_texton(key, TEX, n, S0, end, fixed))
    ref = np.asarray(_unpadded(TEX, key, n, S0, end, fixed, "whitened"))
    assert_same(out, ref)


@pytest.mark.parametrize("n", [65, 193])
def test_amplifying_texton_banded_fallback_equals_unpadded(n):
    amp = eqx.tree_at(lambda t: t.A1, TEX, TEX.A1 * 1.8)
    assert not bool(bridge_usable(amp.A1, amp.A2, n - 4))
    key = jax.random.key(9)
    out = np.asarray(synthesize_texton(key, amp, n, S0, E0))
    ref = np.asarray(_unpadded(amp, key, n, S0, E0, None, "whitened"))
    np.testing.assert_allclose(out, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


@pytest.mark.parametrize(("n", "tol"), [(30, 1e-12), (193, 1e-8)])
def test_vmap_over_keys_batched_bridge_equals_unpadded(n, tol):
    """The batched bridge sums the zero rows of the padding into its 2k × 2k system and its
    GEMMs: equal to rounding, not bit for bit. Its rounding grows with the length (at 193
    frames of this texton the unpadded batched bridge itself is 2.9e-9 from the single
    solve, the bucketed one 1.0e-9), hence the looser bound there."""
    keys = jax.random.split(jax.random.key(4), 5)
    out = np.asarray(jax.vmap(lambda k: synthesize_texton(k, TEX, n, S0, E0))(keys))
    ref = np.asarray(jax.vmap(lambda k: _unpadded(TEX, k, n, S0, E0, None, "whitened"))(keys))
    np.testing.assert_allclose(out, ref, rtol=0, atol=tol * np.abs(ref).max())
    one = np.asarray(synthesize_texton(keys[2], TEX, n, S0, E0))
    np.testing.assert_allclose(out[2], one, rtol=0, atol=tol * np.abs(one).max())


def test_gradient_through_the_bucket_is_finite_and_matches_unpadded():
    n = 100

    def f(A1, bucketed):
        t = eqx.tree_at(lambda q: q.A1, TEX, A1)
        if bucketed:
            y = synthesize_texton(jax.random.key(0), t, n, S0, E0)
        else:
            y = _unpadded(t, jax.random.key(0), n, S0, E0, None, "whitened")
        return jnp.sum(y[n // 2] ** 2)

    g = np.asarray(jax.grad(f)(TEX.A1, True))
    g0 = np.asarray(jax.grad(f)(TEX.A1, False))
    assert np.isfinite(g).all()
    np.testing.assert_allclose(g, g0, rtol=1e-9, atol=1e-12)
