"""A small simulated fleet and a map comparison shared by the tiled-build tests."""

from __future__ import annotations

import numpy as np


def small_fleet(n: int = 8, length_m: float = 1400.0, seed: int = 5):
    from hdmap_core.simulation.fleet import SimConfig, simulate_fleet
    from hdmap_core.simulation.synthetic import synthetic_highway

    gt = synthetic_highway("motorway", length_m=length_m, seed=seed)
    cfg = SimConfig(n_drives=n, snippet_length_min_m=600, snippet_length_max_m=1200)
    return simulate_fleet(gt, config=cfg, seed=seed).drives


def same_map(a, b) -> None:
    assert len(a.features) == len(b.features) > 0
    for f, g in zip(a.features, b.features):
        assert f.id == g.id and int(f.type) == int(g.type)
        np.testing.assert_array_equal(np.asarray(f.points), np.asarray(g.points))
        assert tuple(f.predecessors) == tuple(g.predecessors) and tuple(f.successors) == tuple(g.successors)
    assert [t.id for t in a.topology] == [t.id for t in b.topology]
    for t, u in zip(a.topology, b.topology):
        assert tuple(t.features) == tuple(u.features)
