"""Motion editing as optimisation through the differentiable decode and forward kinematics
(design §6): pose edits ("the right hand here at frame m, the texton's dynamics otherwise"),
foot contacts and the floor, and cleaning of synthesised motion. Two solvers of the same
least squares: Gauss–Newton with the banded normal equations (the default; root trajectory held
for edits, a smooth root offset for cleaning; ``vmap``-batched by :func:`edit_many`) and
optimistix's Levenberg–Marquardt with conjugate gradients and an L-BFGS fallback
(``solver="lm"``; needed for velocity targets).
"""

from ._api import (
    edit as edit,
    edit_many as edit_many,
    edit_residuals as edit_residuals,
    segments_of as segments_of,
)
from ._banded.solve import (
    BandedGaussNewton as BandedGaussNewton,
    BandedProblem as BandedProblem,
    BandedSolve as BandedSolve,
    solve_banded as solve_banded,
)
from ._banded.terms import (
    Columns as Columns,
    FrameResidual as FrameResidual,
    HeightBounds as HeightBounds,
    PointTargets as PointTargets,
    ResidualTerm as ResidualTerm,
    RootOffset as RootOffset,
    Rows as Rows,
)
from ._clean import (
    CleanResult as CleanResult,
    clean as clean,
    clean_weights as clean_weights,
    contact_plants as contact_plants,
    load_contacts as load_contacts,
    save_contacts as save_contacts,
    swing_guidance as swing_guidance,
)
from ._constraints import (
    Constraints as Constraints,
    EditWeights as EditWeights,
    make_constraints as make_constraints,
)
from ._jacobians import channel_colouring as channel_colouring
from ._prior import (
    FrameSegments as FrameSegments,
    WhitenedTextons as WhitenedTextons,
    frame_segments as frame_segments,
    prior_hessian as prior_hessian,
    prior_residuals as prior_residuals,
    smoothness_hessian as smoothness_hessian,
)
from ._solve import EditResult as EditResult, solve_edit as solve_edit
from ._synth import synthesize as synthesize

__all__ = [
    "BandedGaussNewton",
    "BandedProblem",
    "BandedSolve",
    "CleanResult",
    "Columns",
    "Constraints",
    "EditResult",
    "EditWeights",
    "FrameResidual",
    "FrameSegments",
    "HeightBounds",
    "PointTargets",
    "ResidualTerm",
    "RootOffset",
    "Rows",
    "WhitenedTextons",
    "channel_colouring",
    "clean",
    "clean_weights",
    "contact_plants",
    "edit",
    "edit_many",
    "edit_residuals",
    "frame_segments",
    "load_contacts",
    "make_constraints",
    "prior_hessian",
    "prior_residuals",
    "save_contacts",
    "segments_of",
    "smoothness_hessian",
    "solve_banded",
    "solve_edit",
    "swing_guidance",
    "synthesize",
]
