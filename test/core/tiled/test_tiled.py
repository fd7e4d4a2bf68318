"""The tiled build: tile tasks from clips equal the live tiles' functions, and the map is the same
in one process and on a Dask LocalCluster of two workers (ids and geometry)."""

from __future__ import annotations

import numpy as np
import pytest
from tiled_fleet import same_map, small_fleet

from hdmap_core.errors import ConfigError, NoUsableDataError
from hdmap_core.live.tiles import TileConfig, map_tile, observe_tile
from hdmap_core.pipeline import presets
from hdmap_core.tiled import tasks
from hdmap_core.tiled.build import build_tiled
from hdmap_core.tiled.clips import MemorySource
from hdmap_core.tiled.cluster import SerialRunner


@pytest.mark.slow
def test_tasks_from_clips_equal_the_live_tiles_on_full_drives():
    drives = small_fleet()
    tc = TileConfig(tile_size_m=256.0, margin_m=96.0)
    pc = presets.preset("default")
    src = MemorySource(drives, tc)
    key = max(src.tiles(), key=lambda k: len(src.drive_ids(k)))  # the busiest tile
    covering = [d for d in drives if d.drive_id in set(src.drive_ids(key))]
    obs = tasks.observe(src, pc, key)
    ref = observe_tile(covering, key, tile_config=tc, pipeline_config=pc)
    assert len(obs) == len(ref) > 0
    assert [(o.pivot_id, o.index) for o in obs] == [(o.pivot_id, o.index) for o in ref]
    from hdmap_core.live.tiles import fleet_offsets

    model = fleet_offsets(obs, pipeline_config=pc)
    graphs = tasks.map_connect(src, pc, key, tasks.model_of(model, src.drive_ids(key)))
    from hdmap_core.live.tiles import connect_tile

    ref_graphs = connect_tile(
        map_tile(covering, key, tile_config=tc, pipeline_config=pc, offset_model=model), key, pipeline_config=pc
    )
    assert len(graphs) == len(ref_graphs) > 0
    for g, r in zip(graphs, ref_graphs):
        assert g.key == r.key
        np.testing.assert_array_equal(g.node_xy, r.node_xy)
        np.testing.assert_array_equal(g.node_uid, r.node_uid)
    # the offsets restricted to the tile's drives are the fleet model's for them
    small = tasks.model_of(model, src.drive_ids(key))
    for did in src.drive_ids(key):
        s = np.linspace(0, 500, 7)
        np.testing.assert_array_equal(small.offset(did, s), model.offset(did, s))
    assert set(small.drives) <= set(src.drive_ids(key))


@pytest.mark.slow
def test_tiled_build_is_the_same_map_on_one_process_and_on_two_dask_workers():
    pytest.importorskip("distributed")
    from hdmap_core.tiled.cluster import DaskRunner

    drives = small_fleet()
    src = MemorySource(drives, TileConfig(tile_size_m=384.0, margin_m=96.0))
    pc = presets.preset("default")
    one = build_tiled(src, config=pc, runner=SerialRunner())
    runner = DaskRunner.local(2)
    try:
        assert runner.workers == 2
        two = build_tiled(src, config=pc, runner=runner)
        # the stitch per region of one tile on the workers, joined across the borders: the same map
        regional = build_tiled(src, config=pc, runner=runner, stitch_tiles=1)
    finally:
        runner.close()
    same_map(one.map, two.map)
    same_map(one.map, regional.map)
    assert len({(k[0], k[1]) for k in src.tiles()}) > 2 and regional.report.graphs == one.report.graphs
    assert "stitching" not in regional.report.stage_seconds
    assert one.report.tiles == two.report.tiles == len(src.tiles())
    assert one.report.observations == two.report.observations > 0
    peaks = two.report.peak_rss_mb
    assert set(peaks) >= {"main", "scheduler"} and sum(k.startswith("worker") for k in peaks) == 2


@pytest.mark.slow
def test_tiled_build_maps_the_road_as_the_whole_fleet_build_does():
    from hdmap_core.pipeline.driver import build_map

    drives = small_fleet()
    pc = presets.preset("default")
    tiled = build_tiled(MemorySource(drives, TileConfig(tile_size_m=512.0, margin_m=128.0)), config=pc).map
    whole = build_map(drives, config=pc).map

    def points(m):
        return np.vstack([np.asarray(f.points) for f in m.features])

    from scipy.spatial import cKDTree

    # every point of either map lies near a point of the other (the same lines, other pivots)
    for a, b in ((points(tiled), points(whole)), (points(whole), points(tiled))):
        d, _ = cKDTree(b).query(a)
        assert np.median(d) < 0.5 and np.mean(d < 2.0) > 0.95


@pytest.mark.slow
def test_regional_stitch_in_one_process_is_the_global_stitch():
    drives = small_fleet(n=5)
    src = MemorySource(drives, TileConfig(tile_size_m=256.0, margin_m=96.0))
    pc = presets.preset("default")
    one = build_tiled(src, config=pc)
    for n in (1, 2):
        same_map(one.map, build_tiled(src, config=pc, stitch_tiles=n).map)
    with pytest.raises(ConfigError):
        build_tiled(src, config=pc, stitch_tiles=0)


def test_tiled_build_needs_a_tile():
    with pytest.raises(NoUsableDataError):
        build_tiled(MemorySource([], TileConfig()), config=presets.preset("default"))


@pytest.mark.slow
def test_tiled_build_without_adjustment_runs_one_pass_per_tile():
    drives = small_fleet(n=5)
    pc = presets.preset("naive")
    assert pc.final_pass is None
    res = build_tiled(MemorySource(drives, TileConfig(tile_size_m=512.0, margin_m=128.0)), config=pc)
    assert res.report.observations == 0 and "adjustment" not in res.report.stage_seconds
    assert len(res.map.features) > 0
