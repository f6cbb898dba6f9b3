"""Frame terms and segment scores (design §3.2–§3.3): the blocked kernel, the full-dimensional
stacked-lag kernel, the per-texton reference, worker threads, O(1) prefix-sum scores, clips
packed end to end, and segment rows.
"""
