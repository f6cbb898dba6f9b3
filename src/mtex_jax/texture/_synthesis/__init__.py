"""Synthesis (design §5): texton paths, key poses, constrained per-texton synthesis (banded
normal equations and the bridge recursion), whole sequences and the virtual choreographer.
"""
