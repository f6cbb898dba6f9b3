"""Per-texton synthesis (issue 5 item 2): dense least squares, exact constraints, statistics."""

from __future__ import annotations

import logging

import equinox as eqx
import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from jax.test_util import check_grads
from scipy import stats

from mtex_jax.internal import constrained_equations, solve_constrained
from mtex_jax.texture import Texton, fit_texton, spectral_radius, synthesize_texton
from mtex_jax.texture._noise.draws import sincos_turn, standard_normal
from mtex_jax.texture._synthesis.bridge import bridge_usable


def make_texton(seed: int, D: int, k: int) -> Texton:
    """A random texton with a non-isotropic, non-diagonal noise factor ``B``."""
    rng = np.random.default_rng(seed)
    C = np.linalg.qr(rng.standard_normal((D, k)))[0]
    A1 = 0.9 * np.linalg.qr(rng.standard_normal((k, k)))[0]
    A2 = 0.15 * rng.standard_normal((k, k))
    Bm = np.tril(0.3 * rng.standard_normal((k, k)))
    Bm[np.diag_indices(k)] = rng.uniform(0.2, 0.8, k)
    return Texton(
        mu=jnp.asarray(rng.standard_normal(D)),
        C=jnp.asarray(C),
        A1=jnp.asarray(A1),
        A2=jnp.asarray(A2),
        d=jnp.asarray(0.1 * rng.standard_normal(k)),
        B=jnp.asarray(Bm),
        sigma2=jnp.asarray(0.01),
        m0=jnp.zeros(2 * k),
        S0=jnp.eye(2 * k),
    )


def as_np(tex: Texton) -> dict[str, np.ndarray]:
    return {f: np.asarray(getattr(tex, f)) for f in ("mu", "C", "A1", "A2", "d", "B")}


def dense_equations(
    tex: Texton, v: np.ndarray, x_held: np.ndarray, held: np.ndarray, whiten: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The l−2 (weighted) dynamics equations ``G x_free = r`` densely, held states moved right."""
    t = as_np(tex)
    length, k = x_held.shape
    W = np.linalg.inv(t["B"]) if whiten else np.eye(k)
    free = np.flatnonzero(~held)
    col = {int(f): i for i, f in enumerate(free)}
    G = np.zeros(((length - 2) * k, len(free) * k))
    r = np.zeros((length - 2) * k)
    for j in range(2, length):
        rows = slice((j - 2) * k, (j - 1) * k)
        r[rows] = W @ (t["d"] + t["B"] @ v[j - 2])
        for frame, coef in ((j, np.eye(k)), (j - 1, -t["A1"]), (j - 2, -t["A2"])):
            if held[frame]:
                r[rows] -= W @ coef @ x_held[frame]
            else:
                G[rows, col[frame] * k : (col[frame] + 1) * k] = W @ coef
    return G, r


def dense_lstsq(tex: Texton, v: np.ndarray, x_held: np.ndarray, held: np.ndarray, whiten: bool):
    """Dense reference: stack the l−2 dynamics equations, move held states right, lstsq."""
    G, r = dense_equations(tex, v, x_held, held, whiten)
    x = x_held.copy()
    free = np.flatnonzero(~held)
    if len(free):
        x[free] = np.linalg.lstsq(G, r, rcond=None)[0].reshape(-1, x.shape[1])
    return x


def lapack_shapes(jaxpr):
    """Operand shapes of every Cholesky and triangular solve in a jaxpr (nested ones too)."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name in ("cholesky", "triangular_solve"):
            yield tuple(eqn.invars[0].aval.shape)
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            yield from lapack_shapes(sub)


def noise(key, length: int, k: int) -> np.ndarray:
    """The equation noise ``v`` ``(l−2, k)`` that ``synthesize_texton`` draws from ``key``."""
    return np.asarray(standard_normal(key, (length - 2, k), jnp.float64))


def random_states_case(tex: Texton, length: int, rng: np.random.Generator, n_edit: int):
    t = as_np(tex)
    k = t["A1"].shape[0]
    xs = rng.standard_normal((length, k))
    ys = t["mu"] + xs @ t["C"].T  # poses in the texton subspace
    mask = np.zeros(length, bool)
    if n_edit and length > 4:
        mask[rng.choice(np.arange(2, length - 2), size=min(n_edit, length - 4), replace=False)] = (
            True
        )
    return xs, ys, mask


@pytest.mark.parametrize("weighting", ["whitened", "paper"])
@pytest.mark.parametrize(
    ("length", "k", "n_edit", "seed"),
    [
        (4, 2, 0, 0),
        (5, 1, 0, 1),
        (6, 2, 0, 6),  # both ends held, no edits: the bridge recursion from here on
        (9, 3, 0, 7),
        (40, 4, 0, 8),
        (13, 3, 3, 4),
        (31, 4, 5, 5),
    ],
)
def test_matches_dense_lstsq_and_constraints_exact(weighting, length, k, n_edit, seed):
    tex = make_texton(seed, D=7, k=k)
    t = as_np(tex)
    rng = np.random.default_rng(seed + 100)
    xs, ys, mask = random_states_case(tex, length, rng, n_edit)
    held = mask.copy()
    held[:2] = held[-2:] = True
    x_held = np.where(held[:, None], xs, 0.0)
    for key in (None, jax.random.key(seed)):
        out = np.asarray(
            synthesize_texton(key, tex, length, ys[:2], ys[-2:], (mask, ys), weighting=weighting)
        )
        assert out.shape == (length, 7)
        # perturb-and-MAP: least squares of the equations with the noise v of the key
        v = np.zeros((length - 2, k)) if key is None else noise(key, length, k)
        ref = dense_lstsq(tex, v, x_held, held, weighting == "whitened")
        x = (out - t["mu"]) @ t["C"]
        assert np.linalg.norm(x - ref) <= 1e-9 * np.linalg.norm(ref)
        # constraints hold exactly: first two, last two and every fixed frame
        np.testing.assert_allclose(out[held], ys[held], rtol=0, atol=1e-9)


def test_noise_driven_matches_recursion_and_open_end():
    tex = make_texton(7, D=6, k=3)
    t = as_np(tex)
    length = 15
    rng = np.random.default_rng(0)
    _, ys, _ = random_states_case(tex, length, rng, 0)
    key = jax.random.key(3)
    out = np.asarray(synthesize_texton(key, tex, length, ys[:2]))
    v = noise(key, length, 3)
    x = list((ys[:2] - t["mu"]) @ t["C"])
    for j in range(2, length):
        x.append(t["A1"] @ x[j - 1] + t["A2"] @ x[j - 2] + t["d"] + t["B"] @ v[j - 2])
    np.testing.assert_allclose(out, t["mu"] + np.array(x) @ t["C"].T, rtol=1e-10, atol=1e-10)
    # open end through the least-squares path (empty edit mask) is the same sample
    none = (np.zeros(length, bool), np.zeros((length, 6)))
    out2 = np.asarray(synthesize_texton(key, tex, length, ys[:2], fixed=none))
    np.testing.assert_allclose(out2, out, rtol=1e-9, atol=1e-9)
    # ... and an edited frame in the middle is held while the tail still follows the dynamics
    mask = np.zeros(length, bool)
    mask[6] = True
    out3 = np.asarray(synthesize_texton(key, tex, length, ys[:2], fixed=(mask, ys)))
    np.testing.assert_allclose(out3[6], ys[6], atol=1e-9)
    x3 = (out3 - t["mu"]) @ t["C"]
    for j in range(9, length):  # frames whose equations involve no held/solved coupling
        pred = t["A1"] @ x3[j - 1] + t["A2"] @ x3[j - 2] + t["d"] + t["B"] @ v[j - 2]
        np.testing.assert_allclose(x3[j], pred, atol=1e-9)


def conditional_gaussian(tex: Texton, length: int, x_held: np.ndarray, held: np.ndarray):
    """Exact conditional law of the free states, by covariance conditioning (dense).

    Given ``x_0, x_1``, the states ``x_2 … x_{l−1}`` are jointly Gaussian: ``x = T⁻¹(c + S v)``
    with the lower block-triangular ``T`` of the recursion. Condition on the other held frames
    with the usual Schur-complement formulas (independent of the precision-form solver).
    """
    t = as_np(tex)
    k = t["A1"].shape[0]
    n = length - 2
    T = np.eye(n * k)
    c = np.tile(t["d"], n)
    for j in range(2, length):
        r = slice((j - 2) * k, (j - 1) * k)
        for lag, A in ((1, t["A1"]), (2, t["A2"])):
            p = j - lag
            if p >= 2:
                T[r, (p - 2) * k : (p - 1) * k] = -A
            else:
                c[r] += A @ x_held[p]
    Tinv = np.linalg.inv(T)
    S = np.kron(np.eye(n), t["B"])
    mean = Tinv @ c
    cov = Tinv @ S @ S.T @ Tinv.T
    h = np.repeat(held[2:], k)
    f = ~h
    xc = x_held[2:].reshape(-1)[h]
    K = cov[np.ix_(f, h)] @ np.linalg.inv(cov[np.ix_(h, h)])
    m = mean[f] + K @ (xc - mean[h])
    P = cov[np.ix_(f, f)] - K @ cov[np.ix_(h, f)]
    return m, P


@pytest.mark.parametrize("weighting", ["whitened", "paper"])
def test_open_end_with_edits_exact_for_unstable_texton(weighting):
    """end=None with edits: least squares up to the last held frame, the dynamics after it.

    An unstable texton (spectral radius ≈ 1.3) over 120 frames: a least-squares solve over
    the open tail would be as ill-conditioned as ρ^(2·90) (it gave 18 % relative error on
    the tail in a trial before the tail was taken out of the least squares).
    """
    tex = make_texton(7, D=6, k=3)
    tex = eqx.tree_at(lambda t: t.A1, tex, tex.A1 * 1.4)
    assert float(spectral_radius(tex)) > 1.2
    t = as_np(tex)
    length, last = 120, 30
    rng = np.random.default_rng(4)
    xs, ys, _ = random_states_case(tex, length, rng, 0)
    mask = np.zeros(length, bool)
    mask[[6, last]] = True
    held = mask.copy()
    held[:2] = True
    x_held = np.where(held[:, None], xs, 0.0)
    for key in (None, jax.random.key(8)):
        out = synthesize_texton(key, tex, length, ys[:2], fixed=(mask, ys), weighting=weighting)
        x = (np.asarray(out) - t["mu"]) @ t["C"]
        v = np.zeros((length - 2, 3))
        if key is not None:
            v = noise(key, length, 3)
        # reference: dense least squares of the equations j = 2 … last, then the recursion
        ref = np.zeros((length, 3))
        ref[: last + 1] = dense_lstsq(
            tex, v[: last - 1], x_held[: last + 1], held[: last + 1], weighting == "whitened"
        )
        for j in range(last + 1, length):
            ref[j] = t["A1"] @ ref[j - 1] + t["A2"] @ ref[j - 2] + t["d"] + t["B"] @ v[j - 2]
        assert np.abs(ref).max() > 1e6  # the tail really grows
        rel = np.linalg.norm(x - ref, axis=1) / np.maximum(np.linalg.norm(ref, axis=1), 1.0)
        assert rel.max() < 1e-9, rel.max()
        np.testing.assert_allclose(out[held], ys[held], rtol=0, atol=1e-9)


@pytest.mark.parametrize("edit", [False, True])
def test_statistics_match_exact_conditional(edit):
    """≥ 2,000 constrained samples: mean and covariance of the free states vs the exact law.

    Without edits the samples come from the bridge recursion, with an edited frame from the
    banded solve (both under ``vmap`` over keys).

    Tolerances from the sample size N: with Σ the exact covariance (p free coordinates), the
    whitened sample mean ``√N Σ^{-1/2}(m̂ − m)`` is N(0, I_p) so ``N‖·‖²`` is χ²_p: we require it
    below the 1 − 1e-6 quantile. The whitened sample covariance ``Σ^{-1/2} Ŝ Σ^{-1/2}`` has
    entries with standard deviation ``√(2/N)`` (diagonal) and ``√(1/N)`` (off-diagonal): we
    require every entry within ``6·√(2/N)`` of the identity (≈ 0.095 for N = 8,000).
    """
    k, length, N = 2, 12, 8000
    tex = make_texton(11, D=5, k=k)
    rng = np.random.default_rng(1)
    xs, ys, _ = random_states_case(tex, length, rng, 0)
    mask = np.zeros(length, bool)
    mask[6] = edit  # one edited frame as well
    held = mask.copy()
    held[:2] = held[-2:] = True
    x_held = np.where(held[:, None], xs, 0.0)
    keys = jax.random.split(jax.random.key(2024), N)
    sample = jax.jit(
        jax.vmap(lambda key: synthesize_texton(key, tex, length, ys[:2], ys[-2:], (mask, ys)))
    )
    out = np.asarray(sample(keys))
    t = as_np(tex)
    X = ((out - t["mu"]) @ t["C"])[:, ~held].reshape(N, -1)
    m, P = conditional_gaussian(tex, length, x_held, held)
    p = len(m)
    L = np.linalg.cholesky(P)
    Z = np.linalg.solve(L, (X - m).T).T  # whitened by the exact law
    chi2 = N * np.sum(Z.mean(0) ** 2)
    assert chi2 < stats.chi2.ppf(1 - 1e-6, p), chi2
    Sw = np.cov(Z.T)
    tol = 6 * np.sqrt(2 / N)
    assert np.abs(Sw - np.eye(p)).max() < tol, np.abs(Sw - np.eye(p)).max()
    # zero noise gives the conditional mean exactly
    mean = synthesize_texton(None, tex, length, ys[:2], ys[-2:], (mask, ys))
    xm = ((np.asarray(mean) - t["mu"]) @ t["C"])[~held].reshape(-1)
    np.testing.assert_allclose(xm, m, rtol=1e-9, atol=1e-9)
    # the unweighted (paper) variant is not the exact conditional law for non-isotropic B
    outp = np.asarray(
        jax.vmap(
            lambda key: synthesize_texton(
                key, tex, length, ys[:2], ys[-2:], (mask, ys), weighting="paper"
            )
        )(keys)
    )
    Zp = np.linalg.solve(L, (((outp - t["mu"]) @ t["C"])[:, ~held].reshape(N, -1) - m).T).T
    assert np.abs(np.cov(Zp.T) - np.eye(p)).max() > tol


def test_edits_do_not_recompile(caplog):
    tex = make_texton(3, D=6, k=2)
    length = 20
    rng = np.random.default_rng(0)
    _, ys, _ = random_states_case(tex, length, rng, 0)
    m1 = np.zeros(length, bool)
    m1[5] = True
    m2 = np.zeros(length, bool)
    m2[[7, 9, 13]] = True
    synthesize_texton(None, tex, length, ys[:2], ys[-2:], (m1, ys))
    with jax.log_compiles(), caplog.at_level(logging.DEBUG):
        out = np.asarray(synthesize_texton(None, tex, length, ys[:2], ys[-2:], (m2, ys + 1.0)))
    assert not [r for r in caplog.records if "_constrained_key" in r.getMessage()]
    # positive control: the log does show a compilation for a length of another shape bucket
    _, ys3, _ = random_states_case(tex, 100, rng, 0)
    m3 = np.zeros(100, bool)
    m3[[7, 9, 13]] = True
    with jax.log_compiles(), caplog.at_level(logging.DEBUG):
        synthesize_texton(None, tex, 100, ys3[:2], ys3[-2:], (m3, ys3))
    assert [r for r in caplog.records if "_constrained_key" in r.getMessage()]
    t = as_np(tex)
    np.testing.assert_allclose(
        out[[7, 9, 13]], t["mu"] + ((ys[[7, 9, 13]] + 1 - t["mu"]) @ t["C"]) @ t["C"].T, atol=1e-9
    )


def test_fitted_texton_extrapolates_and_is_differentiable():
    rng = np.random.default_rng(5)
    T = 400
    phase = np.linspace(0, 12 * np.pi, T)
    Y = np.stack([np.sin(phase + i) * (1 + 0.1 * i) for i in range(8)], 1)
    Y = Y + 0.01 * rng.standard_normal(Y.shape)
    tex = fit_texton(Y, state_dim=3)
    for length in (4, 60):  # shorter and longer than a typical segment: MT Fig. 10
        out = np.asarray(synthesize_texton(jax.random.key(0), tex, length, Y[:2], Y[50:52]))
        assert out.shape == (length, 8) and np.isfinite(out).all()
        np.testing.assert_allclose(out[-2:], Y[50:52], atol=0.05)  # end poses near the subspace


@pytest.mark.slow  # 30 s on 2 cores (the default run is kept near 15 min)
def test_differentiable_in_key_poses_and_dynamics():
    """Through the bridge (no edits): poses and the texton's A1, B, with and without noise."""
    small = make_texton(1, D=4, k=2)
    length = 10
    s0, e0 = jnp.asarray(np.arange(8.0).reshape(2, 4) / 8), jnp.ones((2, 4))
    for key in (None, jax.random.key(4)):
        f = jax.jit(lambda s, e, key=key: synthesize_texton(key, small, length, s, e))
        check_grads(f, (s0, e0), order=1, modes=("fwd", "rev"))

        def g(A1, B, key=key):
            tex = eqx.tree_at(lambda t: (t.A1, t.B), small, (A1, B))
            return synthesize_texton(key, tex, length, s0, e0)

        check_grads(jax.jit(g), (small.A1, small.B), order=1, modes=("fwd", "rev"))


def test_input_errors():
    tex = make_texton(0, D=5, k=2)
    y2 = np.zeros((2, 5))
    with pytest.raises(ValueError, match="length must be >= 4"):
        synthesize_texton(None, tex, 3, y2, y2)
    with pytest.raises(ValueError, match="start must have shape"):
        synthesize_texton(None, tex, 8, np.zeros((3, 5)), y2)
    with pytest.raises(ValueError, match="end contains NaN"):
        synthesize_texton(None, tex, 8, y2, np.full((2, 5), np.nan))
    with pytest.raises(ValueError, match="weighting"):
        synthesize_texton(None, tex, 8, y2, y2, weighting="lsq")  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="fixed mask"):
        synthesize_texton(None, tex, 8, y2, y2, (np.zeros(7, bool), np.zeros((8, 5))))


@pytest.mark.parametrize("edit", [False, True])
@pytest.mark.parametrize("weighting", ["whitened", "paper"])
def test_vmap_over_keys_equals_single_calls_and_factorises_once(weighting, edit):
    """vmap over the noise shares one factorisation (no batched LAPACK call); every sample
    equals the unbatched synthesis with the same key, and gradients go through both paths.

    Without an edit: the bridge (batched form under vmap, single form per call); with one:
    the banded solve."""
    tex = make_texton(21, D=6, k=3)
    length = 15
    rng = np.random.default_rng(3)
    _, ys, _ = random_states_case(tex, length, rng, 0)
    mask = np.zeros(length, bool)
    mask[7] = edit
    keys = jax.random.split(jax.random.key(5), 4)

    def one(key, s):
        return synthesize_texton(key, tex, length, s, ys[-2:], (mask, ys), weighting=weighting)

    batched = jax.jit(jax.vmap(one, in_axes=(0, None)))
    out = np.asarray(batched(keys, ys[:2]))
    for i in range(len(keys)):
        np.testing.assert_allclose(out[i], np.asarray(one(keys[i], ys[:2])), atol=1e-10)
    jaxpr = jax.make_jaxpr(jax.vmap(one, in_axes=(0, None)))(keys, ys[:2]).jaxpr

    shapes = list(lapack_shapes(jaxpr))
    assert shapes and all(len(s) == 2 for s in shapes), shapes
    f = jax.jit(lambda s: jax.vmap(one, in_axes=(0, None))(keys[:2], s))
    check_grads(f, (jnp.asarray(ys[:2]),), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)


def test_standard_normal_is_standard_normal():
    """The Box–Muller noise: Kolmogorov–Smirnov against N(0, 1), moments, float32, and the
    polynomial (cos 2πu, sin 2πu) against numpy, quadrant boundaries included."""
    z = np.asarray(standard_normal(jax.random.key(0), (400, 501), jnp.float64)).ravel()
    assert z.size == 200_400 and np.isfinite(z).all()
    assert stats.kstest(z, "norm").pvalue > 1e-6
    n = z.size
    assert abs(z.mean()) < 5 / np.sqrt(n) and abs(z.var() - 1) < 5 * np.sqrt(2 / n)
    assert abs(stats.skew(z)) < 5 * np.sqrt(6 / n) and abs(stats.kurtosis(z)) < 5 * np.sqrt(24 / n)
    # independent halves: the cosine and the sine parts are uncorrelated
    h = z.size // 2
    assert abs(np.corrcoef(z[:h], z[h : 2 * h])[0, 1]) < 5 / np.sqrt(h)
    z32 = standard_normal(jax.random.key(1), (20001, 3), jnp.float32)
    assert z32.dtype == jnp.float32 and z32.shape == (20001, 3)
    assert stats.kstest(np.asarray(z32, np.float64).ravel(), "norm").pvalue > 1e-6
    # an odd size: the last sine is dropped, the rest is the same draw
    odd = np.asarray(standard_normal(jax.random.key(2), (7,), jnp.float64))
    even = np.asarray(standard_normal(jax.random.key(2), (8,), jnp.float64))
    assert odd.shape == (7,) and np.isfinite(odd).all()
    u = np.asarray(jax.random.uniform(jax.random.key(2), (2, 4), jnp.float64))
    r = np.sqrt(-2 * np.log1p(-u[0]))
    np.testing.assert_allclose(
        even, np.concatenate([r * np.cos(2 * np.pi * u[1]), r * np.sin(2 * np.pi * u[1])]), 1e-13
    )
    np.testing.assert_allclose(odd, even[:7], 1e-13)
    u = np.concatenate(
        [np.random.default_rng(0).uniform(size=100_000), [0.0, 0.25, 0.5, 0.75, 1 - 2**-53]]
    )
    c, s_ = (np.asarray(a) for a in sincos_turn(jnp.asarray(u)))
    np.testing.assert_allclose(c, np.cos(2 * np.pi * u), rtol=0, atol=2e-15)
    np.testing.assert_allclose(s_, np.sin(2 * np.pi * u), rtol=0, atol=2e-15)


@pytest.mark.parametrize("weighting", ["whitened", "paper"])
def test_constrained_to_its_own_noise_driven_end_is_the_noise_driven_motion(weighting):
    """Same key, end poses taken from the noise-driven motion of that key: the least squares
    has a zero residual there, so the constrained sample is that motion (the control is 0)."""
    tex = make_texton(12, D=9, k=4)
    length = 37
    rng = np.random.default_rng(2)
    _, ys, _ = random_states_case(tex, length, rng, 0)
    key = jax.random.key(11)
    free = np.asarray(synthesize_texton(key, tex, length, ys[:2]))
    bridged = np.asarray(
        synthesize_texton(key, tex, length, ys[:2], free[-2:], weighting=weighting)
    )
    np.testing.assert_allclose(bridged, free, rtol=0, atol=1e-9 * np.abs(free).max())


@pytest.mark.slow  # the default run's budget (about 15 min); CI runs it after
@pytest.mark.parametrize("rho", [0.95, 1.3])
def test_bridge_at_paper_scale_equals_banded_solve_and_dense(rho):
    """k = 15, the bridge against the banded solve of the same equations (length 172) and
    against dense least squares (length 60). A texton with spectral radius 1.3 amplifies by
    ~1.3^168 over the segment: the bridge reports itself unusable and the banded solve is
    used, with the same result."""
    k, D = 15, 20
    tex = make_texton(30, D=D, k=k)
    s = rho / float(spectral_radius(tex))
    tex = eqx.tree_at(lambda t: (t.A1, t.A2), tex, (tex.A1 * s, tex.A2 * s**2))
    t = as_np(tex)
    rng = np.random.default_rng(5)
    for length in (60, 172):
        xs, ys, _ = random_states_case(tex, length, rng, 0)
        key = jax.random.key(length)
        v = noise(key, length, k)
        out = np.asarray(synthesize_texton(key, tex, length, ys[:2], ys[-2:]))
        x = (out - t["mu"]) @ t["C"]
        w = jnp.asarray(v) @ tex.B.T
        assert bool(bridge_usable(tex.A1, tex.A2, length - 4)) == (rho < 1), (rho, length)
        eqs = constrained_equations(
            tex, length, w, jnp.asarray(ys[:2]), jnp.asarray(ys[-2:]), None, "whitened"
        )
        banded, ok = solve_constrained(tex, eqs, w)
        assert bool(ok)
        banded = np.asarray(banded)
        assert np.linalg.norm(x - banded) <= 1e-10 * np.linalg.norm(banded)
        if length == 60:
            held = np.zeros(length, bool)
            held[:2] = held[-2:] = True
            ref = dense_lstsq(tex, v, np.where(held[:, None], xs, 0.0), held, whiten=True)
            assert np.linalg.norm(x - ref) <= 1e-9 * np.linalg.norm(ref)


def test_bridge_under_vmap_over_poses_textons_and_keys():
    """The bridge's batched form (one texton; noises and/or key poses batched) and its
    generic form (textons batched) equal single calls; vmap over poses factorises once (no
    batched LAPACK call, also not in the banded branch of the fallback)."""
    tex = make_texton(40, D=8, k=3)
    length = 23  # n = 19 free frames: not a multiple of the recursion's block of 4
    rng = np.random.default_rng(9)
    S = jnp.asarray(rng.standard_normal((5, 2, 8)))
    E = jnp.asarray(rng.standard_normal((5, 2, 8)))
    keys = jax.random.split(jax.random.key(3), 5)
    one = lambda t, key, s, e: synthesize_texton(key, t, length, s, e)
    single = np.stack([np.asarray(one(tex, keys[i], S[i], E[i])) for i in range(5)])
    both = jax.jit(jax.vmap(one, in_axes=(None, 0, 0, 0)))(tex, keys, S, E)
    np.testing.assert_allclose(np.asarray(both), single, rtol=1e-10, atol=1e-10)
    poses = jax.jit(jax.vmap(one, in_axes=(None, None, 0, 0)))(tex, keys[0], S, E)
    ref = np.stack([np.asarray(one(tex, keys[0], S[i], E[i])) for i in range(5)])
    np.testing.assert_allclose(np.asarray(poses), ref, rtol=1e-10, atol=1e-10)
    jaxpr = jax.make_jaxpr(jax.vmap(one, in_axes=(None, None, 0, 0)))(tex, keys[0], S, E)

    shapes = list(lapack_shapes(jaxpr.jaxpr))
    assert shapes and all(len(s) == 2 for s in shapes), shapes
    # textons batched (one contracting, one amplifying: bridge and banded fallback mixed)
    amp = eqx.tree_at(lambda t: t.A1, tex, tex.A1 * 3.0)
    assert bool(bridge_usable(tex.A1, tex.A2, length - 4))
    assert not bool(bridge_usable(amp.A1, amp.A2, length - 4))
    stacked = jax.tree.map(lambda a, b: jnp.stack([a, b]), tex, amp)
    texs = jax.jit(jax.vmap(one, in_axes=(0, None, None, None)))(stacked, keys[0], S[0], E[0])
    for i, t in enumerate((tex, amp)):
        ref_i = np.asarray(one(t, keys[0], S[0], E[0]))
        np.testing.assert_allclose(np.asarray(texs[i]), ref_i, rtol=1e-9, atol=1e-9)


def test_amplifying_texton_gradients_stay_finite():
    """A texton that overflows over the segment is solved banded; its gradients (also with
    respect to A1, through the unused bridge branch) stay finite."""
    tex = make_texton(41, D=5, k=2)
    tex = eqx.tree_at(lambda t: t.A1, tex, tex.A1 * 1.6)
    length = 1200
    assert not bool(bridge_usable(tex.A1, tex.A2, length - 4))
    rng = np.random.default_rng(1)
    s0, e0 = jnp.asarray(rng.standard_normal((2, 5))), jnp.asarray(rng.standard_normal((2, 5)))

    def f(A1):
        t = eqx.tree_at(lambda q: q.A1, tex, A1)
        return jnp.sum(synthesize_texton(jax.random.key(0), t, length, s0, e0)[length // 2])

    g = jax.jit(jax.grad(f))(tex.A1)
    assert np.isfinite(np.asarray(g)).all()


def test_bridge_float32_smoke():
    tex32 = jax.tree.map(lambda a: a.astype(jnp.float32), make_texton(42, D=6, k=3))
    rng = np.random.default_rng(4)
    s0 = rng.standard_normal((2, 6)).astype(np.float32)
    e0 = rng.standard_normal((2, 6)).astype(np.float32)
    out = synthesize_texton(jax.random.key(1), tex32, 30, s0, e0)
    assert out.dtype == jnp.float32 and np.isfinite(np.asarray(out)).all()
    assert bool(bridge_usable(tex32.A1, tex32.A2, 26))  # the bridge, not the fallback
    # the conditional mean against float64 (the noise draws differ between dtypes)
    mean = np.asarray(synthesize_texton(None, tex32, 30, s0, e0))
    mean64 = np.asarray(synthesize_texton(None, make_texton(42, D=6, k=3), 30, s0, e0))
    err = np.abs(mean - mean64).max() / np.abs(mean64).max()
    assert err < 1e-4, err


@pytest.mark.parametrize("fixed_edit", [False, True])
def test_non_finite_texton_raises_not_nan(fixed_edit):
    """NaN in the texton's drift reaches neither the bridge's nor the banded solve's output
    silently: the runtime check raises."""
    tex = make_texton(43, D=5, k=2)
    bad = eqx.tree_at(lambda t: t.d, tex, tex.d.at[0].set(jnp.nan))
    y2 = np.zeros((2, 5))
    fixed = (np.arange(12) == 5, np.zeros((12, 5))) if fixed_edit else None
    with pytest.raises(Exception, match="non-finite"):
        jax.block_until_ready(synthesize_texton(jax.random.key(0), bad, 12, y2, y2, fixed))


@settings(deadline=None, max_examples=15)
@pytest.mark.slow  # 27 s on 2 cores (the default run is kept near 15 min)
@given(
    k=st.integers(1, 4),
    length=st.integers(4, 41),
    n_edit=st.integers(0, 3),
    paper=st.booleans(),
    seed=st.integers(0, 10_000),
)
def test_random_sizes_match_dense_lstsq(k, length, n_edit, paper, seed):
    """Random sizes (hypothesis): every path (bridge without edits, banded with them, short
    lengths) equals dense least squares of the same equations and noise to 1e-9, and the
    held frames hold."""
    weighting = "paper" if paper else "whitened"
    tex = make_texton(seed, D=k + 3, k=k)
    rng = np.random.default_rng(seed)
    xs, ys, mask = random_states_case(tex, length, rng, n_edit)
    held = mask.copy()
    held[:2] = held[-2:] = True
    key = jax.random.key(seed)
    out = np.asarray(
        synthesize_texton(key, tex, length, ys[:2], ys[-2:], (mask, ys), weighting=weighting)
        if n_edit
        else synthesize_texton(key, tex, length, ys[:2], ys[-2:], weighting=weighting)
    )
    t = as_np(tex)
    x = (out - t["mu"]) @ t["C"]
    ref = dense_lstsq(tex, noise(key, length, k), np.where(held[:, None], xs, 0.0), held, not paper)
    assert np.linalg.norm(x - ref) <= 1e-9 * np.linalg.norm(ref)
    np.testing.assert_allclose(out[held], ys[held], rtol=0, atol=1e-9)
