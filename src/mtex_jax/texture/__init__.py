"""Motion Texture (Li, Wang & Shum 2002): textons (second-order LDS), their fitting and
likelihoods, learning by EM (also data-parallel over the processes of a ``jax.distributed`` job:
:func:`learn_distributed`), segmentation, texton paths and synthesis.
"""

from ._config import (
    LearnConfig as LearnConfig,
)
from ._learning.distributed import (
    learn_distributed as learn_distributed,
)
from ._learning.init import (
    greedy_init as greedy_init,
    threshold_for_textons as threshold_for_textons,
)
from ._learning.learn import (
    bic_select as bic_select,
    learn as learn,
)
from ._model import (
    MotionTexture as MotionTexture,
    load_texture as load_texture,
)
from ._noise.innovation_process import (
    InnovationProcess as InnovationProcess,
    draw_innovations as draw_innovations,
    fit_innovation_process as fit_innovation_process,
    innovation_statistics as innovation_statistics,
    process_from_statistics as process_from_statistics,
    segment_innovations as segment_innovations,
)
from ._noise.residual_bank import (
    PLAUSIBLE_TAIL as PLAUSIBLE_TAIL,
    ResidualBank as ResidualBank,
    draw_residuals as draw_residuals,
    plausible_limit as plausible_limit,
    residual_bank as residual_bank,
)
from ._observation import (
    OBSERVATION_MODELS as OBSERVATION_MODELS,
    FullObservation as FullObservation,
    ObservationModel as ObservationModel,
    PaperObservation as PaperObservation,
    ResidualObservation as ResidualObservation,
    TiedObservation as TiedObservation,
    observation_model as observation_model,
)
from ._scoring.frame_terms import (
    frame_terms as frame_terms,
)
from ._scoring.frame_terms_ref import (
    init_terms as init_terms,
)
from ._scoring.scores import (
    SegmentScorer as SegmentScorer,
    segment_scores as segment_scores,
)
from ._segmentation.durations import (
    fit_durations as fit_durations,
    flat_durations as flat_durations,
)
from ._segmentation.forward import (
    forward_log_likelihood as forward_log_likelihood,
    log_likelihood as log_likelihood,
)
from ._segmentation.many import (
    log_likelihood_many as log_likelihood_many,
    segment_many as segment_many,
)
from ._segmentation.segment import (
    Segmentation as Segmentation,
    segment as segment,
    segment_scorer as segment_scorer,
    viterbi_segments as viterbi_segments,
)
from ._summary import texture_summary as texture_summary
from ._synthesis.checks import (
    DEFAULT_TRANSITION as DEFAULT_TRANSITION,
)
from ._synthesis.choreograph import (
    choreograph as choreograph,
    match_texton as match_texton,
)
from ._synthesis.paths import (
    MAX_SELF_REPEATS as MAX_SELF_REPEATS,
    path_cost as path_cost,
    path_of_length as path_of_length,
    random_path as random_path,
    shortest_path as shortest_path,
)
from ._synthesis.sequence import (
    CHUNK_FRAMES as CHUNK_FRAMES,
    Synthesis as Synthesis,
    SynthesisChunk as SynthesisChunk,
    SynthesisStream as SynthesisStream,
    synthesize as synthesize,
    synthesize_chunks as synthesize_chunks,
)
from ._synthesis.texton_synthesis import (
    synthesize_texton as synthesize_texton,
)
from ._texton.fit import (
    fit_texton as fit_texton,
    texton_from_stats as texton_from_stats,
)
from ._texton.lds_refine import (
    RefineReport as RefineReport,
    refine_texton as refine_texton,
)
from ._texton.likelihood import (
    exact_log_likelihood as exact_log_likelihood,
    exact_log_likelihood_segments as exact_log_likelihood_segments,
    segment_log_likelihood as segment_log_likelihood,
)
from ._texton.sample import (
    sample_texton as sample_texton,
)
from ._texton.select import (
    choose_state_dim as choose_state_dim,
    n_params as n_params,
)
from ._texton.stats import (
    DynamicsStats as DynamicsStats,
    FrameStats as FrameStats,
    Subspace as Subspace,
    dynamics_stats as dynamics_stats,
    frame_stats as frame_stats,
    subspace_from_stats as subspace_from_stats,
)
from ._texton.texton import (
    Texton as Texton,
    companion_matrix as companion_matrix,
    spectral_radius as spectral_radius,
    stack_textons as stack_textons,
)
from ._vocabulary import (
    SUCCESSOR_MIN as SUCCESSOR_MIN,
    Vocabulary as Vocabulary,
    vocabulary as vocabulary,
)

__all__ = [
    "CHUNK_FRAMES",
    "DEFAULT_TRANSITION",
    "MAX_SELF_REPEATS",
    "OBSERVATION_MODELS",
    "PLAUSIBLE_TAIL",
    "SUCCESSOR_MIN",
    "DynamicsStats",
    "FrameStats",
    "FullObservation",
    "InnovationProcess",
    "LearnConfig",
    "MotionTexture",
    "ObservationModel",
    "PaperObservation",
    "RefineReport",
    "ResidualBank",
    "ResidualObservation",
    "SegmentScorer",
    "Segmentation",
    "Subspace",
    "Synthesis",
    "SynthesisChunk",
    "SynthesisStream",
    "Texton",
    "TiedObservation",
    "Vocabulary",
    "bic_select",
    "choose_state_dim",
    "choreograph",
    "companion_matrix",
    "draw_innovations",
    "draw_residuals",
    "dynamics_stats",
    "exact_log_likelihood",
    "exact_log_likelihood_segments",
    "fit_durations",
    "fit_innovation_process",
    "fit_texton",
    "flat_durations",
    "forward_log_likelihood",
    "frame_stats",
    "frame_terms",
    "greedy_init",
    "init_terms",
    "innovation_statistics",
    "learn",
    "learn_distributed",
    "load_texture",
    "log_likelihood",
    "log_likelihood_many",
    "match_texton",
    "n_params",
    "observation_model",
    "path_cost",
    "path_of_length",
    "plausible_limit",
    "process_from_statistics",
    "random_path",
    "refine_texton",
    "residual_bank",
    "sample_texton",
    "segment",
    "segment_innovations",
    "segment_log_likelihood",
    "segment_many",
    "segment_scorer",
    "segment_scores",
    "shortest_path",
    "spectral_radius",
    "stack_textons",
    "subspace_from_stats",
    "synthesize",
    "synthesize_chunks",
    "synthesize_texton",
    "texton_from_stats",
    "texture_summary",
    "threshold_for_textons",
    "viterbi_segments",
    "vocabulary",
]
