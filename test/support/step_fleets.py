"""Step-observation fleets for the offset adjustment's tests (``simulation.chains``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from hdmap_core.simulation.chains import ChainSimConfig, SimTruth, simulate_step_observations
from hdmap_core.steps import StepObservations

LANE_SHIFT_M = 2.5  # the extra bias of the victim drive


def lane_ambiguous_fleet(base: ChainSimConfig, *, seed: int = 8) -> tuple[list[StepObservations], SimTruth, str]:
    """Dashed lines 3.5 m apart, rarely seen borders outside, and the longest drive moved by
    ``LANE_SHIFT_M``: by raw position most of its dashed samples are nearer the neighbouring line
    (a whole-drive lane ambiguity), so the re-association and the lane-shift search have work to
    do. Returns (observations, truth, the moved drive's id)."""
    sim = replace(
        base,
        line_offsets_m=(-7.0, -3.5, 0.0, 3.5, 7.0),
        line_types=(3, 2, 2, 2, 3),
        line_detect_prob=(0.15, 0.9, 0.9, 0.9, 0.15),
    )
    obs, truth = simulate_step_observations(config=sim, seed=seed)
    victim = truth.drive_ids[int(np.argmax([g[-1] - g[0] for g in truth.grid_s_m]))]
    moved = []
    for o in obs:
        hit = np.asarray(o.drive_ids) == victim
        moved.append(replace(o, lateral_m=np.where(hit, o.lateral_m + LANE_SHIFT_M, o.lateral_m)) if hit.any() else o)
    return moved, truth, victim
