"""Motion Texture (Li, Wang & Shum 2002): textons (second-order LDS), their fitting and
likelihoods, learning by EM, segmentation, texton paths and synthesis.
"""

from ._lds_refine import (
    RefineReport as RefineReport,
)
from ._lds_refine import (
    exact_log_likelihood_segments as exact_log_likelihood_segments,
)
from ._lds_refine import (
    refine_texton as refine_texton,
)
from ._learn import (
    LearnConfig as LearnConfig,
)
from ._learn import (
    MotionTexture as MotionTexture,
)
from ._learn import (
    bic_select as bic_select,
)
from ._learn import (
    greedy_init as greedy_init,
)
from ._learn import (
    learn as learn,
)
from ._learn import (
    load_texture as load_texture,
)
from ._learn import (
    texture_summary as texture_summary,
)
from ._learn import (
    threshold_for_textons as threshold_for_textons,
)
from ._linalg import (
    BandedSolution as BandedSolution,
)
from ._linalg import (
    BlockTridiagCholesky as BlockTridiagCholesky,
)
from ._linalg import (
    block_banded_matvec as block_banded_matvec,
)
from ._linalg import (
    block_banded_solve as block_banded_solve,
)
from ._linalg import (
    block_banded_solve_status as block_banded_solve_status,
)
from ._linalg import (
    block_tridiag_cholesky as block_tridiag_cholesky,
)
from ._linalg import (
    block_tridiag_solve as block_tridiag_solve,
)
from ._paths import (
    path_cost as path_cost,
)
from ._paths import (
    path_of_length as path_of_length,
)
from ._paths import (
    random_path as random_path,
)
from ._paths import (
    shortest_path as shortest_path,
)
from ._segment import (
    Segmentation as Segmentation,
)
from ._segment import (
    segment as segment,
)
from ._segment import (
    segment_scorer as segment_scorer,
)
from ._segment import (
    viterbi_segments as viterbi_segments,
)
from ._sequence import (
    Synthesis as Synthesis,
)
from ._sequence import (
    choreograph as choreograph,
)
from ._sequence import (
    match_texton as match_texton,
)
from ._sequence import (
    synthesize as synthesize,
)
from ._synthesis import (
    synthesize_texton as synthesize_texton,
)
from ._texton import (
    DynamicsStats as DynamicsStats,
)
from ._texton import (
    FrameStats as FrameStats,
)
from ._texton import (
    SegmentScorer as SegmentScorer,
)
from ._texton import (
    Subspace as Subspace,
)
from ._texton import (
    Texton as Texton,
)
from ._texton import (
    companion_matrix as companion_matrix,
)
from ._texton import (
    dynamics_stats as dynamics_stats,
)
from ._texton import (
    exact_log_likelihood as exact_log_likelihood,
)
from ._texton import (
    fit_texton as fit_texton,
)
from ._texton import (
    frame_stats as frame_stats,
)
from ._texton import (
    frame_terms as frame_terms,
)
from ._texton import (
    init_terms as init_terms,
)
from ._texton import (
    sample_texton as sample_texton,
)
from ._texton import (
    segment_log_likelihood as segment_log_likelihood,
)
from ._texton import (
    segment_scores as segment_scores,
)
from ._texton import (
    spectral_radius as spectral_radius,
)
from ._texton import (
    stack_textons as stack_textons,
)
from ._texton import (
    subspace_from_stats as subspace_from_stats,
)
from ._texton import (
    texton_from_stats as texton_from_stats,
)

__all__ = [
    "BandedSolution",
    "BlockTridiagCholesky",
    "DynamicsStats",
    "FrameStats",
    "LearnConfig",
    "MotionTexture",
    "RefineReport",
    "SegmentScorer",
    "Segmentation",
    "Subspace",
    "Synthesis",
    "Texton",
    "bic_select",
    "block_banded_matvec",
    "block_banded_solve",
    "block_banded_solve_status",
    "block_tridiag_cholesky",
    "block_tridiag_solve",
    "choreograph",
    "companion_matrix",
    "dynamics_stats",
    "exact_log_likelihood",
    "exact_log_likelihood_segments",
    "fit_texton",
    "frame_stats",
    "frame_terms",
    "greedy_init",
    "init_terms",
    "learn",
    "load_texture",
    "match_texton",
    "path_cost",
    "path_of_length",
    "random_path",
    "refine_texton",
    "sample_texton",
    "segment",
    "segment_log_likelihood",
    "segment_scorer",
    "segment_scores",
    "shortest_path",
    "spectral_radius",
    "stack_textons",
    "subspace_from_stats",
    "synthesize",
    "synthesize_texton",
    "texton_from_stats",
    "texture_summary",
    "threshold_for_textons",
    "viterbi_segments",
]
