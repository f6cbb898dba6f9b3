"""The learned motion texture (MT §3): textons, the transition matrix and the metadata needed to
encode and decode motion, with its model file (``.npz`` arrays + JSON metadata, never
unpickled)."""

from __future__ import annotations

import os
from typing import Any, Literal, overload

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, Float, Int

from ..core import as_array, check_real, load_arrays_json, save_arrays_json
from ..motion import ContactModel, FeatureMap, Motion
from ._config import LearnConfig
from ._noise.innovation_process import InnovationProcess
from ._noise.residual_bank import ResidualBank
from ._observation import observation_model
from ._segmentation.forward import log_likelihood
from ._segmentation.many import log_likelihood_many, segment_many
from ._segmentation.path_terms import best_path_terms
from ._segmentation.segment import segment
from ._texton.texton import TEXTON_FIELDS, Texton
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
        contacts: the :class:`~mtex_jax.motion.ContactModel` of the training clips (feet,
            contact thresholds and the training floor, design §10.4) that
            :func:`mtex_jax.edit.synthesize` with ``clean=True`` uses; fitted by :func:`learn`
            from clips, ``None`` for a texture learned from observation arrays (static: it is
            metadata, never traced).
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
    contacts: ContactModel | None = eqx.field(default=None, static=True)

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
        if self.contacts is not None:
            fm = self.feature_map
            if not isinstance(self.contacts, ContactModel):
                raise TypeError("MotionTexture.contacts must be a ContactModel or None")
            if fm is None or not self.contacts.skeleton.same_structure(fm.skeleton):
                raise ValueError("MotionTexture.contacts must be on the feature map's skeleton")
            if float(self.contacts.fps) != float(fm.fps):
                raise ValueError(
                    f"MotionTexture.contacts are at {self.contacts.fps:g} Hz, the feature map "
                    f"at {fm.fps:g} Hz"
                )

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
        y = as_array(Y)
        if y.ndim != 2 or y.shape[1] != self.obs_dim:
            raise ValueError(f"Y must have shape (T, {self.obs_dim}), got {tuple(y.shape)}")
        return y

    def log_likelihood(
        self,
        Y: Float[Any, "T D"] | Motion | list[Any],
        *,
        mean: bool = False,
        per_frame: bool = False,
    ) -> Any:
        """Marginal ``log p(Y)`` over all segmentations and labels (design §10.1), in nats.

        The semi-Markov forward algorithm (:func:`~mtex_jax.texture.log_likelihood`); it is
        ``≥`` :meth:`best_path_log_likelihood`. ``mean=True`` divides by the number of frames
        ``T`` (every frame is scored: the first two of each segment by the texton's
        initial-state density). A density on the feature map's z-scored observation vectors.
        A list of clips is scored in one call (:func:`~mtex_jax.texture.log_likelihood_many`,
        design §11) and gives a ``(S,)`` array, one value per clip.

        Raises:
            ValueError: ``per_frame=True``: the marginal sums over every segmentation and has
                no exact per-frame decomposition (use ``mean=True``, or the best path's
                per-frame terms, :meth:`best_path_log_likelihood` with ``per_frame=True``).
        """
        if per_frame:
            raise ValueError(
                "log_likelihood(per_frame=True): the marginal log p(Y) sums over all "
                "segmentations and does not decompose exactly into per-frame terms; use "
                "mean=True for nats per frame (the total divided by T), or "
                "best_path_log_likelihood(Y, per_frame=True) for the per-frame terms of the "
                "best segmentation"
            )
        if isinstance(Y, list | tuple):
            ys = [self.observations(y) for y in Y]
            lls = np.asarray(log_likelihood_many(*self._dp_args(ys)))
            return lls / np.asarray([y.shape[0] for y in ys]) if mean else lls
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
        return float(ll) / (y.shape[0] if mean else 1)

    @overload
    def best_path_log_likelihood(
        self, Y: Float[Any, "T D"] | Motion, *, mean: bool = ..., per_frame: Literal[False] = ...
    ) -> float: ...

    @overload
    def best_path_log_likelihood(
        self, Y: Float[Any, "T D"] | Motion, *, mean: bool = ..., per_frame: Literal[True]
    ) -> np.ndarray: ...

    def best_path_log_likelihood(
        self, Y: Float[Any, "T D"] | Motion, *, mean: bool = False, per_frame: bool = False
    ) -> float | np.ndarray:
        """``log p(Y, best segmentation)``: the score of :meth:`segment` (the E-step's
        objective, design §3.1, §4.2), in nats.

        ``mean=True`` divides it by the number of frames ``T``. ``per_frame=True`` returns its
        exact decomposition ``(T,)`` (summing to the score): frame ``t`` of a segment
        ``[b, e]`` of texton ``i`` gets its observation term, plus its dynamics term for
        ``t ≥ b + 2``; the initial-state density of the segment's first two states is split
        by the chain rule, ``log p(x_b)`` at ``b`` and ``log p(x_{b+1} | x_b)`` at ``b + 1``;
        the segment's initial or transition log-probability (and its duration's, with
        learned durations) is added at ``b``.
        """
        if mean and per_frame:
            raise ValueError("mean=True and per_frame=True exclude each other")
        y = self.observations(Y)
        seg = self.segment(y)
        if per_frame:
            return best_path_terms(self, y, seg)
        return float(seg.score) / (y.shape[0] if mean else 1)

    def segment(self, Y: Float[Any, "T D"] | Motion | list[Any]) -> Any:
        """Optimal segmentation of observations ``Y (T, D)`` (or a :class:`Motion`); of a list
        of clips, a list of segmentations computed in one call (design §11)."""
        if isinstance(Y, list | tuple):
            return segment_many(*self._dp_args([self.observations(y) for y in Y]))
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

    def _dp_args(self, ys: list[Array]) -> tuple[Any, ...]:
        return (
            self.textons,
            jnp.log(jnp.asarray(self.M)),
            jnp.log(jnp.asarray(self.pi)),
            ys,
            self.config.tmin,
            self.config.tmax,
            self.log_durations,
        )

    # ------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write to a ``.npz`` (arrays) with JSON metadata; no pickle."""
        save_arrays_json(path, *self.to_arrays_json())

    def to_arrays_json(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """The arrays and the JSON metadata of the model file (:meth:`save`); read back by
        :func:`texture_of_arrays_json`."""
        arrays, tmeta = texton_arrays(self.textons)
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
            **tmeta,
            "feature_map": None,
        }
        if self.feature_map is not None:
            fa, fmeta = self.feature_map.to_arrays_json()
            arrays.update({f"feature_map.{k}": v for k, v in fa.items()})
            meta["feature_map"] = fmeta
        if self.contacts is not None:  # on the feature map's skeleton, at its frame rate
            arrays["contacts.height_threshold"] = np.asarray(self.contacts.height_threshold)
            arrays["contacts.speed_threshold"] = np.asarray(self.contacts.speed_threshold)
            meta["contacts"] = {
                "feet": [int(f) for f in self.contacts.feet],
                "floor": float(self.contacts.floor),
            }
            if self.contacts.stance is not None:
                meta["contacts"]["stance"] = float(self.contacts.stance)
        return arrays, meta


_REQUIRED = ("M", "pi", "key_poses", "key_pose_labels", "segment_lengths", "segments", "history")
_CONTACT_MEMBERS = ("contacts.height_threshold", "contacts.speed_threshold")


def load_texture(path: str | os.PathLike[str]) -> MotionTexture:
    """Read a :class:`MotionTexture` written by :meth:`MotionTexture.save`.

    Raises:
        ValueError: naming the file and the problem (corrupt or truncated archive, another kind
            of file, unsupported format version, missing, unknown, too large or inconsistent
            arrays, NaN or inf values, a transition matrix or ``pi`` that is negative or not
            stochastic).
    """
    arrays, meta = load_arrays_json(
        path, kind=_KIND, required=_REQUIRED, allowed=(*TEXTURE_MEMBERS, *_CONTACT_MEMBERS)
    )
    check_texture_arrays(path, arrays)
    if meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(
            f"{path}: format version {meta.get('format_version')!r} is not supported "
            f"(this mtex_jax reads version {FORMAT_VERSION})"
        )
    try:
        return texture_of_arrays_json(arrays, meta)
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError, IndexError) as e:
        raise ValueError(f"{path}: invalid motion texture file: {e}") from None


def texton_arrays(tex: Texton, prefix: str = "texton.") -> tuple[dict[str, np.ndarray], dict]:
    """A texton stack's arrays (``prefix`` + field: the dynamics core, then its observation
    member's parameters) and the metadata that reads them back (:func:`texton_of_arrays`):
    the model file's layout."""
    member = tex.observation.to_arrays(tex.sigma2)  # its parameters, or the white residual
    arrays = {
        f"{prefix}{f}": np.asarray(v)
        for f, v in [*((f, getattr(tex, f)) for f in TEXTON_FIELDS), *member.items()]
    }
    meta = {
        "texton_fields": [*TEXTON_FIELDS, *member],
        "observation": tex.observation.name,
        "dof": tex.dof,
    }
    return arrays, meta


def texton_of_arrays(
    arrays: dict[str, np.ndarray], meta: dict[str, Any], prefix: str = "texton."
) -> Texton:
    """The texton stack of :func:`texton_arrays`' arrays and metadata."""
    fields = meta["texton_fields"]
    missing = [f for f in fields if f"{prefix}{f}" not in arrays]
    if missing:
        raise ValueError(f"missing arrays {[prefix + f for f in missing]}")
    # files before the observation models: the paper's; no dof: Gaussian innovations
    choice = observation_model(meta.get("observation", "paper"))
    tf = {f: jnp.asarray(arrays[f"{prefix}{f}"]) for f in fields}
    core = {f: tf.pop(f) for f in TEXTON_FIELDS if f in tf}
    dof = meta.get("dof")
    return Texton(**core, observation=choice.from_arrays(tf), dof=dof)


def texture_of_arrays_json(arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> MotionTexture:
    """The :class:`MotionTexture` of a model file's arrays and metadata
    (:meth:`MotionTexture.to_arrays_json`; :func:`load_texture` checks them first)."""
    textons = texton_of_arrays(arrays, meta)
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
        contacts=_contacts_of(arrays, meta, fm),
        config=cfg,
        threshold=check_real(meta["threshold"], "threshold", low=0.0),
    )


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


def _contacts_of(
    arrays: dict[str, np.ndarray], meta: dict[str, Any], fm: FeatureMap | None
) -> ContactModel | None:
    """The file's training contacts, checked as a fitted :class:`ContactModel` is; ``None``
    in files without them (learned from arrays, or written before textures carried them)."""
    have = [k for k in _CONTACT_MEMBERS if k in arrays]
    c = meta.get("contacts")
    if not have and c is None:
        return None
    if len(have) != len(_CONTACT_MEMBERS) or not isinstance(c, dict):
        raise ValueError(
            f"contacts: the arrays {', '.join(_CONTACT_MEMBERS)} and the metadata 'contacts' "
            "come together"
        )
    if fm is None:
        raise ValueError("contacts: a texture without a feature map has no skeleton for them")
    try:
        return ContactModel(
            fm.skeleton,
            c["feet"],
            arrays["contacts.height_threshold"],
            arrays["contacts.speed_threshold"],
            c["floor"],
            fm.fps,
            c.get("stance"),
        )
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"contacts: {e}") from None


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
