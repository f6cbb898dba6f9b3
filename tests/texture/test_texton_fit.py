"""The texton container and its closed-form fit (design §2): shapes, the numpy
re-derivation of the M-step, segments and batches, recovery of known systems, the stability
projection."""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np
import pytest

from mtex_jax.texture import (
    DynamicsStats,
    FrameStats,
    Texton,
    dynamics_stats,
    fit_texton,
    frame_stats,
    spectral_radius,
    stack_textons,
    subspace_from_stats,
    texton_from_stats,
)
from mtex_jax.texture._texton.texton import TEXTON_FIELDS
from texton_cases import (
    anisotropic_data,
    make_oscillator_system,
    np_companion,
    numpy_fit,
    random_texton_np,
    recovery_errors,
    simulate,
    to_texton,
)

# --------------------------------------------------------------------------------------------
# Texton container
# --------------------------------------------------------------------------------------------


def test_texton_shapes_stack_and_index():
    rng = np.random.default_rng(0)
    ts = [to_texton(random_texton_np(rng, 9, 3)) for _ in range(4)]
    st = stack_textons(ts)
    assert (st.n_textons, st.state_dim, st.obs_dim, st.batch_shape) == (4, 3, 9, (4,))
    assert ts[0].n_textons == 1 and not ts[0].is_stacked
    np.testing.assert_array_equal(st[2].A1, ts[2].A1)
    np.testing.assert_array_equal(st[1:3].S0, jnp.stack([ts[1].S0, ts[2].S0]))
    np.testing.assert_allclose(st.Q[3], ts[3].B @ ts[3].B.T)
    with pytest.raises(TypeError):
        ts[0][0]


def test_texton_check_init_rejects_bad_shapes():
    p = random_texton_np(np.random.default_rng(1), 6, 2)
    for name, bad in [
        ("C", np.zeros((6, 3))),
        ("A2", np.zeros((2, 3))),
        ("d", np.zeros(3)),
        ("B", np.zeros((2,))),
        ("sigma2", np.zeros(2)),
        ("m0", np.zeros(2)),
        ("S0", np.zeros((2, 2))),
        ("mu", np.zeros(5)),
    ]:
        q = dict(p, **{name: bad})
        with pytest.raises(ValueError, match=f"Texton.{name}|Texton.C"):
            to_texton(q)
    with pytest.raises(ValueError, match="k=4"):  # k > D
        Texton(
            mu=jnp.zeros(3),
            C=jnp.zeros((3, 4)),
            A1=jnp.zeros((4, 4)),
            A2=jnp.zeros((4, 4)),
            d=jnp.zeros(4),
            B=jnp.eye(4),
            sigma2=jnp.ones(()),
            m0=jnp.zeros(8),
            S0=jnp.eye(8),
        )
    with pytest.raises(ValueError, match="stack_textons"):
        stack_textons([to_texton(p), to_texton(random_texton_np(np.random.default_rng(2), 6, 3))])
    with pytest.raises(ValueError, match="empty"):
        stack_textons([])


# --------------------------------------------------------------------------------------------
# Fitting: numpy re-derivation, segments, batching, summable statistics
# --------------------------------------------------------------------------------------------

SEG_IDS = np.array(
    [0] * 10 + [1] * 7 + [-1] * 3 + [2] * 3 + [3] * 2 + [4] * 1 + [0] * 8 + [5] * 12 + [-1] * 2
)


def test_multi_segment_fit_matches_numpy_rederivation():
    rng = np.random.default_rng(3)
    T, D, k = len(SEG_IDS), 8, 3
    Y = anisotropic_data(rng, T, D)
    q_floor, s2_floor, kappa = 1e-7, 1e-9, 2.5
    tex = fit_texton(
        Y,
        SEG_IDS,
        state_dim=k,
        ridge=0.0,
        q_floor=q_floor,
        sigma2_floor=s2_floor,
        init_prior_weight=kappa,
    )
    ref = numpy_fit(Y, SEG_IDS, k, q_floor, s2_floor, kappa)
    for name in ("mu", "C", "A1", "A2", "d", "Q", "sigma2", "m0", "S0"):
        np.testing.assert_allclose(
            np.asarray(getattr(tex, name)), ref[name], rtol=1e-10, atol=1e-10, err_msg=name
        )
    np.testing.assert_allclose(np.asarray(tex.B), np.linalg.cholesky(ref["Q"]), atol=1e-10)


def test_boundary_terms_are_dropped():
    """Adjacent segments with different ids must not share a dynamics term."""
    rng = np.random.default_rng(4)
    Y = anisotropic_data(rng, 40, 6)
    ids = np.array([0] * 20 + [1] * 20)
    sub = subspace_from_stats(frame_stats(Y, ids), state_dim=2)
    merged = dynamics_stats(Y, np.zeros(40, int), sub)
    split = dynamics_stats(Y, ids, sub)
    assert float(merged.n3) == 38 and float(split.n3) == 36
    assert float(merged.n_start) == 1 and float(split.n_start) == 2
    assert float(split.n2) == 38


def test_batched_sequences_equal_concatenation_with_boundary_mask():
    rng = np.random.default_rng(5)
    T, D, k = 50, 7, 3
    Y = np.stack([anisotropic_data(rng, T, D), anisotropic_data(rng, T, D)])
    m1 = np.where(np.arange(T) < 30, 0, 1)
    m2 = np.where(np.arange(T) % 17 == 5, -1, 0)
    mask = np.stack([m1, m2])
    batched = fit_texton(Y, mask, state_dim=k)
    concat = fit_texton(
        Y.reshape(2 * T, D), np.concatenate([m1, np.where(m2 >= 0, m2 + 10, -1)]), state_dim=k
    )
    for name in TEXTON_FIELDS:
        np.testing.assert_allclose(
            getattr(batched, name), getattr(concat, name), rtol=1e-10, atol=1e-10, err_msg=name
        )
    # the same through summed two-pass statistics (what a multi-sequence M-step does)
    fs = frame_stats(Y[0], m1) + frame_stats(Y[1], m2)
    assert isinstance(fs, FrameStats)
    sub = subspace_from_stats(fs, state_dim=k)
    ds = sum([dynamics_stats(Y[0], m1, sub), dynamics_stats(Y[1], m2, sub)])
    assert isinstance(ds, DynamicsStats)
    two_pass = texton_from_stats(sub, ds)
    for name in TEXTON_FIELDS:
        np.testing.assert_allclose(
            getattr(two_pass, name), getattr(batched, name), rtol=1e-10, atol=1e-10
        )


def test_mask_none_and_boolean_mask():
    rng = np.random.default_rng(6)
    Y = anisotropic_data(rng, 40, 6)
    a = fit_texton(Y, state_dim=2)
    b = fit_texton(Y, np.zeros(40, np.int64), state_dim=2)
    c = fit_texton(Y, np.ones(40, bool), state_dim=2)
    for name in TEXTON_FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        np.testing.assert_array_equal(getattr(a, name), getattr(c, name))


# --------------------------------------------------------------------------------------------
# Recovery of known systems
# --------------------------------------------------------------------------------------------

# Tolerances at T = 5000: about 2-3x the largest error observed over these seeds; the errors
# are statistical (they shrink as 1/sqrt(T), see the next test).
RECOVERY_TOL = dict(eig=0.15, A=0.08, d=0.2, Q=0.1, subspace=0.003)


@pytest.mark.parametrize("k", [4, 8, 15])
def test_recovers_known_systems(k):
    D, T = 60, 5000
    for seed in range(3):
        rng = np.random.default_rng(1000 * k + seed)
        system = make_oscillator_system(rng, k, D)
        _, Y = simulate(rng, system, T)
        tex = fit_texton(Y[0], state_dim=k)
        err = recovery_errors(tex, system)
        for name, tol in RECOVERY_TOL.items():
            assert err[name] < tol, (k, seed, name, err)
        # observation noise is recovered too (sigma2 = 1e-6 in the generator)
        np.testing.assert_allclose(float(tex.sigma2), system["sigma2"], rtol=0.05)


@pytest.mark.parametrize("k", [4, 15])
def test_recovery_error_shrinks_like_inverse_sqrt_T(k):
    """RMS error over 4 independent runs at T = 5000 vs T = 20000: ratio ≈ √4 = 2."""
    D, reps = 60, 4
    rng = np.random.default_rng(77 + k)
    system = make_oscillator_system(rng, k, D)
    rms = {}
    for T in (5000, 20000):
        _, Y = simulate(rng, system, T, reps=reps)
        errs = [recovery_errors(fit_texton(Y[r], state_dim=k), system) for r in range(reps)]
        rms[T] = {n: np.sqrt(np.mean([e[n] ** 2 for e in errs])) for n in ("A", "Q", "d")}
    for name in ("A", "Q"):
        ratio = rms[5000][name] / rms[20000][name]
        assert 1.4 < ratio < 2.9, (name, rms)
    # all three parameters together
    total = sum(rms[5000].values()) / sum(rms[20000].values())
    assert 1.5 < total < 2.7, rms


# --------------------------------------------------------------------------------------------
# Stability projection
# --------------------------------------------------------------------------------------------


def test_rho_max_projection():
    rng = np.random.default_rng(8)
    # a random walk: the unconstrained fit has companion spectral radius ≈ 1
    Y = np.cumsum(rng.standard_normal((400, 6)), axis=0)
    free = fit_texton(Y, state_dim=3)
    rho_free = float(spectral_radius(free))
    assert rho_free > 0.95
    rho_max = 0.9
    proj = fit_texton(Y, state_dim=3, rho_max=rho_max)
    rho = float(spectral_radius(proj))
    assert rho <= rho_max + 1e-12
    np.testing.assert_allclose(rho, rho_max, rtol=1e-9)
    # radial scaling: every companion eigenvalue is multiplied by s = rho_max / rho_free
    s = rho_max / rho_free
    np.testing.assert_allclose(proj.A1, s * free.A1, rtol=1e-9)
    np.testing.assert_allclose(proj.A2, s * s * free.A2, rtol=1e-9)
    ev_f = np.sort_complex(np.linalg.eigvals(np_companion(*map(np.asarray, (free.A1, free.A2)))))
    ev_p = np.sort_complex(np.linalg.eigvals(np_companion(*map(np.asarray, (proj.A1, proj.A2)))))
    np.testing.assert_allclose(ev_p, s * ev_f, atol=1e-9)
    # d and Q are the least-squares offset / residual covariance for the projected A1, A2
    X = (Y - np.asarray(proj.mu)) @ np.asarray(proj.C)
    Z = np.hstack([X[1:-1], X[:-2]])
    r0 = X[2:] - Z @ np.hstack([np.asarray(proj.A1), np.asarray(proj.A2)]).T
    np.testing.assert_allclose(proj.d, r0.mean(axis=0), atol=1e-9)
    res = r0 - r0.mean(axis=0)
    np.testing.assert_allclose(proj.Q, res.T @ res / len(res) + 1e-6 * np.eye(3), rtol=1e-8)
    # a bound above the free radius changes nothing
    loose = fit_texton(Y, state_dim=3, rho_max=rho_free + 0.5)
    np.testing.assert_allclose(loose.A1, free.A1, rtol=1e-12)
    with pytest.raises(ValueError, match="rho_max"):
        fit_texton(Y, state_dim=3, rho_max=-1.0)
