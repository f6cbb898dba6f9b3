"""Benchmark: per-frame texton log-density terms at the paper's scale (issue 3, SPEC §3).

``frame_terms`` for T = 50,000 frames, N_t = 246 textons, D = 60, k = 15 in float64 (MT §7:
49,800 frames, 246 textons, state dimension 12–15, observation dimension 60), against two
vectorised numpy implementations of the same computation, timed in the same run:

* ``numpy (same algorithm)``: a line-by-line numpy transcription of the JAX algorithm (centre
  the frames once, one GEMM ``Y [C | μ]`` per texton, whitened residual by three GEMMs with
  ``B⁻¹``, ``A1``, ``A2`` folded in, ``‖r‖² = ‖y − μ‖² − ‖x‖²``), looping over textons only;
* ``numpy (straightforward)``: the textbook formulation a user would write: per texton
  ``X = (Y − μ) C``, residual ``X_t − A1 X_{t−1} − A2 X_{t−2} − d``, a linear solve with
  ``B``, and ``‖Y − μ‖² − ‖X‖²``; also vectorised over frames, looping over textons only.

All three are checked equal (rtol 1e-9). Runs are interleaved (JAX, numpy, numpy, JAX, …) so
that background load on the shared machine affects all of them alike; medians are reported.
Compile time is reported separately: (a) AOT ``lower().compile()`` of the jitted call and
(b) the first public call minus the warm median. Writes ``benchmarks/results/frame_terms.md``
and ``frame_terms.json``.

Usage: ``python benchmarks/bench_frame_terms.py [--repeats 5] [--T 50000] ...``
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

from _machine import cpu_and_memory  # noqa: E402  (benchmarks/ is on sys.path)

try:
    from mtex_jax._texton import Texton, frame_terms
except ImportError:  # running from a source checkout without installation
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    from mtex_jax._texton import Texton, frame_terms

RESULTS = Path(__file__).resolve().parent / "results"


# --------------------------------------------------------------------------------------------
# data
# --------------------------------------------------------------------------------------------


def random_textons(rng: np.random.Generator, n: int, D: int, k: int) -> dict[str, np.ndarray]:
    """``n`` random valid textons (stable dynamics, PD covariances) as stacked numpy arrays."""
    C = np.linalg.qr(rng.standard_normal((n, D, k)))[0]
    A1 = rng.standard_normal((n, k, k)) / np.sqrt(k)
    A2 = 0.5 * rng.standard_normal((n, k, k)) / np.sqrt(k)
    for i in range(n):  # scale to spectral radius 0.95
        F = np.block([[A1[i], A2[i]], [np.eye(k), np.zeros((k, k))]])
        s = 0.95 / np.max(np.abs(np.linalg.eigvals(F)))
        A1[i] *= s
        A2[i] *= s * s
    tril = np.tril(0.05 * rng.standard_normal((n, k, k)), -1)
    B = tril + np.eye(k) * rng.uniform(0.1, 0.4, (n, k, 1))
    L0 = np.tril(0.1 * rng.standard_normal((n, 2 * k, 2 * k)), -1) + np.eye(2 * k)
    return dict(
        mu=0.3 * rng.standard_normal((n, D)),
        C=C,
        A1=A1,
        A2=A2,
        d=0.05 * rng.standard_normal((n, k)),
        B=B,
        sigma2=rng.uniform(0.01, 0.1, n),
        m0=rng.standard_normal((n, 2 * k)),
        S0=L0 @ np.swapaxes(L0, -1, -2),
    )


# --------------------------------------------------------------------------------------------
# numpy implementations
# --------------------------------------------------------------------------------------------

LOG_2PI = np.log(2 * np.pi)


def numpy_same_algorithm(p: dict[str, np.ndarray], Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Transcription of the JAX algorithm in numpy (vectorised over frames, loop over textons)."""
    n, D, k = p["C"].shape
    T = Y.shape[0]
    ybar = Y.mean(axis=0)
    Yc = Y - ybar
    yn = np.einsum("td,td->t", Yc, Yc)
    dyn = np.zeros((n, T))
    obs = np.empty((n, T))
    eye = np.eye(k)
    for i in range(n):
        C, B = p["C"][i], p["B"][i]
        mc = p["mu"][i] - ybar
        P = Yc @ np.concatenate([C, mc[:, None]], axis=1)
        X = P[:, :k] - mc @ C
        Binv = np.linalg.solve(B, eye)
        W = X[2:] @ Binv.T - X[1:-1] @ (Binv @ p["A1"][i]).T - X[:-2] @ (Binv @ p["A2"][i]).T
        W -= Binv @ p["d"][i]
        logdet = 2 * np.sum(np.log(np.diag(B)))
        dyn[i, 2:] = -0.5 * (k * LOG_2PI + logdet + np.einsum("tk,tk->t", W, W))
        r2 = np.maximum(yn - 2 * P[:, k] + mc @ mc - np.einsum("tk,tk->t", X, X), 0.0)
        s2 = p["sigma2"][i]
        obs[i] = -0.5 * ((D - k) * (LOG_2PI + np.log(s2)) + r2 / s2)
    return dyn, obs


def numpy_straightforward(p: dict[str, np.ndarray], Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Textbook formulation (vectorised over frames, loop over textons)."""
    n, D, k = p["C"].shape
    T = Y.shape[0]
    dyn = np.zeros((n, T))
    obs = np.empty((n, T))
    for i in range(n):
        Yc = Y - p["mu"][i]
        X = Yc @ p["C"][i]
        E = X[2:] - X[1:-1] @ p["A1"][i].T - X[:-2] @ p["A2"][i].T - p["d"][i]
        W = np.linalg.solve(p["B"][i], E.T)
        logdet = 2 * np.sum(np.log(np.diag(p["B"][i])))
        dyn[i, 2:] = -0.5 * (k * LOG_2PI + logdet + np.sum(W * W, axis=0))
        r2 = np.maximum(np.sum(Yc * Yc, axis=1) - np.sum(X * X, axis=1), 0.0)
        s2 = p["sigma2"][i]
        obs[i] = -0.5 * ((D - k) * (LOG_2PI + np.log(s2)) + r2 / s2)
    return dyn, obs


# --------------------------------------------------------------------------------------------
# timing
# --------------------------------------------------------------------------------------------


def _timed(fn: Any) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = fn()
    out = jax.block_until_ready(out)
    return time.perf_counter() - t0, out


def _timed_cpu(fn: Any) -> tuple[float, float]:
    """Wall time and process CPU time (all threads) of one call."""
    c0 = time.process_time()
    wall, _ = _timed(fn)
    return wall, time.process_time() - c0


def _openblas_setter() -> Any:
    """``set_num_threads`` of numpy's bundled OpenBLAS via ctypes, or ``None`` if not found."""
    import ctypes
    import glob

    libdir = Path(np.__file__).resolve().parent.parent / "numpy.libs"
    for lib_path in glob.glob(str(libdir / "*openblas*")):
        lib = ctypes.CDLL(lib_path)
        for name in ("scipy_openblas_set_num_threads64_", "openblas_set_num_threads"):
            if hasattr(lib, name):
                return getattr(lib, name)
    return None


def machine_info() -> dict[str, Any]:
    model, mem_gb = cpu_and_memory()
    blas = "unknown"
    try:
        cfg = np.show_config(mode="dicts")  # type: ignore[call-arg]
        blas = cfg["Build Dependencies"]["blas"]["name"]  # type: ignore[index]
    except Exception:
        pass
    return dict(
        cpu=model,
        cores=os.cpu_count(),
        memory_gb=round(mem_gb, 1),
        python=platform.python_version(),
        jax=jax.__version__,
        numpy=np.__version__,
        numpy_blas=blas,
        jax_backend=jax.default_backend(),
        platform=platform.platform(),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description="Benchmark mtex_jax frame_terms against numpy.")
    ap.add_argument("--T", type=int, default=50_000)
    ap.add_argument("--n-textons", type=int, default=246)
    ap.add_argument("--D", type=int, default=60)
    ap.add_argument("--k", type=int, default=15)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--chunk-size", type=int, default=1)
    ap.add_argument("--skip-straightforward", action="store_true")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    T, n, D, k = args.T, args.n_textons, args.D, args.k

    rng = np.random.default_rng(0)
    p = random_textons(rng, n, D, k)
    Y = np.cumsum(0.05 * rng.standard_normal((T, D)), axis=0) + rng.standard_normal(D)
    textons = Texton(**{name: jnp.asarray(v) for name, v in p.items()})
    Yj = jnp.asarray(Y)
    load_before = os.getloadavg()

    # --- compile time, measured two ways ---
    t0 = time.perf_counter()
    compiled = (
        jax.jit(lambda tex, y: frame_terms(tex, y, chunk_size=args.chunk_size))
        .lower(textons, Yj)
        .compile()
    )
    aot_compile = time.perf_counter() - t0
    first_call, (dyn_j, obs_j) = _timed(
        lambda: frame_terms(textons, Yj, chunk_size=args.chunk_size)
    )

    # --- correctness against both numpy versions ---
    dyn_n, obs_n = numpy_same_algorithm(p, Y)
    np.testing.assert_allclose(np.asarray(dyn_j), dyn_n, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(obs_j), obs_n, rtol=1e-9, atol=1e-9)
    max_abs_diff = float(
        max(np.max(np.abs(np.asarray(dyn_j) - dyn_n)), np.max(np.abs(np.asarray(obs_j) - obs_n)))
    )
    if not args.skip_straightforward:
        dyn_s, obs_s = numpy_straightforward(p, Y)
        np.testing.assert_allclose(dyn_s, dyn_n, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(obs_s, obs_n, rtol=1e-9, atol=1e-9)
    del dyn_n, obs_n

    # --- numpy's BLAS threads: OpenBLAS threads spin-wait and can collapse on a loaded
    # machine, so time the numpy baseline with the default threads and with one thread and
    # keep the faster setting (the conservative choice for the JAX speed-up) ---
    setter = _openblas_setter()
    blas_trial: dict[str, float] = {}
    blas_threads = "default"
    if setter is not None:
        blas_trial["default"] = _timed(lambda: numpy_same_algorithm(p, Y))[0]
        setter(1)
        blas_trial["1"] = _timed(lambda: numpy_same_algorithm(p, Y))[0]
        if blas_trial["1"] < blas_trial["default"]:
            blas_threads = "1"
        else:
            setter(os.cpu_count() or 1)

    # --- interleaved warm timings ---
    times: dict[str, list[float]] = {"jax": [], "jax_aot": [], "numpy_same": []}
    if not args.skip_straightforward:
        times["numpy_straightforward"] = []
    runs: dict[str, Any] = {
        "jax": lambda: frame_terms(textons, Yj, chunk_size=args.chunk_size),
        "jax_aot": lambda: compiled(textons, Yj),
        "numpy_same": lambda: numpy_same_algorithm(p, Y),
        "numpy_straightforward": lambda: numpy_straightforward(p, Y),
    }
    cpu_times: dict[str, list[float]] = {key: [] for key in times}
    for _ in range(args.repeats):
        for key in times:
            wall, cpu = _timed_cpu(runs[key])
            times[key].append(wall)
            cpu_times[key].append(cpu)
    load_after = os.getloadavg()

    med = {key: statistics.median(v) for key, v in times.items()}
    result: dict[str, Any] = dict(
        date=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        sizes=dict(T=T, n_textons=n, D=D, k=k, dtype="float64", chunk_size=args.chunk_size),
        compile_s=dict(
            aot_lower_compile=aot_compile, first_call_minus_warm=first_call - med["jax"]
        ),
        first_call_s=first_call,
        times_s=times,
        median_s=med,
        median_cpu_s={key: statistics.median(v) for key, v in cpu_times.items()},
        min_s={key: min(v) for key, v in times.items()},
        ratio_numpy_same_over_jax=med["numpy_same"] / med["jax"],
        max_abs_diff_vs_numpy=max_abs_diff,
        numpy_blas_threads=blas_threads,
        numpy_blas_thread_trial_s=blas_trial,
        load_average_before=load_before,
        load_average_after=load_after,
        machine=machine_info(),
    )
    mins = result["min_s"]
    result["ratio_min_numpy_same_over_min_jax"] = mins["numpy_same"] / mins["jax"]
    if "numpy_straightforward" in med:
        result["ratio_numpy_straightforward_over_jax"] = med["numpy_straightforward"] / med["jax"]
        result["ratio_min_numpy_straightforward_over_min_jax"] = (
            mins["numpy_straightforward"] / mins["jax"]
        )
    write_results(result, args.out)
    print(json.dumps({k: v for k, v in result.items() if k != "times_s"}, indent=2))


def _fmt_load(values: Any) -> str:
    return ", ".join(f"{x:.2f}" for x in values)


def write_results(r: dict[str, Any], out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "frame_terms.json").write_text(json.dumps(r, indent=2) + "\n")
    s, m, med = r["sizes"], r["machine"], r["median_s"]
    gflop = 2 * s["T"] * s["n_textons"] * (s["D"] * (s["k"] + 1) + 3 * s["k"] ** 2) / 1e9
    target_speed = r["ratio_numpy_same_over_jax"] >= 5.0
    target_time = med["jax"] < 5.0
    lines = [
        "# Benchmark: `frame_terms` (issue 3)",
        "",
        f"Generated by `benchmarks/bench_frame_terms.py` on {r['date']}.",
        "",
        "## Sizes",
        "",
        f"T = {s['T']:,} frames, N_t = {s['n_textons']} textons, D = {s['D']}, k = {s['k']}, "
        f"{s['dtype']}, textons per `lax.map` step = {s['chunk_size']}. Output: two "
        f"({s['n_textons']}, {s['T']:,}) arrays (dynamics and residual log-densities).",
        "",
        "## Results (seconds; median of interleaved runs)",
        "",
        "| what | median wall | best wall | median CPU (all threads) | all runs (wall) |",
        "| --- | ---: | ---: | ---: | --- |",
    ]
    names = {
        "jax": "JAX `frame_terms` (public call, incl. input checks)",
        "jax_aot": "JAX AOT-compiled executable",
        "numpy_same": "numpy, same algorithm",
        "numpy_straightforward": "numpy, straightforward formulation",
    }
    for key, label in names.items():
        if key in med:
            runs = ", ".join(f"{t:.3f}" for t in r["times_s"][key])
            cpu = r["median_cpu_s"][key]
            best = r["min_s"][key]
            lines.append(f"| {label} | {med[key]:.3f} | {best:.3f} | {cpu:.3f} | {runs} |")
    lines += [
        "",
        f"- Compile time: AOT `lower().compile()` {r['compile_s']['aot_lower_compile']:.2f} s; "
        f"first public call {r['first_call_s']:.2f} s = "
        f"{r['compile_s']['first_call_minus_warm']:.2f} s above the warm median.",
        f"- Speed-up over numpy (same algorithm): **{r['ratio_numpy_same_over_jax']:.2f}×** "
        f"(medians), {r['ratio_min_numpy_same_over_min_jax']:.2f}× (best runs).",
    ]
    if "ratio_numpy_straightforward_over_jax" in r:
        lines.append(
            "- Speed-up over numpy (straightforward): "
            f"**{r['ratio_numpy_straightforward_over_jax']:.2f}×** (medians), "
            f"{r['ratio_min_numpy_straightforward_over_min_jax']:.2f}× (best runs)."
        )
    lines += [
        f"- numpy BLAS threads used: {r['numpy_blas_threads']} (trial run, numpy same "
        f"algorithm: {r['numpy_blas_thread_trial_s']}); the faster setting is kept.",
        f"- Max |JAX − numpy| over all terms: {r['max_abs_diff_vs_numpy']:.2e} "
        "(checked to rtol 1e-9).",
        f"- Target ≥ 5× faster than numpy (same algorithm, medians): "
        f"{'met' if target_speed else '**not met**'}; target < 5 s (median): "
        f"{'met' if target_time else '**not met**'}.",
        "- The best runs are the closest to an unloaded machine; the medians include "
        "whatever the other processes on this shared machine were doing.",
        "",
        "## Notes",
        "",
        f"- Both implementations do the same ≈{gflop:.0f} GFLOP (per frame and texton: the "
        "projection "
        "`Y [C | μ]`, D·(k+1) multiply-adds, and the whitened residual, 3k² multiply-adds). "
        "XLA's CPU backend runs this program on one core here (CPU time ≈ wall time), so the "
        "JAX advantage comes from fusing the elementwise work into the GEMMs "
        "(one pass instead of several over each (T, k) array), not from threads.",
        "- numpy's OpenBLAS with its default 2 threads collapses when the shared 2-core "
        "machine is loaded (threads spin-wait), which is why the one-thread setting is kept "
        "when it is faster; on an idle machine the default setting may win.",
        "- Formulations tried for the JAX kernel (all checked equal): three slice-GEMMs fused "
        "with the reduction (used; fastest), one (k × 3k) GEMM then shifted adds, stacking "
        "`[x_t, x_{t−1}, x_{t−2}]` into one (3k × k) GEMM, folding the offset into the "
        "projection, several textons per projection GEMM (wider GEMM, but strided per-texton "
        "slices), time blocking for cache residency (≈10 % at best, within noise), "
        "`vmap` over textons (batched dots are slow on CPU) and splitting the textons into "
        "independent loops (no inter-op parallelism). None reached 5× over the numpy "
        "transcription; the flop count is the same on both sides, so 5× would need ≥ 5× "
        "the numpy kernel's efficiency on one core.",
        "",
        "## Machine",
        "",
        f"- CPU: {m['cpu']}, {m['cores']} cores, {m['memory_gb']} GB RAM; {m['platform']}",
        f"- Python {m['python']}, JAX {m['jax']} ({m['jax_backend']}), numpy {m['numpy']} "
        f"(BLAS: {m['numpy_blas']})",
        f"- Load average (1, 5, 15 min) before: {_fmt_load(r['load_average_before'])}; "
        f"after: {_fmt_load(r['load_average_after'])}. The machine is "
        "shared; runs were interleaved so that background load affects all variants alike.",
        "",
    ]
    (out / "frame_terms.md").write_text("\n".join(lines))


if __name__ == "__main__":
    main()
