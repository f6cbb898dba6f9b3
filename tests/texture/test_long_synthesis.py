"""Long syntheses in bounded memory (design §5.11, issue 57): a path drawn whole, its frames
synthesised block by block, decoded and written in pieces.

The references: the single-texton solver for every texton on either side of a block boundary,
the whole synthesis for the pieces of a stream (three pieces), :meth:`FeatureMap.decode` for
:meth:`FeatureMap.decode_chunks`, and :func:`write_bvh` of the whole motion for the file
written piece by piece. The run at the limit itself (a million frames under an address-space
limit) is in ``tests/test_long_synthesis_memory.py``.
"""

from __future__ import annotations

import filecmp
import itertools

import jax
import numpy as np
import pytest

import mtex_jax as mj
from mtex_jax.texture._synthesis import sequence
from shared_textures import four_clip_texture


@pytest.fixture(scope="module")
def texture():
    return four_clip_texture()


def test_textons_across_a_block_boundary_equal_single_texton_synthesis(texture):
    """A path longer than one block of :func:`~sequence.block_rows` textons: every texton
    around the boundaries (zero noise, spread correction) equals ``synthesize_texton`` held at
    its key poses and the next texton's, as inside a block."""
    P = sequence.block_rows(texture)
    n = 2 * P + 5
    rng = np.random.default_rng(1)
    path = rng.integers(0, texture.n_textons, n)
    lengths = rng.integers(12, 30, n)
    s = mj.synthesize(
        None, texture, path=path, lengths=lengths, residual="subspace", transition=None
    )
    Y, st, kp = np.asarray(s.Y), np.asarray(s.starts), np.asarray(texture.key_poses)
    segs = np.asarray(s.key_segments)
    assert Y.shape == (lengths.sum(), texture.obs_dim)
    for m in (0, P - 2, P - 1, P, P + 1, 2 * P - 1, 2 * P, n - 2):
        t = jax.tree.map(lambda a, i=path[m]: a[i], texture.textons)
        ref = mj.texture.synthesize_texton(
            None, t, int(lengths[m]) + 2, kp[segs[m]], kp[segs[m + 1]]
        )
        got = Y[st[m] : st[m] + lengths[m]]
        np.testing.assert_allclose(got, np.asarray(ref)[: lengths[m]], rtol=1e-9, atol=1e-9)


def test_blocks_draw_their_own_innovations(texture):
    """Each block's innovations come from a key of its own (block 0: the synthesis's key, as
    a synthesis of one block always had): the second block of a path of one repeated texton
    and lengths does not replay the first block's motion, and the same key gives the same
    motion again."""
    P = sequence.block_rows(texture)
    path = np.full(2 * P, 0)
    lengths = np.full(2 * P, 20)
    a = mj.synthesize(jax.random.key(4), texture, path=path, lengths=lengths, decode=False)
    b = mj.synthesize(jax.random.key(4), texture, path=path, lengths=lengths, decode=False)
    Y = np.asarray(a.Y)
    np.testing.assert_array_equal(Y, np.asarray(b.Y))
    first, second = Y[: 20 * P], Y[20 * P :]
    assert np.abs(first - second).max() > 0.1


@pytest.mark.parametrize("x64", [True, False], ids=["float64", "float32"])
def test_a_stream_of_three_pieces_equals_the_whole_synthesis(texture, x64):
    """The pieces of :func:`synthesize_chunks` at 3 × the piece size: their observations,
    path and lengths are :func:`synthesize`'s bit for bit; the first piece's motion too, the
    later pieces' motion up to the rounding of the running root sums (the root carried from
    piece to piece). With ``chunk_frames = CHUNK_FRAMES`` the motion is bit for bit too."""
    tex = (
        texture
        if x64
        else jax.tree.map(
            lambda a: a.astype(np.float32) if getattr(a, "dtype", None) == np.float64 else a,
            texture,
        )
    )
    C = 7000
    n = 3 * C
    whole = mj.synthesize(jax.random.key(2), tex, n_frames=n)
    stream = mj.texture.synthesize_chunks(jax.random.key(2), tex, n_frames=n, chunk_frames=C)
    np.testing.assert_array_equal(stream.path, np.asarray(whole.path))
    np.testing.assert_array_equal(stream.lengths, np.asarray(whole.lengths))
    np.testing.assert_array_equal(stream.starts, np.asarray(whole.starts))
    pieces = list(stream)
    assert [p.start for p in pieces] == [0, C, 2 * C]
    assert [p.n_frames for p in pieces] == [C, C, C]
    np.testing.assert_array_equal(np.concatenate([p.Y for p in pieces]), np.asarray(whole.Y))
    # metres: the running sums of 21,000 float32 steps 30 m from the origin round by about
    # eps(30 m) ≈ 4e-6 m a step, ~5e-4 m after 21,000 (a random walk), in either order
    tol = 1e-9 if x64 else 2e-3
    for name in ("root_positions", "rotations"):
        got = np.concatenate([getattr(p.motion, name) for p in pieces])
        ref = np.asarray(getattr(whole.motion, name))
        np.testing.assert_array_equal(got[:C], ref[:C])
        np.testing.assert_allclose(got, ref, rtol=0, atol=tol)
    # a whole synthesis longer than one piece is decoded in pieces of CHUNK_FRAMES
    exact = mj.texture.synthesize_chunks(jax.random.key(2), tex, n_frames=n)
    got = np.concatenate([p.motion.rotations for p in exact])
    np.testing.assert_array_equal(got, np.asarray(whole.motion.rotations))
    with pytest.raises(ValueError, match="iterated once"):
        list(stream)


def test_stream_options_and_refusals(texture):
    """The stream passes ``synthesize``'s options on and refuses unknown ones and bad piece
    sizes, naming them."""
    key = jax.random.key(0)
    a = mj.texture.synthesize_chunks(key, texture, n_frames=500, replay="shuffled")
    b = mj.synthesize(key, texture, n_frames=500, replay="shuffled")
    np.testing.assert_array_equal(np.concatenate([p.Y for p in a]), np.asarray(b.Y))
    with pytest.raises(TypeError, match=r"unknown options.*'replays'"):
        mj.texture.synthesize_chunks(key, texture, n_frames=500, replays="shuffled")
    with pytest.raises(ValueError, match="chunk_frames must be >= 1"):
        mj.texture.synthesize_chunks(key, texture, n_frames=500, chunk_frames=0)
    with pytest.raises(ValueError, match="MAX_GENERATED_FRAMES"):
        mj.texture.synthesize_chunks(key, texture, n_frames=10**9)


def test_decode_chunks_continues_the_root(texture):
    """Decoding a clip's observations in uneven pieces (one of a single frame) gives the
    clip's motion: the root position and heading carried exactly, the first piece equal to
    ``decode``'s bit for bit."""
    fm = texture.feature_map
    clip = mj.load_example("dance_a").resample(fm.fps)
    Y = np.asarray(fm.encode(clip))
    sp, sh = fm.start_of(clip)
    whole = fm.decode(Y, sp, sh)
    T = Y.shape[0]
    cuts = [0, 10, 11, 30, T]
    parts = list(fm.decode_chunks([Y[a:b] for a, b in itertools.pairwise(cuts)], sp, sh))
    assert [p.n_frames for p in parts] == [10, 1, 19, T - 30]
    for name in ("root_positions", "rotations"):
        got = np.concatenate([getattr(p, name) for p in parts])
        np.testing.assert_array_equal(got[:10], np.asarray(getattr(whole, name))[:10])
        np.testing.assert_allclose(got, np.asarray(getattr(whole, name)), atol=1e-12)
    np.testing.assert_allclose(
        np.concatenate([p.root_positions for p in parts]), clip.root_positions, atol=1e-9
    )
    with pytest.raises(ValueError, match=r"each piece must have shape \(t, \d+\)"):
        list(fm.decode_chunks([Y[:10], Y[10:20, :3]]))


def test_bvh_written_in_pieces_is_the_file_of_the_whole_motion(tmp_path):
    """:func:`write_bvh_chunks` of a clip cut into pieces writes :func:`write_bvh`'s file byte
    for byte; too few or too many frames, or a piece on another skeleton, write nothing."""
    from mtex_jax.io import write_bvh, write_bvh_chunks

    m = mj.load_example("dance_a")
    write_bvh(tmp_path / "whole.bvh", m)
    n = m.n_frames
    cuts = [0, 1, n // 2, n // 2 + 1, n]
    write_bvh_chunks(
        tmp_path / "pieces.bvh", (m[a:b] for a, b in itertools.pairwise(cuts)), m.n_frames
    )
    assert filecmp.cmp(tmp_path / "whole.bvh", tmp_path / "pieces.bvh", shallow=False)
    bad = tmp_path / "bad.bvh"
    with pytest.raises(ValueError, match=f"have 40 frames, not {n}"):
        write_bvh_chunks(bad, [m[:40]], n)
    with pytest.raises(ValueError, match="more than n_frames = 50"):
        write_bvh_chunks(bad, [m[:40], m[40:90]], 50)
    other = mj.load_example("walk")
    with pytest.raises(ValueError, match="another skeleton or frame rate"):
        write_bvh_chunks(bad, [m[:10], other[:10]], 20)
    assert not bad.exists()


def test_long_quaternion_checks_run_in_blocks(monkeypatch):
    """The unit-quaternion check and normalisation of :class:`Motion` run in blocks of frames
    (no float64 copy of a long clip): with blocks of 7 frames, a bad quaternion in a later
    block is named at its own frame, and near-unit quaternions are normalised as a whole."""
    from mtex_jax.motion import _motion

    m = mj.load_example("walk")
    q = np.asarray(m.rotations).copy()
    whole = mj.Motion(m.skeleton, m.fps, m.root_positions, q * (1 + 1e-6))
    monkeypatch.setattr(_motion, "_BLOCK", 7)
    blocked = mj.Motion(m.skeleton, m.fps, m.root_positions, q * (1 + 1e-6))
    np.testing.assert_array_equal(np.asarray(blocked.rotations), np.asarray(whole.rotations))
    bad = q.copy()
    bad[23, 2] *= 2.0
    with pytest.raises(ValueError, match=r"frame 23, joint 2 .*norm 2, not a unit"):
        mj.Motion(m.skeleton, m.fps, m.root_positions, bad)


def test_cli_synth_writes_a_long_synthesis_in_pieces(texture, tmp_path, monkeypatch, capsys):
    """``mtex synth`` of more frames than one piece streams: the BVH file is the file of the
    whole synthesis (``write_bvh`` of ``synthesize``), with one progress line per piece on
    stderr, and ``--gif`` / ``--clean`` are refused before any work with a clear message."""
    from mtex_jax.cli import _texture_cmds, main
    from mtex_jax.io import write_bvh

    model = tmp_path / "tex.npz"
    texture.save(model)
    monkeypatch.setattr(_texture_cmds, "CHUNK_FRAMES", 600)
    monkeypatch.setattr(sequence, "CHUNK_FRAMES", 600)
    out = tmp_path / "long.bvh"
    assert main(["synth", str(model), "--frames", "1500", "-o", str(out), "--seed", "5"]) == 0
    cap = capsys.readouterr()
    progress = [ln for ln in cap.err.splitlines() if ln.startswith("[mtex synth]")]
    assert len(progress) == 3 and progress[-1].startswith("[mtex synth] 1,500 / 1,500 frames")
    assert "in pieces of 600" in cap.out
    ref = mj.synthesize(jax.random.key(5), mj.load_texture(model), n_frames=1500)
    write_bvh(tmp_path / "ref.bvh", ref.motion)
    assert filecmp.cmp(out, tmp_path / "ref.bvh", shallow=False)
    for extra, what in ((["--gif", str(tmp_path / "a.gif")], "--gif"), (["--clean"], "--clean")):
        args = ["synth", str(model), "--frames", "1500", "-o", str(tmp_path / "b.bvh"), *extra]
        assert main(args) != 0
        err = capsys.readouterr().err
        assert f"{what}: --frames 1,500 is more than one piece of 600 frames" in err
        assert not (tmp_path / "b.bvh").exists()
