"""Edits and cleaning in shape buckets (design §11): the banded Gauss–Newton solve is compiled
once per bucket of lengths, and the padding changes no result.

The reference is the same public call with the bucketing turned off (``edit_length`` the
identity: the solve on the exact shape, as before the buckets); programs are counted with
JAX's own monitoring events (:func:`mtex_jax.core.count_compiles`).
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

import edit_setup
import mtex_jax as mj
from mtex_jax.core import count_compiles
from mtex_jax.edit import _bucket

FIELDS = ("Y", "u", "cost", "prior_cost", "position_error", "plant_slide", "floor_depth")


@pytest.fixture(scope="module")
def tex():
    return edit_setup.texture()


@pytest.fixture(scope="module")
def long_syn(tex):
    return mj.synthesize(jax.random.key(11), tex, n_frames=170)


def test_edit_length_buckets():
    n = np.arange(1, 5000)
    b = np.array([_bucket.edit_length(int(k)) for k in n])
    assert (b >= n).all() and (np.diff(b) >= 0).all()
    assert (b[n <= 128] == 128).all()
    assert (b[n > 128] < 1.25 * n[n > 128]).all()  # padding below a quarter
    assert _bucket.edit_length(1201) == 1280 and _bucket.edit_length(1280) == 1280
    assert len(set(b[(n >= 200) & (n <= 3000)])) == 16
    with pytest.raises(ValueError, match="n >= 1"):
        _bucket.edit_length(0)


def _target_edit(tex, syn, n):
    """Reach with the hand at the middle frame of the first ``n`` frames of ``syn``."""
    fm = tex.feature_map
    Y = np.asarray(syn.Y)[:n]
    sk = fm.skeleton
    hand = sk.index(edit_setup.hand(tex))
    P = np.asarray(fm.joint_positions(Y))
    cons = mj.edit.make_constraints(
        sk,
        n,
        tex.obs_dim,
        positions=[(hand, n // 2, P[n // 2, hand] + 0.03)],
    )
    seg = mj.edit.segments_of(tex, syn)
    own = lambda a: jax.device_put(np.asarray(a)[:n])  # an eager slice compiles per length
    cut = mj.edit.FrameSegments(
        labels=own(seg.labels), dyn_labels=own(seg.dyn_labels), position=own(seg.position)
    )
    return mj.edit.edit(tex, Y, cons, segments=cut)


def _same(a, b, atol=1e-9):
    for f in FIELDS:
        np.testing.assert_allclose(
            np.asarray(getattr(a, f)), np.asarray(getattr(b, f)), rtol=1e-9, atol=atol, err_msg=f
        )
    assert int(a.steps) == int(b.steps) and bool(a.converged) == bool(b.converged)


@pytest.mark.parametrize("n", [128, 129, 160])
def test_bucketed_edit_equals_unpadded(tex, long_syn, n, monkeypatch):
    """At a bucket's edge (128: none of it padded), one past it (129 → 160: 31 padding
    frames) and at the next edge."""
    res = _target_edit(tex, long_syn, n)
    assert np.shape(res.Y) == (n, tex.obs_dim)
    monkeypatch.setattr(_bucket, "edit_length", lambda k: k)
    ref = _target_edit(tex, long_syn, n)
    _same(res, ref)
    assert res.met  # the edit did its work (1 mm)


def test_edit_and_clean_compile_once_per_bucket(tex, long_syn):
    contacts = edit_setup.contacts()
    syns = {n: mj.synthesize(jax.random.key(n), tex, n_frames=n) for n in (129, 140, 151, 160)}
    _target_edit(tex, long_syn, 129)
    mj.edit.clean(tex, syns[129], contacts, loglik=False)
    with count_compiles() as c:
        for n in (140, 151, 160):
            _target_edit(tex, long_syn, n).Y.block_until_ready()
            mj.edit.clean(tex, syns[n], contacts, loglik=False).Y.block_until_ready()
    assert c.programs == 0


def test_bucketed_clean_equals_unpadded(tex, monkeypatch):
    """Cleaning pads its swing-foot guidance targets too (one per foot and frame)."""
    contacts = edit_setup.contacts()
    syn = mj.synthesize(jax.random.key(4), tex, n_frames=137)
    res = mj.edit.clean(tex, syn, contacts, loglik=False)
    monkeypatch.setattr(_bucket, "edit_length", lambda k: k)
    ref = mj.edit.clean(tex, syn, contacts, loglik=False)
    _same(res.edit, ref.edit)
    np.testing.assert_allclose(
        np.asarray(res.motion.root_positions), np.asarray(ref.motion.root_positions), atol=1e-9
    )
    assert res.skating_after.median == pytest.approx(ref.skating_after.median, abs=1e-9)
