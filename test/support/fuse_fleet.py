"""The fast path's test fleet: 14 drives of 550-700 m over a 700 m synthetic motorway, sorted by
id (the last one is fused into the tiles the others settled)."""

from __future__ import annotations

from hdmap_core.model import Drive
from hdmap_core.simulation.fleet import SimConfig, simulate_fleet
from hdmap_core.simulation.synthetic import synthetic_highway

N_DRIVES = 14


def fuse_fleet() -> list[Drive]:
    gt = synthetic_highway("motorway", length_m=700.0, seed=1)
    sim = simulate_fleet(
        gt, config=SimConfig(n_drives=N_DRIVES, snippet_length_min_m=550.0, snippet_length_max_m=700.0), seed=4
    )
    return sorted(sim.drives, key=lambda d: d.drive_id)
