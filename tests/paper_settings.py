"""The paper's learning settings (white residual, flat durations, EM's textons kept, no pruning,
no stability projection), as ``LearnConfig.paper()`` sets them, without its state dimension.
Tests of the paper's machinery (and those whose fixtures need several textons from tiny data)
pin them with ``**PAPER``."""

import dataclasses

from mtex_jax import LearnConfig

_DEFAULTS = dataclasses.asdict(LearnConfig())
PAPER = {
    k: v
    for k, v in dataclasses.asdict(LearnConfig.paper()).items()
    if k != "state_dim" and v != _DEFAULTS[k]
}
