"""Textures that several test modules learn with the same clips and settings, learned once per
test process (pytest-xdist worker) and shared: the compiled programs and the EM run are paid
once. A :class:`~mtex_jax.MotionTexture` is an immutable pytree, so sharing it cannot couple
the tests; each test module writes its own files from it."""

from __future__ import annotations

import functools
from pathlib import Path

import mtex_jax as mj
from paper_settings import PAPER


@functools.cache
def dance_pair_texture() -> mj.MotionTexture:
    """The paper's model (``LearnConfig.paper``, ``k = 4``, segments of 10-30 frames, two EM
    iterations) learned from the embedded ``dance_a`` and ``dance_b`` clips at 30 Hz; it carries
    their contact model. The small texture of test_hostile, test_hostile_contacts and
    test_reliability."""
    clips = [mj.load_example("dance_a"), mj.load_example("dance_b")]
    cfg = mj.LearnConfig.paper(tmin=10, tmax=30, state_dim=4, fps=30.0, max_iter=2)
    return mj.learn(clips, cfg)


@functools.cache
def four_clip_texture() -> mj.MotionTexture:
    """The paper's model (``k = 6``, segments of 12-36 frames, greedy threshold 0.3, three EM
    iterations) learned from the embedded ``dance_a``, ``dance_b``, ``walk`` and ``run`` clips
    at 30 Hz. The texture of test_sequence and test_long_synthesis."""
    clips = [mj.load_example(n) for n in ("dance_a", "dance_b", "walk", "run")]
    cfg = mj.LearnConfig(
        tmin=12, tmax=36, state_dim=6, fps=30.0, threshold=0.3, max_iter=3, **PAPER
    )
    return mj.learn(clips, cfg)


@functools.cache
def salsa30_texture(cmu_dir: Path) -> mj.MotionTexture:
    """The paper's model (``k = 6``, segments of 30-90 frames, greedy threshold 0.3, two EM
    iterations) learned from the first three CMU salsa clips (``cmu_dir``, sorted by name) at
    30 Hz. The texture of test_evaluate's CMU model file and of test_metrics_baselines'
    prediction test."""
    clips = [mj.read_bvh(f).resample(30.0) for f in sorted(cmu_dir.glob("*.bvh"))[:3]]
    cfg = mj.LearnConfig(
        tmin=30, tmax=90, state_dim=6, fps=30.0, threshold=0.3, max_iter=2, **PAPER
    )
    return mj.learn(clips, cfg)


@functools.cache
def salsa_tracking_texture() -> mj.MotionTexture:
    """The defaults (``LearnConfig(fps=30.0)``) learned from the shipped salsa clips 60_01 to
    60_04 at 30 Hz (training clips of the fixed split); it carries their contact model. The
    prior of the tracking tests, which track the held-out 60_12."""
    from mtex_jax.io import load_salsa

    clips = [load_salsa(n) for n in ("60_01", "60_02", "60_03", "60_04")]
    return mj.learn(clips, mj.LearnConfig(fps=30.0))
