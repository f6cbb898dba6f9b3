"""Per-frame texton terms and O(1) segment scores (design §3.1–§3.3) against scipy and the
direct segment likelihood: time blocks, wide states, full textons, workers, retracing."""

import threading

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

from mtex_jax.texture import (
    SegmentScorer,
    fit_texton,
    frame_terms,
    init_terms,
    segment_log_likelihood,
    segment_scores,
    stack_textons,
)
from mtex_jax.texture._scoring import (
    frame_terms as frame_terms_module,
    frame_terms_ref,
    workers as scoring_workers,
)
from texton_cases import (
    anisotropic_data,
    assert_terms_equal_reference,
    random_texton_np,
    scipy_frame_terms,
    scipy_segment_ll,
    to_texton,
)
from traces import count_traces

# --------------------------------------------------------------------------------------------
# Per-frame terms, segment scores and the direct segment likelihood
# --------------------------------------------------------------------------------------------


def test_segment_log_likelihood_matches_scipy():
    rng = np.random.default_rng(9)
    p = random_texton_np(rng, 7, 3)
    Yseg = rng.standard_normal((9, 7))
    np.testing.assert_allclose(
        float(segment_log_likelihood(to_texton(p), Yseg)), scipy_segment_ll(p, Yseg), rtol=1e-11
    )


def test_frame_and_init_terms_match_scipy():
    rng = np.random.default_rng(10)
    D, k, T = 8, 3, 12
    ps = [random_texton_np(rng, D, k) for _ in range(3)]
    st = stack_textons([to_texton(p) for p in ps])
    Y = rng.standard_normal((T, D)) + 2.0
    dyn, obs = frame_terms(st, Y)
    init = init_terms(st, Y)
    assert dyn.shape == obs.shape == init.shape == (3, T)
    for i, p in enumerate(ps):
        X = (Y - p["mu"]) @ p["C"]
        Q = p["B"] @ p["B"].T
        assert dyn[i, 0] == 0 and dyn[i, 1] == 0
        for t in range(2, T):
            mean = p["A1"] @ X[t - 1] + p["A2"] @ X[t - 2] + p["d"]
            ref = scipy.stats.multivariate_normal.logpdf(X[t], mean, Q)
            np.testing.assert_allclose(dyn[i, t], ref, rtol=1e-11)
        r = (Y - p["mu"]) - X @ p["C"].T
        ref_obs = -0.5 * ((D - k) * np.log(2 * np.pi * p["sigma2"]) + (r**2).sum(1) / p["sigma2"])
        np.testing.assert_allclose(obs[i], ref_obs, rtol=1e-11)
        for b in range(T - 1):
            ref = scipy.stats.multivariate_normal.logpdf(
                np.concatenate([X[b], X[b + 1]]), p["m0"], p["S0"]
            )
            np.testing.assert_allclose(init[i, b], ref, rtol=1e-11)
        assert init[i, T - 1] == -np.inf
    # a single (unstacked) texton gives (T,) arrays equal to the stacked rows
    d1, o1 = frame_terms(st[1], Y)
    np.testing.assert_allclose(d1, dyn[1], rtol=1e-13)
    np.testing.assert_allclose(o1, obs[1], rtol=1e-13)
    # the per-texton algorithm (chunk_size) and other time blocks give the same result
    for chunk in (2, 1):
        dc, oc = frame_terms_ref.frame_terms_per_texton(st, Y, chunk_size=chunk)
        np.testing.assert_allclose(dc, dyn, rtol=1e-12, err_msg=f"chunk {chunk}")
        np.testing.assert_allclose(oc, obs, rtol=1e-12, err_msg=f"chunk {chunk}")
    for kw in (dict(block_size=1), dict(block_size=5)):
        d3, o3 = frame_terms(st, Y, **kw)
        np.testing.assert_allclose(d3, dyn, rtol=1e-12, err_msg=str(kw))
        np.testing.assert_allclose(o3, obs, rtol=1e-12, err_msg=str(kw))


@pytest.mark.parametrize(
    ("T", "block_size"),
    [(1, None), (2, None), (3, None), (3, 1), (10, 3), (10, 4), (10, 10), (10, 64), (41, 8)],
)
def test_frame_terms_time_blocks_cover_every_frame(T, block_size):
    # blocks that do not divide T (the last block overlaps), blocks longer than T, T < 3
    rng = np.random.default_rng(13)
    D, k = 5, 2
    ps = [random_texton_np(rng, D, k) for _ in range(2)]
    st = stack_textons([to_texton(p) for p in ps])
    Y = rng.standard_normal((T, D)) + 1.0
    dyn, obs = frame_terms(st, Y, block_size=block_size)
    assert dyn.shape == obs.shape == (2, T)
    assert_terms_equal_reference(ps, Y, dyn, obs)


@pytest.mark.parametrize(("D", "k"), [(20, 20), (23, 18)])
def test_frame_terms_beyond_the_unrolled_state_dimension(D, k):
    """k > 16: the vectorised sums over the state index and the wider automatic time blocks,
    against the scipy reference and against short blocks."""
    rng = np.random.default_rng(21)
    ps = [random_texton_np(rng, D, k) for _ in range(3)]
    st = stack_textons([to_texton(p) for p in ps])
    Y = rng.standard_normal((700, D)) * 0.3 + 0.5
    dyn, obs = frame_terms(st, Y)
    assert_terms_equal_reference(ps, Y, dyn, obs)
    dyn7, obs7 = frame_terms(st, Y, block_size=7)
    np.testing.assert_allclose(np.asarray(dyn7), np.asarray(dyn), rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(np.asarray(obs7), np.asarray(obs), rtol=1e-10, atol=1e-9)


@pytest.mark.parametrize(
    ("T", "block_size"), [(2, None), (3, None), (3, 1), (10, 3), (10, 64), (41, 8), (300, None)]
)
def test_full_texton_kernel_blocks_and_init_terms_against_scipy(T, block_size):
    """k = D: the stacked-lag kernel (``_frame_terms_full``) on blocks that do and do not
    divide T, blocks longer than T and short T; dyn and the initial-state terms (through
    ``segment_scores``) against scipy densities of each texton."""
    rng = np.random.default_rng(T)
    D = 5
    ps = [random_texton_np(rng, D, D) for _ in range(3)]
    st = stack_textons([to_texton(p) for p in ps])
    Y = rng.standard_normal((T, D)) * 0.5 + 1.0
    dyn, obs = frame_terms(st, Y, block_size=block_size)
    assert_terms_equal_reference(ps, Y, dyn, obs)
    np.testing.assert_array_equal(obs, 0.0)
    init = np.asarray(segment_scores(st, Y, block_size=block_size).init)
    for i, p in enumerate(ps):
        X = (Y - p["mu"]) @ p["C"]
        for b in range(T - 1):
            pair = np.concatenate([X[b], X[b + 1]])
            ref = scipy.stats.multivariate_normal.logpdf(pair, p["m0"], p["S0"])
            np.testing.assert_allclose(init[i, b], ref, rtol=1e-10)
        assert init[i, T - 1] == -np.inf


def test_frame_terms_ill_conditioned_q_and_k_equal_d():
    # B with singular values from 1e-3 to 1 (the whitened coordinates rescale by 1/s); then
    # textons with k = D (no residual dimensions: obs = 0)
    rng = np.random.default_rng(14)
    D, k, T = 7, 4, 30
    p = random_texton_np(rng, D, k)
    q1 = np.linalg.qr(rng.standard_normal((k, k)))[0]
    p["B"] = np.linalg.cholesky(q1 @ np.diag([1.0, 0.1, 1e-2, 1e-3]) ** 2 @ q1.T)
    X = rng.standard_normal((T, k)) * 0.1
    Y = X @ p["C"].T + p["mu"] + 0.01 * rng.standard_normal((T, D))
    dyn, obs = frame_terms(to_texton(p), Y)
    ref_dyn, ref_obs = scipy_frame_terms(p, Y)
    np.testing.assert_allclose(dyn, ref_dyn, rtol=1e-9)
    np.testing.assert_allclose(obs, ref_obs, rtol=1e-11)
    pk = random_texton_np(rng, k, k)
    Yk = rng.standard_normal((T, k))
    dyn_k, obs_k = frame_terms(stack_textons([to_texton(pk)] * 2), Yk, block_size=7)
    np.testing.assert_array_equal(obs_k, 0.0)
    np.testing.assert_allclose(dyn_k[1], scipy_frame_terms(pk, Yk)[0], rtol=1e-11, atol=1e-12)


def test_frame_terms_block_and_chunk_arguments_are_validated():
    rng = np.random.default_rng(15)
    st = stack_textons([to_texton(random_texton_np(rng, 4, 2)) for _ in range(2)])
    Y = rng.standard_normal((12, 4))
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="block_size"):
            frame_terms(st, Y, block_size=bad)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="chunk_size"):
            frame_terms_ref.frame_terms_per_texton(st, Y, chunk_size=bad)  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        frame_terms(st, Y, chunk_size=1)  # type: ignore[call-arg]  # no longer a public knob


@pytest.mark.parametrize("workers", [2, 3, 7, 12])
def test_frame_terms_split_over_concurrent_executions(workers, monkeypatch):
    """Textons split into row blocks computed by executions from separate threads and
    assembled in place equal the scipy reference (7 textons: blocks of unequal size, more
    workers than textons), in a short block size so that each block's windows overlap; under
    jit the call is one computation with the same values."""
    import warnings

    rng = np.random.default_rng(16)
    D, k, T = 6, 3, 53
    ps = [random_texton_np(rng, D, k) for _ in range(7)]
    st = stack_textons([to_texton(p) for p in ps])
    Y = rng.standard_normal((T, D)) + 0.5
    parts = min(workers, 7)
    assert scoring_workers.n_parts(workers, st, jnp.asarray(Y)) == parts
    calls = []  # (thread, rows) of every kernel execution
    kernel = frame_terms_module.frame_terms_jit

    def spy(textons, *args, **kwargs):
        calls.append((threading.get_ident(), textons.n_textons))
        return kernel(textons, *args, **kwargs)

    monkeypatch.setattr("mtex_jax.texture._scoring.frame_terms.frame_terms_jit", spy)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # e.g. a donated buffer that could not be reused
        dyn, obs = frame_terms(st, Y, workers=workers, block_size=8)
    monkeypatch.undo()
    # one execution per block, from more than one thread (a pool thread that is done may
    # take another block), blocks of 7 // parts rows or one more
    assert len(calls) == parts and len({t for t, _ in calls}) >= 2
    assert sorted(r for _, r in calls) == sorted(
        7 * (i + 1) // parts - 7 * i // parts for i in range(parts)
    )
    assert dyn.shape == obs.shape == (7, T)
    assert_terms_equal_reference(ps, Y, dyn, obs)
    jitted = jax.jit(lambda t, y: frame_terms(t, y, workers=workers, block_size=8))(st, Y)
    np.testing.assert_allclose(jitted[0], dyn, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(jitted[1], obs, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="NaN or inf"):
        frame_terms(st, np.where(np.arange(T)[:, None] == 40, np.nan, Y), workers=workers)


def test_frame_terms_split_keeps_the_callers_thread_local_settings():
    """The block executions run in other threads under the caller's settings: here x64 is
    off globally and on in the caller's thread only (``jax.enable_x64``), so a block run
    under the global setting would compute in float32."""
    rng = np.random.default_rng(18)
    ps = [random_texton_np(rng, 6, 3) for _ in range(4)]
    Y = rng.standard_normal((30, 6))
    jax.config.update("jax_enable_x64", False)
    try:
        with jax.enable_x64(True):
            st = stack_textons([to_texton(p) for p in ps])
            dyn, obs = frame_terms(st, Y, workers=3)
            one = frame_terms(st, Y, workers=1)
    finally:
        jax.config.update("jax_enable_x64", True)
    assert dyn.dtype == obs.dtype == jnp.float64
    np.testing.assert_allclose(dyn, one[0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(obs, one[1], rtol=1e-12, atol=1e-12)
    assert_terms_equal_reference(ps, Y, dyn, obs)


def test_frame_terms_workers_choice_and_validation():
    rng = np.random.default_rng(17)
    st = stack_textons([to_texton(random_texton_np(rng, 4, 2)) for _ in range(3)])
    small, large = jnp.zeros((10, 4)), jnp.zeros((2**20 // 3 + 1, 4))
    cores = scoring_workers.available_cores()
    assert scoring_workers.n_parts(None, st, small) == 1  # too little work: one execution
    assert scoring_workers.n_parts(None, st, large) == min(cores, 3)
    assert scoring_workers.n_parts(1, st, large) == 1
    traced = jax.jit(lambda y: jnp.asarray(scoring_workers.n_parts(2, st, y)))(small)
    assert int(traced) == 1  # under a trace: one computation
    Y = rng.standard_normal((12, 4))
    for bad in (0, -1, 2.5, True, "2"):
        with pytest.raises(ValueError, match="workers"):
            frame_terms(st, Y, workers=bad)  # type: ignore[arg-type]


def test_prefix_sum_scores_equal_direct_segment_likelihood():
    rng = np.random.default_rng(11)
    T, D, k, n_t = 150, 10, 4, 4
    Y = anisotropic_data(rng, T, D)
    # textons fitted on different parts of the data (realistic magnitudes), one random
    textons = [fit_texton(Y[j * 30 : j * 30 + 45], state_dim=k) for j in range(n_t - 1)]
    textons.append(to_texton(random_texton_np(rng, D, k)))
    st = stack_textons(textons)
    scorer = segment_scores(st, Y)
    assert isinstance(scorer, SegmentScorer)
    assert scorer.cum_dyn.shape == (n_t, T + 1) and scorer.init.shape == (n_t, T)
    triples = []
    for L in (2, 5, 40):  # few distinct lengths: the reference compiles once per length
        for _ in range(10):
            b = int(rng.integers(0, T - L + 1))
            triples.append((b, b + L - 1, int(rng.integers(0, n_t))))
    triples += [(0, 39, 0), (T - 2, T - 1, 3), (0, 1, 2), (T - 40, T - 1, 1)]
    b, e, i = (np.array(v) for v in zip(*triples, strict=True))
    fast = np.asarray(scorer.score(b, e, i))
    ref = np.array(
        [float(segment_log_likelihood(textons[ii], Y[bb : ee + 1])) for bb, ee, ii in triples]
    )
    np.testing.assert_allclose(fast, ref, rtol=1e-9, atol=1e-9)
    # the kernel's time blocks (window edges at other frames, a last window overlapping the
    # previous one) change nothing; a bad block size is rejected
    for block_size in (1, 7, 200):
        other = segment_scores(st, Y, block_size=block_size)
        np.testing.assert_allclose(np.asarray(other.score(b, e, i)), fast, rtol=1e-12, atol=1e-9)
        np.testing.assert_array_equal(np.isinf(other.init), np.isinf(scorer.init))
    with pytest.raises(ValueError, match="block_size"):
        segment_scores(st, Y, block_size=0)
    # broadcasting over all textons, and invalid segments give -inf
    all_i = np.asarray(scorer.score(b[None, :], e[None, :], np.arange(n_t)[:, None]))
    assert all_i.shape == (n_t, len(triples))
    np.testing.assert_allclose(all_i[i, np.arange(len(triples))], fast, rtol=1e-12)
    bad = scorer.score(
        np.array([5, 5, -1, 3, 3]), np.array([5, 4, 3, T, 6]), np.array([0] * 4 + [9])
    )
    assert np.all(np.asarray(bad) == -np.inf)
    # scores_ending_at = score with b = e − L + 1
    se = np.asarray(scorer.scores_ending_at(40, np.array([2, 3, 10, 41, 42])))
    for j, L in enumerate([2, 3, 10, 41]):
        np.testing.assert_allclose(se[:, j], scorer.score(40 - L + 1, 40, np.arange(n_t)))
    assert np.all(se[:, 4] == -np.inf)
    # jit/vmap friendly
    jitted = jax.jit(lambda s, b, e, i: s.score(b, e, i))(scorer, b, e, i)
    np.testing.assert_allclose(jitted, fast, rtol=1e-13)


def test_frame_terms_do_not_retrace_for_new_data():
    rng = np.random.default_rng(12)
    st = stack_textons([to_texton(random_texton_np(rng, 6, 2)) for _ in range(3)])
    frame_terms(st, rng.standard_normal((40, 6)))
    frame_terms_ref.frame_terms_per_texton(st, rng.standard_normal((40, 6)), chunk_size=1)
    with count_traces() as seen:
        for _ in range(3):
            st2 = jax.tree.map(lambda a: a * 1.01, st)
            frame_terms(st2, rng.standard_normal((40, 6)))
            frame_terms_ref.frame_terms_per_texton(st2, rng.standard_normal((40, 6)), chunk_size=1)
    assert seen["frame_terms_impl"] == 0
    assert seen["_all_terms_impl"] == 0
    fit_texton(rng.standard_normal((40, 6)), state_dim=2)
    with count_traces() as seen:
        for _ in range(3):
            fit_texton(rng.standard_normal((40, 6)), rng.integers(-1, 3, 40), state_dim=2)
    assert seen["_fit_texton_impl"] == 0
