"""Building blocks for libraries built on mtex_jax (the one documented internal namespace, as
``optimistix.internal``).

Nothing here is part of the stable API. It holds the pieces of constrained texton synthesis
(design §5.3) that a downstream library reuses to pose its own constrained problems on a
texton: the noise of a texton, the masked least-squares problem, its normal equations, their
banded solve, and the observation of the solved states. Nothing in the package imports this
module, and tests count traces and spy on kernels themselves.
"""

# constrained texton synthesis: the noise, the masked normal equations, their banded solve and
# the observation of the states
from ..texture._synthesis.normal import (
    constrained_equations as constrained_equations,
    normal_system as constrained_normal_system,
    observe as observe_states,
    solve_constrained as solve_constrained,
)
from ..texture._synthesis.texton_synthesis import draw_noise as draw_noise

__all__ = [
    "constrained_equations",
    "constrained_normal_system",
    "draw_noise",
    "observe_states",
    "solve_constrained",
]
