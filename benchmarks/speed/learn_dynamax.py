"""The dynamax ``LinearAutoregressiveHMM`` baseline and the per-frame comparison helpers for
part (c) of ``bench_learn.py`` (also used by ``bench_quality.py``).
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from learn_common import _median, _timed, _timed_cpu

from mtex_jax.texture import frame_terms, init_terms

Array = Any  # jax arrays, for annotations

# --------------------------------------------------------------------------------------------
# (c) dynamax LinearAutoregressiveHMM side by side
# --------------------------------------------------------------------------------------------


def _regularised_emissions(K: int, D: int, lags: int, ridge: float, floor: float) -> Any:
    """dynamax's LARHMM emissions with a relative ridge on the regression and a covariance floor.

    Without them, the M-step's residual covariances become singular on these features (some
    channels are constant within the frames a state takes, e.g. fingers that move in a few
    clips only) and EM returns NaN after one iteration. Same floors as our textons
    (``LearnConfig.ridge`` = 1e-6 relative, ``q_floor`` = ``sigma2_floor`` = 1e-6 absolute).
    """
    from dynamax.hidden_markov_model.models.arhmm import LinearAutoregressiveHMMEmissions

    class Regularised(LinearAutoregressiveHMMEmissions):
        def m_step(self, params: Any, props: Any, batch_stats: Any, m_step_state: Any) -> Any:
            st = dict(batch_stats)
            xx = st["sum_xxT"]  # (batch, K, M, M)
            scale = jnp.mean(jnp.diagonal(xx.sum(0), axis1=-2, axis2=-1), axis=-1)
            eye_m = jnp.eye(xx.shape[-1], dtype=xx.dtype)
            st["sum_xxT"] = xx.at[0].add(ridge * (scale + 1.0)[:, None, None] * eye_m)
            st["sum_w"] = st["sum_w"].at[0].add(1e-8)  # an empty state: no 0/0
            params, state = super().m_step(params, props, st, m_step_state)
            eye_d = jnp.eye(params.covs.shape[-1], dtype=params.covs.dtype)
            return params._replace(covs=params.covs + floor * eye_d), state

    return Regularised(K, D, num_lags=lags)


def dynamax_run(
    Ytr: list[np.ndarray],
    Yte: list[np.ndarray],
    K: int,
    n_iter: int,
    lags: int,
    plain_iters: int,
) -> dict[str, Any]:
    from dynamax.hidden_markov_model import LinearAutoregressiveHMM

    D = Ytr[0].shape[1]

    def model(regularised: bool) -> Any:
        hmm = LinearAutoregressiveHMM(K, D, num_lags=lags)
        if regularised:
            hmm.emission_component = _regularised_emissions(K, D, lags, 1e-6, 1e-6)
        return hmm

    hmm = model(True)

    def lagged(y: np.ndarray) -> tuple[Array, Array]:
        yj = jnp.asarray(y)
        u = hmm.compute_inputs(yj)
        return yj[lags:], u[lags:]  # condition on the first `lags` real frames, no zero padding

    pairs = [lagged(y) for y in Ytr]
    E = jnp.concatenate([p[0] for p in pairs])
    U = jnp.concatenate([p[1] for p in pairs])
    n_train = int(E.shape[0])
    t_init, (params, props) = _timed(
        lambda: hmm.initialize(jr.PRNGKey(0), method="kmeans", emissions=E)
    )
    out: dict[str, Any] = dict(
        K=K,
        num_lags=lags,
        train_frames=n_train,
        init="kmeans (dynamax), key 0",
        init_s=t_init,
    )

    def chained_em(model_: Any, n: int) -> tuple[Any, np.ndarray, list[float], list[float]]:
        """``n`` EM iterations as ``n`` chained calls of one jitted 1-iteration ``fit_em``.

        Identical to ``fit_em(num_iters=n)`` (the scan carries only the parameters: the M-step
        state of these components is ``None``), but compiled once, so every call after the
        first is a warm, individually timed EM iteration.
        """
        step = jax.jit(
            lambda p, e, u: model_.fit_em(p, props, e, inputs=u, num_iters=1, verbose=False)
        )
        p, lps, times, cpus = params, [], [], []
        for _ in range(n):
            t, c, (p, lp) = _timed_cpu(lambda p=p: step(p, E, U))
            times.append(t)
            cpus.append(c)
            lps.append(float(np.asarray(lp)[0]))
        return p, np.asarray(lps), times, cpus

    # unregularised dynamax as shipped
    p_plain, lp_plain, _, _ = chained_em(model(False), plain_iters)
    finite = np.isfinite(lp_plain)
    out["plain"] = dict(
        iterations=plain_iters,
        log_prob_per_frame=[float(x) / n_train for x in lp_plain],
        # index of the first non-finite log p = number of M-steps before it turned NaN
        first_nonfinite_iteration=int(np.argmin(finite)) if not finite.all() else None,
        params_finite=bool(
            all(np.all(np.isfinite(np.asarray(a))) for a in jax.tree.leaves(p_plain))
        ),
    )
    # regularised: compile once, time every iteration
    p_fit, lps, times, cpus = chained_em(hmm, n_iter)
    per_iter = _median(times[1:]) if n_iter > 1 else math.nan
    lps = np.asarray(lps)
    held_marg, held_vit, frames, per_frame = [], [], [], []
    for y in Yte:
        e, u = lagged(y)
        held_marg.append(float(hmm.marginal_log_prob(p_fit, e, inputs=u)))
        z = hmm.most_likely_states(p_fit, e, inputs=u)
        held_vit.append(float(hmm.log_prob(p_fit, z, e, inputs=u)))
        frames.append(int(e.shape[0]))
        # emission log-density of every frame under its Viterbi state (transitions left out)
        per_frame.append(
            np.asarray(
                jax.vmap(
                    lambda zt, yt, ut: hmm.emission_distribution(p_fit, zt, inputs=ut).log_prob(yt)
                )(z, e, u)
            )
        )
    nf = sum(frames)
    out.update(
        iterations=n_iter,
        iteration_times_s=times,
        iteration_cpu_s=cpus,
        cpu_per_iteration_s=_median(cpus[1:]) if n_iter > 1 else math.nan,
        per_iteration_s=per_iter,
        compile_s=times[0] - per_iter,
        train_log_prob_per_frame=[float(x) / n_train for x in lps],
        last_iteration_gain_per_frame=float(lps[-1] - lps[-2]) / n_train if n_iter > 1 else None,
        heldout_frames=frames,
        heldout_marginal=held_marg,
        heldout_viterbi_joint=held_vit,
        heldout_marginal_per_frame=sum(held_marg) / nf,
        heldout_viterbi_joint_per_frame=sum(held_vit) / nf,
        heldout_frame_median_viterbi_path=float(np.median(np.concatenate(per_frame))),
        heldout_path=_tail(np.concatenate(per_frame)),
        heldout_frame_median_viterbi_path_per_clip=[float(np.median(x)) for x in per_frame],
    )
    return out


def _tail(v: np.ndarray) -> dict[str, float]:
    """Mean per-frame value and the part of it that the worst 1 % of frames contribute."""
    n = len(v)
    worst = np.sort(v)[: max(n // 100, 1)]
    return dict(mean=float(v.mean()), worst_1pct_contribution=float(worst.sum() / n))


def frame_values(tex: Any, y: np.ndarray, seg: Any) -> np.ndarray:
    """Per-frame log-density along our optimal segmentation (transitions and ``π`` left out).

    Frame ``t`` of a segment ``(b, L, i)`` gets ``obs_i(t) + dyn_i(t)`` for ``t ≥ b + 2`` and
    ``obs_i(t) + init_i(b) / 2`` for ``t ∈ {b, b + 1}``; the values sum to the segment scores.
    """
    dyn, obs = (np.asarray(a) for a in frame_terms(tex.textons, jnp.asarray(y)))
    init = np.asarray(init_terms(tex.textons, jnp.asarray(y)))
    out = np.empty(y.shape[0])
    for b, length, i in seg.to_list():
        t = np.arange(b, b + length)
        out[t] = obs[i, t] + np.where(t >= b + 2, dyn[i, t], 0.5 * init[i, b])
    return out
