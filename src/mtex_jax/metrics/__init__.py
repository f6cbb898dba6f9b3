"""Motion quality, measured: held-out likelihood and prediction against baselines, realism of
joint speed/acceleration/jerk distributions, foot contacts, skating and floor penetration,
transitions, and novelty (SPEC §10.4).
"""

# --- likelihood baselines and prediction (baselines module) ---

# --- motion metrics (realism, contacts, transitions, novelty) ---

__all__: list[str] = []
