"""Write the documentation site's results page from the benchmarks' results files.

Usage (from the repository root; ``.ci/run`` runs it before ``mkdocs build``)::

    python tools/results_page.py            # writes docs/results.md and docs/results/*.png
    python tools/results_page.py --check    # fails if docs/results.md is out of date

The page is never edited by hand. It holds:

* a summary built from the raw numbers (``benchmarks/**/results/**/*.json``): the held-out
  density and realism of the models, and four plots;
* every results report (``benchmarks/**/results/**/*.md``) under a heading that says what it
  measures, in a fixed order; a report this script does not know yet goes to "Other results",
  so nothing a benchmark writes is left off.

Each results file names the command that made it (a report: a ``Made by:`` line; raw numbers:
a top-level ``"command"``), and each report the machine it ran on; the script refuses to write
the page while a results file does not.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
PAGE = ROOT / "docs" / "results.md"
FIGURES = ROOT / "docs" / "results"

# Known reports, in page order: file stem -> (section title, what it measures).
REPORTS: dict[str, tuple[str, str]] = {
    "tracking": (
        "Tracking: 3-D motion from 2-D joints",
        "Monocular tracking of the 4 held-out salsa clips (150 frames at 30 Hz, 17 joints, "
        "synthetic 2 px observations; hard: 10 % missing joints, 5 % outliers, bones scaled "
        "by 0.9-1.1; and the hard problems with the person's skeleton given) with the "
        "texture's MAP smoother (batch and fixed-lag), the implicit "
        "model's particle filter (bootstrap and Gauss-Newton proposals), a constant-velocity "
        "filter and a smoothness-only MAP (design §12).",
    ),
    "quality": (
        "Motion quality on the held-out split",
        "The yardstick of every quality claim: the models learned on the 10 training clips of "
        "the fixed salsa split, judged on the 4 held-out clips. Density of the held-out "
        "observation vectors (nats per frame) against AR(2), constant-velocity, hold-last and "
        "ARHMM baselines; realism of generated motion as Wasserstein distances of joint speed, "
        "acceleration and jerk, divided by the real-vs-real floor (1.0 = as far from the "
        "held-out dancers as other real dancing); foot skating, floor penetration, transitions, "
        "novelty and copying (design §10.4).",
    ),
    "implicit_quality": (
        "Implicit model: quality of synthesis",
        "The implicit model's synthesis (design §7.5) on the same split, 32 syntheses of 20 s "
        "per row, with the contribution of each part of the default sampler.",
    ),
    "implicit_quality_validation": (
        "Implicit model: validation folds",
        "The folds of the training clips on which the implicit model's defaults were chosen "
        "(the held-out clips were not used).",
    ),
    "edit": (
        "Editing and cleaning",
        "Cleaning synthesised motion (foot skating, the floor) and a hand edit, with "
        "`mtex_jax.edit` (design §6.3–§6.6): realism before and after, how local an edit is, "
        "and the time of one edit and of a batch.",
    ),
    "innovations": (
        "Innovations of real dance",
        "Why the textons' innovations are Student-t and why synthesis replays real residuals "
        "(design §2.10, §10.7, §10.8): the heavy tails and the autocorrelation of the "
        "one-step residuals of the training clips.",
    ),
    "learn_defaults": (
        "Learning with the defaults",
        "A full `learn` on the salsa clips with the default `LearnConfig`.",
    ),
    "learn": (
        "Learning: E-step, `learn`, ARHMM baseline",
        "The segmentation E-step at the paper's scale, a full `learn` with the paper's "
        "settings, and a dynamax autoregressive HMM as a baseline.",
    ),
    "scale": (
        "Learning at scale",
        "Full learns from 7,000 to 50,000 frames (the paper's scale), the E-step against its "
        "computed bound, and two processes against one (design §4.8, §10.6).",
    ),
    "estep/learn": (
        "The E-step at the paper's scale",
        "One E-step (segment scores and the semi-Markov Viterbi, design §3.2, §4.2) on "
        "50,000 frames and 246 textons.",
    ),
    "frame_terms": (
        "Frame terms",
        "The blocked frame-term kernel (design §3.3) against NumPy transcriptions of the same "
        "formulas.",
    ),
    "forward": (
        "Forward algorithm against Viterbi",
        "The marginal likelihood (semi-Markov forward algorithm, design §10.1) against the "
        "Viterbi on the same segment scores.",
    ),
    "synthesis": (
        "Constrained synthesis of one texton",
        "The bridge recursion, the banded solve and a dense solve of MT eqs. (6)–(9) "
        "(design §5.3–§5.5).",
    ),
    "implicit": (
        "Implicit model: speed, sampling and tracking",
        "Tree search against exact sampling (SBS eqs. (3), (7)–(8)), synthesis cost per frame, "
        "and particle-filter tracking with the implicit prior against constant velocity "
        "(design §7).",
    ),
    "implicit_tracking_check": (
        "Implicit model: tracking on other clips",
        "Tracking with the implicit prior on clips it was not tuned on.",
    ),
}

# The density and realism rows of the summary (names as in quality.json), in table order.
DENSITY_ROWS = [
    ("motion texture (marginal)", "motion texture, defaults (forward algorithm)"),
    ("paper model, 4 textons (k = 12) (marginal)", "the paper's model"),
    ("AR(2)", "one full-covariance AR(2)"),
    ("dynamax ARHMM (K = 3, 2 lags)", "dynamax linear ARHMM"),
    ("hold last frame", "hold the last frame"),
    ("constant velocity", "constant velocity"),
]
MOTION_ROWS = [
    ("real (held out) @60 Hz", "real, held out"),
    ("texture constrained (sampled noise)", "texture, defaults (`synthesize`)"),
    ("texture constrained (sampled noise), cleaned", "the same, cleaned (`edit.clean`)"),
    ("texture constrained (zero noise)", "texture, zero noise"),
    ("texture constrained (sampled noise), independent innovations", "texture, white innovations"),
    ("AR(2) samples", "AR(2) samples"),
    ("implicit tree sampler @30 Hz", "implicit, tree sampler, defaults"),
    ("implicit exact sampler @30 Hz", "implicit, exact sampler, defaults"),
    ("implicit tree sampler, paper settings", "implicit, the paper's sampler"),
]


def results_files(suffix: str) -> dict[str, Path]:
    """Every results file of ``benchmarks/`` with this suffix, keyed by its name in its folder.

    A file counts when a folder called ``results`` is among its parents; the key is its path
    below that folder without the suffix (``quality``, ``estep/learn``).
    """
    found: dict[str, Path] = {}
    for path in sorted(BENCH.rglob(f"*{suffix}")):
        parts = path.relative_to(BENCH).parts
        if "results" not in parts[:-1]:
            continue
        last = len(parts) - 1 - parts[::-1].index("results")
        below = parts[last + 1 :]
        key = "/".join(below)[: -len(suffix)]
        found.setdefault(key, path)
    return found


def _load(jsons: dict[str, Path], key: str) -> Any:
    path = jsons.get(key)
    if path is None:
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _fmt(x: Any, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    if isinstance(x, (int, float)):
        if abs(x) >= 1000:
            return f"{x:,.0f}".replace(",", " ")
        return f"{x:.{digits}f}"
    return str(x)


def summary(jsons: dict[str, Path]) -> list[str]:
    """The summary tables from ``quality.json``."""
    q = _load(jsons, "quality")
    if not isinstance(q, dict):
        return []
    out = ["## Summary", ""]
    tex = q.get("texture", {})
    if tex:
        out += [
            "In this run the default texture, learned on the 10 training clips, had "
            f"{tex.get('textons', '?')} textons, "
            f"observation model `{tex.get('observation', '?')}`, state dimension "
            f"{tex.get('state_dim', '?')}, {tex.get('durations', '?')} durations.",
            "",
        ]
    dens = q.get("density", {})
    rows = [(label, dens[key]) for key, label in DENSITY_ROWS if key in dens]
    if rows:
        out += [
            "**Density of the held-out clips** (texture observation vectors; the mean is "
            "dominated by a few capture glitches in the held-out clips, the median frame shows "
            "typical frames):",
            "",
            "| model | mean log-likelihood / frame | median frame | one-step MSE (z²) |",
            "| --- | ---: | ---: | ---: |",
        ]
        for label, r in rows:
            out.append(
                f"| {label} | {_fmt(r.get('loglik_per_frame'), 1)} | "
                f"{_fmt(r.get('median_frame'), 1)} | {_fmt(r.get('prediction_mse'))} |"
            )
        out.append("")
    motion = q.get("rows", {})
    rows = [(label, motion[key]) for key, label in MOTION_ROWS if key in motion]
    if rows:
        out += [
            "**Generated motion against the held-out dancers** (W1 distances of joint speed, "
            "acceleration and jerk as multiples of the real-vs-real floor; skating: median "
            "horizontal speed of a low foot; copying: share of steps that continue the training "
            "frame of the step before):",
            "",
            "| set | speed | acc | jerk | skating (m/s) | below the floor (m) | copied steps |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for label, r in rows:
            out.append(
                f"| {label} | {_fmt(r.get('speed_ratio'))} | {_fmt(r.get('acceleration_ratio'))} "
                f"| {_fmt(r.get('jerk_ratio'))} | {_fmt(r.get('skating_median'))} | "
                f"{_fmt(r.get('penetration_max'), 3)} | {_fmt(r.get('copy_fraction'))} |"
            )
        out.append("")
    return out


def _plot_quality(q: Any, ax: Any) -> bool:
    motion = q.get("rows", {}) if isinstance(q, dict) else {}
    rows = [(label, motion[key]) for key, label in MOTION_ROWS[1:] if key in motion]
    if not rows:
        return False
    names = [label.replace("`", "") for label, _ in rows]
    width = 0.27
    for j, (field, name) in enumerate(
        [("speed_ratio", "speed"), ("acceleration_ratio", "acceleration"), ("jerk_ratio", "jerk")]
    ):
        ys = [max(float(r.get(field, float("nan"))), 1e-3) for _, r in rows]
        ax.barh([i + (j - 1) * width for i in range(len(rows))], ys, height=width, label=name)
    ax.set_yticks(range(len(rows)), names, fontsize=7)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.axvline(1.0, color="k", lw=0.8)
    ax.set_xlabel("W1 / real-vs-real floor (1 = real)")
    ax.set_title("Realism of generated motion (held-out salsa)", fontsize=9)
    ax.legend(fontsize=7)
    return True


def _plot_scale(s: Any, ax: Any) -> bool:
    learns = s.get("learn", []) if isinstance(s, dict) else []
    if not learns:
        return False
    frames = [r["frames"] for r in learns]
    ax.plot(frames, [r["wall_s"] for r in learns], "o-", label="wall")
    for key, name in [("e_step", "E-steps"), ("m_step", "M-steps")]:
        ys = [r.get("split_s", {}).get(key) for r in learns]
        if all(y is not None for y in ys):
            ax.plot(frames, ys, "s--", label=name)
    ax.set_xlabel("training frames (60 Hz)")
    ax.set_ylabel("seconds")
    ax.set_title("A full learn with the defaults", fontsize=9)
    ax.legend(fontsize=7)
    return True


def _plot_implicit(i: Any, ax: Any) -> bool:
    speed = i.get("speed", []) if isinstance(i, dict) else []
    rows = [r for r in speed if "tree_uniform_s" in r and "exact_s" in r]
    if not rows:
        return False
    n = [r["n"] for r in rows]
    # the benchmark's calls draw 300 samples
    ax.loglog(n, [r["tree_uniform_s"] / 300 * 1e6 for r in rows], "o-", label="tree search")
    ax.loglog(n, [r["exact_s"] / 300 * 1e6 for r in rows], "s-", label="exact")
    ax.set_xlabel("windows in the database")
    ax.set_ylabel("µs per sample")
    ax.set_title("Implicit model: sampling cost", fontsize=9)
    ax.legend(fontsize=7)
    return True


def _plot_edit(e: Any, ax: Any) -> bool:
    ed = e.get("edit", {}) if isinstance(e, dict) else {}
    xs, ys = ed.get("decay_s"), ed.get("decay_max_m")
    if not xs or not ys:
        return False
    pts = [(x, y * 1000.0) for x, y in zip(xs, ys, strict=False) if y > 0]
    ax.semilogy([p[0] for p in pts], [p[1] for p in pts], "o-")
    ax.set_xlabel("seconds from the edited frame")
    ax.set_ylabel("largest joint displacement (mm)")
    ax.set_title("A hand edit stays local", fontsize=9)
    return True


def _plot_tracking(t: Any, ax: Any) -> bool:
    plot = t.get("plot", {}) if isinstance(t, dict) else {}
    curves = plot.get("error_mm", {})
    if not curves:
        return False
    for name, ys in curves.items():
        ax.plot(plot["frames"][: len(ys)], ys, lw=1.0, label=name)
    ax.set_yscale("log")
    ax.set_xlabel(f"frame of {plot.get('clip', '?')} (30 Hz)")
    ax.set_ylabel("mean joint error (mm)")
    ax.set_title("Tracking error per frame (held-out clip, easy)", fontsize=9)
    ax.legend(fontsize=6)
    return True


def figures(jsons: dict[str, Path]) -> list[str]:
    """Draw the plots into ``docs/results/`` and return the Markdown that shows them."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - the plot extra is missing
        return ["*(matplotlib is not installed: no plots.)*", ""]
    FIGURES.mkdir(parents=True, exist_ok=True)
    plots = [
        ("realism.png", _plot_quality, "quality", (7.0, 3.6)),
        ("learn_scale.png", _plot_scale, "scale", (4.6, 3.2)),
        ("implicit_sampling.png", _plot_implicit, "implicit", (4.6, 3.2)),
        ("edit_locality.png", _plot_edit, "edit", (4.6, 3.2)),
        ("tracking_error.png", _plot_tracking, "tracking", (6.4, 3.4)),
    ]
    out = ["## Plots", ""]
    for name, draw, key, size in plots:
        fig, ax = plt.subplots(figsize=size, dpi=90)
        ok = draw(_load(jsons, key), ax)
        if ok:
            fig.tight_layout()
            fig.savefig(FIGURES / name, metadata={"Software": None})
            out += [f"![{name[:-4].replace('_', ' ')}](results/{name})", ""]
        plt.close(fig)
    if (ROOT / "docs" / "demo_filmstrip.png").is_file():
        out += [
            "A new salsa synthesised by `mtex demo` from the default texture (the filmstrip of "
            "the README and of `out/new_dance.png`):",
            "",
            "![a new salsa from mtex demo, as a filmstrip](demo_filmstrip.png)",
            "",
        ]
    return out


_HEADING = re.compile(r"^(#{1,5}) ", flags=re.M)


def report_section(key: str, path: Path, title: str, about: str) -> list[str]:
    """One results report under its own heading, its headings one level down."""
    text = path.read_text(encoding="utf-8").strip()
    lines = text.splitlines()
    if lines and lines[0].startswith("# "):
        original = lines[0][2:].strip()
        text = "\n".join(lines[1:]).strip()
    else:
        original = ""
    text = _HEADING.sub(lambda m: "#" * (len(m.group(1)) + 1) + " ", text)
    src = path.relative_to(ROOT).as_posix()
    out = [f"## {title}", "", about, ""]
    out += [f"*From `{src}`" + (f" ({original})" if original else "") + ".*", "", text, ""]
    return out


def without_command() -> list[str]:
    """The results files that do not name the command that made them."""
    missing = []
    for path in results_files(".md").values():
        if not re.search(r"^Made by: `[^`]+`", path.read_text(encoding="utf-8"), flags=re.M):
            missing.append(f"{path.relative_to(ROOT)}: no line 'Made by: `<command>`'")
    jsons = results_files(".json")
    for key, path in jsons.items():
        data = _load(jsons, key)
        if not (isinstance(data, dict) and isinstance(data.get("command"), str)):
            missing.append(f'{path.relative_to(ROOT)}: no top-level "command"')
    return missing


def build() -> str:
    """The whole page as a string (and the plots written to ``docs/results/``)."""
    mds = results_files(".md")
    jsons = results_files(".json")
    out = [
        "# Results",
        "",
        "<!-- Generated by tools/results_page.py from benchmarks/**/results/; do not edit. -->",
        "",
        "What the benchmarks measured, on the 2-core CPU of the development machine in float64. "
        "The machine was shared with other jobs, so treat wall times as approximate; each "
        "report below names the command that made it and the machine it ran on. The quality "
        "figures use the fixed split of the shipped salsa clips (`mtex_jax.io.salsa_split()`: "
        "10 clips for training, 4 held out); nothing tuned looks at the held-out clips.",
        "",
    ]
    out += summary(jsons)
    out += figures(jsons)
    known = [k for k in REPORTS if k in mds]
    # validation folds go with their summary
    folds = sorted(k for k in mds if k.startswith("implicit_quality_validation_"))
    for key in known:
        title, about = REPORTS[key]
        out += report_section(key, mds[key], title, about)
        if key == "implicit_quality_validation":
            for fold in folds:
                name = fold.removeprefix("implicit_quality_validation_").replace("-", ", ")
                out += report_section(fold, mds[fold], f"Validation fold {name}", "")
    others = [k for k in mds if k not in REPORTS and k not in folds]
    if others:
        out += ["## Other results", ""]
        for key in others:
            out += report_section(key, mds[key], key, "")
    return "\n".join(out).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    """Write (or, with ``--check``, compare) ``docs/results.md``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="fail if the page is out of date")
    args = parser.parse_args(argv)
    missing = without_command()
    if missing:
        print("results files that do not say which command made them:\n" + "\n".join(missing))
        return 1
    text = build()
    if args.check:
        current = PAGE.read_text(encoding="utf-8") if PAGE.exists() else ""
        if current != text:
            print(f"{PAGE.relative_to(ROOT)} is out of date: run tools/results_page.py")
            return 1
        return 0
    PAGE.write_text(text, encoding="utf-8")
    print(f"wrote {PAGE.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
