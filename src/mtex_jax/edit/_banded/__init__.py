"""The banded Gauss–Newton solver of edits and cleaning (design §6.5, §6.6): :mod:`.solve`
minimises the banded objective with multiplier rounds, :mod:`.normal` factors and solves each
fresh step's normal equations, one frame per block.
"""
