"""The metrics' kernels in shape buckets (design §11): the baselines' densities and
predictions and the texture's one-step predictions of a padded sequence equal those of the
kernels called on the unpadded sequence. The rows are computed by the same operations; a
GEMM over one row may take another CPU kernel than over many (1 ulp at 3 frames), so rows are
compared to ``1e-13`` of the largest entry (bit for bit at the other lengths here), and the
host sum of the log-density to 1e-12 relative (its order of summation differs)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import edit_setup
import mtex_jax as mj
from mtex_jax import metrics as M
from mtex_jax.metrics import _baselines as B, _prediction as P

RNG = np.random.default_rng(0)
D = 5
# a smooth random walk: AR(2)-like data
Y = np.cumsum(np.cumsum(0.01 * RNG.standard_normal((2100, D)), axis=0), axis=0)
Y += 0.05 * RNG.standard_normal(Y.shape)


def assert_rows(out, ref) -> None:
    out, ref = np.asarray(out), np.asarray(ref)
    assert out.shape == ref.shape
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-13 * np.abs(ref).max())


@pytest.fixture(scope="module", params=["ar2", "constant_velocity", "hold_last"])
def model(request):
    fit = {"ar2": M.fit_ar2, "constant_velocity": M.constant_velocity, "hold_last": M.hold_last}
    return fit[request.param]([Y[:700], Y[700:1500]])


@pytest.mark.parametrize("n", [3, 1023, 1024, 1025, 2049])
def test_baseline_kernels_equal_unpadded(model, n):
    y = jnp.asarray(Y[:n])
    assert_rows(model.predict(Y[:n]), B._predict(model, y))
    fld = model.frame_log_density(Y[:n])
    assert fld.shape == (n - 1,)
    assert_rows(fld, B._frame_log_density(model, y))
    chain = model.log_likelihood(Y[:n], per_frame=True)
    assert chain.shape == (n,)
    assert_rows(chain, B._chain_log_density(model, y))
    total = float(jnp.sum(B._frame_log_density(model, y)))
    ll = model.log_likelihood(Y[:n])
    assert abs(ll - total) <= 1e-12 * abs(total)
    assert abs(model.log_likelihood(Y[:n], mean=True) - total / n) <= 1e-12 * abs(total / n)


def test_baseline_checks_still_raise(model):
    bad = Y[:50].copy()
    bad[7, 2] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        model.log_likelihood(bad)
    with pytest.raises(ValueError, match=">= 3"):
        model.predict(Y[:2])


@pytest.fixture(scope="module")
def tex_and_y():
    tex = edit_setup.texture()
    return tex, np.asarray(mj.synthesize(jax.random.key(3), tex, n_frames=1100).Y)


B_ = P.PREDICT_BLOCK
EDGES = [300, B_ + 1, B_ + 2, B_ + 3, 2 * B_ + 3]


@pytest.mark.parametrize("n", EDGES)
def test_texture_predict_equals_unpadded(tex_and_y, n):
    tex, Yt = tex_and_y
    Yt = Yt[:n]
    pred, labels = M.texture_predict(tex, Yt)
    ref = P._predict_labelled(tex.textons, jnp.asarray(labels[1:-1]), jnp.asarray(Yt))
    assert pred.shape == (n - 2, Yt.shape[1])
    assert_rows(pred, ref)
