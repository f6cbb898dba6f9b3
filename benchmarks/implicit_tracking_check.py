"""Quick tracking check after issue 18 (body-weighted database): 300 particles with the implicit
prior against 3,000 with constant velocity on bench_implicit.py's evaluation clips (leave one
clip out; 150 frames from frame 30; seeds 0, 1), with the hyper-parameters bench_implicit.py tuned
on 60_03 before issue 18 (not re-tuned). Run from benchmarks/: ../.venv/bin/python
implicit_tracking_check.py. Result: results/implicit_tracking_check.md."""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np

import bench_implicit as b
import mtex_jax as mj
from mtex_jax.implicit import make_problem, track

s = b.load(30.0)
out = []
for i in (4, 7, 10):
    model = mj.implicit.learn([m for k, m in enumerate(s) if k != i], 10)
    prob = make_problem(jax.random.PRNGKey(100 + i), model, s[i], n_frames=150, start=30)
    for seed in (0, 1):
        ri = track(
            jax.random.PRNGKey(seed),
            model,
            prob,
            prior="implicit",
            n_particles=300,
            beta=0.1,
            noise=0.03,
            likelihood_sigma=10.0,
        )
        rc = track(
            jax.random.PRNGKey(seed),
            model,
            prob,
            prior="constant_velocity",
            n_particles=3000,
            cv_noise=0.3,
            likelihood_sigma=10.0,
        )
        a, c = 1000 * float(np.mean(ri.error)), 1000 * float(np.mean(rc.error))
        out.append((i, seed, a, c))
        print(i, seed, f"implicit300 {a:.0f} mm  cv3000 {c:.0f} mm", flush=True)
print("mean", np.mean([o[2] for o in out]), np.mean([o[3] for o in out]))
