"""Benchmark: constrained synthesis of one texton (issue 5, design §5, MT §5.4).

Length ``l = 172``, ``k = 15``, ``D = 60``, float64; first two, last two frames held. Timed:

* ``bridge (public call)``: :func:`mtex_jax.texture.synthesize_texton` as a user calls
  it (Python input checks + the jitted core), one texton; with both ends held and no edits it
  uses the bridge recursion (``solve_bridge`` of ``texture/_synthesis/bridge.py``);
* ``bridge (jit)``: the whole call inside one ``jax.jit`` (key → sample), one texton;
* ``bridge (vmap N, threefry keys)``: ``jax.jit(jax.vmap(...))`` over ``N`` default
  (threefry) keys, time per texton — the figure the issue's target refers to;
* ``bridge (vmap N, rbg keys)``: the same with ``jax.random.key(..., impl="rbg")`` keys, a
  documented JAX option a user may choose (separate row; the threefry row is the reference);
* ``banded solve``: the same sample (same key, same equations and noise) from the masked
  normal equations and the block-banded solver, the general path of ``synthesize_texton``
  (edits, open ends) and its only path before the bridge — the baseline of the speed-up;
* ``noise only``: drawing the ``(l−2, k)`` equation noise alone under ``vmap`` (the library's
  Box–Muller draw, and ``jax.random.normal`` for comparison) — context for how much of the
  vmap time is random number generation;
* ``dense solve``: the same sample with the normal matrix assembled as a dense ``(l·k)²``
  matrix and a dense Cholesky solve (jit), one texton.

Compile time is measured separately (AOT ``lower().compile()``); then a warm-up call, then
``--repeats`` interleaved rounds of timed calls with ``block_until_ready`` (single-texton rows:
an untimed call, then ``--per-round`` timed calls per round; a pause after the dense solve so
that its BLAS worker threads are idle again); medians are reported with the
10th percentile, the minimum and the median process CPU time per call (on a shared machine the
wall time includes waiting for a core; CPU time above wall time means XLA ran threads in
parallel). The bridge, banded and dense results are checked against each other (rtol 1e-8)
and the batched samples against single calls. Writes ``benchmarks/results/synthesis.md`` and
``synthesis.json``.

Usage: ``python benchmarks/speed/bench_synthesis.py [--repeats 21] [--batch 1000]``
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

import jax.numpy as jnp
import numpy as np

try:
    import mtex_jax  # noqa: F401
except ImportError:  # running from a source checkout without installation
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "src"))
# the constrained synthesis' building blocks (the dense reference and the noise)
from mtex_jax.internal import (
    constrained_equations,
    constrained_normal_system as normal_system,
    draw_noise as draw_noise,
    observe_states as observe,
    solve_constrained,
)
from mtex_jax.texture import Texton, synthesize_texton
from mtex_jax.texture._synthesis.bridge import bridge_usable

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import RESULTS, command


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
    """The same sample with dense linear algebra: the masked normal equations ``J x = g``
    (with the key's equation noise ``v``, as :func:`synthesize_texton` draws it) assembled as
    a dense ``(l·k)²`` matrix and solved by a dense Cholesky factorisation."""
    k = tex.C.shape[-1]
    s = normal_system(tex, draw_noise(tex, key, length), start, end, None, "whitened")
    n = length
    J = jnp.zeros((n, k, n, k), tex.mu.dtype)
    i = jnp.arange(n)
    J = J.at[i, :, i, :].set(s.diag)
    J = J.at[i[1:], :, i[:-1], :].set(s.off1)
    J = J.at[i[:-1], :, i[1:], :].set(jnp.swapaxes(s.off1, -1, -2))
    J = J.at[i[2:], :, i[:-2], :].set(s.off2)
    J = J.at[i[:-2], :, i[2:], :].set(jnp.swapaxes(s.off2, -1, -2))
    Lc = jnp.linalg.cholesky(J.reshape(n * k, n * k))
    x = jax.scipy.linalg.cho_solve((Lc, True), s.rhs.reshape(n * k))
    x = jnp.where(s.held[:, None], s.x_held, x.reshape(n, k))
    return tex.mu + x @ tex.C.T


def banded_synthesis(tex: Texton, key: jax.Array, length: int, start, end) -> jax.Array:
    """The same sample from the masked normal equations and the block-banded solver."""
    w = draw_noise(tex, key, length) @ tex.B.T
    eqs = constrained_equations(tex, length, w, start, end, None, "whitened")
    return observe(tex, *solve_constrained(tex, eqs, w))


def timed(fn, *args: Any) -> float:
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0


def timed_cpu(fn, *args: Any) -> tuple[float, float]:
    """Wall and process-CPU seconds of one call."""
    t0, c0 = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0, time.process_time() - c0


def main() -> None:
    ap = argparse.ArgumentParser(description="constrained texton synthesis benchmark")
    ap.add_argument("--repeats", type=int, default=21)
    ap.add_argument("--dense-repeats", type=int, default=5)
    ap.add_argument("--per-round", type=int, default=5, help="timed single calls per round")
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--length", type=int, default=172)
    ap.add_argument("--k", type=int, default=15)
    ap.add_argument("--D", type=int, default=60)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    L, k, D, nb = args.length, args.k, args.D, args.batch

    load_before = os.getloadavg()
    rng = np.random.default_rng(0)
    tex = random_texton(rng, D, k)
    assert bool(bridge_usable(tex.A1, tex.A2, L - 4))  # the bridge rows time the bridge
    Y = np.asarray(tex.mu) + rng.standard_normal((4, k)) @ np.asarray(tex.C).T
    start, end = jnp.asarray(Y[:2]), jnp.asarray(Y[2:])
    key = jax.random.key(0)
    keys = jax.random.split(jax.random.key(1), nb)
    key_rbg = jax.random.key(0, impl="rbg")
    keys_rbg = jax.random.split(jax.random.key(1, impl="rbg"), nb)

    public = lambda kk: synthesize_texton(kk, tex, L, start, end)
    one = jax.jit(lambda kk: synthesize_texton(kk, tex, L, start, end))
    batch = jax.jit(jax.vmap(lambda kk: synthesize_texton(kk, tex, L, start, end)))
    banded = jax.jit(lambda kk: banded_synthesis(tex, kk, L, start, end))
    banded_batch = jax.jit(jax.vmap(lambda kk: banded_synthesis(tex, kk, L, start, end)))
    dense = jax.jit(lambda kk: dense_synthesis(tex, kk, L, start, end))
    noise = jax.jit(jax.vmap(lambda kk: draw_noise(tex, kk, L)))
    noise_jax = jax.jit(jax.vmap(lambda kk: jax.random.normal(kk, (L - 2, k), jnp.float64)))

    compile_s = {}
    for name, f, a in (
        ("bridge (jit)", one, key),
        ("bridge (vmap, threefry keys)", batch, keys),
        ("bridge (vmap, rbg keys)", batch, keys_rbg),
        ("banded solve (jit)", banded, key),
        ("banded solve (vmap)", banded_batch, keys),
        ("dense solve", dense, key),
    ):
        t0 = time.perf_counter()
        f.lower(a).compile()
        compile_s[name] = time.perf_counter() - t0
    t_first_public = timed(public, key)

    # warm-up and correctness
    yb, yd, yband = np.asarray(one(key)), np.asarray(dense(key)), np.asarray(banded(key))
    yp = np.asarray(public(key))
    yv = np.asarray(batch(keys))
    yr = np.asarray(batch(keys_rbg))
    rel = float(np.linalg.norm(yb - yd) / np.linalg.norm(yd))
    rel_banded = float(np.linalg.norm(yb - yband) / np.linalg.norm(yband))
    assert rel < 1e-8 and rel_banded < 1e-8, (rel, rel_banded)
    assert np.allclose(yp, yb, rtol=1e-12, atol=1e-12)
    assert np.allclose(yv[0], np.asarray(one(keys[0])), rtol=1e-10, atol=1e-10)
    assert np.allclose(yr[0], np.asarray(one(keys_rbg[0])), rtol=1e-10, atol=1e-10)
    assert np.allclose(np.asarray(banded_batch(keys))[0], yv[0], rtol=1e-10, atol=1e-10)
    held_err = float(np.abs(yb[[0, 1, -2, -1]] - Y).max())
    jax.block_until_ready((noise(keys), noise_jax(keys), one(key_rbg)))

    # name -> (function, argument, divisor, rounds); single calls are timed ``--per-round``
    # times per round (after one untimed call, so that a variant is not timed right after the
    # benchmark's own previous, heavier variant), the dense solve is followed by a pause that
    # lets OpenBLAS's spinning worker threads go idle before the next variant is timed
    rows = {
        "bridge (public call)": (public, key, 1, args.repeats),
        "bridge (jit)": (one, key, 1, args.repeats),
        f"bridge (vmap {nb}, threefry keys, per texton)": (batch, keys, nb, args.repeats),
        f"bridge (vmap {nb}, rbg keys, per texton)": (batch, keys_rbg, nb, args.repeats),
        "banded solve (jit)": (banded, key, 1, args.repeats),
        f"banded solve (vmap {nb}, per texton)": (banded_batch, keys, nb, args.repeats),
        f"noise only: vmap {nb}, the library's Box–Muller draw (per texton)": (
            noise,
            keys,
            nb,
            args.repeats,
        ),
        f"noise only: vmap {nb}, jax.random.normal (per texton)": (
            noise_jax,
            keys,
            nb,
            args.repeats,
        ),
        "dense solve (jit)": (dense, key, 1, args.dense_repeats),
    }
    wall: dict[str, list[float]] = {n: [] for n in rows}
    cpu: dict[str, list[float]] = {n: [] for n in rows}
    for r in range(args.repeats):
        for name, (f, a, div, reps) in rows.items():
            if r >= reps:
                continue
            if div == 1 and name != "dense solve (jit)":
                jax.block_until_ready(f(a))  # untimed
                for _ in range(args.per_round):
                    w, c = timed_cpu(f, a)
                    wall[name].append(w)
                    cpu[name].append(c)
            else:
                w, c = timed_cpu(f, a)
                wall[name].append(w / div)
                cpu[name].append(c / div)
            if name == "dense solve (jit)":
                time.sleep(0.3)
    load_after = os.getloadavg()
    stats = {
        name: {
            "median": statistics.median(wall[name]),
            "p10": float(np.percentile(wall[name], 10)),
            "min": min(wall[name]),
            "cpu_median": statistics.median(cpu[name]),
        }
        for name in rows
    }
    single = stats["bridge (jit)"]["median"]
    vmap_name = f"bridge (vmap {nb}, threefry keys, per texton)"
    per_v = stats[vmap_name]["median"]
    banded_med = stats["banded solve (jit)"]["median"]
    banded_v = stats[f"banded solve (vmap {nb}, per texton)"]["median"]
    dense_med = stats["dense solve (jit)"]["median"]
    for name, st in stats.items():
        print(
            f"{name:58s} median {st['median'] * 1e3:9.4f}  p10 {st['p10'] * 1e3:9.4f}  "
            f"min {st['min'] * 1e3:9.4f}  cpu {st['cpu_median'] * 1e3:9.4f} ms"
        )
    print(f"banded / bridge: {banded_med / single:.2f}x; dense / bridge: {dense_med / single:.0f}x")
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
            "load_average_1_5_15min_before": list(load_before),
            "load_average_1_5_15min_after": list(load_after),
        },
        "seconds_per_texton": stats,
        "compile_seconds": compile_s,
        "first_public_call_seconds": t_first_public,
        "banded_over_bridge_jit": banded_med / single,
        "banded_over_bridge_vmap": banded_v / per_v,
        "dense_over_bridge_jit": dense_med / single,
        "bridge_vs_dense_relative_difference": rel,
        "bridge_vs_banded_relative_difference": rel_banded,
        "max_abs_error_at_held_frames": held_err,
        "targets": {"single_ms": 1.0, "vmap_per_texton_ms": 0.1, "paper_ms": "25-35"},
        "targets_met_by_median": {
            "single_ms": single <= 1e-3,
            "vmap_per_texton_ms (threefry keys)": per_v <= 1e-4,
        },
    }
    if args.no_write:
        return
    result = {"command": command(), **result}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "synthesis.json").write_text(json.dumps(result, indent=2) + "\n")
    table = "\n".join(
        f"| {n} | {st['median'] * 1e3:.4f} | {st['p10'] * 1e3:.4f} | {st['min'] * 1e3:.4f} "
        f"| {st['cpu_median'] * 1e3:.4f} |"
        for n, st in stats.items()
    )
    ok1 = "met" if single <= 1e-3 else "NOT met"
    ok2 = "met" if per_v <= 1e-4 else "NOT met"
    rbg_v = stats[f"bridge (vmap {nb}, rbg keys, per texton)"]["median"]
    noise_v = stats[f"noise only: vmap {nb}, the library's Box–Muller draw (per texton)"]["median"]
    lb = ", ".join(f"{x:.1f}" for x in load_before)
    la = ", ".join(f"{x:.1f}" for x in load_after)
    md = f"""# Constrained synthesis of one texton (issue 5)

Made by: `{result["command"]}`

Run on {result["date_utc"]}, {platform.platform()},
{os.cpu_count()} CPUs, jax {jax.__version__} ({jax.default_backend()}); load average (1, 5, 15 min)
{lb} before / {la} after (shared machine: other jobs were running).

Length {L}, k = {k}, D = {D}, float64, whitened (exact conditional sample), first two and last
two frames held. {args.repeats} interleaved rounds (dense: {args.dense_repeats}) after a
warm-up; in each round every variant is timed once (single-texton rows: one untimed call, then
{args.per_round} timed calls), compile time separate. Wall-clock milliseconds per texton;
"cpu" is the median process CPU time per texton (above the wall time when XLA used both cores).

| variant | median | p10 | min | cpu (median) |
|---|---|---|---|---|
{table}

- target ≤ 1 ms per texton (single, jit): **{ok1}** (median {single * 1e3:.3f} ms)
- target ≤ 0.1 ms per texton in a vmap batch of {nb} (default threefry keys): **{ok2}**
  (median {per_v * 1e3:.4f} ms); with rbg keys {rbg_v * 1e3:.4f} ms; drawing the noise alone
  takes {noise_v * 1e3:.4f} ms per texton of that
- method: the bridge recursion (the free motion from the start frames plus the control that
  brings it to the end frames, from a 2k × 2k system; `solve_bridge`); the
  same least-squares solution as the banded solve of the masked normal equations:
  banded / bridge **{banded_med / single:.1f}×** (single), **{banded_v / per_v:.1f}×** (vmap)
- the paper: 25–35 ms per texton
- dense `(l·k)²` solve / bridge (jit): **{dense_med / single:.0f}×**
- bridge vs dense result: relative difference {rel:.2e}; vs banded {rel_banded:.2e}; held
  frames error {held_err:.1e}
- compile (AOT lower+compile), s: {", ".join(f"{n} {s:.2f}" for n, s in compile_s.items())};
  first public call (trace + compile + run): {t_first_public:.2f} s
"""
    (RESULTS / "synthesis.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
