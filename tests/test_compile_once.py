"""Shape buckets (design §11): every public call that takes a length compiles a few programs
over many lengths, and the padding changes no result.

Each entry point is called once (warm-up), then over lengths that cross bucket edges; the
programs lowered in that loop are counted with JAX's own monitoring events
(:func:`mtex_jax.core.count_compiles`: a persistent-cache hit still lowers, so the count does
not depend on the cache). The results are compared with the computation on the unpadded
shapes (the lower-level kernels called with the exact length).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import edit_setup
import mtex_jax as mj
from mtex_jax import texture as T
from mtex_jax.core import BUCKET_FRAMES, bucket_length, count_compiles, pad_frames
from mtex_jax.texture._synthesis import sequence as seq

# crossing the edges of the 1024-frame buckets: three buckets, ten lengths
LENGTHS = [200, 1023, 1024, 1025, 1600, 2047, 2048, 2049, 2600, 3000]


@pytest.fixture(scope="module")
def tex():
    return edit_setup.texture()


@pytest.fixture(scope="module")
def Y(tex):
    return np.asarray(mj.synthesize(jax.random.key(0), tex, n_frames=3000).Y)


def _programs(f, lengths=LENGTHS, warm=1500) -> int:
    f(warm)
    with count_compiles() as c:
        for n in lengths:
            f(n)
    return c.programs


def test_bucket_length_and_pad_frames():
    assert [bucket_length(n) for n in (0, 1, 1024, 1025, 3000)] == [1024, 1024, 1024, 2048, 3072]
    assert bucket_length(5, 4) == 8
    with pytest.raises(ValueError, match="n >= 0"):
        bucket_length(-1)
    y = np.arange(6.0).reshape(3, 2)
    p = np.asarray(pad_frames(y, 5))
    assert p.shape == (5, 2) and (p[:3] == y).all() and (p[3:] == y[-1]).all()
    # traced: the same values, and differentiable
    g = jax.grad(lambda a: jnp.sum(pad_frames(a, 5)))(jnp.asarray(y))
    assert np.allclose(np.asarray(g)[:2], 1.0) and np.allclose(np.asarray(g)[2], 3.0)
    with pytest.raises(ValueError, match="cannot pad"):
        pad_frames(y, 2)


def test_count_compiles_counts_new_shapes_only():
    f = jax.jit(lambda x: x * 3.0)
    x7, x8, x9 = (jax.device_put(np.ones(n)) for n in (7, 8, 9))
    f(x7)
    with count_compiles() as c:
        f(x7)
    assert c.programs == 0
    with count_compiles() as c:
        f(x8)
        f(x9)
    assert c.programs == 2


def test_log_likelihood_and_segment_compile_per_bucket(tex, Y):
    assert _programs(lambda n: tex.log_likelihood(Y[:n])) <= 3
    assert _programs(lambda n: tex.segment(Y[:n]).score.block_until_ready()) <= 3


@pytest.mark.parametrize("n", [BUCKET_FRAMES - 1, BUCKET_FRAMES, BUCKET_FRAMES + 1, 300])
def test_padded_likelihood_and_segmentation_equal_unpadded(tex, Y, n):
    """The bucketed public calls against the kernels on the exact length (no padding)."""
    lM, lp = jnp.log(jnp.asarray(tex.M)), jnp.log(jnp.asarray(tex.pi))
    tmin, tmax = tex.config.tmin, tex.config.tmax
    sc = T.segment_scores(tex.textons, Y[:n])
    ref = T.forward_log_likelihood(sc, lM, lp, jnp.asarray(n), tmin, tmax, tex.log_durations)
    got = tex.log_likelihood(Y[:n])
    assert abs(got - float(ref)) <= 1e-9 * abs(float(ref))
    seg = tex.segment(Y[:n])
    vit = T.viterbi_segments(sc, lM, lp, jnp.asarray(n), tmin, tmax, tex.log_durations)
    assert seg.to_list() == vit.to_list()
    assert np.shape(seg.starts) == np.shape(vit.starts)  # K = T // tmin + 1 slots, as before
    assert abs(float(seg.score) - float(vit.score)) <= 1e-9 * abs(float(vit.score))


def test_log_likelihood_many_equals_one_by_one(tex, Y):
    Ys = [Y[:400], Y[100:1300], Y[:90]]
    args = (tex.textons, jnp.log(jnp.asarray(tex.M)), jnp.log(jnp.asarray(tex.pi)))
    cfg = tex.config
    many = np.asarray(
        T.log_likelihood_many(*args, Ys, cfg.tmin, cfg.tmax, log_durations=tex.log_durations)
    )
    one = [
        float(T.log_likelihood(*args, y, cfg.tmin, cfg.tmax, log_durations=tex.log_durations))
        for y in Ys
    ]
    assert many.shape == (3,)
    np.testing.assert_allclose(many, one, rtol=1e-9)
    with pytest.raises(ValueError, match="non-empty list"):
        T.log_likelihood_many(*args, [], cfg.tmin, cfg.tmax)
    with pytest.raises(ValueError, match="sequence 1 has 5 frames"):
        T.log_likelihood_many(*args, [Y[:100], Y[:5]], cfg.tmin, cfg.tmax)


def test_synthesize_compiles_per_bucket():
    """On a default texture (its innovations replay the residual bank, drawn per bucket); a
    texture without a bank draws its Gaussian or process innovations at the shape they had
    before the buckets, so that their values stay the same (a program per path shape)."""
    tex = edit_setup.default_texture()
    assert tex.residuals is not None
    key = jax.random.key(3)
    assert _programs(lambda n: mj.synthesize(key, tex, n_frames=n).Y.block_until_ready()) <= 3


def test_synthesis_padding_changes_nothing(tex, monkeypatch):
    """The path and frame padding of the bucketed synthesis against the padding it had before
    the buckets (8 textons, 16 frames)."""
    key = jax.random.key(5)
    runs = []
    for pad_t, pad_f in ((seq._PAD_TEXTONS, seq._PAD_FRAMES), (8, 16)):
        monkeypatch.setattr(seq, "_PAD_TEXTONS", pad_t)
        monkeypatch.setattr(seq, "_PAD_FRAMES", pad_f)
        s = mj.synthesize(key, tex, n_frames=517)
        runs.append((np.asarray(s.Y), np.asarray(s.motion.root_positions), np.asarray(s.path)))
    assert (runs[0][2] == runs[1][2]).all()
    np.testing.assert_allclose(runs[0][0], runs[1][0], rtol=0, atol=1e-10)
    np.testing.assert_allclose(runs[0][1], runs[1][1], rtol=0, atol=1e-10)


def test_choreograph_compiles_per_bucket():
    """``path_of_length``'s dynamic programme runs in 64-step buckets; the synthesis along the
    planned path is :func:`synthesize`'s (on a default texture, as
    :func:`test_synthesize_compiles_per_bucket`)."""
    tex = edit_setup.default_texture()
    key = jax.random.key(2)
    Y = np.asarray(mj.synthesize(key, tex, n_frames=500).Y)
    a, b = Y[100:102], Y[400:402]
    f = lambda n: T.choreograph(key, tex, a, b, n_frames=n).Y.block_until_ready()
    assert _programs(f, lengths=[300, 450, 811, 1203, 1999], warm=700) <= 3


@pytest.mark.parametrize("mode", ["ends", "free", "edits"])
def test_synthesize_texton_compiles_per_bucket(tex, mode):
    """``synthesize_texton`` of a learned texton between two key poses (the bridge), noise
    driven, and with edits (banded): one program per bucket of lengths. The results against
    the unpadded computation: ``tests/texture/test_texton_buckets.py``."""
    # a stable texton (noise driven, an unstable one overflows over 3,000 frames)
    i = int(np.argmin(np.asarray(T.spectral_radius(tex.textons))))
    t = jax.tree.map(lambda a: a[i], tex.textons)
    assert float(T.spectral_radius(t)) < 1.0
    kp = np.asarray(tex.key_poses)
    s, e = kp[0], kp[-1]
    key = jax.random.key(4)

    def f(n):
        if mode == "ends":
            return T.synthesize_texton(key, t, n, s, e).block_until_ready()
        if mode == "free":
            return T.synthesize_texton(key, t, n, s).block_until_ready()
        mask = np.zeros(n, bool)
        mask[n // 2] = True
        poses = np.broadcast_to(kp[1, 0], (n, kp.shape[-1]))
        return T.synthesize_texton(key, t, n, s, e, (mask, poses)).block_until_ready()

    assert _programs(f) <= 3


def test_metric_kernels_compile_per_bucket(tex, Y):
    """The baselines' densities and predictions and the texture's one-step predictions (its
    segmentation's programs, one per 1,024-frame bucket, and one prediction program on
    fixed blocks of frames). The results against the unpadded kernels:
    ``tests/metrics/test_metric_buckets.py``."""
    from mtex_jax import metrics as M

    ar = M.fit_ar2([Y[:1000]])
    assert _programs(lambda n: ar.log_likelihood(Y[:n])) <= 3
    assert _programs(lambda n: ar.log_likelihood(Y[:n], per_frame=True)) <= 3
    assert _programs(lambda n: np.asarray(ar.predict(Y[:n]))) <= 3
    assert _programs(lambda n: np.asarray(M.texture_predict(tex, Y[:n])[0])) <= 3


def test_decode_in_a_bucket_equals_unpadded(tex, Y):
    fm = tex.feature_map
    m = fm.decode(Y[:777])
    # traced: the program on the exact shape
    pos = jax.jit(lambda y: fm.decode(y).root_positions)(jnp.asarray(Y[:777]))
    assert m.n_frames == 777
    np.testing.assert_allclose(np.asarray(m.root_positions), np.asarray(pos), rtol=0, atol=1e-12)
    assert _programs(lambda n: fm.decode(Y[:n]).root_positions.block_until_ready()) <= 3


@pytest.mark.slow
def test_implicit_synthesize_and_track_compile_per_bucket(cmu_motions):
    clips = [c.resample(30.0) for c in cmu_motions[:2]]
    model = mj.implicit.learn(clips, 4)
    key = jax.random.key(1)

    def syn(n):
        mj.implicit.synthesize(model, key, clips[0], n, 0.5).root_positions.block_until_ready()

    assert _programs(syn, [200, 1023, 1030, 2100, 600], warm=1500) <= 3
    # the first frames of a bucketed run are those of a shorter one (prefix-stable draws)
    a = mj.implicit.synthesize(model, key, clips[0], 300, 0.5)
    b = mj.implicit.synthesize(model, key, clips[0], 200, 0.5)
    np.testing.assert_allclose(
        np.asarray(a.root_positions)[:150], np.asarray(b.root_positions)[:150], atol=1e-12
    )

    # the problems are made first (make_problem's own work is not the filter's)
    probs = {
        n: mj.tracking.make_problem(jax.random.key(2), model, clips[1], n_frames=n)
        for n in (200, 50, 120, 333, 500)
    }

    def trk(n):
        mj.tracking.track(key, model, probs[n], n_particles=16).error.block_until_ready()

    assert _programs(trk, [50, 120, 333, 500], warm=200) <= 2
