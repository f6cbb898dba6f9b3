"""Observation models beyond the paper (residual AR(2), full-dimensional textons), explicit
durations, the state-dimension choice and stable-by-default textons (issue 16), each against
an independent reference: numpy least squares, a dense Gaussian over all frames of a segment,
brute-force enumeration of segmentations."""

from __future__ import annotations

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import multivariate_normal

import mtex_jax as mj
from dp_problems import compositions
from mtex_jax.texture import (
    FullObservation,
    PaperObservation,
    ResidualObservation,
    Texton,
    choose_state_dim,
    fit_durations,
    fit_texton,
    frame_terms,
    init_terms,
    observation_model,
    sample_texton,
    segment,
    segment_log_likelihood,
    segment_scores,
    spectral_radius,
    stack_textons,
)
from mtex_jax.texture._scoring.frame_terms_ref import frame_terms_per_texton


def _smooth(rng, T, D, n_osc=3):
    t = np.arange(T)[:, None]
    w = rng.uniform(0.05, 0.3, size=(n_osc, 1, 1))
    ph = rng.uniform(0, 6, size=(n_osc, 1, D))
    amp = rng.normal(size=(n_osc, 1, D))
    y = np.sum(amp * np.sin(w * t[None] + ph), axis=0)
    return y + 0.05 * rng.normal(size=(T, D)) + np.cumsum(0.02 * rng.normal(size=(T, D)), 0)


# --------------------------------------------------------------------------------------------
# M-step against numpy least squares
# --------------------------------------------------------------------------------------------
def test_residual_mstep_is_least_squares():
    rng = np.random.default_rng(0)
    Y = _smooth(rng, 200, 7)
    k = 3
    tex = fit_texton(jnp.asarray(Y), state_dim=k, observation=ResidualObservation(), ridge=0.0)
    assert tex.observation.name == "residual"
    # numpy: the residual outside the fitted subspace, pooled over its coordinates
    C, mu = np.asarray(tex.C), np.asarray(tex.mu)
    R = (Y - mu) - (Y - mu) @ C @ C.T
    X = np.stack([R[1:-1].ravel(), R[:-2].ravel()], axis=1)
    a, *_ = np.linalg.lstsq(X, R[2:].ravel(), rcond=None)
    np.testing.assert_allclose(np.asarray(tex.observation.a), a, rtol=1e-6, atol=1e-9)
    e = R[2:].ravel() - X @ a
    np.testing.assert_allclose(float(tex.observation.s2), e @ e / ((200 - 2) * (7 - k)), rtol=1e-6)
    # the subspace and dynamics are the paper's fit
    paper = fit_texton(jnp.asarray(Y), state_dim=k, ridge=0.0)
    np.testing.assert_allclose(np.asarray(paper.A1), np.asarray(tex.A1), atol=1e-10)
    assert paper.observation == PaperObservation()  # no parameters beyond σ²


def test_residual_mstep_over_segments_pools_valid_triples():
    """Two segments: the residual regression uses only triples inside one segment."""
    rng = np.random.default_rng(1)
    Y = _smooth(rng, 120, 6)
    mask = np.repeat([0, 1], 60)
    tex = fit_texton(
        jnp.asarray(Y), jnp.asarray(mask), state_dim=2, observation=ResidualObservation(), ridge=0.0
    )
    C, mu = np.asarray(tex.C), np.asarray(tex.mu)
    R = (Y - mu) - (Y - mu) @ C @ C.T
    rows, tgt = [], []
    for b in (0, 60):
        r = R[b : b + 60]
        rows.append(np.stack([r[1:-1].ravel(), r[:-2].ravel()], 1))
        tgt.append(r[2:].ravel())
    X, t = np.concatenate(rows), np.concatenate(tgt)
    a = np.linalg.solve(X.T @ X, X.T @ t)
    np.testing.assert_allclose(np.asarray(tex.observation.a), a, rtol=1e-4)


def test_full_texton_is_ar2_on_y():
    """k = D: no residual; the dynamics are the least-squares AR(2) of y (rotated)."""
    rng = np.random.default_rng(2)
    Y = _smooth(rng, 300, 4)
    tex = fit_texton(jnp.asarray(Y), state_dim=4, observation=FullObservation(), ridge=0.0)
    A1, A2, C = (np.asarray(getattr(tex, f)) for f in ("A1", "A2", "C"))
    X = np.concatenate([Y[1:-1], Y[:-2], np.ones((298, 1))], axis=1)
    coef, *_ = np.linalg.lstsq(X, Y[2:], rcond=None)
    np.testing.assert_allclose(C @ A1 @ C.T, coef[:4].T, atol=1e-6)
    np.testing.assert_allclose(C @ A2 @ C.T, coef[4:8].T, atol=1e-6)
    with pytest.raises(ValueError, match="full"):
        fit_texton(jnp.asarray(Y), state_dim=3, observation=FullObservation())


# --------------------------------------------------------------------------------------------
# per-frame terms against a dense Gaussian
# --------------------------------------------------------------------------------------------
def _residual_texton(rng, D=4, k=2):
    Y = _smooth(rng, 150, D)
    tex = fit_texton(jnp.asarray(Y), state_dim=k, observation=ResidualObservation())
    assert abs(float(tex.observation.a[0])) > 0.1  # a real residual AR(2), not white noise
    return tex, Y


def _dense_logpdf(tex: Texton, Y: np.ndarray) -> float:
    """log N(vec Y; m, S) of the generative residual model, built as a linear map of its
    Gaussian innovations: x_1, x_2 ~ N(m0, S0), x_t = A1 x_{t−1} + A2 x_{t−2} + d + B v_t;
    ρ_1, ρ_2 ~ N(0, σ² I), ρ_t = a₁ ρ_{t−1} + a₂ ρ_{t−2} + e_t (e ~ N(0, s_r² I)) in an
    orthonormal basis P of the complement of C; y_t = μ + C x_t + P ρ_t."""
    L, D = Y.shape
    C, mu = np.asarray(tex.C), np.asarray(tex.mu)
    k = C.shape[1]
    q, _ = np.linalg.qr(np.concatenate([C, np.eye(D)], axis=1))
    P = q[:, k:D]
    A1, A2, d, B = (np.asarray(getattr(tex, f)) for f in ("A1", "A2", "d", "B"))
    m0, S0 = np.asarray(tex.m0), np.asarray(tex.S0)
    a1, a2 = np.asarray(tex.observation.a)
    s2, sr2 = float(tex.sigma2), float(tex.observation.s2)
    r = D - k
    n_in = 2 * k + (L - 2) * k + 2 * r + (L - 2) * r  # innovations, all standard normal
    L0 = np.linalg.cholesky(S0)
    # x_t = xm[t] + Xmap[t] @ eps ; rho_t = Rmap[t] @ eps
    xm, Xmap, Rmap = [], [], []
    col = 0
    for t in range(2):
        xm.append(m0[t * k : (t + 1) * k])
        M = np.zeros((k, n_in))
        M[:, : 2 * k] = L0[t * k : (t + 1) * k]
        Xmap.append(M)
    col = 2 * k
    for _t in range(2, L):
        xm.append(A1 @ xm[-1] + A2 @ xm[-2] + d)
        M = A1 @ Xmap[-1] + A2 @ Xmap[-2]
        M[:, col : col + k] += B
        col += k
        Xmap.append(M)
    for _t in range(2):
        M = np.zeros((r, n_in))
        M[:, col : col + r] = math.sqrt(s2) * np.eye(r)
        col += r
        Rmap.append(M)
    for _t in range(2, L):
        M = a1 * Rmap[-1] + a2 * Rmap[-2]
        M[:, col : col + r] += math.sqrt(sr2) * np.eye(r)
        col += r
        Rmap.append(M)
    mean = np.concatenate([mu + C @ xm[t] for t in range(L)])
    A = np.concatenate([C @ Xmap[t] + P @ Rmap[t] for t in range(L)])
    return float(multivariate_normal(mean, A @ A.T).logpdf(Y.ravel()))


@pytest.mark.parametrize("L", [3, 5, 8])
def test_residual_segment_likelihood_equals_dense_gaussian(L):
    rng = np.random.default_rng(10 + L)
    tex, Y = _residual_texton(rng)
    seg = Y[40 : 40 + L]
    want = _dense_logpdf(tex, seg)
    got = float(segment_log_likelihood(tex, jnp.asarray(seg)))
    np.testing.assert_allclose(got, want, rtol=1e-8)


def test_blocked_kernel_and_prefix_sums_agree_with_direct_reference():
    rng = np.random.default_rng(4)
    texs = [_residual_texton(np.random.default_rng(s), D=6, k=2)[0] for s in range(3)]
    stack = stack_textons(texs)
    Y = jnp.asarray(_smooth(rng, 90, 6))
    dyn, obs = frame_terms(stack, Y, block_size=13)
    dyn_r, obs_r = frame_terms_per_texton(stack, Y)
    np.testing.assert_allclose(np.asarray(dyn), np.asarray(dyn_r), rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(np.asarray(obs), np.asarray(obs_r), rtol=1e-9, atol=1e-8)
    sc = segment_scores(stack, Y)
    for b, e, i in [(0, 10, 0), (5, 40, 1), (30, 89, 2), (70, 72, 0)]:
        want = float(segment_log_likelihood(stack[i], Y[b : e + 1]))
        np.testing.assert_allclose(float(sc.score(b, e, i)), want, rtol=1e-9)
    assert init_terms(stack, Y).shape == (3, 90)


def test_paper_textons_score_as_before():
    """A paper texton has a = 0, s_r² = σ²: its terms equal the white-noise formula."""
    rng = np.random.default_rng(5)
    Y = _smooth(rng, 80, 5)
    tex = fit_texton(jnp.asarray(Y), state_dim=2)
    dyn, obs = frame_terms(tex, jnp.asarray(Y))
    C, mu, s2 = np.asarray(tex.C), np.asarray(tex.mu), float(tex.sigma2)
    r = (Y - mu) - (Y - mu) @ C @ C.T
    want = -0.5 * (3 * np.log(2 * np.pi * s2) + np.sum(r * r, 1) / s2)
    np.testing.assert_allclose(np.asarray(obs), want, rtol=1e-9)
    X = (Y - mu) @ C
    w = X[2:] - X[1:-1] @ np.asarray(tex.A1).T - X[:-2] @ np.asarray(tex.A2).T - np.asarray(tex.d)
    Q = np.asarray(tex.B) @ np.asarray(tex.B).T
    want_dyn = multivariate_normal(np.zeros(2), Q).logpdf(w)
    np.testing.assert_allclose(np.asarray(dyn)[2:], want_dyn, rtol=1e-9)


# --------------------------------------------------------------------------------------------
# durations
# --------------------------------------------------------------------------------------------
def test_fit_durations_rows_are_distributions_and_follow_the_data():
    lengths = np.array([10, 11, 10, 12, 28, 30, 29, 31, 30, 29])
    labels = np.array([0, 0, 0, 0, 1, 1, 1, 1, 1, 1])
    ld = fit_durations(lengths, labels, 3, 8, 32)
    np.testing.assert_allclose(np.exp(ld).sum(axis=1), 1.0, rtol=1e-12)
    assert 9 <= 8 + int(np.argmax(ld[0])) <= 12
    assert 26 <= 8 + int(np.argmax(ld[1])) <= 31
    assert ld.min() >= np.log(0.01 / 25) - 1e-12  # the flat floor
    # texton 2 has no segment: the pooled distribution, broad
    assert np.exp(ld[2]).max() < np.exp(ld[0]).max()
    with pytest.raises(ValueError, match="lie in"):
        fit_durations(np.array([40]), np.array([0]), 1, 8, 32)


def _brute_best(textons, log_M, log_pi, Y, tmin, tmax, log_dur):
    T, n_t = Y.shape[0], log_pi.shape[0]
    one = [textons[i] for i in range(n_t)]
    seg_ll: dict[tuple[int, int, int], float] = {}  # each segment's likelihood computed once

    def ll(b: int, L: int, i: int) -> float:
        if (b, L, i) not in seg_ll:
            seg_ll[b, L, i] = float(segment_log_likelihood(one[i], Y[b : b + L]))
        return seg_ll[b, L, i]

    best, arg = -np.inf, None
    for comp in compositions(T, tmin, tmax):
        starts = np.concatenate([[0], np.cumsum(comp)[:-1]]).astype(int)
        for labels in itertools.product(range(n_t), repeat=len(comp)):
            s = log_pi[labels[0]] + sum(log_M[a, b] for a, b in itertools.pairwise(labels))
            for b, L, i in zip(starts, comp, labels, strict=True):
                s += ll(int(b), int(L), int(i))
                s += log_dur[i, L - tmin]
            if s > best:
                best, arg = s, list(zip(starts.tolist(), comp, labels, strict=True))
    return best, arg


@pytest.mark.parametrize(("T", "tmin", "tmax"), [(10, 3, 5), (12, 3, 7), (9, 3, 3)])
def test_duration_viterbi_equals_brute_force(T, tmin, tmax):
    rng = np.random.default_rng(T)
    texs = [_residual_texton(np.random.default_rng(s), D=4, k=2)[0] for s in (1, 2)]
    stack = stack_textons(texs)
    Y = _smooth(rng, T, 4)
    log_M = np.log(rng.dirichlet(np.ones(2), size=2))
    log_pi = np.log(rng.dirichlet(np.ones(2)))
    # strongly peaked durations, so that they change the optimum
    log_dur = np.log(rng.dirichlet(0.3 * np.ones(tmax - tmin + 1), size=2) + 1e-12)
    want, arg = _brute_best(stack, log_M, log_pi, Y, tmin, tmax, log_dur)
    cache: dict = {}
    seg = segment(stack, log_M, log_pi, jnp.asarray(Y), tmin, tmax, log_durations=log_dur)
    np.testing.assert_allclose(float(seg.score), want, rtol=1e-9)
    got = [(b, L, i) for b, L, i in seg.to_list()]
    assert got == [(int(b), int(L), int(i)) for b, L, i in arg], cache
    # forward >= Viterbi with the same durations
    fw = mj.texture.log_likelihood(
        stack, log_M, log_pi, jnp.asarray(Y), tmin, tmax, log_durations=log_dur
    )
    assert float(fw) >= float(seg.score) - 1e-9


def _numpy_duration_dp(scorer, log_M, log_pi, T, tmin, tmax, log_dur):
    """The duration-aware Viterbi scores of every prefix of the frames, ``(T,)``, by a plain
    numpy DP over (end, texton, length)."""
    n_t = log_pi.shape[0]
    b, e = np.meshgrid(np.arange(T), np.arange(T), indexing="ij")
    table = np.asarray(scorer.score(b[None], e[None], np.arange(n_t)[:, None, None]))
    V = np.full((T, n_t), -np.inf)  # best score of frames 0 … e with a segment of i ending at e
    for end in range(T):
        L = np.arange(tmin, min(tmax, end + 1) + 1)  # every length of the last segment at once
        start = end - L + 1
        # entering texton j: log π at frame 0, else the best predecessor i ending before start
        prev = np.max(V[np.maximum(start - 1, 0)][:, :, None] + log_M, axis=1)
        enter = np.where((start == 0)[:, None], log_pi, prev)
        cand = enter + table[:, start, end].T + log_dur[:, L - tmin].T  # (lengths, textons)
        if len(L):
            V[end] = cand.max(axis=0)
    return V.max(axis=1)


@pytest.mark.parametrize("gather_max_bytes", [0, 2**40])
@pytest.mark.parametrize(("T", "tmin", "tmax"), [(90, 3, 40), (330, 3, 300)])
def test_duration_viterbi_long_length_ranges_equal_numpy_dp(
    T, tmin, tmax, gather_max_bytes, monkeypatch
):
    """Length ranges below and above the unrolled windowed maximum (``Wn`` 38 and 298), with
    the window gathered or (``gather_max_bytes = 0``, ``Wn`` 38) the unrolled chain of
    shifted slices, against an independent numpy DP on the same segment scores."""
    from mtex_jax.texture._segmentation import recursion as _recursion

    monkeypatch.setattr(_recursion, "_GATHER_MAX_BYTES", gather_max_bytes)
    jax.clear_caches()  # the choice is made when tracing: trace again with this setting
    rng = np.random.default_rng(tmax)
    texs = [_residual_texton(np.random.default_rng(s), D=4, k=2)[0] for s in (1, 2)]
    stack = stack_textons(texs)
    Y = jnp.asarray(_smooth(rng, T, 4))
    log_M = np.log(rng.dirichlet(np.ones(2), size=2))
    log_pi = np.log(rng.dirichlet(np.ones(2)))
    scorer = segment_scores(stack, Y)
    n_valid = jnp.arange(T - 2 * tmax // 3, T + 1)  # many prefixes of the frames
    ramp = np.linspace(0.0, 200.0, tmax - tmin + 1)
    for log_dur in (  # random and peaked; favouring the shortest; favouring the longest
        np.log(rng.dirichlet(0.3 * np.ones(tmax - tmin + 1), size=2) + 1e-12),
        np.stack([-ramp, -ramp]),
        np.stack([ramp, ramp]),
    ):
        want = _numpy_duration_dp(scorer, log_M, log_pi, T, tmin, tmax, log_dur)
        got = jax.vmap(
            lambda n, d=log_dur: (
                mj.texture.viterbi_segments(scorer, log_M, log_pi, n, tmin, tmax, d).score
            )
        )(n_valid)
        np.testing.assert_allclose(np.asarray(got), want[np.asarray(n_valid) - 1], rtol=1e-10)
    seg = segment(stack, log_M, log_pi, Y, tmin, tmax, log_durations=log_dur)
    np.testing.assert_allclose(float(seg.score), want[-1], rtol=1e-10)


def test_duration_viterbi_bad_input():
    texs = stack_textons([_residual_texton(np.random.default_rng(s))[0] for s in (1, 2)])
    Y = jnp.asarray(_smooth(np.random.default_rng(0), 12, 4))
    lm, lp = np.log(np.full((2, 2), 0.5)), np.log(np.full(2, 0.5))
    with pytest.raises(ValueError, match="log_durations must have shape"):
        segment(texs, lm, lp, Y, 3, 5, log_durations=np.zeros((2, 4)))
    with pytest.raises(ValueError, match="finite tmax"):
        segment(texs, lm, lp, Y, 3, None, log_durations=np.zeros((2, 4)))
    with pytest.raises(ValueError, match="NaN"):
        segment(texs, lm, lp, Y, 3, 5, log_durations=np.full((2, 3), np.nan))


# --------------------------------------------------------------------------------------------
# state dimension, learning defaults, stability
# --------------------------------------------------------------------------------------------
def test_choose_state_dim_loglik_matches_the_fitted_texton():
    """The closed-form plug-in log-likelihood of choose_state_dim equals the fitted texton's
    dynamics + residual terms (the frame terms summed without the initial two frames)."""
    rng = np.random.default_rng(6)
    ys = [_smooth(rng, 400, 8)]
    for obs in ("paper", "residual"):
        _, table = choose_state_dim(ys, observation_model(obs), candidates=[3], ridge=0.0)
        tex = fit_texton(
            jnp.asarray(ys[0]),
            state_dim=3,
            observation=observation_model(obs),
            ridge=0.0,
            q_floor=1e-12,
            sigma2_floor=1e-12,
        )
        dyn, ob = (np.asarray(a) for a in frame_terms(tex, jnp.asarray(ys[0])))
        got = dyn[2:].sum() + (ob.sum() if obs == "paper" else ob[2:].sum())
        np.testing.assert_allclose(table[0]["loglik"], got, rtol=1e-6)


def _clips(seed=0, n=3, T=240, D=5):
    rng = np.random.default_rng(seed)
    return [_smooth(rng, T, D) for _ in range(n)]


@pytest.fixture(scope="module")
def default_texture():
    """Clips and the texture learned from them with the default settings: learned once for
    the tests of the defaults and of the fitted durations."""
    ys = _clips()
    return ys, mj.learn(ys, mj.LearnConfig(tmin=20, tmax=60, max_iter=3))


def test_learn_defaults_are_stable_tied_with_durations(default_texture):
    ys, tex = default_texture
    cfg = tex.config
    assert cfg.observation == "tied" and cfg.durations == "lognormal" and cfg.init == "chunks"
    assert cfg.state_dim == 5 and cfg.dof == 4.0
    assert tex.textons.observation.name == "tied"
    assert tex.log_durations is not None and tex.log_durations.shape == (tex.n_textons, 41)
    np.testing.assert_allclose(np.exp(np.asarray(tex.log_durations)).sum(1), 1.0, rtol=1e-9)
    assert float(jnp.max(spectral_radius(tex.textons))) <= 1.0 + 1e-9
    counts = np.bincount(np.asarray(tex.segments)[:, 3], minlength=tex.n_textons)
    assert counts.min() >= min(3, len(counts) and counts.sum())
    # 10,000 frames of noise-driven synthesis from every texton's own key poses stay finite
    # and within a small multiple of the training range
    span = max(np.abs(y).max() for y in ys)
    kp = np.asarray(tex.key_poses)
    lab = np.asarray(tex.key_pose_labels)
    for i in range(tex.n_textons):
        t = tex.textons[i]
        x1, x2 = (np.asarray(t.C).T @ (p - np.asarray(t.mu)) for p in kp[lab == i][0])
        _, out = sample_texton(jax.random.key(i), t, 10_000, x1, x2)
        out = np.asarray(out)
        assert np.isfinite(out).all()
        assert np.abs(out).max() < 20 * span


def test_synthesis_draws_lengths_from_the_fitted_durations(default_texture):
    import equinox as eqx

    _, tex = default_texture
    assert tex.log_durations is not None
    # every texton's duration distribution a point mass at 33 frames
    point = np.full(tex.log_durations.shape, -np.inf)
    point[:, 33 - 20] = 0.0
    tex33 = eqx.tree_at(lambda t: t.log_durations, tex, jnp.asarray(point))
    syn = mj.synthesize(jax.random.key(0), tex33, n_frames=300, decode=False)
    lens = np.asarray(syn.lengths)
    assert lens.sum() == 300 and np.all(lens[:-1] == 33), lens
    path = np.asarray(syn.path)
    np.testing.assert_array_equal(
        np.asarray(mj.synthesize(jax.random.key(1), tex33, path, decode=False).lengths), 33
    )
    # the paper's choice: the lengths of the key poses' training segments
    seg = mj.synthesize(
        jax.random.key(0), tex33, n_frames=300, decode=False, lengths_from="segments"
    )
    train_lengths = set(np.asarray(tex.segment_lengths).tolist())
    assert set(np.asarray(seg.lengths)[:-1].tolist()) <= train_lengths
    with pytest.raises(ValueError, match="lengths_from"):
        mj.synthesize(jax.random.key(0), tex33, n_frames=300, lengths_from="fitted")


def test_learned_models_round_trip_and_old_files_load_as_paper(tmp_path):
    ys = _clips(1)
    tex = mj.learn(ys, mj.LearnConfig(tmin=20, tmax=60, max_iter=2, observation="residual"))
    p = tmp_path / "t.npz"
    tex.save(p)
    back = mj.load_texture(p)
    assert back.textons.observation.name == "residual"
    np.testing.assert_array_equal(np.asarray(back.log_durations), np.asarray(tex.log_durations))
    np.testing.assert_allclose(
        np.asarray(back.textons.observation.a), np.asarray(tex.textons.observation.a)
    )
    Y = jnp.asarray(ys[0])
    assert back.log_likelihood(Y) == pytest.approx(tex.log_likelihood(Y), rel=1e-12)
    # a file of the previous format: no residual arrays, durations or observation fields
    paper = mj.learn(
        ys,
        mj.LearnConfig(
            tmin=20, tmax=60, max_iter=2, observation="paper", durations="flat", state_dim=2
        ),
    )
    old = tmp_path / "old.npz"
    paper.save(old)
    arrays, meta = mj.core.load_arrays_json(old, kind="mtex_jax.MotionTexture")
    meta["texton_fields"] = [f for f in meta["texton_fields"] if not f.startswith("res_")]
    meta.pop("observation")
    for f in ("observation", "durations"):
        meta["config"].pop(f)
    arrays = {k: v for k, v in arrays.items() if "res_" not in k}
    stripped = tmp_path / "stripped.npz"
    mj.core.save_arrays_json(stripped, arrays, meta)
    got = mj.load_texture(stripped)
    assert got.textons.observation.name == "paper" and got.config.durations == "flat"
    assert got.log_likelihood(Y) == pytest.approx(paper.log_likelihood(Y), rel=1e-12)


def test_full_observation_learns_ar_hsmm():
    ys = _clips(2, D=4)
    tex = mj.learn(ys, mj.LearnConfig(tmin=20, tmax=60, max_iter=2, observation="full"))
    assert tex.textons.state_dim == 4 == tex.config.state_dim
    assert tex.textons.observation.name == "full"
    with pytest.raises(ValueError, match="full"):
        mj.learn(ys, mj.LearnConfig(tmin=20, tmax=60, observation="full", state_dim=2))


def test_config_rejects_unknown_models():
    with pytest.raises(ValueError, match="observation"):
        mj.LearnConfig(observation="kalman")
    with pytest.raises(ValueError, match="durations"):
        mj.LearnConfig(durations="poisson")


def test_paper_config():
    cfg = mj.LearnConfig.paper(tmin=30, min_segments=3)
    assert (cfg.observation, cfg.durations, cfg.selection) == ("paper", "flat", "none")
    assert (cfg.state_dim, cfg.rho_max, cfg.tmin, cfg.min_segments) == (12, None, 30, 3)
    assert mj.LearnConfig.paper().min_segments == 1
    with pytest.raises(ValueError, match="observation"):
        mj.LearnConfig.paper(observation="kalman")


def test_float32_smoke():
    ys = [y.astype(np.float32) for y in _clips(3)]
    tex = mj.learn(ys, mj.LearnConfig(tmin=20, tmax=60, max_iter=2))
    assert tex.textons.mu.dtype == jnp.float32
    ll = tex.log_likelihood(jnp.asarray(ys[0]))
    assert np.isfinite(ll)
