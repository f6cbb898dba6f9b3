"""The texton (design §2, §3): its container, sufficient statistics, closed-form fit with
Student-t IRLS, choice of the state dimension, direct and Kalman likelihoods, EM refinement
and sampling. Modules import each other's public-spelled names; the API is
``mtex_jax.texture``.
"""
