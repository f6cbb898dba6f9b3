"""The likelihood contract of a texture (issue 43, item 5): ``mean=True`` is the total over the
number of frames; ``per_frame=True`` is an exact decomposition, for the best path, against an
independent numpy/scipy re-derivation; the marginal has none and says so."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import multivariate_normal

import mtex_jax as mj
from mtex_jax.texture import segment_log_likelihood


def _clips(seed: int = 0, T: int = 150, D: int = 4) -> list[np.ndarray]:
    """Three clips of 30-frame pieces of three kinds of sine motion (a few textons)."""
    rng = np.random.default_rng(seed)
    t = np.arange(30)
    out = []
    for s in range(3):
        parts = [
            np.stack([np.sin(0.15 * (1 + (j + s) % 3) * t + d) + j % 3 for d in range(D)], 1)
            for j in range(T // 30)
        ]
        out.append(np.concatenate(parts) + 0.1 * rng.normal(size=(T, D)))
    return out


@pytest.fixture(scope="module")
def paper_tex():
    """The paper's model (Gaussian innovations, white residual) with learned durations."""
    cfg = mj.LearnConfig.paper(tmin=10, tmax=40, state_dim=2, durations="lognormal", max_iter=3)
    return mj.learn(_clips(), cfg)


@pytest.fixture(scope="module")
def default_tex():
    """The default model (tied textons, Student-t innovations, learned durations)."""
    cfg = mj.LearnConfig(tmin=10, tmax=40, max_iter=3, min_segments=1, selection="none")
    return mj.learn(_clips(1), cfg)


def _numpy_path_frames(tex, y: np.ndarray) -> np.ndarray:
    """Per-frame terms of the paper's texton model along ``tex.segment(y)``, from the model's
    definition (design §2.1, §2.8, §3.1) with scipy densities: states ``x_t = Cᵀ(y_t − μ)``,
    the isotropic residual outside the subspace, Gaussian dynamics from the third frame, the
    initial-state density by the chain rule, the transition and duration at the first frame."""
    T, D = y.shape
    names = ("C", "mu", "sigma2", "m0", "S0", "B", "A1", "A2", "d")
    f = {n: np.asarray(getattr(tex.textons, n), np.float64) for n in names}
    k = f["C"].shape[-1]
    log_pi, log_M = np.log(np.asarray(tex.pi)), np.log(np.asarray(tex.M))
    out = np.full(T, np.nan)
    prev = -1
    for b, n, i in tex.segment(y).to_list():
        C, mu, s2 = f["C"][i], f["mu"][i], float(f["sigma2"][i])
        m0, S0, Q = f["m0"][i], f["S0"][i], f["B"][i] @ f["B"][i].T
        x = (y[b : b + n] - mu) @ C
        r2 = np.sum((y[b : b + n] - mu) ** 2, axis=1) - np.sum(x * x, axis=1)
        vals = -0.5 * ((D - k) * np.log(2 * np.pi * s2) + r2 / s2)
        for t in range(2, n):
            mean = f["A1"][i] @ x[t - 1] + f["A2"][i] @ x[t - 2] + f["d"][i]
            vals[t] += multivariate_normal(mean, Q).logpdf(x[t])
        vals[0] += multivariate_normal(m0[:k], S0[:k, :k]).logpdf(x[0])
        gain = S0[k:, :k] @ np.linalg.inv(S0[:k, :k])
        cond = S0[k:, k:] - gain @ S0[:k, k:]
        vals[1] += multivariate_normal(m0[k:] + gain @ (x[0] - m0[:k]), cond).logpdf(x[1])
        vals[0] += log_pi[i] if prev < 0 else log_M[prev, i]
        if tex.log_durations is not None:
            vals[0] += float(tex.log_durations[i, n - tex.config.tmin])
        out[b : b + n] = vals
        prev = i
    return out


def test_best_path_per_frame_against_numpy_on_the_paper_model(paper_tex):
    y = _clips(5)[0]
    got = paper_tex.best_path_log_likelihood(y, per_frame=True)
    assert isinstance(got, np.ndarray) and got.shape == (y.shape[0],)
    np.testing.assert_allclose(got, _numpy_path_frames(paper_tex, y), rtol=1e-8, atol=1e-8)
    assert paper_tex.contacts is None  # learned from arrays: no feet, no contact model
    total = paper_tex.best_path_log_likelihood(y)
    np.testing.assert_allclose(got.sum(), total, rtol=1e-12)
    np.testing.assert_allclose(float(paper_tex.segment(y).score), total, rtol=1e-12)
    assert paper_tex.best_path_log_likelihood(y, mean=True) == pytest.approx(
        total / y.shape[0], rel=1e-14
    )


def test_best_path_per_frame_sums_to_each_segment_on_the_default_model(default_tex):
    """Tied textons with Student-t innovations: each segment's frames sum to its direct
    likelihood (the per-segment reference, not the prefix sums) plus its transition and
    duration log-probabilities, and all frames to the best path's score."""
    tex = default_tex
    assert tex.textons.dof is not None and tex.log_durations is not None
    y = _clips(6)[1]
    got = tex.best_path_log_likelihood(y, per_frame=True)
    log_pi, log_M = np.log(np.asarray(tex.pi)), np.log(np.asarray(tex.M))
    prev = -1
    for b, n, i in tex.segment(y).to_list():
        want = float(segment_log_likelihood(tex.textons[i], y[b : b + n]))
        want += (log_pi[i] if prev < 0 else log_M[prev, i]) + float(
            tex.log_durations[i, n - tex.config.tmin]
        )
        np.testing.assert_allclose(got[b : b + n].sum(), want, rtol=1e-10, atol=1e-9)
        prev = i
    np.testing.assert_allclose(got.sum(), tex.best_path_log_likelihood(y), rtol=1e-12)


def test_marginal_mean_and_no_per_frame(paper_tex):
    y = _clips(7)[2]
    total = paper_tex.log_likelihood(y)
    assert paper_tex.log_likelihood(y, mean=True) == pytest.approx(total / len(y), rel=1e-14)
    with pytest.raises(ValueError, match=r"does not decompose exactly.*mean=True.*best_path"):
        paper_tex.log_likelihood(y, per_frame=True)
    with pytest.raises(ValueError, match="exclude each other"):
        paper_tex.best_path_log_likelihood(y, per_frame=True, mean=True)
