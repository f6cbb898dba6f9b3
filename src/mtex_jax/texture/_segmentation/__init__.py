"""Segmentations (design §4.2, §10.1, §10.2): the semi-Markov Viterbi, the forward algorithm
(marginal likelihood) and segment-length distributions.
"""
