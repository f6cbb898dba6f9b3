"""jax-moseq's AR-HMM row of ``bench_quality.py`` (issue 39): states used and held-out
log-likelihood of the sticky HDP AR-HMM of MoSeq (Wiltschko et al. 2015), fitted by
jax-moseq's Gibbs sampler on the texture's training observation vectors.

The model is ``jax_moseq.models.arhmm``: ``init_model`` then ``resample_model`` sweeps, with
keypoint-moseq's default hyperparameters of its AR-only stage (``alpha = 5.7``,
``gamma = 1000``, ``kappa = 1e6``, ``S_0_scale = 0.01``, ``K_0_scale = 10``) except two lags
(the texture's AR(2)) and at most 50 states. Nothing is tuned, least of all on the held-out
clips.

The likelihoods are computed here, not by jax-moseq: the marginal over the state paths by an
HMM forward algorithm (:func:`hmm_forward`) with the last Gibbs sample's ``Ab``, ``Q`` and
``pi`` and a uniform initial state (as jax-moseq's own sampler and
``marginal_log_likelihood`` take it), conditioned on the first two frames of every clip; "per
frame" divides by the ``T − 2`` frames so scored. Beside it, as the other rows of the density
table: the median and worst per-frame predictive log-density ``log p(y_t | y_{<t})`` and the
one-step predictive-mean error (:func:`score`). The training value is checked against
jax-moseq's ``marginal_log_likelihood`` on the same sample (which uses dynamax's
``hmm_filter``).

jax-moseq is an optional dependency (``pip install -e ".[bench,moseq]"``; it pins
``dynamax<1.0.3``). Without it :func:`moseq_row` returns ``{"reason": ...}``. It can also run
the fit under another interpreter that has it (``python=PATH``): this file is then run as a
script there, with the vectors passed in an ``.npz`` file and the row returned as JSON::

    PY benchmarks/quality/quality_moseq.py --input vectors.npz --output row.json [--iters 30]

(``vectors.npz``: arrays ``train_0, train_1, …, held_0, …``, each ``(T, D)``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.linalg import solve_triangular

NLAGS = 2  # the texture's AR(2)
NUM_STATES = 50
# keypoint-moseq's defaults (its project config) for the AR-only stage, lags and states aside
TRANS = dict(alpha=5.7, gamma=1000.0, kappa=1e6)
AR = dict(S_0_scale=0.01, K_0_scale=10.0)
USED_SHARE = 0.01  # a state is "used" with at least this share of the training frames


# ---------------------------------------------------------------- likelihoods (numpy only)


def ar_terms(y: np.ndarray, Ab: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Log-densities ``(T − L, K)`` and means ``(T − L, K, D)`` of frames ``L..T−1`` of
    ``y (T, D)`` under each of the ``K`` AR states, in jax-moseq's layout: ``Ab (K, D, L·D + 1)``
    acts on ``[y_{t−L}, …, y_{t−1}, 1]`` (oldest lag first), ``Q (K, D, D)`` the noise
    covariances."""
    y = np.asarray(y, dtype=np.float64)
    T, D = y.shape
    L = (Ab.shape[-1] - 1) // D
    if Ab.shape[-1] != L * D + 1 or T <= L:
        raise ValueError(f"Ab of shape {Ab.shape} does not fit {D} channels, or T = {T} <= {L}")
    x_in = np.concatenate([y[i : T - L + i] for i in range(L)] + [np.ones((T - L, 1))], axis=1)
    K = Ab.shape[0]
    chol = np.linalg.cholesky(Q)  # (K, D, D)
    inv = np.stack([solve_triangular(c, np.eye(D), lower=True) for c in chol])  # chol⁻¹
    # one product for every state each: the means, and the whitened residuals
    # chol⁻¹ (y − Ab x) = [y, x] @ [chol⁻ᵀ; −(chol⁻¹ Ab)ᵀ]
    means = (x_in @ Ab.reshape(K * D, -1).T).reshape(T - L, K, D)
    B = np.concatenate([inv.transpose(0, 2, 1), -np.transpose(inv @ Ab, (0, 2, 1))], axis=1)
    w = (np.concatenate([y[L:], x_in], axis=1) @ B.transpose(1, 0, 2).reshape(-1, K * D)).reshape(
        T - L, K, D
    )
    logdet = 2.0 * np.sum(np.log(np.diagonal(chol, axis1=1, axis2=2)), axis=1)  # (K,)
    out = -0.5 * (np.sum(w * w, axis=-1) + logdet + D * np.log(2.0 * np.pi))
    return out, means


def ar_frame_loglik(y: np.ndarray, Ab: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """The ``(T − L, K)`` log-densities of :func:`ar_terms`."""
    return ar_terms(y, Ab, Q)[0]


def hmm_forward_frames(
    log_lik: np.ndarray, pi: np.ndarray, p0: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The forward algorithm with per-frame normalisation (no logarithm of ``pi``, whose
    entries may be 0).

    Args:
        log_lik: ``(T, K)`` emission log-densities.
        pi: ``(K, K)`` row-stochastic transition matrix.
        p0: ``(K,)`` initial distribution (default uniform).

    Returns:
        ``(frame, predicted)``: ``frame[t] = log p(y_t | y_{<t})`` (their sum is the
        marginal log-likelihood) and ``predicted[t] = p(z_t | y_{<t})``, ``(T, K)``.
    """
    log_lik = np.asarray(log_lik, dtype=np.float64)
    T, K = log_lik.shape
    pi = np.asarray(pi, dtype=np.float64)
    alpha = np.full(K, 1.0 / K) if p0 is None else np.asarray(p0, dtype=np.float64)
    frame, predicted = np.empty(T), np.empty((T, K))
    for t in range(T):
        if t > 0:
            alpha = alpha @ pi
        predicted[t] = alpha
        m = np.max(log_lik[t])
        alpha = alpha * np.exp(log_lik[t] - m)
        s = float(alpha.sum())
        frame[t] = m + np.log(s)
        alpha = alpha / s
    return frame, predicted


def hmm_forward(log_lik: np.ndarray, pi: np.ndarray, p0: np.ndarray | None = None) -> float:
    """``log Σ_z p0[z_0] Π pi[z_{t−1}, z_t] Π exp(log_lik[t, z_t])``
    (:func:`hmm_forward_frames`; ``p0`` uniform by default)."""
    return float(np.sum(hmm_forward_frames(log_lik, pi, p0)[0]))


def marginal_loglik(ys: list[np.ndarray], Ab, Q, pi) -> list[float]:
    """Per clip: the log-likelihood of frames ``L..T−1`` given frames ``0..L−1``, marginal
    over the state paths (:func:`hmm_forward`, uniform initial state)."""
    Ab, Q, pi = (np.asarray(a, dtype=np.float64) for a in (Ab, Q, pi))
    return [hmm_forward(ar_frame_loglik(y, Ab, Q), pi) for y in ys]


def score(ys: list[np.ndarray], Ab, Q, pi) -> dict[str, Any]:
    """Marginal log-likelihood per clip, the per-frame predictive log-densities
    ``log p(y_t | y_{<t})`` (median, worst) and the one-step predictive-mean error
    (``Σ_k p(z_t = k | y_{<t}) · mean_k``, squared, per dimension) over the frames ``L..T−1``
    of every clip."""
    Ab, Q, pi = (np.asarray(a, dtype=np.float64) for a in (Ab, Q, pi))
    L = (Ab.shape[-1] - 1) // Ab.shape[-2]
    clips, frames, sq, n = [], [], 0.0, 0
    for y in ys:
        ll, means = ar_terms(y, Ab, Q)
        fr, pred = hmm_forward_frames(ll, pi)
        yhat = np.einsum("tk,tkd->td", pred, means)
        sq += float(np.sum((yhat - y[L:]) ** 2))
        n += yhat.size
        clips.append(float(np.sum(fr)))
        frames.append(fr)
    fr = np.concatenate(frames)
    return dict(
        clips=clips,
        per_frame=float(np.sum(clips) / fr.size),
        median_frame=float(np.median(fr)),
        worst_frame=float(np.min(fr)),
        prediction_mse=sq / n,
        frames=int(fr.size),
    )


# ---------------------------------------------------------------- the fit (needs jax-moseq)


def _padded(ys: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    T = max(len(y) for y in ys)
    x = np.zeros((len(ys), T, ys[0].shape[1]))
    mask = np.zeros((len(ys), T))
    for i, y in enumerate(ys):
        x[i, : len(y)], mask[i, : len(y)] = y, 1.0
    return x, mask


def _fit_row(train_y, held_y, iters, seed, num_states, kappa) -> dict[str, Any]:
    from importlib.metadata import version

    import jax
    import jax.numpy as jnp
    import jax.random as jr
    from jax_moseq.models import arhmm

    D = train_y[0].shape[1]
    trans = dict(TRANS, kappa=float(kappa), num_states=num_states)
    ar = dict(AR, latent_dim=D, nlags=NLAGS)
    x, mask = _padded(train_y)
    data = dict(x=jnp.asarray(x), mask=jnp.asarray(mask))  # the working precision of jax
    n_train = sum(len(y) - NLAGS for y in train_y)
    t0 = time.perf_counter()
    model = arhmm.init_model(data, seed=jr.PRNGKey(seed), trans_hypparams=trans, ar_hypparams=ar)
    jax.block_until_ready(model["states"]["z"])
    t_init = time.perf_counter() - t0
    trace, t_trace = [], 0.0
    for _ in range(iters):
        model = arhmm.resample_model(data, **model)
        jax.block_until_ready(model["states"]["z"])
        t1 = time.perf_counter()
        ll = arhmm.log_joint_likelihood(**data, **model["states"], **model["params"])
        trace.append(float(ll["x"] + ll["z"]) / n_train)
        t_trace += time.perf_counter() - t1
    wall = time.perf_counter() - t0 - t_trace
    params = {k: np.asarray(v) for k, v in model["params"].items()}
    valid = np.asarray(mask)[:, NLAGS:] > 0
    z = np.asarray(model["states"]["z"])[valid]
    counts = np.bincount(z, minlength=num_states)
    share = np.sort(counts / counts.sum())[::-1]
    # dwell times of the last sample's state paths (within clips)
    runs = []
    for i, y in enumerate(train_y):
        zi = np.asarray(model["states"]["z"])[i, : len(y) - NLAGS]
        edges = np.flatnonzero(np.diff(zi)) + 1
        runs.extend(np.diff(np.concatenate([[0], edges, [len(zi)]])).tolist())

    t2 = time.perf_counter()
    tr = score(train_y, params["Ab"], params["Q"], params["pi"])
    he = score(held_y, params["Ab"], params["Q"], params["pi"])
    t_eval = time.perf_counter() - t2
    # jax-moseq's own forward (dynamax's hmm_filter, padded frames masked) on the same sample
    try:
        theirs = float(arhmm.marginal_log_likelihood(**data, **model["params"]))
        check = abs(theirs - sum(tr["clips"])) / abs(sum(tr["clips"]))
    except Exception as e:  # a check only: report it, keep the row
        theirs, check = None, f"{type(e).__name__}: {str(e)[:200]}"
    return dict(
        package=f"jax-moseq {version('jax-moseq')}",
        versions=dict(
            jax_moseq=version("jax-moseq"),
            dynamax=version("dynamax"),
            jax=jax.__version__,
            python=sys.version.split()[0],
        ),
        interpreter=sys.executable,
        x64=bool(jax.config.jax_enable_x64),
        model="sticky HDP AR-HMM (jax_moseq.models.arhmm), Gibbs: init_model + resample_model",
        hypparams=dict(trans=trans, ar=ar),
        iterations=iters,
        seed=seed,
        max_states=num_states,
        states_used=int(np.sum(counts > 0)),
        states_used_1pct=int(np.sum(counts >= USED_SHARE * counts.sum())),
        usage_top10=[float(s) for s in share[:10]],
        median_dwell_frames=float(np.median(runs)),
        mean_dwell_frames=float(np.mean(runs)),
        held_loglik_per_frame=he["per_frame"],
        held_median_frame=he["median_frame"],
        held_worst_frame=he["worst_frame"],
        held_prediction_mse=he["prediction_mse"],
        train_loglik_per_frame=tr["per_frame"],
        train_median_frame=tr["median_frame"],
        train_prediction_mse=tr["prediction_mse"],
        held_per_clip=[
            dict(frames=len(y), loglik_per_frame=v / (len(y) - NLAGS))
            for y, v in zip(held_y, he["clips"], strict=True)
        ],
        frames=dict(train=tr["frames"], held=he["frames"]),
        likelihood=(
            "marginal over states: HMM forward (uniform initial state) with the last Gibbs "
            f"sample's Ab, Q, pi, conditioned on the first {NLAGS} frames of each clip; per "
            f"frame over the T - {NLAGS} scored frames"
        ),
        train_joint_loglik_per_frame_trace=trace,
        train_marginal_jax_moseq=theirs,
        train_marginal_rel_diff=check,
        init_s=t_init,
        wall_s=wall,
        eval_s=t_eval,
    )


def moseq_row(
    train_y: list[np.ndarray],
    held_y: list[np.ndarray],
    iters: int = 30,
    seed: int = 0,
    *,
    num_states: int = NUM_STATES,
    kappa: float = TRANS["kappa"],
    python: str | os.PathLike | None = None,
) -> dict[str, Any]:
    """jax-moseq's AR-HMM fitted on ``train_y`` and scored on ``held_y`` (lists of
    ``(T, D)`` observation vectors).

    In this interpreter if ``python`` is None (call it after ``jax_enable_x64``, as the
    benchmark does), else under the interpreter ``python`` (a venv with jax-moseq).

    Returns:
        the row (states used, held-out and training log-likelihood per frame, iterations,
        wall time, versions, ...), or ``{"package": "jax-moseq", "reason": why not}`` when
        jax-moseq cannot be imported or the fit fails.
    """
    if python is not None:
        return _run_elsewhere(train_y, held_y, iters, seed, num_states, kappa, str(python))
    try:
        import jax_moseq.models.arhmm  # noqa: F401
    except Exception as e:
        return dict(
            package="jax-moseq",
            reason=f"jax-moseq cannot be imported here ({type(e).__name__}: {e}); install "
            'it with pip install -e ".[bench,moseq]" (jax-moseq 0.3.7 pins dynamax<1.0.3)',
        )
    try:
        return _fit_row(train_y, held_y, iters, seed, num_states, kappa)
    except Exception as e:
        return dict(package="jax-moseq", reason=f"the fit failed: {type(e).__name__}: {e}")


def _run_elsewhere(train_y, held_y, iters, seed, num_states, kappa, python) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="moseq-") as tmp:
        inp, out = Path(tmp) / "vectors.npz", Path(tmp) / "row.json"
        arrays = {f"train_{i}": y for i, y in enumerate(train_y)}
        arrays |= {f"held_{i}": y for i, y in enumerate(held_y)}
        np.savez(inp, **arrays)
        cmd = [python, str(Path(__file__).resolve()), "--input", str(inp), "--output", str(out)]
        cmd += ["--iters", str(iters), "--seed", str(seed), "--num-states", str(num_states)]
        cmd += ["--kappa", repr(float(kappa))]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        except OSError as e:
            return dict(package="jax-moseq", reason=f"cannot run {python}: {e}")
        if proc.returncode != 0 or not out.exists():
            tail = proc.stderr.strip().splitlines()[-3:]
            return dict(
                package="jax-moseq",
                reason=f"{python} exited {proc.returncode}: " + " | ".join(tail),
            )
        return json.loads(out.read_text())


def _load(path: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    with np.load(path) as f:
        parts = {
            tag: sorted(
                (k for k in f.files if k.startswith(tag)), key=lambda k: int(k.split("_")[1])
            )
            for tag in ("train_", "held_")
        }
        return [f[k] for k in parts["train_"]], [f[k] for k in parts["held_"]]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--input", type=Path, required=True, help=".npz of train_i / held_i (T, D)")
    ap.add_argument("--output", type=Path, required=True, help="the row as JSON")
    ap.add_argument("--iters", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--num-states", type=int, default=NUM_STATES)
    ap.add_argument("--kappa", type=float, default=TRANS["kappa"])
    args = ap.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)  # before any array is made, as the benchmark
    train_y, held_y = _load(args.input)
    row = moseq_row(
        train_y, held_y, args.iters, args.seed, num_states=args.num_states, kappa=args.kappa
    )
    args.output.write_text(json.dumps(row, indent=1))


if __name__ == "__main__":
    main()
