"""The contract of an observation model (design §10.3), run over every member of the registry:
what each member's parameters, M-step, frame terms and file arrays must satisfy.

A new member passes these tests or is not a member: its M-step maximises the score it defines,
its frame terms are the dense Gaussian (or Student-t) density of the model they describe
(scipy's, with no texton algebra), it survives a model file, and what it generates stays
bounded.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import mtex_jax as mj
from mtex_jax.texture import (
    OBSERVATION_MODELS,
    ObservationModel,
    fit_texton,
    frame_terms,
    init_terms,
    sample_texton,
    segment_log_likelihood,
    stack_textons,
)

D, K, T = 5, 2, 300

#: every member of the registry; a member with Student-t innovations also with ν = 4
CASES = [
    pytest.param(name, dof, id=name if dof is None else f"{name}-t{dof:g}")
    for name, member in OBSERVATION_MODELS.items()
    for dof in ((None, 4.0) if member.student_t else (None,))
]


def _data(seed: int, T: int = T) -> np.ndarray:
    """Smooth motion-like frames: oscillations, a drift and small noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(T)[:, None]
    w = rng.uniform(0.05, 0.3, size=(3, 1, 1))
    ph = rng.uniform(0, 6, size=(3, 1, D))
    amp = rng.normal(size=(3, 1, D))
    y = np.sum(amp * np.sin(w * t[None] + ph), axis=0)
    return y + 0.05 * rng.normal(size=(T, D)) + np.cumsum(0.02 * rng.normal(size=(T, D)), 0)


def _k(member: ObservationModel) -> int:
    fixed = member.fixed_state_dim(D)
    return K if fixed is None else fixed


def _fit(name: str, dof: float | None, Y: np.ndarray, **kw):
    member = OBSERVATION_MODELS[name]
    return fit_texton(jnp.asarray(Y), state_dim=_k(member), observation=member, dof=dof, **kw)


def test_the_registry_holds_members_that_choose_their_model():
    assert set(OBSERVATION_MODELS) == {"paper", "residual", "full", "tied"}
    for name, member in OBSERVATION_MODELS.items():
        assert isinstance(member, ObservationModel) and member.name == name
        assert mj.texture.observation_model(name) is member
        assert mj.texture.observation_model(member) is member
    with pytest.raises(TypeError, match=r"ResidualObservation\(\)"):
        fit_texton(jnp.asarray(_data(0)), state_dim=K, observation="residual")


@pytest.mark.parametrize(("name", "dof"), CASES)
def test_frame_terms_are_the_dense_density_of_the_model(name, dof):
    """Every frame's ``dyn + obs`` (``t ≥ 2``) is ``log p(y_t | y_{t−1}, y_{t−2})`` of the
    model in ``D`` dimensions, and a segment's first two frames ``init + obs + obs`` are
    ``log p(y_b, y_{b+1})``: scipy's multivariate normal (or t) with the covariance written
    out densely, against the blocked kernel."""
    Y = _data(1)
    tex = _fit(name, dof, Y)
    dyn, obs = (np.asarray(a)[0] for a in frame_terms(stack_textons([tex]), jnp.asarray(Y)))
    init = np.asarray(init_terms(stack_textons([tex]), jnp.asarray(Y)))[0]
    mu, C = np.asarray(tex.mu), np.asarray(tex.C)
    A1, A2, d, B = (np.asarray(a) for a in (tex.A1, tex.A2, tex.d, tex.B))
    k = C.shape[1]
    P = np.eye(D) - C @ C.T  # onto the residual
    s2 = float(tex.sigma2)
    member = tex.observation
    if name == "residual":
        a1, a2 = np.asarray(member.a)
        sr2 = float(member.s2)
    else:
        a1 = a2 = 0.0
        sr2 = s2
    X = (Y - mu) @ C
    R = (Y - mu) @ P
    cov = C @ B @ B.T @ C.T + sr2 * P  # of y_t given the two frames before
    for t in (2, 3, 50, T - 1):
        mean = mu + C @ (A1 @ X[t - 1] + A2 @ X[t - 2] + d) + a1 * R[t - 1] + a2 * R[t - 2]
        if dof is None:
            want = stats.multivariate_normal(mean, cov).logpdf(Y[t])
        else:
            want = stats.multivariate_t(mean, cov, df=dof).logpdf(Y[t])
        np.testing.assert_allclose(dyn[t] + obs[t], want, rtol=1e-9, atol=1e-9)
    # the first two frames of a segment: [x_b; x_{b+1}] ~ N(m0, S0), white residuals of σ²
    C2 = np.kron(np.eye(2), C)
    cov0 = C2 @ np.asarray(tex.S0) @ C2.T + s2 * np.kron(np.eye(2), P)
    mean0 = np.concatenate([mu, mu]) + C2 @ np.asarray(tex.m0)
    for b in (0, 7, T - 2):
        want = stats.multivariate_normal(mean0, cov0).logpdf(np.concatenate([Y[b], Y[b + 1]]))
        np.testing.assert_allclose(init[b] + obs[b] + obs[b + 1], want, rtol=1e-9, atol=1e-9)
    assert k == _k(OBSERVATION_MODELS[name])


@pytest.mark.parametrize(("name", "dof"), CASES)
def test_the_fit_maximises_the_score_it_is_scored_by(name, dof):
    """The member's M-step and its frame terms agree: the segment's score (the per-segment
    reference, equal to the blocked kernel's sum) is largest at the fitted offset ``d`` and
    at the member's own fitted parameters; a small step either way in any of them lowers
    it."""
    Y = _data(2)
    tex = _fit(name, dof, Y, ridge=0.0)
    Yj = jnp.asarray(Y)
    score = float(segment_log_likelihood(tex, Yj))
    dyn, obs = frame_terms(stack_textons([tex]), Yj)
    init = init_terms(stack_textons([tex]), Yj)
    blocked = float(init[0, 0] + jnp.sum(dyn[0, 2:]) + jnp.sum(obs[0]))
    np.testing.assert_allclose(blocked, score, rtol=1e-10)

    def moved(t):
        return float(segment_log_likelihood(t, Yj))

    rng = np.random.default_rng(0)
    steps = [lambda t, u: eqx_set(t, d=t.d + u * rng.normal(size=t.d.shape))]
    if name == "residual":
        steps += [
            lambda t, u: eqx_set(t, a=t.observation.a + u * rng.normal(size=2)),
            lambda t, u: eqx_set(t, s2=t.observation.s2 * (1 + 10 * u)),
        ]
    tol = 1e-9 * abs(score) if dof is None else 1e-6 * abs(score)  # IRLS: 10 steps
    for step in steps:
        for u in (1e-2, -1e-2):
            assert moved(step(tex, u)) < score + tol


def eqx_set(tex, **kw):
    """The texton with ``d`` or its member's ``a`` / ``s2`` replaced."""
    for name, v in kw.items():
        if name == "d":
            tex = eqx.tree_at(lambda t: t.d, tex, jnp.asarray(v, tex.d.dtype))
        else:
            tex = eqx.tree_at(
                lambda t, n=name: getattr(t.observation, n), tex, jnp.asarray(v, tex.d.dtype)
            )
    return tex


@pytest.fixture(scope="module")
def textures():
    """A small texture learned with each member (each case once), and its clips."""
    ys = [_data(10 + i, 200) for i in range(2)]
    out = {}
    for p in CASES:
        name, dof = p.values
        member = OBSERVATION_MODELS[name]
        free = member.fixed_state_dim(D) is None
        cfg = mj.LearnConfig(
            tmin=15,
            tmax=50,
            max_iter=1,
            observation=member,
            state_dim=K if free else None,
            dof=dof,
            selection="none",
        )
        out[p.id] = mj.learn(ys, cfg)
    return ys, out


@pytest.mark.parametrize(("name", "dof"), CASES)
def test_a_model_file_keeps_the_member(textures, tmp_path, name, dof):
    ys, texs = textures
    tex = texs[name if dof is None else f"{name}-t{dof:g}"]
    member = tex.textons.observation
    assert type(member) is type(OBSERVATION_MODELS[name]) and member.fitted
    assert tex.config.observation == name and tex.textons.dof == dof
    # the member's own arrays round trip
    again = member.from_arrays(member.to_arrays(tex.textons.sigma2))
    assert jax.tree.structure(again) == jax.tree.structure(member)
    for a, b in zip(jax.tree.leaves(again), jax.tree.leaves(member), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # and so does the texture
    p = tmp_path / "t.npz"
    tex.save(p)
    back = mj.load_texture(p)
    assert jax.tree.structure(back.textons) == jax.tree.structure(tex.textons)
    for a, b in zip(jax.tree.leaves(back.textons), jax.tree.leaves(tex.textons), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    Y = jnp.asarray(ys[0])
    assert float(back.log_likelihood(Y)) == float(tex.log_likelihood(Y))


@pytest.mark.parametrize(("name", "dof"), CASES)
def test_what_a_member_generates_stays_bounded(textures, name, dof):
    """Noise-driven synthesis of a learned texture and a long sample of one of its textons
    stay finite and within a few times the clips' range."""
    ys, texs = textures
    tex = texs[name if dof is None else f"{name}-t{dof:g}"]
    span = float(np.max(np.abs(np.concatenate(ys))))
    Y = np.asarray(mj.synthesize(jax.random.key(1), tex, n_frames=400).Y)
    assert Y.shape == (400, D) and np.isfinite(Y).all()
    assert np.abs(Y).max() < 3 * span
    _, y = sample_texton(jax.random.key(2), tex.textons[0], 2000)
    assert np.isfinite(np.asarray(y)).all()
    assert np.abs(np.asarray(y)).max() < 10 * span
