"""White-box building blocks for tests and advanced users (the one documented internal
namespace, as ``optimistix.internal``).

Nothing here is part of the stable API: these are the kernels and helpers that the public
functions are built from, exposed so that tests can check them against independent references
without importing private modules. Nothing in the package imports this module.
"""

# the implicit model: tree-sampling kernels, for eqx.debug.get_num_traces
from ..implicit._tree import (
    _sample_exact_traced as sample_exact_traced,
    _sample_tree_traced as sample_tree_traced,
)

# the implicit model: FeatureMap encoding of a clip, padded to share compilations
from ..implicit._windows import _encode as encode_motion

# DeepMimic: the number of values in one frame of a humanoid3d clip
from ..io._deepmimic import FRAME_SIZE as DEEPMIMIC_FRAME_SIZE

# block-tridiagonal Cholesky kernels behind block_tridiag_solve (right-hand sides as rows)
from ..linalg._blocktridiag import (
    block_tridiag_factor as block_tridiag_factor,
    solve_rows_fused as solve_rows_fused,
    solve_rows_plain as solve_rows_plain,
    solve_rows_unbatched as solve_rows_unbatched,
    substitute_rows as substitute_rows,
)

# rotations: angles wrapped to (-π, π]
from ..motion._rotation import wrap_angle as wrap_angle

# texton synthesis noise: Box-Muller standard normals and the polynomial cos/sin of 2πu
from ..texture._noise.draws import (
    sincos_turn as sincos_turn,
    standard_normal as standard_normal,
)

# frame terms: the jitted kernel (to spy on) and the traced kernels (to count traces)
from ..texture._scoring.frame_terms import (
    frame_terms_jit as frame_terms_jit,
    frame_terms_traced as frame_terms_traced,
)
from ..texture._scoring.frame_terms_ref import (
    all_terms_traced as all_terms_traced,
    frame_terms_per_texton as frame_terms_per_texton,
)

# frame terms over threads: usable cores and the number of concurrent executions
from ..texture._scoring.workers import (
    available_cores as available_cores,
    n_parts as frame_terms_parts,
)

# texton synthesis: whether the bridge recursion is accurate for a texton and length
from ..texture._synthesis.bridge import bridge_usable as bridge_usable

# key poses of a texton path: training-segment chains and outlier key-pose pairs
from ..texture._synthesis.keyposes import (
    key_pair_jumps as key_pair_jumps,
    key_pose_instances as key_pose_instances,
    next_segments as next_segments,
    usable_key_poses as usable_key_poses,
)

# constrained texton synthesis: the masked normal equations and their banded solve
from ..texture._synthesis.normal import (
    constrained_equations as constrained_equations,
    normal_system as constrained_normal_system,
    observe as observe_states,
    solve_constrained as solve_constrained,
)

# path synthesis: the core computation of a whole texton path (one compilation per size)
from ..texture._synthesis.sequence import path_core as path_core

# texton synthesis noise of one texton: independent or from an innovation process
from ..texture._synthesis.texton_synthesis import draw_noise as draw_noise

# texton fitting: the traced kernel, for eqx.debug.get_num_traces
from ..texture._texton.fit import fit_texton_traced as fit_texton_traced

# the array fields of a Texton, in file order
from ..texture._texton.texton import TEXTON_FIELDS as TEXTON_FIELDS

# rendering: world-to-plot rotations taking each up axis (0, 1, 2) to plot z
from ..viz._panel import TO_PLOT as TO_PLOT

__all__ = [
    "DEEPMIMIC_FRAME_SIZE",
    "TEXTON_FIELDS",
    "TO_PLOT",
    "all_terms_traced",
    "available_cores",
    "block_tridiag_factor",
    "bridge_usable",
    "constrained_equations",
    "constrained_normal_system",
    "draw_noise",
    "encode_motion",
    "fit_texton_traced",
    "frame_terms_jit",
    "frame_terms_parts",
    "frame_terms_per_texton",
    "frame_terms_traced",
    "key_pair_jumps",
    "key_pose_instances",
    "next_segments",
    "observe_states",
    "path_core",
    "sample_exact_traced",
    "sample_tree_traced",
    "sincos_turn",
    "solve_constrained",
    "solve_rows_fused",
    "solve_rows_plain",
    "solve_rows_unbatched",
    "standard_normal",
    "substitute_rows",
    "usable_key_poses",
    "wrap_angle",
]
