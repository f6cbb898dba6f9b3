"""Benchmark: cleaning and editing synthesised salsa (issue 17).

On the quality benchmark's fixed split (``../shared/data/README.md``; loaded and judged exactly
as ``bench_quality.py`` does: the README's ``LearnConfig`` on the 10 training clips at 60 Hz,
``MotionJudge(train, held, fps)`` against the 4 held-out clips), in one run:

1. **Clean**: ``n`` constrained syntheses of 10 s (sampled noise), judged before and after
   :func:`mtex_jax.edit.clean` beside the real held-out clips (foot skating median/p95 over low
   steps, penetration below the training floor, acceleration/jerk W1 distances and their ratio
   to the real-vs-real floor), and the texture's log-likelihood per frame lost by cleaning
   (forward algorithm).
2. **Edit**: the right hand moved at frame m of each synthesis (10 cm forward, 5 cm up):
   error at the target and the decay curve (largest joint displacement against the distance
   in time from the edit).
3. **Time**: cleaning 10 s at 60 Hz (compile separately, then the median of repeats with
   ``block_until_ready``); one edit against a ``vmap`` batch of 16 (``edit_many``, per
   motion). The load average is recorded at the start, before the timings and at the end
   (the machine is shared).

Run: ``.venv/bin/python benchmarks/quality/bench_edit.py`` (``--quick`` for a smoke run). Writes
``benchmarks/results/edit.md`` and ``edit.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)  # the benchmark's choice; the library never does this
# one CPU device per core, so that edit_many can split its batch between them (the single edit
# and cleaning run on the first device as before); also the benchmark's choice
jax.config.update("jax_num_cpu_devices", os.cpu_count() or 1)

import numpy as np

import mtex_jax as mj
from mtex_jax import edit as E, metrics

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench_quality import FPS, HELD, TRAIN, load  # the same split, clips and frame rate

from _common import RESULTS as OUT, command

SECONDS = 10.0
DECAY_S = (0.0, 0.05, 0.1, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
KEYS = ("acceleration_ratio", "jerk_ratio", "skating_median", "skating_p95")
KEYS2 = ("penetration_max", "penetration_share", "acceleration_w1", "jerk_w1")


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def timed(fn) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    return time.perf_counter() - t0, out


def hand_edit(tex, syn, m: int, offset) -> tuple[Any, np.ndarray, np.ndarray]:
    fm = tex.feature_map
    j = fm.skeleton.index("rHand")
    sp, sh = fm.start_of(syn.motion)
    P0 = np.asarray(fm.joint_positions(syn.Y, sp, sh))
    target = P0[m, j] + np.asarray(offset)
    cons = E.make_constraints(fm.skeleton, syn.n_frames, fm.dim, positions=[("rHand", m, target)])
    return cons, P0, target


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a smoke run (2 syntheses, 1 repeat)")
    ap.add_argument("--n", type=int, default=4, help="syntheses to clean and edit")
    ap.add_argument("--repeats", type=int, default=3, help="timing repeats")
    args = ap.parse_args()
    n_syn, repeats = (2, 1) if args.quick else (args.n, args.repeats)
    res: dict[str, Any] = dict(
        command=command(),
        machine=dict(
            platform=platform.platform(),
            cpus=os.cpu_count(),
            load_start=os.getloadavg(),
            jax=jax.__version__,
            dtype="float64",
        ),
        split=dict(train=TRAIN, held_out=HELD),
        seconds=SECONDS,
        fps=FPS,
    )
    log("reading clips")
    train = [m.resample(FPS) for m in load(TRAIN)]
    held = [m.resample(FPS) for m in load(HELD)]
    cfg = mj.LearnConfig(tmin=60, tmax=180, state_dim=12, fps=FPS, min_segments=3)
    log("learning the motion texture (README settings)")
    t_learn, tex = timed(lambda: mj.learn(train, cfg))
    res["texture"] = dict(learn_s=t_learn, textons=tex.n_textons, obs_dim=tex.obs_dim)
    judge = metrics.MotionJudge(train, held, fps=FPS)
    contacts = judge.contacts  # fitted on the training clips only
    res["contacts"] = dict(
        feet=list(contacts.foot_names),
        height_threshold=contacts.height_threshold.tolist(),
        speed_threshold=contacts.speed_threshold.tolist(),
        floor=contacts.floor,
    )
    n = int(SECONDS * FPS)
    keys = jax.random.split(jax.random.key(2026), n_syn)
    log(f"synthesising {n_syn} x {SECONDS:.0f} s")
    syns = [mj.synthesize(k, tex, n_frames=n) for k in keys]

    # ------------------------------------------------------------------ clean
    log("cleaning (the first call compiles)")
    t_first, _ = timed(lambda: E.clean(tex, syns[0], contacts, loglik=False))
    cleaned, times = [], []
    for i, s in enumerate(syns):
        t, c = timed(lambda s=s: E.clean(tex, s, contacts))
        cleaned.append(c)
        times.append(t)
        log(f"  synthesis {i}: {t:.1f} s; {c.edit.report().splitlines()[0]}")
    real = judge.real_rows()["real (held out)"]
    before = judge.judge([s.motion for s in syns if s.motion is not None], copy=False)
    after = judge.judge([c.motion for c in cleaned], copy=False)
    res["clean"] = dict(
        real={k: real[k] for k in KEYS + KEYS2},
        before={k: before[k] for k in KEYS + KEYS2},
        after={k: after[k] for k in KEYS + KEYS2},
        loglik_before=[c.loglik_before for c in cleaned],
        loglik_after=[c.loglik_after for c in cleaned],
        loglik_lost_per_frame=float(np.mean([c.loglik_lost for c in cleaned])),
        converged=[bool(c.edit.converged) for c in cleaned],
        met=[bool(c.edit.met) for c in cleaned],
        plant_height_error=[float(c.edit.plant_height_error) for c in cleaned],
        steps=[int(c.edit.steps) for c in cleaned],
        used_bfgs=[bool(c.edit.used_bfgs) for c in cleaned],
        plant_slide=[float(c.edit.plant_slide) for c in cleaned],
        contact_share=[float(c.labels.mean()) for c in cleaned],
    )

    # ------------------------------------------------------------------ edit
    log("editing: the right hand 10 cm forward and 5 cm up at the middle frame")
    m = n // 2
    errors, decay = [], []
    for s in syns:
        cons, P0, target = hand_edit(tex, s, m, [0.10, 0.05, 0.0])
        r = E.edit(tex, s, cons)
        fm = tex.feature_map
        P = np.asarray(fm.joint_positions(r.Y, *fm.start_of(s.motion)))
        errors.append(float(np.linalg.norm(P[m, fm.skeleton.index("rHand")] - target)))
        moved = np.linalg.norm(P - P0, axis=-1).max(axis=1)
        dist = np.abs(np.arange(n) - m) / FPS
        decay.append([float(moved[dist >= d].max()) for d in DECAY_S])
    res["edit"] = dict(
        converged=[
            bool(E.edit(tex, s, hand_edit(tex, s, m, [0.10, 0.05, 0.0])[0]).converged) for s in syns
        ],
        frame=m,
        offset_m=[0.10, 0.05, 0.0],
        error_m=errors,
        decay_s=list(DECAY_S),
        decay_max_m=np.max(np.array(decay), axis=0).tolist(),
    )

    # ------------------------------------------------------------------ time
    log("timing: clean of 10 s, one edit, a batch of 16 (edit_many) edits")
    res["machine"]["load_timing"] = os.getloadavg()
    clean_t = [
        timed(lambda: E.clean(tex, syns[0], contacts, loglik=False))[0] for _ in range(repeats)
    ]
    cons, _, _ = hand_edit(tex, syns[0], m, [0.10, 0.05, 0.0])
    t_edit_first, _ = timed(lambda: E.edit(tex, syns[0], cons).Y)
    edit_t = [timed(lambda: E.edit(tex, syns[0], cons).Y)[0] for _ in range(repeats)]
    batch = [syns[i % n_syn] for i in range(16)]
    bcons = [hand_edit(tex, s, m - 5 * i, [0.10, 0.05, 0.0])[0] for i, s in enumerate(batch)]
    t_batch_first, _ = timed(lambda: E.edit_many(tex, batch, bcons).Y)
    batch_out: list[Any] = []
    batch_t = []
    for _ in range(max(1, repeats - 1)):  # a batch call takes about half a minute
        t, out = timed(lambda: E.edit_many(tex, batch, bcons))
        batch_t.append(t)
        batch_out = [out]
    first = jax.devices()[:1]  # the same batch as one vmap on one device
    t_one_dev_first, _ = timed(lambda: E.edit_many(tex, batch, bcons, devices=first).Y)
    one_dev_t = [
        timed(lambda: E.edit_many(tex, batch, bcons, devices=first).Y)[0]
        for _ in range(max(1, repeats - 1))
    ]
    res["time"] = dict(
        clean_first_call_s=t_first,
        clean_s_median=float(np.median(clean_t)),
        clean_s_all=clean_t,
        clean_per_synthesis_s=times,
        edit_first_call_s=t_edit_first,
        edit_s_median=float(np.median(edit_t)),
        batch16_first_call_s=t_batch_first,
        batch16_s_median=float(np.median(batch_t)),
        batch16_per_motion_s=float(np.median(batch_t)) / 16,
        batch16_converged=int(np.sum(np.asarray(batch_out[0].converged))),
        devices=len(jax.devices()),
        batch16_one_device_first_call_s=t_one_dev_first,
        batch16_one_device_s_median=float(np.median(one_dev_t)),
        batch16_one_device_per_motion_s=float(np.median(one_dev_t)) / 16,
        batch16_repeats=len(batch_t),
        frames=n,
        obs_dim=tex.obs_dim,
        repeats=repeats,
    )
    log("anatomy of a Gauss-Newton step: one edit against a batch of 16, per motion")
    res["anatomy"] = anatomy(tex, syns[0], cons, repeats=repeats)
    res["time"]["edit_steps"] = int(E.edit(tex, syns[0], cons).steps)
    res["time"]["batch16_steps"] = np.asarray(batch_out[0].steps).tolist()
    res["machine"]["load_end"] = os.getloadavg()
    OUT.mkdir(parents=True, exist_ok=True)
    name = "edit_quick" if args.quick else "edit"
    from mtex_jax.core import atomic_write

    with atomic_write(OUT / f"{name}.json", "w") as f:
        json.dump(res, f, indent=1)
    with atomic_write(OUT / f"{name}.md", "w") as f:
        f.write(report(res))
    log(f"wrote {OUT / name}.md")


def anatomy(tex, syn, cons, batch: int = 16, repeats: int = 3) -> dict[str, Any]:
    """Where a Gauss–Newton step's time goes, for one edit and per motion of a ``vmap`` batch.

    Times (compiled, median of ``repeats``) the step's two big parts on the edit's own
    shapes: the per-frame Jacobians (coloured tangents, as the solver, and one tangent per
    channel) and the block Cholesky solve of the normal equations."""
    from mtex_jax.edit._api import check_constraints, kept_channels, observations_of, segments_of
    from mtex_jax.edit._banded import _normal_solve
    from mtex_jax.edit._jacobians import (
        channel_colouring,
        frame_jacobians,
        kept_positions,
        root_free_channels,
    )
    from mtex_jax.edit._prior import WhitenedTextons, prior_hessian, smoothness_hessian
    from mtex_jax.edit._solve import problem

    fm = tex.feature_map
    Y, sp, sh = observations_of(tex, syn, None, None)
    cons = check_constraints(cons, Y, fm)
    w = E.EditWeights()
    tx = WhitenedTextons.of(tex.textons, Y.dtype)
    seg = segments_of(tex, syn)
    prob = problem(fm, tx, seg, Y, sp, sh, cons, w, True, kept_channels(cons, fm, None))
    free = jnp.asarray(root_free_channels(fm), Y.dtype)
    col = channel_colouring(fm, prob.keep)
    T, D = Y.shape
    pr, sm = prior_hessian(tx, seg, Y.dtype), smoothness_hessian(T, D, Y.dtype)
    bands = tuple(w.prior**2 * pr[i] + w.smooth**2 * sm[i] for i in range(3))
    solve_args = (*bands, w.anchor * jnp.ones(D), cons.pose_mask, jnp.zeros_like(Y), Y, True)

    def pos(y, a, b):
        return kept_positions(fm, prob.sub, prob.keep, y, a, b)

    parts: dict[str, Any] = {
        "jacobians (coloured)": (
            lambda y, a, b: frame_jacobians(lambda v: pos(v, a, b), y, free, col),
            (Y, sp, sh),
        ),
        "jacobians (one tangent per channel)": (
            lambda y, a, b: frame_jacobians(lambda v: pos(v, a, b), y, free),
            (Y, sp, sh),
        ),
        "block Cholesky solve": (_normal_solve, solve_args),
    }
    stack = lambda args: tuple(jnp.stack([a] * batch) for a in args)
    out: dict[str, Any] = dict(colours=col.n_colours, channels=D, batch=batch)

    def median_time(f, args) -> float:
        timed(lambda: f(*args))  # compiles
        return float(np.median([timed(lambda: f(*args))[0] for _ in range(repeats)]))

    for name, (fn, args) in parts.items():
        t1 = median_time(jax.jit(fn), args)
        tb = median_time(jax.jit(jax.vmap(fn)), stack(args))
        out[name] = dict(single_s=t1, batch_per_motion_s=tb / batch)
        log(f"  {name}: one {t1:.3f} s, batch of {batch} {tb / batch:.3f} s per motion")
    return out


def report(r: dict[str, Any]) -> str:
    c, t, e = r["clean"], r["time"], r["edit"]
    fmt = lambda v: "—" if v is None else f"{v:.3g}"
    od = t.get("batch16_one_device_per_motion_s")
    one_dev_s = "—" if od is None else f"{od:.2f}"
    one_dev_ratio = "—" if od is None else f"{t['edit_s_median'] / max(od, 1e-9):.2f}"
    lines = [
        "# Editing and cleaning (issue 17)",
        "",
        f"Made by: `{r.get('command', 'python benchmarks/quality/bench_edit.py')}`",
        "",
        f"One run; {r['machine']['platform']}, "
        f"{r['machine']['cpus']} CPUs, 1-minute load average {r['machine']['load_start'][0]:.1f} "
        f"at the start, {r['machine']['load_timing'][0]:.1f} before the timings and "
        f"{r['machine']['load_end'][0]:.1f} at the end (shared machine); float64. Texture: the "
        f"README's settings on the 10 training clips at {r['fps']:g} Hz "
        f"({r['texture']['textons']} textons, D = {r['texture']['obs_dim']}); "
        f"{len(c['converged'])} syntheses of {r['seconds']:g} s; judged by `MotionJudge` "
        "against the 4 held-out clips; contacts fitted on the training clips "
        f"(feet {', '.join(r['contacts']['feet'])}, floor {r['contacts']['floor']:.4f} m).",
        "",
        "## Clean",
        "",
        "| set | acc ratio | jerk ratio | skating median (m/s) | skating p95 (m/s) | "
        "deepest below floor (m) | frames below |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, row in (
        ("real, held out", c["real"]),
        ("raw synthesis", c["before"]),
        ("cleaned", c["after"]),
    ):
        lines.append(
            f"| {name} | {fmt(row['acceleration_ratio'])} | {fmt(row['jerk_ratio'])} | "
            f"{fmt(row['skating_median'])} | {fmt(row['skating_p95'])} | "
            f"{fmt(row['penetration_max'])} | {fmt(row['penetration_share'])} |"
        )
    sk_m = c["after"]["skating_median"] / c["real"]["skating_median"]
    sk_p = c["after"]["skating_p95"] / c["real"]["skating_p95"]
    lines += [
        "",
        f"Skating after cleaning / real: median {sk_m:.2f}x, p95 {sk_p:.2f}x (target <= 1.5x). "
        f"Log-likelihood per frame (forward algorithm): before "
        f"{np.mean(c['loglik_before']):.2f}, after {np.mean(c['loglik_after']):.2f}; lost "
        f"{c['loglik_lost_per_frame']:.3f} nats per frame. Solver (banded Gauss–Newton, "
        "root trajectory free as a smooth offset; converged = a step lowered the cost by "
        f"less than 0.1 %): converged {sum(c['converged'])} of {len(c['converged'])} (steps "
        f"{c['steps']}, cap 12); plants and floor met to 1 mm in {sum(c['met'])}; largest "
        f"planted-foot speed after {max(c['plant_slide']):.3g} m/s, largest plant height "
        f"error {1e3 * max(c['plant_height_error']):.1f} mm; share of (step, foot) planted "
        f"{np.mean(c['contact_share']):.2f}.",
        "",
        f"## Edit: right hand +10 cm forward, +5 cm up at frame {e['frame']}",
        "",
        f"Error at the target: {', '.join(f'{1e3 * v:.3f} mm' for v in e['error_m'])}; "
        f"solver converged in {sum(e['converged'])} of {len(e['converged'])}.",
        "",
        "| at least this far from the edit (s) | "
        + " | ".join(f"{d:g}" for d in e["decay_s"])
        + " |",
        "| --- | " + " | ".join("---:" for _ in e["decay_s"]) + " |",
        "| largest joint displacement (mm) | "
        + " | ".join(f"{1e3 * v:.3g}" for v in e["decay_max_m"])
        + " |",
        "",
        "## Time",
        "",
        f"Cleaning {r['seconds']:g} s at {r['fps']:g} Hz ({t['frames']} frames, D = "
        f"{t['obs_dim']}): first call {t['clean_first_call_s']:.1f} s (compiles), then median "
        f"{t['clean_s_median']:.2f} s over {t['repeats']} repeats (target <= 5 s); per "
        f"synthesis {', '.join(f'{v:.1f}' for v in t['clean_per_synthesis_s'])} s (with the "
        "two likelihood passes). One hand edit: first call "
        f"{t['edit_first_call_s']:.1f} s, then {t['edit_s_median']:.2f} s. A batch of 16 "
        f"edits (`edit_many`) split between the {t.get('devices', 1)} CPU devices "
        "(`jax_num_cpu_devices` = cores; each device a `vmap` of 8, the block Cholesky "
        "factorisations one motion after the other inside it): first call "
        f"{t['batch16_first_call_s']:.1f} s, then (median of {t['batch16_repeats']}) "
        f"{t['batch16_s_median']:.2f} s = **{t['batch16_per_motion_s']:.2f} s per motion** "
        f"(one edit's time / the batch's time per motion = "
        f"**{t['edit_s_median'] / max(t['batch16_per_motion_s'], 1e-9):.2f}**; "
        f"{t['batch16_converged']} of 16 converged). The same batch as one `vmap` on one "
        f"device: {one_dev_s} s per motion (ratio {one_dev_ratio}). Gauss–Newton steps: the edit "
        f"{t['edit_steps']}; the batch runs until its slowest member stops "
        f"(steps {min(t['batch16_steps'])}–{max(t['batch16_steps'])}).",
        "",
    ]
    a = r.get("anatomy")
    if a:
        lines += [
            "### Anatomy of a Gauss–Newton step (compiled, median of repeats)",
            "",
            f"The edit's shapes ({t['frames']} frames, D = {a['channels']}; "
            f"{a['colours']} coloured tangents); a batch of {a['batch']} copies under `vmap`.",
            "",
            "| part | one motion (s) | batch, per motion (s) |",
            "| --- | ---: | ---: |",
        ]
        for name, v in a.items():
            if isinstance(v, dict):
                lines.append(f"| {name} | {v['single_s']:.3f} | {v['batch_per_motion_s']:.3f} |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
