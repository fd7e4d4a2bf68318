"""Tests of hdmap_core.live.region: every tile of a map made by one build, cut into tiles."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.live.region import cut_into_tiles, map_region
from hdmap_core.live.tiles import TileConfig, select_steps, tile_bounds, tiles_of_drive
from hdmap_core.steps import Segment

from segment_samples import point_step, step_runs


def test_cut_into_tiles_keeps_of_each_tile_what_select_steps_keeps():
    # a pivot crossing tiles of 100 m: x = -30 .. 250, leaving (0, 0) for (0, 1) and coming back
    xs = [-30, -10, 0, 20, 99.9, 100, 150, 150, 199, 230, 250]
    ys = [5, 5, 5, 5, 5, 5, 5, 120, 5, 5, 5]
    seg = Segment("p", tuple(point_step("p", i, x, y) for i, (x, y) in enumerate(zip(xs, ys))))
    other = Segment("q", tuple(point_step("q", i, 10.0 * i, 50.0) for i in range(5)))
    keys = [(-1, 0), (0, 0), (1, 0), (2, 0), (1, 1), (5, 5)]
    out = cut_into_tiles([seg, Segment("e", ()), other], keys, tile_size_m=100.0)
    assert set(out) == set(keys) and out[(5, 5)] == []
    for k in keys:
        assert step_runs(out[k]) == step_runs(select_steps([seg, other], tile_bounds(k, tile_size_m=100.0)))
    assert step_runs(out[(1, 0)]) == [("p", [5, 6]), ("p", [8])]  # split where the pivot left the tile
    # steps in a tile not asked for are dropped
    assert step_runs(cut_into_tiles([seg], [(0, 0)], tile_size_m=100.0)[(0, 0)]) == [("p", [2, 3, 4])]


@pytest.mark.slow
def test_map_region_is_the_offline_pass_on_the_drive_set_cut_into_tiles():
    from hdmap_core.pipeline import presets
    from hdmap_core.pipeline.driver import map_stretches
    from hdmap_core.simulation.fleet import SimConfig, simulate_fleet
    from hdmap_core.simulation.synthetic import synthetic_highway

    gt = synthetic_highway("motorway", length_m=600.0, seed=3)
    fleet = simulate_fleet(gt, config=SimConfig(n_drives=4, snippet_length_min_m=400, snippet_length_max_m=500), seed=3)
    tc = TileConfig(tile_size_m=128.0, margin_m=64.0, seed=2)
    pc = presets.preset("default")
    keys = sorted({k for d in fleet.drives for k in tiles_of_drive(d, config=tc)})
    a = map_region(fleet.drives, keys, tile_config=tc, pipeline_config=pc)
    b = map_region(list(reversed(fleet.drives)), keys, tile_config=tc, pipeline_config=pc)  # any order
    whole = map_stretches(sorted(fleet.drives, key=lambda d: d.drive_id), config=pc, seed=2)
    assert set(a.segments) == set(keys) and a.model is not None
    n_steps = sum(len(s.steps) for s in whole.segments)
    assert n_steps > 0 and sum(len(s.steps) for k in keys for s in a.segments[k]) == n_steps  # every step once
    for k in keys:
        assert step_runs(a.segments[k]) == step_runs(b.segments[k])
        assert step_runs(a.segments[k]) == step_runs(select_steps(whole.segments, tile_bounds(k, tile_size_m=128.0)))
        for sa, sb in zip(a.segments[k], b.segments[k]):
            for x, y in zip(sa.steps, sb.steps):
                np.testing.assert_array_equal(x.lateral_m, y.lateral_m)


@pytest.mark.slow
def test_the_region_job_reading_its_drives_itself_makes_the_same_tiles():
    """The mapper's worker reads the region's drives from the store (``load_drives``), already
    checked when they came (``checked``): the tiles are those of the drives handed over."""
    from hdmap_core.live.jobs import run_job
    from hdmap_core.live.scheduler import REGION, Job
    from hdmap_core.pipeline import presets
    from hdmap_core.simulation.fleet import SimConfig, simulate_fleet
    from hdmap_core.simulation.synthetic import synthetic_highway

    gt = synthetic_highway("motorway", length_m=600.0, seed=4)
    fleet = simulate_fleet(gt, config=SimConfig(n_drives=4, snippet_length_min_m=400, snippet_length_max_m=500), seed=4)
    tc = TileConfig(tile_size_m=128.0, margin_m=64.0, seed=1)
    pc = presets.preset("default")
    keys = sorted({k for d in fleet.drives for k in tiles_of_drive(d, config=tc)})
    used = sorted(fleet.drives, key=lambda d: d.drive_id)[1:]  # a store may hold more than the job's drives
    job = Job(REGION, None, tuple(d.drive_id for d in used), "sig", final=True, tiles=tuple((k, ()) for k in keys))
    kw = {"tile_config": tc, "pipeline_config": pc, "use_fleet_model": True}
    handed = run_job(job, used, **kw)
    read = run_job(job, [], load_drives=lambda: list(reversed(fleet.drives)), **kw)
    checked = map_region(used, keys, tile_config=tc, pipeline_config=pc)
    assert set(read.tiles) == set(keys)
    for k in keys:
        assert step_runs(read.tiles[k]) == step_runs(handed.tiles[k]) == step_runs(checked.segments[k])
        for sa, sb in zip(read.tiles[k], checked.segments[k]):
            for x, y in zip(sa.steps, sb.steps):
                np.testing.assert_array_equal(x.lateral_m, y.lateral_m)
