"""The innovation process of synthesis (:class:`~mtex_jax.texture.InnovationProcess`): the
beta–gamma scale chain against scipy's gamma law, the coloured draws against the
autocorrelations they are given, the estimator against numpy sums and a known process, and the
learner, the file format and path synthesis."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats as st

import mtex_jax as mj
from mtex_jax.texture import (
    FullObservation,
    InnovationProcess,
    LearnConfig,
    draw_innovations,
    fit_innovation_process,
    fit_texton,
    innovation_statistics,
    load_texture,
    process_from_statistics,
    segment_innovations,
    synthesize_texton,
)
from mtex_jax.texture._learning.learn import with_innovations
from mtex_jax.texture._noise.innovation_process import _draw_innovations, _scale_chain

R4 = (0.3, -0.4, -0.1, 0.05)


def _process(r=R4, rho=0.9):
    return InnovationProcess(acf=jnp.asarray(r, dtype=float), persistence=jnp.asarray(rho))


@pytest.mark.parametrize("rho", [0.0, 0.9])
def test_scale_chain_has_gamma_marginals_and_the_given_correlation(rho):
    a = 2.0
    g = np.asarray(_scale_chain(jax.random.key(0), a, jnp.asarray(rho), (60, 4000), jnp.float64))
    # one frame of 4,000 independent chains: the Gamma(a, rate a) law (scipy's cdf)
    assert st.kstest(g[50], st.gamma(a, scale=1 / a).cdf).pvalue > 1e-3
    assert st.kstest(g[0], st.gamma(a, scale=1 / a).cdf).pvalue > 1e-3
    corr = np.corrcoef(g[50], g[49])[0, 1]
    assert abs(corr - rho) < 0.05, corr


@pytest.mark.parametrize("dof", [None, 8.0])
def test_draws_have_the_given_autocorrelation_and_variance(dof):
    v = np.asarray(draw_innovations(jax.random.key(1), _process(), (6000, 30, 2), jnp.float64, dof))
    var = 1.0 if dof is None else dof / (dof - 2)
    for t in (0, 25):  # the filter starts stationary: the first frames too
        assert abs(np.mean(v[:, t] ** 2) / var - 1) < 0.08, (t, np.mean(v[:, t] ** 2))
    for h, r in enumerate(R4, start=1):
        got = np.mean(v[:, 25] * v[:, 25 - h]) / np.mean(v[:, 25] ** 2)
        assert abs(got - r) < 0.04, (h, got, r)


def test_statistics_are_the_numpy_sums_and_add_over_sets():
    rng = np.random.default_rng(2)
    u = [rng.normal(size=(n, 3)) for n in (40, 7, 25)]
    s = innovation_statistics(u, order=2)
    assert np.isclose(s[0], sum((x**2).sum() for x in u))
    assert np.isclose(s[2], sum((x[2:] * x[:-2]).sum() for x in u))
    logs = [np.log((x**2).sum(1)) for x in u]
    assert s[3] == 72 and np.isclose(s[4], sum(x.sum() for x in logs))
    lag5 = [x for x in logs if x.size > 5]
    assert np.isclose(s[6], sum(x[5:] @ x[:-5] for x in lag5)) and s[9] == 35 + 2 + 20
    assert np.allclose(innovation_statistics(u[:1], 2) + innovation_statistics(u[1:], 2), s)


def test_fit_recovers_a_known_process():
    truth = _process(R4, 0.95)
    v = draw_innovations(jax.random.key(3), truth, (150, 200, 20), jnp.float64, 4.0)
    got = fit_innovation_process(list(np.asarray(v)))
    assert np.allclose(np.asarray(got.acf), R4, atol=0.03), got.acf
    assert abs(float(got.persistence) - 0.95) < 0.03, got.persistence
    white = fit_innovation_process(list(np.random.default_rng(4).normal(size=(100, 200, 20))))
    assert np.allclose(np.asarray(white.acf), 0, atol=0.02)
    assert float(white.persistence) < 0.5  # no persistent scale to find


def test_bad_processes_and_statistics_are_rejected():
    with pytest.raises(ValueError, match="positive definite"):
        _process((0.9, -0.9, 0.0, 0.0))
    with pytest.raises(ValueError, match="persistence"):
        _process(rho=1.0)
    with pytest.raises(ValueError, match=r"shape \(p,\)"):
        InnovationProcess(acf=jnp.zeros((2, 2)), persistence=jnp.asarray(0.0))
    with pytest.raises(ValueError, match="no innovations"):
        fit_innovation_process([np.zeros((0, 3))])
    with pytest.raises(ValueError, match="NaN"):
        fit_innovation_process([np.full((5, 3), np.nan)])
    with pytest.raises(ValueError, match="one k"):
        fit_innovation_process([np.zeros((5, 3)), np.zeros((5, 2))])
    with pytest.raises(ValueError, match="wrong shape"):
        process_from_statistics(np.ones(3))
    with pytest.raises(ValueError, match="innovations"):
        LearnConfig(innovations="pink")
    key = jax.random.key(0)
    with pytest.raises(TypeError, match="InnovationProcess"):
        draw_innovations(key, np.zeros(4), (3, 2), jnp.float64, None)  # type: ignore[arg-type]
    for bad in [(5,), (0, 3), (2, 4, 0)]:
        with pytest.raises(ValueError, match=r"shape must be \(\.\.\., n, k\)"):
            draw_innovations(key, _process(), bad, jnp.float64, 4.0)
    with pytest.raises(ValueError, match="dof must be positive"):
        draw_innovations(key, _process(), (4, 3), jnp.float64, 0.0)


def test_draws_compile_once_per_shape():
    draw = eqx.debug.assert_max_traces(_draw_innovations, max_traces=1)
    jitted = eqx.filter_jit(draw)
    p = _process()
    a = jitted(jax.random.key(0), p, (3, 20, 2), jnp.float64, 4.0)
    b = jitted(jax.random.key(1), _process(rho=0.5), (3, 20, 2), jnp.float64, 4.0)
    assert a.shape == b.shape == (3, 20, 2) and not np.allclose(a, b)


def _clips(n, T=240, D=3, seed=5):
    """AR(2) clips whose innovations are coloured and have a persistent scale."""
    rng = np.random.default_rng(seed)
    v = np.asarray(draw_innovations(jax.random.key(seed), _process(R4, 0.9), (n, T, D), float, 4.0))
    out = []
    for s in range(n):
        y = np.zeros((T, D))
        for t in range(2, T):
            y[t] = 1.2 * y[t - 1] - 0.5 * y[t - 2] + 0.3 * v[s, t] + rng.normal(size=D) * 1e-3
        out.append(y)
    return out


def test_learn_fits_the_process_on_the_training_residuals(tmp_path):
    ys = _clips(4)
    cfg = LearnConfig(
        tmin=20, tmax=60, observation="full", init="greedy", max_iter=2, innovations="fitted"
    )
    tex = mj.learn(ys, cfg)
    assert tex.innovations is not None and tex.residuals is None
    # the residuals are those of the learned segmentation, by a numpy re-derivation
    rows = np.asarray(tex.segments)
    u = segment_innovations(tex.textons, ys, rows)
    s, a, n, i = rows[0]
    t = tex.textons[int(i)]
    x = (ys[s][a : a + n] - np.asarray(t.mu)) @ np.asarray(t.C)
    e = x[2:] - x[1:-1] @ np.asarray(t.A1).T - x[:-2] @ np.asarray(t.A2).T - np.asarray(t.d)
    assert np.allclose(u[0], np.linalg.solve(np.asarray(t.B), e.T).T)
    want = fit_innovation_process(u)
    assert np.allclose(np.asarray(tex.innovations.acf), np.asarray(want.acf))
    assert np.asarray(tex.innovations.acf)[1] < -0.2  # the colour of the data (r_2 = −0.4)
    # the file keeps it; files without one (and the paper's model) have none
    tex.save(tmp_path / "t.npz")
    back = load_texture(tmp_path / "t.npz")
    assert back.innovations is not None
    assert np.allclose(np.asarray(back.innovations.acf), np.asarray(tex.innovations.acf))
    assert float(back.innovations.persistence) == float(tex.innovations.persistence)
    assert back.config.innovations == "fitted"
    with np.load(tmp_path / "t.npz") as f:  # a file with half a process
        arrays = {k: f[k] for k in f.files}
    del arrays["innovations.persistence"]
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match=r"bad\.npz.*come together"):
        load_texture(tmp_path / "bad.npz")
    # innovations="white": learn's last step (with_innovations) leaves the model without one
    white_cfg = dataclasses.replace(cfg, innovations="white")
    white = with_innovations(dataclasses.replace(tex, config=white_cfg, innovations=None), ys)
    assert white.innovations is None and white.residuals is None
    white.save(tmp_path / "w.npz")
    assert load_texture(tmp_path / "w.npz").innovations is None
    assert LearnConfig.paper().innovations == "white"
    # synthesis draws from it: finite, reproducible, and other than independent innovations
    a = mj.synthesize(jax.random.key(0), tex, n_frames=150).Y
    b = mj.synthesize(jax.random.key(0), tex, n_frames=150).Y
    c = mj.synthesize(jax.random.key(0), dataclasses.replace(tex, innovations=None), n_frames=150)
    assert np.isfinite(np.asarray(a)).all() and np.array_equal(np.asarray(a), np.asarray(b))
    assert not np.allclose(np.asarray(a), np.asarray(c.Y))
    # zero noise does not draw innovations at all
    z = mj.synthesize(None, tex, np.asarray([0]), lengths=[40]).Y
    z0 = mj.synthesize(
        None, dataclasses.replace(tex, innovations=None), np.asarray([0]), lengths=[40]
    )
    assert np.array_equal(np.asarray(z), np.asarray(z0.Y))


def test_float32_smoke():
    v = draw_innovations(jax.random.key(0), _process(), (2, 16, 3), jnp.float32, 4.0)
    assert v.dtype == jnp.float32 and np.isfinite(np.asarray(v)).all()
    # shape parameters near 0 (ρ = 0.999, a ν of 1): the chain stays positive and finite
    g = np.asarray(_scale_chain(jax.random.key(1), 0.5, jnp.asarray(0.999), (400, 50), jnp.float32))
    assert g.dtype == np.float32 and np.isfinite(g).all() and (g > 0).all()


def test_synthesize_texton_draws_from_a_process():
    """Noise-driven: the texton's recursion (numpy) driven by ``draw_innovations`` with the
    same key; constrained: the end frames held; a bad process is a TypeError."""
    y = _clips(1)[0]
    t = fit_texton(jnp.asarray(y), state_dim=3, observation=FullObservation(), dof=4.0)
    p = _process()
    start = y[:2]
    key = jax.random.key(7)
    out = np.asarray(synthesize_texton(key, t, 40, start, innovations=p))
    v = np.asarray(draw_innovations(key, p, (38, t.state_dim), jnp.float64, t.dof))
    A1, A2, d, B, C, mu = (np.asarray(a) for a in (t.A1, t.A2, t.d, t.B, t.C, t.mu))
    x = list((start - mu) @ C)
    for j in range(38):
        x.append(A1 @ x[-1] + A2 @ x[-2] + d + B @ v[j])
    assert np.allclose(out, mu + np.asarray(x) @ C.T, atol=1e-9)
    white = np.asarray(synthesize_texton(key, t, 40, start))
    assert not np.allclose(out, white)
    end = y[-2:]
    held = np.asarray(synthesize_texton(key, t, 40, start, end, innovations=p))
    assert np.allclose(held[-2:], mu + ((end - mu) @ C) @ C.T, atol=1e-8)
    assert np.allclose(held[:2], mu + ((start - mu) @ C) @ C.T, atol=1e-8)
    with pytest.raises(TypeError, match="InnovationProcess"):
        synthesize_texton(key, t, 40, start, innovations=np.zeros(4))
