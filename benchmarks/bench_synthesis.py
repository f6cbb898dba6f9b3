"""Benchmark: constrained synthesis of one texton (issue 5, SPEC §5, MT §5.4).

Length ``l = 172``, ``k = 15``, ``D = 60``, float64; first two, last two frames held. Timed:

* ``banded (public call)``: :func:`mtex_jax._synthesis.synthesize_texton` as a user calls it
  (Python input checks + the jitted core), one texton;
* ``banded (jit)``: the whole call inside one ``jax.jit`` (key → sample), one texton;
* ``banded (vmap 1000)``: ``jax.jit(jax.vmap(...))`` over 1,000 keys, time per texton;
* ``dense solve``: the same masked normal equations assembled as a dense ``(l·k)²`` matrix and
  solved with ``jnp.linalg.solve`` (jit), one texton — the ratio the banded solver buys.

Compile time is measured separately (AOT ``lower().compile()``); then a warm-up call, then
``--repeats`` interleaved timed calls with ``block_until_ready``; medians are reported. The
banded and dense results are checked equal (rtol 1e-8). Writes
``benchmarks/results/synthesis.md`` and ``synthesis.json``.

Usage: ``python benchmarks/bench_synthesis.py [--repeats 21] [--batch 1000]``
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import jax

jax.config.update("jax_enable_x64", True)  # a script, not the library: float64 as in the issue

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

try:
    from mtex_jax._synthesis import _normal_system, synthesize_texton
    from mtex_jax._texton import Texton
except ImportError:  # running from a source checkout without installation
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    from mtex_jax._synthesis import _normal_system, synthesize_texton
    from mtex_jax._texton import Texton

RESULTS = Path(__file__).resolve().parent / "results"


def random_texton(rng: np.random.Generator, D: int, k: int) -> Texton:
    """A random valid texton: orthonormal ``C``, stable dynamics, full-rank ``B``."""
    C = np.linalg.qr(rng.standard_normal((D, k)))[0]
    A1 = 0.9 * np.linalg.qr(rng.standard_normal((k, k)))[0]
    A2 = 0.05 * rng.standard_normal((k, k))
    B = np.tril(0.05 * rng.standard_normal((k, k)))
    B[np.diag_indices(k)] = rng.uniform(0.1, 0.5, k)
    return Texton(
        mu=jnp.asarray(rng.standard_normal(D)),
        C=jnp.asarray(C),
        A1=jnp.asarray(A1),
        A2=jnp.asarray(A2),
        d=jnp.asarray(0.01 * rng.standard_normal(k)),
        B=jnp.asarray(B),
        sigma2=jnp.asarray(1e-3),
        m0=jnp.zeros(2 * k),
        S0=jnp.eye(2 * k),
    )


def dense_synthesis(tex: Texton, key: jax.Array, length: int, start, end) -> jax.Array:
    """Same masked normal equations, assembled densely and solved with ``jnp.linalg.solve``."""
    k = tex.C.shape[-1]
    v = jax.random.normal(key, (length - 2, k), tex.mu.dtype)
    s = _normal_system(tex, v, start, end, None, "whitened")
    n = length
    J = jnp.zeros((n, k, n, k), tex.mu.dtype)
    i = jnp.arange(n)
    J = J.at[i, :, i, :].set(s.diag)
    J = J.at[i[1:], :, i[:-1], :].set(s.off1)
    J = J.at[i[:-1], :, i[1:], :].set(jnp.swapaxes(s.off1, -1, -2))
    J = J.at[i[2:], :, i[:-2], :].set(s.off2)
    J = J.at[i[:-2], :, i[2:], :].set(jnp.swapaxes(s.off2, -1, -2))
    x = jnp.linalg.solve(J.reshape(n * k, n * k), s.rhs.reshape(n * k)).reshape(n, k)
    x = jnp.where(s.held[:, None], s.x_held, x)
    return tex.mu + x @ tex.C.T


def timed(fn, *args: Any) -> float:
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description="constrained texton synthesis benchmark")
    ap.add_argument("--repeats", type=int, default=21)
    ap.add_argument("--dense-repeats", type=int, default=5)
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--length", type=int, default=172)
    ap.add_argument("--k", type=int, default=15)
    ap.add_argument("--D", type=int, default=60)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    L, k, D, nb = args.length, args.k, args.D, args.batch

    load_before = os.getloadavg()[0]
    rng = np.random.default_rng(0)
    tex = random_texton(rng, D, k)
    Y = np.asarray(tex.mu) + rng.standard_normal((4, k)) @ np.asarray(tex.C).T
    start, end = jnp.asarray(Y[:2]), jnp.asarray(Y[2:])
    key = jax.random.key(0)
    keys = jax.random.split(jax.random.key(1), nb)

    public = lambda kk: synthesize_texton(tex, kk, L, start, end)
    one = jax.jit(lambda kk: synthesize_texton(tex, kk, L, start, end))
    batch = jax.jit(jax.vmap(lambda kk: synthesize_texton(tex, kk, L, start, end)))
    dense = jax.jit(lambda kk: dense_synthesis(tex, kk, L, start, end))

    compile_s = {}
    for name, f, a in (
        ("banded (jit)", one, key),
        ("banded (vmap)", batch, keys),
        ("dense solve", dense, key),
    ):
        t0 = time.perf_counter()
        f.lower(a).compile()
        compile_s[name] = time.perf_counter() - t0
    t_first_public = timed(public, key)

    # warm-up and correctness
    yb, yd = np.asarray(one(key)), np.asarray(dense(key))
    yp = np.asarray(public(key))
    yv = np.asarray(batch(keys))
    rel = float(np.linalg.norm(yb - yd) / np.linalg.norm(yd))
    assert rel < 1e-8, rel
    assert np.allclose(yp, yb, rtol=1e-12, atol=1e-12)
    assert np.allclose(yv[0], np.asarray(one(keys[0])), rtol=1e-10, atol=1e-10)
    held_err = float(np.abs(yb[[0, 1, -2, -1]] - Y).max())

    t: dict[str, list[float]] = {"public": [], "jit": [], "vmap": [], "dense": []}
    for r in range(args.repeats):
        t["jit"].append(timed(one, key))
        t["public"].append(timed(public, key))
        t["vmap"].append(timed(batch, keys))
        if r < args.dense_repeats:
            t["dense"].append(timed(dense, key))
    load_after = os.getloadavg()[0]
    med = {name: statistics.median(v) for name, v in t.items()}
    best = {name: min(v) for name, v in t.items()}
    per = {
        "banded (public call)": med["public"],
        "banded (jit)": med["jit"],
        f"banded (vmap {nb}, per texton)": med["vmap"] / nb,
        "dense solve (jit)": med["dense"],
    }
    for name, s in per.items():
        print(f"{name:32s} {s * 1e3:10.4f} ms")
    print(f"dense / banded(jit) ratio: {med['dense'] / med['jit']:.1f}x")
    print("compile:", {n: round(s, 3) for n, s in compile_s.items()})

    result = {
        "date_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "config": {
            "length": L,
            "k": k,
            "D": D,
            "batch": nb,
            "dtype": "float64",
            "repeats": args.repeats,
            "dense_repeats": args.dense_repeats,
            "held": "first two and last two frames",
            "weighting": "whitened",
        },
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "cpu_count": os.cpu_count(),
            "jax": jax.__version__,
            "backend": jax.default_backend(),
            "load_average_1min_before_after": [load_before, load_after],
        },
        "median_seconds_per_texton": per,
        "min_seconds_per_texton": {
            "banded (public call)": best["public"],
            "banded (jit)": best["jit"],
            f"banded (vmap {nb}, per texton)": best["vmap"] / nb,
            "dense solve (jit)": best["dense"],
        },
        "compile_seconds": compile_s,
        "first_public_call_seconds": t_first_public,
        "dense_over_banded_jit": med["dense"] / med["jit"],
        "banded_vs_dense_relative_difference": rel,
        "max_abs_error_at_held_frames": held_err,
        "targets": {"single_ms": 1.0, "vmap_per_texton_ms": 0.1, "paper_ms": "25-35"},
    }
    if args.no_write:
        return
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "synthesis.json").write_text(json.dumps(result, indent=2) + "\n")
    bests = [best["public"], best["jit"], best["vmap"] / nb, best["dense"]]
    rows = "\n".join(
        f"| {n} | {s * 1e3:.4f} | {b * 1e3:.4f} |"
        for (n, s), b in zip(per.items(), bests, strict=True)
    )
    ok1 = "met" if med["jit"] <= 1e-3 else "NOT met"
    ok2 = "met" if med["vmap"] / nb <= 1e-4 else "NOT met"
    md = f"""# Constrained synthesis of one texton (issue 5)

`python benchmarks/bench_synthesis.py` — {result["date_utc"]}, {platform.platform()},
{os.cpu_count()} CPUs, jax {jax.__version__} ({jax.default_backend()}); 1-min load average
{load_before:.1f} before / {load_after:.1f} after (shared machine: other jobs were running).

Length {L}, k = {k}, D = {D}, float64, whitened (exact conditional sample), first two and last
two frames held. Medians of {args.repeats} interleaved runs (dense: {args.dense_repeats}), after
a warm-up; compile time separate.

| variant | median ms per texton | best (min) ms |
|---|---|---|
{rows}

- target ≤ 1 ms per texton (single, jit): **{ok1}** ({med["jit"] * 1e3:.3f} ms)
- target ≤ 0.1 ms per texton in a vmap batch of {nb}: **{ok2}** ({med["vmap"] / nb * 1e3:.4f} ms)
- the paper: 25–35 ms per texton
- dense `(l·k)²` solve / banded (jit): **{med["dense"] / med["jit"]:.0f}×**
- banded vs dense result: relative difference {rel:.2e}; held frames error {held_err:.1e}
- compile (AOT lower+compile), s: {", ".join(f"{n} {s:.2f}" for n, s in compile_s.items())};
  first public call (trace + compile + run): {t_first_public:.2f} s
"""
    (RESULTS / "synthesis.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
