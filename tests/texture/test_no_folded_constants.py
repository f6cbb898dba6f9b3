"""No prefix sum over a compile-time constant in the scoring programs (issue 57, item 4).

XLA constant-folds an instruction whose operands are all constants, in its slow evaluator, at
every compile: the prefix sum of the residual terms of full-dimensional textons (identically
zero) took seconds and printed "Constant folding an instruction is taking > 1s" alarms to the
user's terminal on a loaded machine. The check walks the traced programs of the three builders
of segment scores (one clip: ``log_likelihood``, ``segment``; clips side by side; clips packed
end to end: ``segment`` and ``log_likelihood`` of many clips) and their nested calls, marks
every value computed from literals alone, and requires that no cumulative reduction
(``cumsum`` and friends, which lower to ``reduce-window``) takes such a value. The data
(textons, clips) are arguments, never constants."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend import core as jcore

import mtex_jax as mj
from mtex_jax.texture._scoring.packing import pack_clips, packed_scores_impl
from mtex_jax.texture._scoring.scores import _segment_scores_impl, batch_scores_impl

CUMULATIVE = {"cumsum", "cumprod", "cummax", "cummin", "cumlogsumexp", "reduce_window_sum"}
#: primitives whose value is not a function of their operands' values alone
EFFECTFUL = {"rng_bit_generator", "random_bits", "random_seed", "random_wrap", "io_callback"}


def _sub_jaxprs(params: dict) -> list:
    subs = []
    for v in params.values():
        for x in v if isinstance(v, tuple | list) else (v,):
            if isinstance(x, jcore.ClosedJaxpr):
                subs.append(x.jaxpr)
            elif isinstance(x, jcore.Jaxpr):
                subs.append(x)
    return subs


def folded_cumulative(jaxpr, const_in: list[bool], found: list[str]) -> list[bool]:
    """Walk ``jaxpr`` (inputs constant where ``const_in``); append to ``found`` each
    cumulative reduction of a constant; return which outputs are constant."""
    const: dict = {v: c for v, c in zip(jaxpr.invars, const_in, strict=True)}
    for v in jaxpr.constvars:  # closed-over data: an argument of the program, not a literal
        const[v] = False

    def is_const(x) -> bool:
        return isinstance(x, jcore.Literal) or const.get(x, False)

    for eqn in jaxpr.eqns:
        ins = [is_const(x) for x in eqn.invars]
        name = eqn.primitive.name
        if name in CUMULATIVE and ins and all(ins):
            found.append(f"{name} of a constant {eqn.outvars[0].aval}")
        subs = _sub_jaxprs(eqn.params)
        if name in ("pjit", "jit", "closed_call", "core_call", "custom_jvp_call", "remat"):
            outs = folded_cumulative(subs[0], ins[: len(subs[0].invars)], found)
        else:
            for sub in subs:  # loops, conditionals: their carries are treated as data
                folded_cumulative(sub, [False] * len(sub.invars), found)
            c = all(ins) and name not in EFFECTFUL and not subs
            outs = [c] * len(eqn.outvars)
        for v, c in zip(eqn.outvars, outs, strict=True):
            const[v] = c
    return [is_const(x) for x in jaxpr.outvars]


def check_program(fn) -> list[str]:
    closed = jax.make_jaxpr(fn)()
    found: list[str] = []
    folded_cumulative(closed.jaxpr, [], found)
    return found


@pytest.fixture(scope="module", params=["tied", "paper"])
def texture(request) -> mj.MotionTexture:
    """A full-dimensional texture (tied, ``k = D``: no residual) and one with a residual."""
    clips = [mj.load_example("dance_a"), mj.load_example("dance_b")]
    kw = {} if request.param == "tied" else {"observation": "paper", "state_dim": 4}
    cfg = mj.LearnConfig(tmin=10, tmax=30, fps=30.0, max_iter=1, **kw)
    return mj.learn(clips, cfg)


def _clips(tex):
    fm = tex.feature_map
    return [jnp.asarray(fm.encode(mj.load_example(n).resample(30.0))) for n in ("walk", "dance_b")]


def test_the_walker_sees_a_cumulative_sum_of_a_constant():
    """The walker itself: a prefix sum of zeros inside a jitted function is found, one of the
    data is not."""
    data = jnp.arange(6.0)

    @jax.jit
    def bad(x):
        return jnp.cumsum(jnp.zeros_like(x) - jnp.mean(jnp.zeros_like(x)))

    @jax.jit
    def good(x):
        return jnp.cumsum(x - jnp.mean(x))

    found = check_program(lambda: bad(data))
    assert len(found) == 1 and found[0].startswith("cumsum of a constant"), found
    assert check_program(lambda: good(data)) == []


def test_scoring_programs_fold_no_prefix_sum(texture):
    tex = texture
    clips = _clips(tex)
    T = max(int(c.shape[0]) for c in clips)
    Ys = jnp.stack([jnp.pad(c, ((0, T - c.shape[0]), (0, 0))) for c in clips])
    pk = pack_clips(np.array([c.shape[0] for c in clips]), T, 2)
    stack = tex.textons
    flat = Ys.reshape(-1, Ys.shape[-1])
    for name, fn in (
        ("one clip", lambda: _segment_scores_impl(stack, clips[0], None, False)),
        ("clips side by side", lambda: batch_scores_impl(stack, Ys, False)),
        (
            "clips packed end to end",
            lambda: packed_scores_impl(
                stack, flat, pk.frames[0], pk.where[0], pk.n[0], check=False
            ),
        ),
    ):
        assert check_program(fn) == [], name
