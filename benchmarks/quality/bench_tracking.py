"""Benchmark: monocular 3-D tracking on the fixed held-out split, both priors (design §12).

The split is ``mtex_jax.io.salsa_split()``: 10 training clips, 4 held out. Every clip is
resampled to 30 Hz. Both priors are learned on the training clips only, with their documented
settings (nothing here is tuned, and no tracker option is chosen on the held-out clips):

* the texture: ``mtex_jax.learn(train, LearnConfig(fps=30.0))``;
* the implicit model: ``mtex_jax.implicit.learn(train, window=10, recent_weight=0.0)``
  (the paper's window distance, which ``learn``'s docstring recommends for tracking).

Data: every held-out clip, 150 tracked frames, the 17 default joints through the default
camera of :func:`mtex_jax.tracking.make_problem` (1000 px, 4 m). The problem is made once per
clip and setting (``jax.random.key(i)`` for clip ``i``), and the two priors track the *same*
frames from the same observations: the implicit problem starts at frame 30 (its window of 10
pose vectors takes frames 30–40, so frames 41–190 are tracked); the texture's problem is the
same problem with the texture's window of 2 observation vectors (frames 38–40) in place of
the implicit one (``make_problem(..., start=38)`` gives that window and the same start state,
checked). Three
settings: *easy* (the defaults: 2 px Gaussian noise), *hard* (``missing=0.1,
outliers=0.05, bone_scale=(0.9, 1.1)``) and *hard, skeleton given* (the hard problems with
``known_bones=True``: the person's drawn bones given to the trackers, which then keep them;
rows: the texture's batch and fixed-lag smoothers and the Gauss–Newton particle filter). The
last separates what the unknown body costs, a size one camera cannot measure, from what the
missing joints and the outliers cost.

Rows (every one through ``mtex_jax.tracking.track``):

* texture MAP, batch: ``MapSmoother()`` (hard: ``bones=True``);
* texture MAP, fixed-lag: ``MapSmoother(lag=10)`` (hard: ``bones=True``);
* implicit particle filter (SBS, the paper's bootstrap filter): ``ParticleFilter(300)``;
* the same with the Gauss–Newton proposal: ``ParticleFilter(300, proposal="gauss_newton")``
  ("not available" when the installed ``ParticleFilter`` has no such option);
* constant-velocity particle filter: ``ParticleFilter(300, dynamics="constant_velocity")``
  (same database statistics, no database search);
* smoothness-only MAP: ``MapSmoother(prior=SmoothPrior())`` (hard: ``bones=True``, so that it
  differs from the texture's batch row only in the prior).

Columns: mean joint error, global (MPJPE in world coordinates), root-relative and after
Procrustes alignment (PA-MPJPE), mm, averaged over the 4 clips (each clip's mean over its
frames); the worst frame (global error, max over frames and clips); the first call
(compilation and the first clip) apart; tracked frames per second warm: every clip's call timed
with ``jax.block_until_ready`` on the result arrays, frames / median wall time. Per-clip rows,
the targets, the machine and its load go to the JSON.

Run: ``.venv/bin/python benchmarks/quality/bench_tracking.py`` (``--quick --out-dir /tmp/x``:
one clip, a smoke run kept out of the results folder). Writes ``benchmarks/results/tracking.md``,
``tracking.json`` and ``tracking_error.png`` (error per frame of every row on the first
held-out clip, easy setting).

The results page draws the per-frame plot from ``tracking.json`` (``tools/results_page.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import equinox as eqx
import jax

jax.config.update("jax_enable_x64", True)  # the benchmark's choice; the library never does this

import numpy as np

import mtex_jax as mj
from mtex_jax import tracking as T
from mtex_jax.io import load_salsa, salsa_split

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import REPO, RESULTS, command, cpu_and_memory

try:  # exported by the package, or still private
    from mtex_jax.tracking import MapSmoother
except ImportError:
    from mtex_jax.tracking._smoother import MapSmoother
try:
    from mtex_jax.tracking import SmoothPrior
except ImportError:
    from mtex_jax.tracking._priors import SmoothPrior

FPS = 30.0
WINDOW = 10  # the implicit model's window (the paper's, at 30 Hz)
N_FRAMES = 150
START = 30  # the implicit problem's first frame; the texture's starts WINDOW - 2 later
TEX_WINDOW = 2
N_PARTICLES = 300
LAG = 10
PROPOSAL = "gauss_newton"
HARD = dict(missing=0.1, outliers=0.05, bone_scale=(0.9, 1.1))
GIVEN = "hard, skeleton given"
SETTINGS = {"easy": {}, "hard": HARD, GIVEN: dict(HARD, known_bones=True)}
TITLES = {
    "easy": "Easy (2 px noise)",
    "hard": "Hard (missing 0.1, outliers 0.05, bones 0.9–1.1)",
    GIVEN: "Hard, the person's skeleton given (the same problems, the drawn bones known)",
}

B_TEX = "texture MAP, batch"
B_LAG = f"texture MAP, fixed-lag (L = {LAG})"
B_PF = f"implicit PF (SBS, bootstrap), {N_PARTICLES}"
B_GN = f"implicit PF, Gauss–Newton proposal, {N_PARTICLES}"
B_CV = f"constant-velocity PF, {N_PARTICLES}"
B_SM = "smoothness-only MAP, batch"


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def proposal_available() -> tuple[bool, str]:
    """Whether the installed ``ParticleFilter`` takes ``proposal=PROPOSAL``."""
    try:
        T.ParticleFilter(n_particles=N_PARTICLES, proposal=PROPOSAL)
    except (TypeError, ValueError) as e:
        return False, f"{type(e).__name__}: {e}"
    return True, ""


def methods(setting: str, with_proposal: bool) -> dict[str, tuple[str, Any]]:
    """Row name -> (prior type, tracker) of one setting (``None``: not available); the setting
    with the skeleton given keeps the rows that can use it, with the bones fixed."""
    gn = T.ParticleFilter(n_particles=N_PARTICLES, proposal=PROPOSAL) if with_proposal else None
    if setting == GIVEN:
        return {
            B_TEX: ("texture", MapSmoother()),
            B_LAG: ("texture", MapSmoother(lag=LAG)),
            B_GN: ("implicit", gn),
        }
    hard = setting == "hard"
    return {
        B_TEX: ("texture", MapSmoother(bones=hard)),
        B_LAG: ("texture", MapSmoother(lag=LAG, bones=hard)),
        B_PF: ("implicit", T.ParticleFilter(n_particles=N_PARTICLES)),
        B_GN: ("implicit", gn),
        B_CV: ("implicit", T.ParticleFilter(n_particles=N_PARTICLES, dynamics="constant_velocity")),
        B_SM: ("texture", MapSmoother(prior=SmoothPrior(), bones=hard)),
    }


def make_problems(
    i: int, clip: mj.Motion, tex: Any, imp: Any, kw: dict[str, Any]
) -> dict[str, T.TrackingProblem]:
    """The texture's and the implicit model's problems of one clip: the same key and the same
    tracked frames; the texture's is the implicit one with the texture's initial window (and
    checked to start from the same state), so that the two differ only in the window.

    (``make_problem`` with ``bone_scale`` lifts the body by a median over the whole slice it
    reads, initial window included, so two problems made for the two priors would differ by
    a few mm in the truth's height; taking the one problem avoids that.)"""
    key = jax.random.key(i)
    p_imp = T.make_problem(key, imp, clip, n_frames=N_FRAMES, start=START, **kw)
    made = T.make_problem(
        key, tex, clip, n_frames=N_FRAMES, start=START + WINDOW - TEX_WINDOW, **kw
    )
    assert made.frames == p_imp.frames and made.joints == p_imp.joints, "problems differ"
    for name in ("init_position", "init_heading"):
        a, b = np.asarray(getattr(made, name)), np.asarray(getattr(p_imp, name))
        assert np.array_equal(a, b), f"the two problems' {name} differ"
    p_tex = eqx.tree_at(lambda p: p.init_window, p_imp, made.init_window)
    return {"texture": p_tex, "implicit": p_imp}


def run_once(method: Any, prior: Any, problem: T.TrackingProblem, key: Any) -> tuple[float, Any]:
    t0 = time.perf_counter()
    res = T.track(key, prior, problem, method)
    jax.block_until_ready(
        (res.mean_joints, res.mean_pose, res.mean_root, res.error, res.error_root_relative)
    )
    return time.perf_counter() - t0, res


def clip_row(res: Any, wall: float) -> dict[str, Any]:
    e = np.asarray(res.error) * 1000
    r = np.asarray(res.error_root_relative) * 1000
    a = np.asarray(res.error_aligned) * 1000
    out = dict(
        global_mm=float(e.mean()),
        root_relative_mm=float(r.mean()),
        aligned_mm=float(a.mean()),
        worst_frame_mm=float(e.max()),
        worst_frame_root_relative_mm=float(r.max()),
        median_frame_mm=float(np.median(e)),
        last_30_frames_mm=float(e[-30:].mean()),
        wall_s=wall,
        finite=bool(np.isfinite(e).all()),
    )
    if res.ess is not None:
        out["ess_mean"] = float(np.mean(np.asarray(res.ess)))
    if res.bone_scale is not None:
        b = np.asarray(res.bone_scale)
        out["bone_scale_range"] = [float(b.min()), float(b.max())]
    if res.labels is not None:
        out["textons_used"] = int(np.unique(np.asarray(res.labels)).size)
    return out


def summarise(per_clip: list[dict[str, Any]], first_s: float) -> dict[str, Any]:
    walls = [c["wall_s"] for c in per_clip]
    med = float(np.median(walls))
    return dict(
        global_mm=float(np.mean([c["global_mm"] for c in per_clip])),
        root_relative_mm=float(np.mean([c["root_relative_mm"] for c in per_clip])),
        aligned_mm=float(np.mean([c["aligned_mm"] for c in per_clip])),
        worst_frame_mm=float(np.max([c["worst_frame_mm"] for c in per_clip])),
        first_call_s=first_s,
        median_wall_s=med,
        frames_per_s=N_FRAMES / med,
        clips=len(per_clip),
    )


def targets(rows: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The targets, each PASS, FAIL or n/a (a row missing)."""
    out: list[dict[str, Any]] = []

    def get(setting: str, row: str, field: str) -> float | None:
        s = rows.get(setting, {}).get(row, {}).get("summary")
        return None if not s else s.get(field)

    def check(name: str, value: float | None, limit: float | None, le: bool, unit: str) -> None:
        if value is None or limit is None:
            out.append(dict(target=name, status="n/a", value=value, limit=limit, unit=unit))
            return
        ok = value <= limit if le else value >= limit
        out.append(
            dict(target=name, status="PASS" if ok else "FAIL", value=value, limit=limit, unit=unit)
        )

    e_batch = get("easy", B_TEX, "global_mm")
    check("easy: texture MAP batch, global ≤ 50 mm", e_batch, 50.0, True, "mm")
    check(
        "easy: texture MAP batch, root-relative ≤ 30 mm",
        get("easy", B_TEX, "root_relative_mm"),
        30.0,
        True,
        "mm",
    )
    for s in ("easy", "hard"):
        b = get(s, B_TEX, "global_mm")
        check(
            f"{s}: fixed-lag global ≤ 1.3 × batch",
            get(s, B_LAG, "global_mm"),
            None if b is None else 1.3 * b,
            True,
            "mm",
        )
    check(
        "hard: texture MAP batch global ≤ 1.5 × easy",
        get("hard", B_TEX, "global_mm"),
        None if e_batch is None else 1.5 * e_batch,
        True,
        "mm",
    )
    for s in ("easy", "hard"):
        check(
            f"{s}: PF with the Gauss–Newton proposal, global ≤ 150 mm",
            get(s, B_GN, "global_mm"),
            150.0,
            True,
            "mm",
        )
    for s in ("easy", "hard"):
        check(
            f"{s}: fixed-lag ≥ 30 tracked frames/s (warm)",
            get(s, B_LAG, "frames_per_s"),
            30.0,
            False,
            "frames/s",
        )
    for s in ("easy", "hard"):
        check(
            f"{s}: batch MAP, a {N_FRAMES}-frame clip ≤ 3 s (warm, median)",
            get(s, B_TEX, "median_wall_s"),
            3.0,
            True,
            "s",
        )
    return out


def target_line(t: dict[str, Any]) -> str:
    v, lim = t["value"], t["limit"]
    vs = "—" if v is None else f"{v:.1f}" if t["unit"] != "s" else f"{v:.2f}"
    ls = "—" if lim is None else f"{lim:.1f}" if t["unit"] != "s" else f"{lim:.2f}"
    return f"{t['status']}: {t['target']} — {vs} {t['unit']} (limit {ls})"


def plot(curves: dict[str, np.ndarray], frames: list[int], clip: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mtex_jax.core import atomic_write

    fig, ax = plt.subplots(figsize=(8.0, 4.4), dpi=110)
    styles = {
        B_TEX: dict(color="C0", lw=1.6),
        B_LAG: dict(color="C0", lw=1.2, ls="--"),
        B_SM: dict(color="C7", lw=1.2),
        B_PF: dict(color="C1", lw=1.2),
        B_GN: dict(color="C3", lw=1.4),
        B_CV: dict(color="C2", lw=1.0),
    }
    for name, ys in curves.items():
        ax.plot(frames[: len(ys)], ys, label=name, **styles.get(name, {}))
    ax.set_yscale("log")
    ax.set_xlabel(f"frame of {clip} (30 Hz)")
    ax.set_ylabel("mean joint error, world (mm, log scale)")
    ax.set_title(f"Tracking error per frame, held-out clip {clip}, easy setting (2 px noise)")
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=3, frameon=False)
    fig.tight_layout()
    with atomic_write(path, "wb") as f:
        fig.savefig(f, format="png", metadata={"Software": None})
    plt.close(fig)


def report(res: dict[str, Any]) -> str:
    L = [
        "# Tracking on the held-out split",
        "",
        f"Made by: `{res['command']}`",
        "",
        f"Machine: {res['machine']['cpu']}, {res['machine']['cpus']} cores, "
        f"Python {res['machine']['python']}, JAX {res['machine']['jax']}, float64; load "
        f"average {res['machine']['load_before'][0]:.1f} at the start, "
        f"{res['machine']['load_after'][0]:.1f} at the end (the machine is shared: wall "
        f"times are approximate). Library at commit `{res['git']['commit'][:10]}`"
        + (
            f" with uncommitted changes to {', '.join(res['git']['dirty'])}"
            if res["git"]["dirty"]
            else ""
        )
        + f". One run, {res['total_s']:.0f} s in all; raw numbers in `tracking.json`.",
        "",
        f"Priors learned on the {len(res['split']['train'])} training clips at 30 Hz: the "
        f"texture (`LearnConfig(fps=30.0)`, {res['priors']['texture']['textons']} textons, "
        f"{res['priors']['texture']['learn_s']:.0f} s) and the implicit model (window 10, "
        f"`recent_weight=0`, {res['priors']['implicit']['windows']:,} windows, "
        f"{res['priors']['implicit']['learn_s']:.0f} s). Tracked: the held-out clips "
        f"{', '.join(res['split']['held_out'])}, {N_FRAMES} frames each (frames "
        f"{res['frames'][0]}–{res['frames'][-1]} at 30 Hz), {res['joints']} joints through "
        "the default camera of `make_problem` (1000 px, 4 m away). Both priors see the same "
        "observations (same key per clip, same frames). Easy: 2 px noise; hard: also 10 % of "
        "the joints missing, 5 % outliers (50–200 px off, full confidence) and every bone "
        "scaled by a factor in [0.9, 1.1] (the MAP rows estimate the bones: `bones=True`). "
        "Hard, skeleton given: the hard problems with the person's drawn bones given to the "
        "trackers (`make_problem(..., known_bones=True)`: a skeleton measured beforehand), "
        "which separates what the unknown body costs from what the missing joints and the "
        "outliers cost. Nothing was tuned on these clips.",
        "",
        f"Errors: mean over the {res['clips']} clips of each clip's mean joint error (mm): "
        "global (world coordinates), root-relative, PA-MPJPE (after the best similarity per "
        "frame); worst: "
        "the largest frame's global error over all clips. First call: compilation and the "
        f"first clip. Frames/s: {N_FRAMES} tracked frames over the median wall time of the "
        f"{res['clips']} warm calls (one per clip, the first clip again included).",
        "",
    ]
    for s in SETTINGS:
        L += [
            f"## {TITLES[s]}",
            "",
            "| tracker | global (mm) | root-relative (mm) | PA-MPJPE (mm) | worst frame (mm) "
            "| first call (s) | warm per clip (s) | frames/s |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for name, row in res["rows"][s].items():
            sm = row.get("summary")
            if sm is None:
                L.append(f"| {name} | not available | | | | | | |")
                continue
            L.append(
                f"| {name} | {sm['global_mm']:.1f} | {sm['root_relative_mm']:.1f} "
                f"| {sm['aligned_mm']:.1f} | {sm['worst_frame_mm']:.0f} "
                f"| {sm['first_call_s']:.1f} | {sm['median_wall_s']:.2f} "
                f"| {sm['frames_per_s']:.0f} |"
            )
        L.append("")
    L += ["## Per clip (global error, mm)", ""]
    for s in SETTINGS:
        names = [n for n, r in res["rows"][s].items() if r.get("summary")]
        L += [
            f"{TITLES[s]}:",
            "",
            "| clip | " + " | ".join(names) + " |",
            "| --- |" + " ---: |" * len(names),
        ]
        for j, clip in enumerate(res["split"]["held_out"][: res["clips"]]):
            vals = [res["rows"][s][n]["per_clip"][j]["global_mm"] for n in names]
            L.append(f"| {clip} | " + " | ".join(f"{v:.1f}" for v in vals) + " |")
        L.append("")
    L += ["## Targets", ""]
    L += [f"- {target_line(t)}" for t in res["targets"]]
    L.append("")
    if res.get("notes"):
        L += ["## Notes", ""] + [f"- {n}" for n in res["notes"]] + [""]
    L += [
        f"The error per frame of every row on {res['plot']['clip']} (easy) is plotted in "
        "`benchmarks/results/tracking_error.png`.",
        "",
    ]
    return "\n".join(L)


def derived_notes(res: dict[str, Any]) -> list[str]:
    """Observations read off the run's numbers (not targets)."""
    rows, notes = res["rows"], []
    for s in SETTINGS:
        for name, row in rows[s].items():
            bad = [c["clip"] for c in row.get("per_clip", []) if not c["finite"]]
            if bad:
                notes.append(f"{s}: {name}: non-finite errors on {', '.join(bad)}")
    used = [c.get("textons_used") for s in SETTINGS for c in rows[s][B_TEX].get("per_clip", [])]
    if used and all(u == 1 for u in used):
        notes.append(
            f"The texture's MAP (batch) segments every {N_FRAMES}-frame estimate as a single "
            f"texton (of {res['priors']['texture']['textons']}): `LearnConfig(fps=30.0)` keeps "
            "the default segment lengths in frames (`tmin=60`, `tmax=180`: 2–6 s at 30 Hz)."
        )
    lag_hard = rows["hard"].get(B_LAG, {}).get("per_clip", [])
    ranges = [c.get("bone_scale_range") for c in lag_hard]
    if ranges and all(r is not None and r[0] == r[1] == 1.0 for r in ranges):
        notes.append(
            "The fixed-lag smoother's hard row returns bone scales of exactly 1 on every clip: "
            "with a known initial window it does not estimate the bones (only the batch solve "
            "of its first frames does, when the initial state is unknown), so it tracks with "
            "the model's bones although `bones=True`."
        )
    return notes


def git_state() -> dict[str, Any]:
    def run(*a: str) -> str:
        try:
            return subprocess.run(
                ["git", *a], cwd=REPO, capture_output=True, text=True, check=False
            ).stdout
        except OSError:
            return ""

    dirty = [ln[3:] for ln in run("status", "--porcelain", "--", "src").splitlines() if ln.strip()]
    return dict(commit=run("rev-parse", "HEAD").strip(), dirty=dirty)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: one clip")
    ap.add_argument("--out-dir", type=Path, default=RESULTS, help="where the outputs go")
    args = ap.parse_args()
    t_start = time.perf_counter()
    cpu, mem = cpu_and_memory()
    res: dict[str, Any] = dict(
        command=command(),
        machine=dict(
            python=platform.python_version(),
            jax=jax.__version__,
            cpus=os.cpu_count(),
            cpu=cpu,
            memory_gb=mem,
            load_before=os.getloadavg(),
        ),
        git=git_state(),
    )
    train_names, held_names = salsa_split()
    n_clips = 1 if args.quick else len(held_names)
    res["split"] = dict(train=train_names, held_out=held_names)
    res["clips"] = n_clips
    log("reading the clips (30 Hz)")
    train = [load_salsa(n).resample(FPS) for n in train_names]
    held = [load_salsa(n).resample(FPS) for n in held_names][:n_clips]

    log("learning the texture on the training clips (LearnConfig(fps=30.0))")
    t0 = time.perf_counter()
    tex = mj.learn([load_salsa(n) for n in train_names], mj.LearnConfig(fps=FPS))
    t_tex = time.perf_counter() - t0
    log(f"  {tex.n_textons} textons in {t_tex:.1f} s")
    log("learning the implicit model on the training clips (window 10, recent_weight=0)")
    t0 = time.perf_counter()
    imp = mj.implicit.learn(train, window=WINDOW, recent_weight=0.0)
    t_imp = time.perf_counter() - t0
    log(f"  {int(np.asarray(imp.database.codes).shape[0])} windows in {t_imp:.1f} s")
    res["priors"] = dict(
        texture=dict(learn_s=t_tex, textons=tex.n_textons, fps=float(tex.feature_map.fps)),
        implicit=dict(
            learn_s=t_imp,
            windows=int(np.asarray(imp.database.codes).shape[0]),
            components=imp.database.n_components,
            window=imp.database.window,
            recent_weight=0.0,
        ),
    )
    priors = {"texture": tex, "implicit": imp}

    avail, why = proposal_available()
    res["proposal"] = dict(name=PROPOSAL, available=avail, reason=why)
    notes: list[str] = []
    if not avail:
        notes.append(f"`ParticleFilter(proposal={PROPOSAL!r})` is not available: {why}")
        log(f"  the {PROPOSAL} proposal is not available: {why}")

    log("making the problems (one per clip, setting and prior type)")
    problems = {
        s: [make_problems(i, c, tex, imp, kw) for i, c in enumerate(held)]
        for s, kw in SETTINGS.items()
    }
    p0 = problems["easy"][0]["texture"]
    res["frames"] = [int(p0.frames[0]), int(p0.frames[-1])]
    res["joints"] = len(p0.joints)

    rows: dict[str, dict[str, Any]] = {}
    results_easy0: dict[str, np.ndarray] = {}
    for s in SETTINGS:
        rows[s] = {}
        for name, (kind, method) in methods(s, avail).items():
            if method is None:
                rows[s][name] = dict(summary=None, reason="not available: " + why)
                continue
            prior = priors[kind]
            key = lambda i: jax.random.key(1000 + i)
            log(f"{s}: {name}: first call (compiles)")
            first_s, _ = run_once(method, prior, problems[s][0][kind], key(0))
            per_clip = []
            for i in range(n_clips):
                wall, r = run_once(method, prior, problems[s][i][kind], key(i))
                row = clip_row(r, wall)
                row["clip"] = held_names[i]
                per_clip.append(row)
                log(
                    f"  {held_names[i]}: {row['global_mm']:.1f} mm global, "
                    f"{row['root_relative_mm']:.1f} root-relative, {wall:.2f} s"
                )
                if s == "easy" and i == 0:
                    results_easy0[name] = np.asarray(r.error) * 1000
            rows[s][name] = dict(
                method=repr(method),
                prior=kind,
                summary=summarise(per_clip, first_s),
                per_clip=per_clip,
            )
            sm = rows[s][name]["summary"]
            log(
                f"  mean {sm['global_mm']:.1f} mm, first call {first_s:.1f} s, "
                f"{sm['frames_per_s']:.0f} frames/s"
            )
    res["rows"] = rows
    res["targets"] = targets(rows)
    for t in res["targets"]:
        print(target_line(t), flush=True)

    res["notes"] = notes + derived_notes(res)

    clip0 = held_names[0]
    res["plot"] = dict(
        clip=clip0,
        setting="easy",
        frames=[int(f) for f in p0.frames],
        error_mm={n: [float(v) for v in ys] for n, ys in results_easy0.items()},
    )
    out = args.out_dir
    out.mkdir(parents=True, exist_ok=True)
    plot(results_easy0, res["plot"]["frames"], clip0, out / "tracking_error.png")
    res["total_s"] = time.perf_counter() - t_start
    res["machine"]["load_after"] = os.getloadavg()
    from mtex_jax.core import atomic_write

    with atomic_write(out / "tracking.json", "w", encoding="utf-8") as f:
        json.dump(res, f, indent=1, ensure_ascii=False)
    with atomic_write(out / "tracking.md", "w", encoding="utf-8") as f:
        f.write(report(res))
    log(f"done in {res['total_s']:.0f} s: {out / 'tracking.md'}")


if __name__ == "__main__":
    main()
