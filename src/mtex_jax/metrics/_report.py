"""One quality report: held-out density and prediction of a motion texture beside the
baselines, and the motion metrics of generated clips beside the real-vs-real floor (design
§10.4). Used by ``mtex evaluate``, ``mtex demo`` and the quality benchmark.

Conventions:

- the *reference* of realism and penetration is the set of real clips the generated ones are
  judged against (the held-out clips), and the *floor* is the same distance between two real
  sets: the training clips against the held-out clips;
- contact thresholds and the floor height come from the training clips;
- novelty and copying are measured against the training clips (what a model may copy).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..motion import Motion
from ..texture import MotionTexture
from ._baselines import constant_velocity, fit_ar2, hold_last, prediction_error
from ._contacts import ContactModel, fit_contacts
from ._kinematics import as_motion_list
from ._novelty import copying, copying_from_indices, novelty
from ._prediction import predict_segmented
from ._realism import RealismResult, realism
from ._transitions import boundary_jumps, jump_p99

__all__ = ["MotionJudge", "density_report"]


class MotionJudge:
    """The real side of every motion metric, computed once: the floor of the realism
    distances, the contact model, the real p99 jump, and the real clips' own figures.

    Args:
        training: real training clips (contacts, floor height, novelty, copying).
        held_out: real held-out clips (the reference of realism and jumps).
        fps: the common frame rate of every metric.
        window: novelty window in seconds.
    """

    def __init__(
        self,
        training: Motion | Sequence[Motion],
        held_out: Motion | Sequence[Motion],
        *,
        fps: float,
        window: float = 1.0,
    ) -> None:
        self.training = as_motion_list(training, "MotionJudge (training)")
        self.held_out = as_motion_list(held_out, "MotionJudge (held out)")
        self.fps = float(fps)
        self.window = float(window)
        # with one set on both sides there is no real-vs-real floor (it would be zero)
        same = self.training is self.held_out or training is held_out
        self.floor: RealismResult | None = (
            None if same else realism(self.training, self.held_out, fps=self.fps)
        )
        self.contacts: ContactModel = fit_contacts(self.training, fps=self.fps)
        self.jump_threshold = jump_p99(self.held_out, self.fps)

    def judge(
        self,
        generated: Motion | Sequence[Motion],
        *,
        boundaries: Sequence[Any] | None = None,
        indices: Sequence[Any] | None = None,
        successor: Any = None,
        index_fps: float | None = None,
        copy: bool = True,
    ) -> dict[str, float | None]:
        """Every motion metric of ``generated`` as a flat dict of numbers.

        Args:
            generated: the clips judged.
            boundaries: per clip, the frames where a new texton starts (for transition jumps).
            indices: the database example chosen at every step, when the generator knows it
                (the implicit model); then copying is counted from it instead of nearest
                neighbours.
            successor: the successor array of that database (with ``indices``).
            index_fps: the frame rate of ``indices`` (with ``indices``).
            copy: measure nearest-neighbour copying (the slowest metric).
        """
        gen = as_motion_list(generated, "judge (generated)")
        r = realism(gen, self.held_out, fps=self.fps, floor=self.floor)
        sk = self.contacts.skating(gen)
        pen = self.contacts.penetration(gen)
        out: dict[str, float | None] = dict(
            speed_w1=r.speed,
            acceleration_w1=r.acceleration,
            jerk_w1=r.jerk,
            speed_ratio=r.speed_ratio,
            acceleration_ratio=r.acceleration_ratio,
            jerk_ratio=r.jerk_ratio,
            skating_median=sk.median,
            skating_p95=sk.p95,
            penetration_max=pen.max_depth,
            penetration_share=pen.share,
        )
        jumps = boundary_jumps(
            gen,
            boundaries if boundaries is not None else [np.zeros(0, int)] * len(gen),
            self.jump_threshold,
            fps=self.fps,
        )
        out["jump_share_above_p99"] = jumps.share_above
        if boundaries is not None:
            out.update(
                boundary_share_above_p99=jumps.boundary_share_above,
                boundary_max=jumps.boundary_max,
                boundary_median=jumps.boundary_median,
            )
        nov = novelty(gen, self.training, window=self.window, fps=self.fps)
        out["novelty_median"] = nov.median
        if indices is not None:
            if successor is None or index_fps is None:
                raise ValueError("judge: indices need successor and index_fps")
            c = copying_from_indices(indices, successor, index_fps)
            out.update(copy_fraction=c.fraction, copy_longest_s=c.longest_run)
        elif copy:
            c = copying(gen, self.training, fps=self.fps)
            out.update(copy_fraction=c.fraction, copy_longest_s=c.longest_run)
        return out

    def real_rows(self) -> dict[str, dict[str, float | None]]:
        """The real clips judged as if generated: the held-out clips (their realism against
        themselves is 0 by definition, so that row reports the training clips' instead, which is
        the floor: ratio 1) and their contacts, jumps, novelty and copying against training."""
        held = self.judge(self.held_out)
        if self.floor is None:
            return {"real (held out)": held}
        train_vs_held = realism(self.training, self.held_out, fps=self.fps, floor=self.floor)
        for q, v in zip(("speed", "acceleration", "jerk"), train_vs_held.distances, strict=True):
            held[f"{q}_w1"] = v
            held[f"{q}_ratio"] = 1.0
        return {"real (held out)": held}


def density_report(
    texture: MotionTexture,
    training: Sequence[Motion],
    held_out: Sequence[Motion],
    *,
    ridge: float = 1e-4,
) -> dict[str, dict[str, float]]:
    """Held-out log-likelihood per frame and one-step prediction error of a motion texture and
    of the closed-form baselines, all on the texture's observation vectors.

    Rows: ``"motion texture (marginal)"`` (the forward algorithm), ``"motion texture (best
    path)"``, ``"AR(2)"``, ``"constant velocity"``, ``"hold last frame"``. Columns:
    ``loglik_per_frame`` (nats, every held-out frame scored, summed over clips and divided by
    their frames), ``prediction_mse`` (mean squared one-step error per dimension, z-units),
    ``frames``.
    """
    if texture.feature_map is None:
        raise ValueError("density_report: the texture has no feature map; it needs motions")
    fm = texture.feature_map
    train_y = [np.asarray(fm.encode(m)) for m in training]
    held_y = [np.asarray(fm.encode(m)) for m in held_out]
    n = sum(len(y) for y in held_y)
    rows: dict[str, dict[str, float]] = {}
    # the clips as one list: one compiled forward and one Viterbi program for all (design §11)
    marg = float(np.sum(texture.log_likelihood(held_y)))
    segs = texture.segment(held_y)  # score and labels of each clip
    best = sum(float(seg.score) for seg in segs)
    preds = [predict_segmented(texture, y, seg)[0] for y, seg in zip(held_y, segs, strict=True)]
    err = prediction_error(
        np.concatenate([np.asarray(p) for p in preds]), np.concatenate([y[2:] for y in held_y])
    )
    rows["motion texture (marginal)"] = dict(loglik_per_frame=marg / n, prediction_mse=err)
    rows["motion texture (best path)"] = dict(loglik_per_frame=best / n, prediction_mse=err)
    for name, fit in (
        ("AR(2)", lambda ys: fit_ar2(ys, ridge=ridge)),
        ("constant velocity", constant_velocity),
        ("hold last frame", hold_last),
    ):
        model = fit(train_y)
        ll = sum(model.log_likelihood(y) for y in held_y)
        e = prediction_error(
            np.concatenate([np.asarray(model.predict(y)) for y in held_y]),
            np.concatenate([y[2:] for y in held_y]),
        )
        rows[name] = dict(loglik_per_frame=ll / n, prediction_mse=e)
    for r in rows.values():
        r["frames"] = float(n)
    return rows
