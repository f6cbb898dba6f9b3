"""The settings of learning a motion texture (:class:`LearnConfig`)."""

from __future__ import annotations

import dataclasses
from typing import Any

from ._observation import ObservationModel, observation_model
from ._texton.checks import check_dof
from ._texton.validate import check_config_limits

# the paper's learning settings (see LearnConfig.paper)
_PAPER: dict[str, Any] = dict(
    state_dim=12,
    observation="paper",
    durations="flat",
    selection="none",
    min_segments=1,
    rho_max=None,
    dof=None,
    innovations="white",
    init="greedy",
)


@dataclasses.dataclass(frozen=True)
class LearnConfig:
    """Settings of :func:`learn` (lengths in frames).

    Attributes:
        tmin: shortest segment (frames, ``>= 3``); the paper uses about 1 s.
        tmax: longest segment (frames); ``None`` = unbounded (paper-exact, ``O(T²)``).
        state_dim: texton state dimension ``k`` (the paper: 12–15); ``None`` (default):
            ``D`` for the full-dimensional models (``"tied"``, ``"full"``), else chosen by BIC
            of one texton fitted on all the clips among 2, 4, … and ``D``
            (:func:`choose_state_dim`); when BIC chooses ``D`` there is no residual left and
            the textons are ``"full"``.
        threshold: greedy-initialisation error threshold (squared one-step prediction error
            per observation dimension, in the units of ``Y``: z-units for motions). ``None``:
            from ``n_textons``, else by BIC over ``bic_thresholds``, else 0.3.
        n_textons: with ``init="chunks"``: the initial number of textons (default ``None``:
            one per 4 chunks, so that the initial vocabulary grows with the data); with
            ``init="greedy"``: the target of the threshold search (used when ``threshold`` is
            ``None``).
        max_iter: most EM iterations.
        tol: EM has converged when the objective ``log P(Y, H)`` gains less than ``tol``
            per frame in an iteration (a change relative to the number of frames, not to the
            objective, whose sign can change during a learn; design §4.6).
        relabel_tol: EM has also converged when at most this share of the frames changed
            texton in an iteration (default 0: none changed). EM stops at convergence (or
            after ``max_iter`` iterations). A positive share stops EM earlier, with a
            different model.
        pseudo_count: Dirichlet pseudo-count added to transition and initial counts.
        fps: resample motions to this frame rate first (``None``: keep; all clips must agree).
        ridge, q_floor, sigma2_floor, init_prior_weight: texton fit regularisation (see
            :func:`fit_texton`).
        rho_max: bound on every texton's companion spectral radius (default 0.999: stable
            textons, so noise-driven synthesis stays bounded); ``None`` = unbounded (the
            paper). Not 1: a texton projected to a unit root keeps the drift ``d`` along it and
            walks away linearly (design §2.7).
        shard: split sequences across all JAX devices when there is more than one. ``None``
            (default): only when they are not CPU devices: XLA:CPU's devices of one process
            share one thread pool, and a learn on several of them stalled in an all-reduce
            that one device never joined (the salsa clips, 2 devices on 2 cores).
        bic_thresholds: thresholds to choose from by BIC (see :func:`bic_select`).
        observation: the observation model of every texton (see :class:`Texton`):
            ``"tied"`` (default: full-dimensional textons sharing their dynamics matrices,
            with per-texton offsets and covariances shrunk to a shared one, design §10.10: a
            new texton costs a move, not a 54-dimensional noise model, so the texture keeps a
            vocabulary), ``"residual"`` (the residual outside the state subspace follows its
            own AR(2)), ``"full"`` (``k = D``: untied AR(2) textons on ``y``, an
            autoregressive HSMM) or ``"paper"`` (MT-11: white residual noise); the registry is
            :data:`OBSERVATION_MODELS`. A member (``ResidualObservation()``) may be given; the
            config keeps its name, and :attr:`observation_model` is the member.
        durations: segment-length distribution of every texton on ``[tmin, tmax]``:
            ``"lognormal"`` (default: a discretised log-normal fitted in the M-step, mixed
            with 1 % of the flat one) or ``"flat"`` (the paper). With ``tmax=None`` the
            durations are flat.
        selection: ``"aic"`` (default): after (at most 5 iterations of) EM, the textons with
            the fewest segments are removed (half of them at first, fewer when that does not
            pay; the clips segmented again and EM rerun for at most 5 iterations) while that
            lowers ``AIC = −2 log P(Y, H) + 2p``, until removing a single texton does not; EM
            then runs to convergence on the textons kept. ``p`` counts the tied model's shrunk
            covariances by their effective number of parameters (design §10.10). The number of
            textons is chosen by the data: AIC estimates the held-out log-likelihood, and on
            folds of the training clips it kept the textons that generalise (design §10.10).
            ``"bic"``: the same with ``p log n`` (fewer textons). ``"none"``: keep EM's
            textons (the paper).
        dof: the dynamics innovations of full-dimensional textons (``k = D``: the
            ``"tied"`` and ``"full"`` models): Student-t
            with ``ν = dof`` degrees of freedom (default 4; see :class:`Texton`), or
            Gaussian (``None``, the paper). Each M-step fits the t by iteratively reweighted
            least squares and the E-step scores frames by the t density: capture glitches
            and sudden contacts cost far less, the fitted scale ``Q`` is that of typical
            frames, and sampled motion is far less jerky. Textons with ``k < D`` are
            Gaussian: when the state dimension resolves to ``k < D`` the learned model's
            config has ``dof=None``.
        innovations: the innovations of synthesis. ``"residuals"`` (default):
            :func:`synthesize` replays blocks of the training residuals themselves (a
            :class:`ResidualBank`, a block bootstrap: each texton on a path replays the
            whitened residuals of one of its own training segments; design §10.8). The model
            file then holds the residuals.
            ``"fitted"``: an :class:`InnovationProcess`, whose autocorrelation at lags 1–4
            and persistence of the Student-t scale are estimated on the training residuals;
            synthesis draws innovations with the same per-frame law and those dependences
            (also fitted with ``"residuals"``, for :func:`synthesize_texton`). ``"white"``:
            independent from frame to frame (the paper). The likelihood is that of
            independent innovations in every case.
        init: the initial segmentation. ``"chunks"`` (default): every clip cut into chunks
            of ``chunk_frames`` frames, clustered by k-means on their mean frames into
            ``n_textons`` textons (default: one per 4 chunks; design §10.10); EM's pruning of
            rare textons and the selection then set their number. ``"greedy"``: the greedy
            segmentation of MT §4 (``threshold``).
        chunk_frames: the chunk length of ``init="chunks"`` (default 80), clipped to
            ``[tmin, tmax]`` (:attr:`chunk_length`).
        min_segments: prune textons that the segmentation gives fewer training segments: after
            each E-step they are removed (``M``, ``π`` renormalised) and the clips segmented
            again by the remaining textons, which EM then refits (a texton fitted on one
            60-frame segment has unreliable dynamics). Default 3; ``1`` = no pruning (the paper).
    """

    tmin: int = 60
    tmax: int | None = 180
    state_dim: int | None = None
    threshold: float | None = None
    n_textons: int | None = None
    max_iter: int = 20
    tol: float = 1e-4
    relabel_tol: float = 0.0
    pseudo_count: float = 0.1
    fps: float | None = None
    ridge: float = 1e-6
    q_floor: float = 1e-6
    sigma2_floor: float = 1e-6
    rho_max: float | None = 0.999
    init_prior_weight: float = 4.0
    shard: bool | None = None
    bic_thresholds: tuple[float, ...] | None = None
    min_segments: int = 3
    observation: str = "tied"
    durations: str = "lognormal"
    selection: str = "aic"
    dof: float | None = 4.0
    innovations: str = "residuals"
    init: str = "chunks"
    chunk_frames: int = 80

    def __post_init__(self) -> None:
        if isinstance(self.min_segments, bool) or not isinstance(self.min_segments, int):
            raise ValueError(
                f"LearnConfig.min_segments must be a positive integer, got {self.min_segments!r}"
            )
        if self.min_segments < 1:
            raise ValueError(f"LearnConfig.min_segments must be >= 1, got {self.min_segments}")
        if not isinstance(self.tmin, int) or self.tmin < 3:
            raise ValueError(f"LearnConfig.tmin must be an integer >= 3, got {self.tmin!r}")
        if self.tmax is not None and (not isinstance(self.tmax, int) or self.tmax < self.tmin):
            raise ValueError(
                f"LearnConfig.tmax must be None or an integer >= tmin = {self.tmin}, "
                f"got {self.tmax!r}"
            )
        if isinstance(self.observation, ObservationModel):  # a member: the config keeps its name
            object.__setattr__(self, "observation", self.observation.name)
        try:
            observation_model(self.observation)
            check_dof(self.dof)
        except ValueError as e:
            raise ValueError(f"LearnConfig.{e}") from None
        if self.init not in ("greedy", "chunks"):
            raise ValueError(f"LearnConfig.init must be 'greedy' or 'chunks', got {self.init!r}")
        if isinstance(self.chunk_frames, bool) or not isinstance(self.chunk_frames, int):
            raise ValueError(
                f"LearnConfig.chunk_frames must be an integer, got {self.chunk_frames!r}"
            )
        if self.selection not in ("bic", "aic", "none"):
            raise ValueError(
                f"LearnConfig.selection must be 'bic', 'aic' or 'none', got {self.selection!r}"
            )
        if self.innovations not in ("fitted", "white", "residuals"):
            raise ValueError(
                "LearnConfig.innovations must be 'fitted', 'white' or 'residuals', "
                f"got {self.innovations!r}"
            )
        if self.durations not in ("flat", "lognormal"):
            raise ValueError(
                f"LearnConfig.durations must be 'flat' or 'lognormal', got {self.durations!r}"
            )
        if self.state_dim is not None and (
            not isinstance(self.state_dim, int) or self.state_dim < 1
        ):
            raise ValueError(
                f"LearnConfig.state_dim must be a positive integer, got {self.state_dim!r}"
            )
        if self.threshold is not None and not self.threshold > 0:
            raise ValueError(f"LearnConfig.threshold must be positive, got {self.threshold!r}")
        if self.n_textons is not None and (
            not isinstance(self.n_textons, int) or self.n_textons < 1
        ):
            raise ValueError(
                f"LearnConfig.n_textons must be a positive integer, got {self.n_textons!r}"
            )
        if not isinstance(self.max_iter, int) or self.max_iter < 0:
            raise ValueError(f"LearnConfig.max_iter must be >= 0, got {self.max_iter!r}")
        if not (isinstance(self.tol, int | float) and 0 <= self.tol < float("inf")):
            raise ValueError(f"LearnConfig.tol must be finite and >= 0, got {self.tol!r}")
        if not (isinstance(self.relabel_tol, int | float) and 0 <= self.relabel_tol < 1):
            raise ValueError(
                f"LearnConfig.relabel_tol must be a share in [0, 1), got {self.relabel_tol!r}"
            )
        if not self.pseudo_count > 0:
            raise ValueError(
                f"LearnConfig.pseudo_count must be positive, got {self.pseudo_count!r}"
            )
        if self.fps is not None and not self.fps > 0:
            raise ValueError(f"LearnConfig.fps must be positive, got {self.fps!r}")
        check_config_limits(self)  # sizes within the limits of mtex_jax.core, reals finite
        if self.init == "chunks" and (self.threshold is not None or self.bic_thresholds):
            raise ValueError(
                "LearnConfig.threshold and bic_thresholds belong to the greedy initialisation: "
                "give init='greedy' with them (the default init='chunks' has no threshold)"
            )

    @property
    def chunk_length(self) -> int:
        """The chunk length ``init="chunks"`` uses: ``chunk_frames`` clipped to
        ``[tmin, tmax]``."""
        hi = self.tmax if self.tmax is not None else max(self.chunk_frames, self.tmin)
        return min(max(self.chunk_frames, self.tmin), hi)

    @property
    def texton_dof(self) -> float | None:
        """The ``dof`` of the textons this config fits: ``dof`` for ``"full"`` ones, else
        ``None`` (textons with ``k < D`` are Gaussian)."""
        return self.dof if self.observation_model.student_t else None

    @property
    def observation_model(self) -> ObservationModel:
        """The member of :attr:`observation` (the model chosen, without parameters)."""
        return observation_model(self.observation)

    @classmethod
    def paper(cls, **overrides: Any) -> LearnConfig:
        """The paper's model (MT §4–5): ``k = 12``, white residual noise and innovations, flat
        durations,
        EM's textons kept (no selection, no pruning) and no stability projection.

        Args:
            **overrides: any other field (e.g. ``tmin``, ``fps``, ``min_segments``).

        Returns:
            The configuration; ``LearnConfig.paper().observation == "paper"``.
        """
        return cls(**{**_PAPER, **overrides})

    def to_json_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        if d["bic_thresholds"] is not None:
            d["bic_thresholds"] = list(d["bic_thresholds"])
        return d
