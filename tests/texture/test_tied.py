"""Tied textons (design §10.10): the M-step against a numpy re-derivation, the structure of
the learned textons, and Student-t weights."""

from __future__ import annotations

import dataclasses

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np
import pytest

from mtex_jax.texture import (
    OBSERVATION_MODELS,
    FullObservation,
    TiedObservation,
    choose_state_dim,
    fit_texton,
    observation_model,
)
from mtex_jax.texture._learning.mstep import fit_all
from mtex_jax.texture._observation.tied import INIT_STARTS, IW_FRAMES
from mtex_jax.texture._scoring.rows import row_chunks
from mtex_jax.texture._texton.options import SolveOptions

RIDGE, Q_FLOOR = 1e-6, 1e-6


def _smooth(rng, T, D):
    t = np.arange(T)[:, None]
    y = np.sin(rng.uniform(0.05, 0.3, (1, D)) * t + rng.uniform(0, 6, (1, D)))
    return y + 0.05 * rng.normal(size=(T, D)) + np.cumsum(0.02 * rng.normal(size=(T, D)), 0)


def _problem(D=4, S=3, T=300, n_tex=3, seed=7):
    rng = np.random.default_rng(seed)
    Y = np.stack([_smooth(rng, T, D) for _ in range(S)])
    rows = []
    for s in range(S):
        b = 0
        while b + 30 <= T:
            n = int(rng.integers(12, 30))
            rows.append((s, b, n, len(rows) % n_tex))
            b += n
    return Y, np.asarray(rows)


def _numpy_tied(Y, rows, n_tex):
    """The tied closed form from the module doc, in numpy, from the frames themselves."""
    D = Y.shape[-1]
    R, N, means = [], [], []
    for i in range(n_tex):
        Z = []
        for s, b, n, lab in rows:
            if lab != i:
                continue
            seg = Y[s, b : b + n]
            Z += [np.concatenate([seg[t], seg[t - 1], seg[t - 2]]) for t in range(2, n)]
        Z = np.asarray(Z)
        m = Z.mean(axis=0)
        R.append((Z - m).T @ (Z - m))
        N.append(len(Z))
        means.append(m)
    Rp = sum(R)
    Rpp = Rp[D:, D:]
    eps = np.finfo(float).eps
    scale = np.trace(Rpp) / (2 * D) + sum(N) * Q_FLOOR
    A = np.linalg.solve(Rpp + (RIDGE * scale + 10 * eps * scale) * np.eye(2 * D), Rp[D:, :D]).T
    A1, A2 = A[:, :D], A[:, D:]
    E = np.concatenate([np.eye(D), -A1, -A2], axis=1)
    S = [E @ r @ E.T for r in R]
    Qbar = sum(S) / sum(N)
    out = []
    for i in range(n_tex):
        m = means[i]
        d = m[:D] - A1 @ m[D : 2 * D] - A2 @ m[2 * D :]
        Q = (S[i] + IW_FRAMES * Qbar) / (N[i] + IW_FRAMES)
        out.append((A1, A2, d, Q))
    return out


def _numpy_initial(Y, rows, n_tex):
    """The initial two-frame Gaussians of design §10.10 in numpy: shrunk towards the pair
    covariance pooled within textons, with INIT_STARTS pseudo-starts."""
    pairs, starts = [], []
    for i in range(n_tex):
        P, S = [], []
        for s, b, n, lab in rows:
            if lab != i:
                continue
            seg = Y[s, b : b + n]
            P += [np.concatenate([seg[t - 1], seg[t]]) for t in range(1, n)]
            S.append(np.concatenate([seg[0], seg[1]]))
        pairs.append(np.asarray(P))
        starts.append(np.asarray(S))
    scatters = [(P - P.mean(0)).T @ (P - P.mean(0)) for P in pairs]
    pooled = sum(scatters) / sum(len(P) for P in pairs)
    out = []
    for P, S in zip(pairs, starts, strict=True):
        mp = P.mean(0)
        m0 = (S.sum(0) + INIT_STARTS * mp) / (len(S) + INIT_STARTS)
        dm = mp - m0
        scat = (S - m0).T @ (S - m0)
        S0 = (scat + INIT_STARTS * (pooled + np.outer(dm, dm))) / (len(S) + INIT_STARTS)
        out.append((m0, S0))
    return out


def test_tied_is_registered_and_full_dimensional():
    model = observation_model("tied")
    assert "tied" in OBSERVATION_MODELS
    assert model.fixed_state_dim(7) == 7 and model.student_t
    # shared dynamics are counted once: a second texton costs less than an untied one
    D = 6
    full = observation_model("full")
    extra_tied = model.n_params(2, D, D) - model.n_params(1, D, D)
    extra_full = full.n_params(2, D, D) - full.n_params(1, D, D)
    assert extra_tied < extra_full
    # its state dimension is fixed (k = D): there is none to choose
    ys = [np.random.default_rng(0).normal(size=(50, D))]
    with pytest.raises(ValueError, match="fixed state dimension"):
        choose_state_dim(ys, model)


def test_tied_m_step_equals_numpy_rederivation():
    """Every texton's dynamics and initial two-frame Gaussian, mapped to y coordinates
    (``C A Cᵀ``, ``C Q Cᵀ``, the offset ``μ + …``), equal the numpy closed form; its mean is
    the untied fit's."""
    D, n_tex = 4, 3
    Y, rows = _problem(D=D, n_tex=n_tex)
    labels, groups = row_chunks(rows[:, 3], 8)
    opts = SolveOptions.make(RIDGE, Q_FLOOR, None, 4.0, TiedObservation(), 1e-6)
    got = fit_all(
        jnp.asarray(Y),
        jnp.asarray(rows),
        (jnp.asarray(labels), jnp.asarray(groups)),
        n_tex,
        30,
        D,
        1e-6,
        opts,
    )
    want = _numpy_tied(Y, rows, n_tex)
    inits = _numpy_initial(Y, rows, n_tex)
    for i, (A1, A2, d, Q) in enumerate(want):
        t = jax.tree.map(lambda a, i=i: np.asarray(a[i]), got)
        C, mu = t.C, t.mu
        np.testing.assert_allclose(C @ t.A1 @ C.T, A1, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(C @ t.A2 @ C.T, A2, rtol=1e-7, atol=1e-9)
        # x_t = Cᵀ(y_t − μ): the y offset is μ − A1 μ − A2 μ + C d_z
        d_y = mu - A1 @ mu - A2 @ mu + C @ t.d
        np.testing.assert_allclose(d_y, d, rtol=1e-7, atol=1e-9)
        Qz = t.B @ t.B.T
        np.testing.assert_allclose(C @ Qz @ C.T, Q + Q_FLOOR * np.eye(D), rtol=1e-7, atol=1e-9)
        # the initial two-frame Gaussian, in y coordinates, and the mean (the untied fit's)
        m0, S0 = inits[i]
        C2 = np.kron(np.eye(2), C)
        np.testing.assert_allclose(np.tile(mu, 2) + C2 @ t.m0, m0, rtol=1e-7, atol=1e-9)
        S0_y = C2 @ t.S0 @ C2.T
        np.testing.assert_allclose(S0_y, S0 + Q_FLOOR * np.eye(2 * D), rtol=1e-7, atol=1e-9)
        mask = np.full(Y.shape[:2], -1)
        for r, (s, b, n, lab) in enumerate(rows):
            if lab == i:
                mask[s, b : b + n] = r
        own = fit_texton(
            jnp.asarray(Y), jnp.asarray(mask), state_dim=D, observation=FullObservation()
        )
        np.testing.assert_allclose(t.mu, np.asarray(own.mu), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("dof", [4.0])
def test_tied_student_t_m_step_is_finite_and_tied(dof):
    D, n_tex = 4, 3
    Y, rows = _problem(D=D, n_tex=n_tex, seed=3)
    labels, groups = row_chunks(rows[:, 3], 8)
    opts = SolveOptions.make(RIDGE, Q_FLOOR, 0.999, 4.0, TiedObservation(), 1e-6, dof=dof)
    got = fit_all(
        jnp.asarray(Y),
        jnp.asarray(rows),
        (jnp.asarray(labels), jnp.asarray(groups)),
        n_tex,
        30,
        D,
        1e-6,
        opts,
    )
    assert got.dof == dof and got.observation.name == "tied"
    A1y = [np.asarray(got.C[i] @ got.A1[i] @ got.C[i].T) for i in range(n_tex)]
    for a in A1y[1:]:
        np.testing.assert_allclose(a, A1y[0], rtol=1e-8, atol=1e-10)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(got))


def test_effective_parameters_of_shrunk_estimates():
    """With the textons' frames and segments, a shrunk ``Q_i`` counts ``N_i/(N_i + ν₀)`` of
    its entries and ``S0`` ``s_i/(s_i + κ)``: a texton with no data costs its offsets only,
    one with unbounded data its full count."""
    model, D = observation_model("tied"), 5
    n_q, n_s0, shared = D * (D + 1) // 2, D * (2 * D + 1), 2 * D * D + D * (D + 1) // 2
    frames, starts = np.array([0.0, IW_FRAMES, 1e12]), np.array([0.0, INIT_STARTS, 1e12])
    got = model.n_params(3, D, D, frames, starts)
    want = shared + 3 * 3 * D + n_q * (0 + 0.5 + 1.0) + n_s0 * (0 + 0.5 + 1.0)
    assert got == pytest.approx(want, rel=1e-9)
    assert model.n_params(3, D, D) == shared + 3 * (3 * D + n_q + n_s0)
    with pytest.raises(ValueError, match="one entry per texton"):
        model.n_params(2, D, D, frames, starts)


def _synthetic_texture(n_true, seed, clips=6, T=600, D=3, tmin=20, tmax=40):
    """Clips drawn from a motion texture of ``n_true`` tied textons (MT §3): a Markov chain of
    textons without self-transitions, segment lengths uniform on ``[tmin, tmax]``; every
    segment starts from its texton's initial two-frame state (around its resting pose) and
    runs its dynamics: shared ``A1 = 0.9 I``, ``A2 = −0.2 I``, its own offset (so its own
    resting pose) and its own Student-t noise scales."""
    rng = np.random.default_rng(seed)
    A1, A2 = 0.9 * np.eye(D), -0.2 * np.eye(D)
    rest = 3.0 * rng.normal(size=(n_true, D))  # stationary means μ_i = (I − A1 − A2)⁻¹ d_i
    d = rest @ (np.eye(D) - A1 - A2).T
    scale = rng.uniform(0.05, 0.15, size=(n_true, D))
    ys = []
    for _ in range(clips):
        y = np.zeros((T, D))
        lab, t = int(rng.integers(n_true)), 0
        while t < T:
            n = int(rng.integers(tmin, tmax + 1))
            for u in range(t, min(t + n, T)):
                if u - t < 2:  # the texton's initial state
                    y[u] = rest[lab] + 0.3 * scale[lab] * rng.normal(size=D)
                else:
                    eps = scale[lab] * rng.standard_t(4.0, size=D)
                    y[u] = A1 @ y[u - 1] + A2 @ y[u - 2] + d[lab] + eps
            t += n
            if n_true > 1:
                lab = int(rng.choice([j for j in range(n_true) if j != lab]))
        ys.append(y)
    return ys


@pytest.mark.parametrize("n_true", [1, 4])
def test_selection_recovers_the_number_of_textons(n_true):
    """From many more initial textons (one per 4 chunks: 45 here), the default selection (AIC
    with the tied model's effective parameters) keeps as many textons as drew the data; so
    does BIC."""
    from mtex_jax.texture import LearnConfig, learn

    ys = _synthetic_texture(n_true, seed=15)
    cfg = LearnConfig(tmin=20, tmax=40, chunk_frames=20)  # otherwise the defaults: tied textons
    tex = learn(ys, cfg)
    assert tex.config.selection == "aic" and tex.n_textons == n_true, tex.summary()
    bic = learn(ys, dataclasses.replace(cfg, selection="bic"))
    assert bic.n_textons == n_true, bic.summary()
    # the vocabulary's figures, counted again from the segmentation and M
    voc, segs, M = tex.summary(), np.asarray(tex.segments), np.asarray(tex.M)
    for i, row in enumerate(voc.rows()):
        mine = segs[segs[:, 3] == i]
        assert row["segments"] == len(mine) and row["frames"] == mine[:, 2].sum()
        assert row["mean_length"] == pytest.approx(mine[:, 2].mean())
        want = sorted(
            ((j, M[i, j]) for j in range(n_true) if j != i and M[i, j] >= 0.1), key=lambda p: -p[1]
        )
        assert [j for j, _ in row["successors"]] == [j for j, _ in want]
    assert voc.largest_share == pytest.approx(np.bincount(segs[:, 3]).max() / len(segs))
    with pytest.raises(IndexError, match="out of range"):
        voc.successors(n_true)


def test_chunk_length_is_clipped_to_the_segment_lengths():
    from mtex_jax.texture import LearnConfig

    assert LearnConfig().chunk_length == 80
    assert LearnConfig(tmin=10, tmax=30).chunk_length == 30
    assert LearnConfig(tmin=100, tmax=300).chunk_length == 100
    assert LearnConfig(tmin=10, tmax=None, chunk_frames=50).chunk_length == 50
