"""The texture-level tools on a texture learned with the default settings (issue 39): texton
paths, the choreographer and a texton-path edit work on its vocabulary."""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np
import pytest

import mtex_jax as mj
from mtex_jax.texture import choreograph, path_cost, path_of_length, shortest_path, synthesize


@pytest.fixture(scope="module")
def tex():
    clips = [mj.io.load_salsa(n) for n in ("60_01", "60_02", "60_03", "60_04")]
    return mj.learn(clips, mj.LearnConfig(tmin=60, tmax=180, fps=60.0, max_iter=3))


def test_default_texture_has_a_vocabulary_and_paths_between_its_textons(tex):
    voc = tex.summary()
    assert voc.n_textons >= 2, str(voc)
    assert int(np.asarray(voc.segments).min()) >= tex.config.min_segments
    # the most frequent texton to the least frequent one, and a path of a given length
    seg = np.asarray(voc.segments)
    u, v = int(np.argmax(seg)), int(np.argmin(seg))
    if u == v:
        v = (u + 1) % voc.n_textons
    path = shortest_path(tex, u, v)
    assert path[0] == u and path[-1] == v and len(set(path.tolist())) == len(path)
    assert np.isfinite(path_cost(tex, path))
    L = len(path) + 2
    path_L, logp = path_of_length(tex, u, v, L)
    assert len(path_L) == L and path_L[0] == u and path_L[-1] == v
    assert logp == pytest.approx(-path_cost(tex, path_L))


def test_choreograph_and_a_texton_path_edit_on_the_default_texture(tex):
    kp, lab = np.asarray(tex.key_poses), np.asarray(tex.key_pose_labels)
    seg = np.asarray(tex.summary().segments)
    u, v = int(np.argmax(seg)), int(np.argsort(seg)[-2])
    start, end = kp[np.flatnonzero(lab == u)[0]], kp[np.flatnonzero(lab == v)[-1]]
    syn = choreograph(jax.random.key(0), tex, start, end, n_frames=600)
    assert syn.n_frames == 600 and np.isfinite(np.asarray(syn.Y)).all()
    np.testing.assert_allclose(np.asarray(syn.Y)[:2], start, atol=0.6)
    # a texton-path edit: one texton of the path replaced by another that may follow its
    # predecessor and precede its successor; the same lengths; the labels follow the edit
    path = np.asarray(syn.path)
    M = np.asarray(tex.M)
    j = len(path) // 2
    prev, nxt = path[j - 1], path[j + 1] if j + 1 < len(path) else None
    ok = [
        c
        for c in range(tex.n_textons)
        if c != path[j] and M[prev, c] > 0 and (nxt is None or M[c, nxt] > 0)
    ]
    assert ok, "no texton can replace the middle one"
    edited = path.copy()
    edited[j] = ok[int(np.argmax([M[prev, c] for c in ok]))]
    new = synthesize(jax.random.key(1), tex, path=edited, lengths=np.asarray(syn.lengths))
    assert np.isfinite(np.asarray(new.Y)).all() and new.n_frames == syn.n_frames
    labels = new.frame_labels()
    b = int(np.sum(np.asarray(syn.lengths)[:j]))
    assert labels[b] == edited[j]
