"""Fixtures shared by the implicit-model test modules, built once per test process: the CMU
salsa clips at 30 Hz, the database's equal-length training chunks and the default implicit
model on them. test_implicit's model and test_tracking's default database are this one model
(the same chunks and window), so it is learned once."""

from __future__ import annotations

import pytest

import mtex_jax as mj
from mtex_jax.implicit import ImplicitModel

#: 60_03 is held out of the database: the probes and the tracked clip come from it
HELD_OUT = 2
#: equal-length training chunks: one jit compilation of the features
CHUNK = 128
#: frames of the default model's windows
WINDOW = 10


@pytest.fixture(scope="session")
def salsa30_held_out() -> int:
    """The index of the clip that :func:`salsa30_chunks` leaves out."""
    return HELD_OUT


@pytest.fixture(scope="session")
def salsa30(cmu_motions) -> list[mj.Motion]:
    """The 14 CMU salsa clips at 30 Hz."""
    return [m.resample(30.0) for m in cmu_motions]


@pytest.fixture(scope="session")
def salsa30_chunks(salsa30) -> list[mj.Motion]:
    """``CHUNK``-frame chunks of every clip but ``HELD_OUT``."""
    train = [m for i, m in enumerate(salsa30) if i != HELD_OUT]
    return [m[i : i + CHUNK] for m in train for i in range(0, m.n_frames - CHUNK + 1, CHUNK)]


@pytest.fixture(scope="session")
def salsa30_model(salsa30_chunks) -> ImplicitModel:
    """The default implicit model (``WINDOW``-frame windows) of :func:`salsa30_chunks`."""
    return mj.implicit.learn(salsa30_chunks, WINDOW)
