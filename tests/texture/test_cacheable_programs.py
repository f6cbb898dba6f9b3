"""The big programs of learning and synthesis carry no host callback (design §11): JAX's
persistent compilation cache does not keep a program with one, so each run of ``mtex demo``
would compile them again.

The programs are traced with the arguments a real call gives them (caught by a spy around the
jitted entry point) and their jaxprs searched for callback primitives; the positive control
traces the same code with the in-program check turned on.
"""

from __future__ import annotations

import equinox as eqx
import jax
import pytest

import edit_setup
import mtex_jax as mj
from mtex_jax.texture._learning import em
from mtex_jax.texture._synthesis import sequence as seq


def _callbacks(fn, *args, **kwargs) -> int:
    jaxpr = eqx.filter_make_jaxpr(lambda *a: fn(*a, **kwargs))(*args)[0]
    return str(jaxpr).count("callback")


def _spy(monkeypatch, module, name: str) -> list:
    calls: list = []
    real = getattr(module, name)

    def spy(*args, **kwargs):
        calls.append((args, kwargs))
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, spy)
    return calls


@pytest.fixture(scope="module")
def tex():
    return edit_setup.default_texture()


def test_synthesis_program_has_no_callback(tex, monkeypatch):
    calls = _spy(monkeypatch, seq, "_path_core_jit")
    mj.synthesize(jax.random.key(0), tex, n_frames=150)
    (args, kwargs), *_ = calls
    assert _callbacks(seq.path_core, *args, **kwargs) == 0


def test_synthesis_failure_is_reported_from_the_host(tex):
    """Without the in-program check a failed solve still raises: NaN parameters give NaN
    frames, and the host check names the problem."""
    bad = eqx.tree_at(lambda t: t.textons.d, tex, tex.textons.d * float("nan"))
    with pytest.raises(ValueError, match="constrained solve of texton"):
        mj.synthesize(jax.random.key(0), bad, n_frames=150)


def test_learning_programs_have_no_callback(monkeypatch):
    seg_calls = _spy(monkeypatch, em, "segment_batch")
    fit_calls = _spy(monkeypatch, em, "fit_all")
    clips = [mj.load_example(n).resample(30.0) for n in mj.io.example_names()]
    mj.learn(clips, mj.LearnConfig(tmin=18, tmax=54, fps=30.0, max_iter=1))
    (args, kwargs), *_ = seg_calls
    assert kwargs.get("check") is False
    assert _callbacks(em.segment_batch, *args, **kwargs) == 0
    # the positive control: the same E-step with its in-program check has one
    assert _callbacks(em.segment_batch, *args, **{**kwargs, "check": True}) > 0
    (args, kwargs), *_ = fit_calls
    assert _callbacks(em.fit_all, *args, **kwargs) == 0
