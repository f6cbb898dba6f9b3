"""The small texture, contacts and synthesis shared by the edit tests: a texture learned on the
embedded DeepMimic clips at 30 Hz with the paper's settings, so the compiled solves stay small."""

from __future__ import annotations

import functools

import jax

import mtex_jax as mj
from mtex_jax.motion import fit_contacts
from paper_settings import PAPER

FPS = 30.0
T = 90


def _clips() -> list[mj.Motion]:
    return [mj.load_example(n).resample(FPS) for n in mj.io.example_names()]


@functools.cache  # learned once per test session, shared by the edit test modules
def texture() -> mj.MotionTexture:
    cfg = mj.LearnConfig(tmin=18, tmax=54, state_dim=6, fps=FPS, threshold=0.3, max_iter=5, **PAPER)
    return mj.learn(_clips(), cfg)


@functools.cache
def default_texture() -> mj.MotionTexture:
    """The same clips learned with the default settings (tied textons, a residual bank)."""
    return mj.learn(_clips(), mj.LearnConfig(tmin=18, tmax=54, fps=FPS, max_iter=5))


@functools.cache
def contacts():
    return fit_contacts(_clips(), fps=FPS)


def synthesis(tex: mj.MotionTexture):
    return mj.synthesize(jax.random.key(1), tex, n_frames=T)


def hand(tex: mj.MotionTexture) -> str:
    """The right hand, or where the arm ends (the DeepMimic humanoid's ends at the elbow)."""
    assert tex.feature_map is not None
    names = tex.feature_map.skeleton.names
    return next(n for n in names if n.lower().endswith(("hand", "wrist", "right_elbow")))
