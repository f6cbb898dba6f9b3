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

#: The untied residual textons with the paper's greedy initialisation (the defaults before the
#: tied textons): tests of the subspace machinery that choose ``state_dim`` or a greedy
#: ``threshold`` pin them with ``**UNTIED``.
UNTIED = dict(observation="residual", init="greedy")
