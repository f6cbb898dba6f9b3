"""The paper's learning settings (white residual, flat durations, EM's textons kept, no pruning,
no stability projection): the defaults before issue 16. Tests of the paper's machinery (and
those whose fixtures need several textons from tiny data) pin them with ``**PAPER``."""

PAPER = dict(observation="paper", durations="flat", selection="none", min_segments=1, rho_max=None)
