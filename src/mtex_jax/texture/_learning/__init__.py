"""Learning a motion texture (design §4): greedy initialisation, the EM loop (explicit state,
init / step / terminate), its E- and M-step kernels, texton labels, selection by BIC, and the
data-parallel learn over the processes of a ``jax.distributed`` job.
"""
