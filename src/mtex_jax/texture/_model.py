"""The learned motion texture (MT §3): textons, the transition matrix and the metadata needed to
encode and decode motion, with its model file (``.npz`` arrays + JSON metadata, never
unpickled)."""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, Float, Int

from ..core import check_real, load_arrays_json, save_arrays_json
from ..motion import FeatureMap, Motion
from ._config import LearnConfig
from ._noise.innovation_process import InnovationProcess
from ._noise.residual_bank import ResidualBank
from ._segmentation.forward import log_likelihood
from ._segmentation.segment import Segmentation, segment
from ._texton.texton import Texton
from ._texton.validate import TEXTURE_MEMBERS, check_texture_arrays
from ._vocabulary import Vocabulary, vocabulary

FORMAT_VERSION = 1
_KIND = "mtex_jax.MotionTexture"


# ---------------------------------------------------------------------------------------------
# The model
# ---------------------------------------------------------------------------------------------
class MotionTexture(eqx.Module):
    """A learned motion texture: textons, their transition matrix and statistics.

    Attributes:
        textons: stacked :class:`Texton` (leading axis ``N_t``).
        M: ``(N_t, N_t)`` transition matrix, rows sum to 1 (``M[l, i] = P(i | l)``).
        pi: ``(N_t,)`` initial texton distribution.
        key_poses: ``(n_seg, 2, D)`` first two frames of every training segment.
        key_pose_labels: ``(n_seg,)`` texton of each key pose pair.
        segment_lengths: ``(n_seg,)`` length of every training segment.
        segments: ``(n_seg, 4)`` training segmentation rows ``(seq, start, length, label)``.
        history: ``(n_iter, 2)`` per EM iteration: objective after the M-step and after the
            E-step (log-likelihood of the segmentation).
        feature_map: the :class:`FeatureMap` of the training clips (``None`` for raw arrays).
        log_durations: ``(N_t, tmax − tmin + 1)`` log-probabilities of each texton's segment
            lengths ``tmin … tmax`` (``LearnConfig.durations``), or ``None``: flat (the paper).
        innovations: the :class:`InnovationProcess` synthesis draws innovations from, or
            ``None``: independent (``LearnConfig.innovations == "white"``, the paper).
        residuals: the :class:`ResidualBank` of the training residuals, or ``None``. When
            present (``LearnConfig.innovations == "residuals"``), :func:`synthesize` replays
            blocks of it instead of drawing from ``innovations``.
        config: the :class:`LearnConfig` (static).
        threshold: the greedy-initialisation threshold used (static).
    """

    textons: Texton
    M: Float[Array, "n n"]
    pi: Float[Array, " n"]
    key_poses: Float[Array, "s 2 D"]
    key_pose_labels: Int[Array, " s"]
    segment_lengths: Int[Array, " s"]
    segments: Int[Array, "s 4"]
    history: Float[Array, "it 2"]
    feature_map: FeatureMap | None
    config: LearnConfig = eqx.field(static=True)
    threshold: float = eqx.field(static=True)
    log_durations: Float[Array, "n L"] | None = None
    innovations: InnovationProcess | None = None
    residuals: ResidualBank | None = None

    def __check_init__(self) -> None:
        n = self.textons.n_textons if self.textons.is_stacked else 1
        if np.shape(self.M) != (n, n):
            raise ValueError(f"MotionTexture.M must have shape ({n}, {n}), got {np.shape(self.M)}")
        if np.shape(self.pi) != (n,):
            raise ValueError(f"MotionTexture.pi must have shape ({n},), got {np.shape(self.pi)}")
        s = np.shape(self.key_pose_labels)[0]
        if np.shape(self.key_poses)[:2] != (s, 2):
            raise ValueError("MotionTexture.key_poses must have shape (n_seg, 2, D)")
        if np.shape(self.segments) != (s, 4) or np.shape(self.segment_lengths) != (s,):
            raise ValueError("MotionTexture.segments / segment_lengths disagree with key poses")
        if self.log_durations is not None:
            tmax = self.config.tmax
            if tmax is None:
                raise ValueError("MotionTexture.log_durations need a finite config.tmax")
            want = (n, tmax - self.config.tmin + 1)
            if np.shape(self.log_durations) != want:
                raise ValueError(
                    f"MotionTexture.log_durations must have shape {want}, "
                    f"got {np.shape(self.log_durations)}"
                )
        if self.residuals is not None:
            k = int(np.shape(self.textons.C)[-1])
            if np.shape(self.residuals.rows)[1] != k:
                raise ValueError(
                    f"MotionTexture.residuals.rows must have {k} columns (the state "
                    f"dimension), got {np.shape(self.residuals.rows)}"
                )
            labels = self.residuals.labels
            if not isinstance(labels, Tracer) and np.asarray(labels).max() >= n:
                raise ValueError(f"MotionTexture.residuals.labels outside [0, {n})")

    @property
    def n_textons(self) -> int:
        return int(np.shape(self.M)[0])

    @property
    def obs_dim(self) -> int:
        return int(np.shape(self.textons.mu)[-1])

    def summary(self) -> Vocabulary:
        """The vocabulary as data (:class:`Vocabulary`): per texton its training segments,
        frames, mean duration, self-transition and successors (``M[i, j] ≥ 0.1``);
        ``print(tex.summary())`` shows it as a table."""
        return vocabulary(self)

    def length_stats(self) -> np.ndarray:
        """Per texton: ``(count, mean, std, min, max)`` of its training segment lengths."""
        out = np.zeros((self.n_textons, 5))
        lab = np.asarray(self.key_pose_labels)
        ln = np.asarray(self.segment_lengths)
        for i in range(self.n_textons):
            li = ln[lab == i]
            if li.size:
                out[i] = (li.size, li.mean(), li.std(), li.min(), li.max())
        return out

    def observations(self, Y: Float[Any, "T D"] | Motion) -> Array:
        """``Y (T, D)`` as given, or a :class:`Motion` encoded by the texture's feature map."""
        if isinstance(Y, Motion):
            if self.feature_map is None:
                raise ValueError("this texture was learned from arrays; pass observations Y")
            Y = self.feature_map.encode(Y)
        y = jnp.asarray(Y)
        if y.ndim != 2 or y.shape[1] != self.obs_dim:
            raise ValueError(f"Y must have shape (T, {self.obs_dim}), got {tuple(y.shape)}")
        return y

    def log_likelihood(self, Y: Float[Any, "T D"] | Motion, *, per_frame: bool = False) -> float:
        """Marginal ``log p(Y)`` over all segmentations and labels (design §10.1), in nats.

        The semi-Markov forward algorithm (:func:`~mtex_jax.texture.log_likelihood`); it is
        ``≥`` :meth:`best_path_log_likelihood`. ``per_frame=True`` divides by the number of
        frames ``T`` (every frame is scored: the first two of each segment by the texton's
        initial-state density). A density on the feature map's z-scored observation vectors.
        """
        y = self.observations(Y)
        ll = log_likelihood(
            self.textons,
            jnp.log(jnp.asarray(self.M)),
            jnp.log(jnp.asarray(self.pi)),
            y,
            self.config.tmin,
            self.config.tmax,
            log_durations=self.log_durations,
        )
        return float(ll) / (y.shape[0] if per_frame else 1)

    def best_path_log_likelihood(
        self, Y: Float[Any, "T D"] | Motion, *, per_frame: bool = False
    ) -> float:
        """``log p(Y, best segmentation)``: the score of :meth:`segment` (the E-step's
        objective), optionally divided by the number of frames."""
        y = self.observations(Y)
        return float(self.segment(y).score) / (y.shape[0] if per_frame else 1)

    def segment(self, Y: Float[Any, "T D"] | Motion) -> Segmentation:
        """Optimal segmentation of observations ``Y (T, D)`` (or a :class:`Motion`)."""
        y = self.observations(Y)
        return segment(
            self.textons,
            jnp.log(jnp.asarray(self.M)),
            jnp.log(jnp.asarray(self.pi)),
            y,
            self.config.tmin,
            self.config.tmax,
            log_durations=self.log_durations,
        )

    # ------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write to a ``.npz`` (arrays) with JSON metadata; no pickle."""
        arrays: dict[str, Any] = {
            f"texton.{f.name}": np.asarray(getattr(self.textons, f.name))
            for f in dataclasses.fields(self.textons)
            if f.name not in ("observation", "dof")
        }
        arrays.update(
            M=np.asarray(self.M),
            pi=np.asarray(self.pi),
            key_poses=np.asarray(self.key_poses),
            key_pose_labels=np.asarray(self.key_pose_labels),
            segment_lengths=np.asarray(self.segment_lengths),
            segments=np.asarray(self.segments),
            history=np.asarray(self.history),
        )
        if self.log_durations is not None:
            arrays["log_durations"] = np.asarray(self.log_durations)
        if self.innovations is not None:
            arrays["innovations.acf"] = np.asarray(self.innovations.acf)
            arrays["innovations.persistence"] = np.asarray(self.innovations.persistence)
        if self.residuals is not None:
            arrays["residuals.rows"] = np.asarray(self.residuals.rows)
            arrays["residuals.starts"] = np.asarray(self.residuals.starts)
            arrays["residuals.lengths"] = np.asarray(self.residuals.lengths)
            arrays["residuals.labels"] = np.asarray(self.residuals.labels)
            if self.residuals.segments is not None:
                arrays["residuals.segments"] = np.asarray(self.residuals.segments)
        meta: dict[str, Any] = {
            "kind": _KIND,
            "format_version": FORMAT_VERSION,
            "config": self.config.to_json_dict(),
            "threshold": self.threshold,
            "texton_fields": [
                f.name
                for f in dataclasses.fields(self.textons)
                if f.name not in ("observation", "dof")
            ],
            "observation": self.textons.observation,
            "dof": self.textons.dof,
            "feature_map": None,
        }
        if self.feature_map is not None:
            fa, fmeta = self.feature_map.to_arrays_json()
            arrays.update({f"feature_map.{k}": v for k, v in fa.items()})
            meta["feature_map"] = fmeta
        save_arrays_json(path, arrays, meta)


_REQUIRED = ("M", "pi", "key_poses", "key_pose_labels", "segment_lengths", "segments", "history")


def load_texture(path: str | os.PathLike[str]) -> MotionTexture:
    """Read a :class:`MotionTexture` written by :meth:`MotionTexture.save`.

    Raises:
        ValueError: naming the file and the problem (corrupt or truncated archive, another kind
            of file, unsupported format version, missing, unknown, too large or inconsistent
            arrays, NaN or inf values, a transition matrix or ``pi`` that is negative or not
            stochastic).
    """
    arrays, meta = load_arrays_json(path, kind=_KIND, required=_REQUIRED, allowed=TEXTURE_MEMBERS)
    check_texture_arrays(path, arrays)
    if meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(
            f"{path}: format version {meta.get('format_version')!r} is not supported "
            f"(this mtex_jax reads version {FORMAT_VERSION})"
        )
    try:
        fields = meta["texton_fields"]
        missing = [f for f in fields if f"texton.{f}" not in arrays]
        if missing:
            raise ValueError(f"missing arrays {['texton.' + f for f in missing]}")
        observation = meta.get("observation", "paper")  # files before the models: paper
        tf = {f: jnp.asarray(arrays[f"texton.{f}"]) for f in fields}
        # no res_*: the paper's residual; no dof: Gaussian innovations
        textons = Texton(**tf, observation=observation, dof=meta.get("dof"))
        fm = None
        if meta.get("feature_map") is not None:
            fa = {k.split(".", 1)[1]: v for k, v in arrays.items() if k.startswith("feature_map.")}
            fm = FeatureMap.from_arrays_json(fa, meta["feature_map"])
        old = {
            "observation": "paper",
            "durations": "flat",
            "selection": "none",
            "dof": None,
            "innovations": "white",
        }
        cfg_d = {**old, **meta["config"]}
        if cfg_d.get("bic_thresholds") is not None:
            cfg_d["bic_thresholds"] = tuple(cfg_d["bic_thresholds"])
        cfg = LearnConfig(**cfg_d)
        return MotionTexture(
            textons=textons,
            M=jnp.asarray(arrays["M"]),
            pi=jnp.asarray(arrays["pi"]),
            key_poses=jnp.asarray(arrays["key_poses"]),
            key_pose_labels=jnp.asarray(arrays["key_pose_labels"]),
            segment_lengths=jnp.asarray(arrays["segment_lengths"]),
            segments=jnp.asarray(arrays["segments"]),
            history=jnp.asarray(arrays["history"]),
            feature_map=fm,
            log_durations=(
                None if "log_durations" not in arrays else jnp.asarray(arrays["log_durations"])
            ),
            innovations=_innovations_of(arrays),
            residuals=_residuals_of(arrays),
            config=cfg,
            threshold=check_real(meta["threshold"], "threshold", low=0.0),
        )
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError, IndexError) as e:
        raise ValueError(f"{path}: invalid motion texture file: {e}") from None


def _innovations_of(arrays: dict[str, np.ndarray]) -> InnovationProcess | None:
    """The file's innovation process; ``None`` in files without one (independent)."""
    have = [k for k in ("innovations.acf", "innovations.persistence") if k in arrays]
    if not have:
        return None
    if len(have) != 2:
        raise ValueError("innovations.acf and innovations.persistence come together")
    return InnovationProcess(
        acf=jnp.asarray(arrays["innovations.acf"]),
        persistence=jnp.asarray(arrays["innovations.persistence"]),
    )


def _residuals_of(arrays: dict[str, np.ndarray]) -> ResidualBank | None:
    """The file's residual bank; ``None`` in files without one (its labels are checked
    against the textons by :class:`MotionTexture`)."""
    names = ("residuals.rows", "residuals.starts", "residuals.lengths", "residuals.labels")
    have = [k for k in names if k in arrays]
    if not have:
        return None
    if len(have) != len(names):
        raise ValueError(f"the arrays {', '.join(names)} come together")
    return ResidualBank(
        rows=jnp.asarray(arrays["residuals.rows"]),
        starts=jnp.asarray(arrays["residuals.starts"]),
        lengths=jnp.asarray(arrays["residuals.lengths"]),
        labels=jnp.asarray(arrays["residuals.labels"]),
        segments=(
            jnp.asarray(arrays["residuals.segments"]) if "residuals.segments" in arrays else None
        ),
    )


def texture_summary(tex: MotionTexture) -> str:
    """A short human-readable description (used by the CLI)."""
    st = tex.length_stats()
    hist = np.asarray(tex.history)
    lines = [
        f"textons: {tex.n_textons}   segments: {len(np.asarray(tex.segments))}   "
        f"state dim: {tex.config.state_dim}   D: {tex.obs_dim}   threshold: {tex.threshold:.4g}",
        f"observation model: {tex.textons.observation}   innovations: "
        + ("Gaussian" if tex.textons.dof is None else f"Student-t, {tex.textons.dof:g} dof"),
        "synthesis innovations: "
        + (
            f"blocks of the {np.shape(tex.residuals.rows)[0]} training residuals"
            if tex.residuals is not None
            else "independent"
            if tex.innovations is None
            else "autocorrelation "
            + ", ".join(f"{r:.2f}" for r in np.asarray(tex.innovations.acf))
            + f"; scale persistence {float(tex.innovations.persistence):.3f}"
        ),
        f"segment lengths (frames): min {int(st[:, 3][st[:, 0] > 0].min())}  "
        f"mean {np.asarray(tex.segment_lengths).mean():.1f}  max {int(st[:, 4].max())}  "
        f"(tmin {tex.config.tmin}, tmax {tex.config.tmax})",
        "objective per EM iteration (after M-step / after E-step):",
    ]
    lines += [f"  {i:2d}: {a:14.2f} / {b:14.2f}" for i, (a, b) in enumerate(hist)]
    return "\n".join(lines)
