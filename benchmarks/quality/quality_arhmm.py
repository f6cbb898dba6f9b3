"""The dynamax linear autoregressive HMM baseline of ``bench_quality.py``: held-out marginal
log-likelihood and one-step predictive-mean error, with the regularised emissions of the learn
benchmark (``speed/learn_dynamax.py``)."""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np


def arhmm_prediction(train_y, held_y, K: int, n_iter: int) -> tuple[float, float, float]:
    from dynamax.hidden_markov_model import LinearAutoregressiveHMM

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from _common import use

    use("speed")
    from learn_dynamax import _regularised_emissions

    D = train_y[0].shape[1]
    hmm = LinearAutoregressiveHMM(K, D, num_lags=2)
    hmm.emission_component = _regularised_emissions(K, D, 2, 1e-6, 1e-6)
    pairs = [(jnp.asarray(y)[2:], hmm.compute_inputs(jnp.asarray(y))[2:]) for y in train_y]
    E = jnp.concatenate([p[0] for p in pairs])
    U = jnp.concatenate([p[1] for p in pairs])
    params, props = hmm.initialize(jax.random.PRNGKey(0), method="kmeans", emissions=E)
    params, lps = hmm.fit_em(params, props, E, inputs=U, num_iters=n_iter, verbose=False)
    sq, n, ll = 0.0, 0, 0.0
    for y in held_y:
        e, u = jnp.asarray(y)[2:], hmm.compute_inputs(jnp.asarray(y))[2:]
        post = hmm.filter(params, e, inputs=u)
        W, b = params.emissions.weights, params.emissions.biases
        means = jnp.einsum("kdm,tm->tkd", W, u) + b
        yhat = jnp.einsum("tk,tkd->td", post.predicted_probs, means)
        sq += float(jnp.sum((yhat - e) ** 2))
        n += int(e.size)
        ll += float(post.marginal_loglik)
    frames = sum(len(y) - 2 for y in held_y)
    return ll / frames, sq / n, float(np.asarray(lps)[-1]) / E.shape[0]
