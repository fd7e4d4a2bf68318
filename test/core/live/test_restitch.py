"""Tests of hdmap_core.live.restitch: the map moved in place after a fusion against the full
re-stitch of the same tiles (no DDS).

A fleet on a synthetic motorway is settled (the region job: the offline build cut into tiles);
one more drive is fused into the settled estimates (``live.fuse``). The moved map (the settled
map's stitch decisions kept, the feature nodes at the fused maxima) must lie within
``MOVED_TOLERANCE_M`` of the full re-connection and re-stitch of the fused tiles, and must have
moved as far as the fusion moved the lines.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import shapely
from fuse_fleet import fuse_fleet

from hdmap_core.errors import HdmapError
from hdmap_core.live.fuse import fuse_drive
from hdmap_core.live.region import map_region
from hdmap_core.live.restitch import (
    MOVED_TOLERANCE_M,
    moved_graphs,
    moved_map,
    raw_id_map,
    remap_ids,
    same_structure,
    stitch_tiles,
)
from hdmap_core.live.tiles import TileConfig, carry_over_ids, connect_tile, stitch_graphs, tiles_of_drive
from hdmap_core.pipeline import presets
from hdmap_core.segment_columns import segment_columns

from bag_samples import assert_maps_equal

TC = TileConfig(tile_size_m=256.0, margin_m=128.0, seed=0)


@pytest.fixture(scope="module")
def fused():
    """The settled tiles of all drives but one, that drive fused into them, and the config."""
    drives = fuse_fleet()
    pc = presets.preset("default")
    base, new = drives[:-1], drives[-1]
    keys = sorted(set().union(*[tiles_of_drive(d, config=TC) for d in base]))
    tiles = map_region(base, keys, tile_config=TC, pipeline_config=pc).segments
    res = fuse_drive(new, {k: tiles[k] for k in tiles_of_drive(new, config=TC) if k in tiles})
    assert res.tiles is not None, res.reason
    after = dict(tiles)
    after.update(res.tiles)
    return tiles, after, sorted(res.tiles), pc, drives


def _graphs(tiles, pc):
    return {k: connect_tile(tiles[k], k, pipeline_config=pc) for k in sorted(tiles)}


def _points_to_lines(a, b) -> np.ndarray:
    """Distance of every feature point of map ``a`` to the nearest line of its type in map ``b`` [m]."""
    out = []
    for t in {int(f.type) for f in a.features}:
        lines = [shapely.LineString(f.points[:, :2]) for f in b.features if int(f.type) == t and len(f.points) >= 2]
        pts = np.concatenate([f.points[:, :2] for f in a.features if int(f.type) == t])
        out.append(
            shapely.distance(shapely.points(pts), shapely.MultiLineString(lines)) if lines else np.full(len(pts), 9e9)
        )
    return np.concatenate(out)


def _same_topology(a, b) -> bool:
    return len(a.topology) == len(b.topology) and all(
        (x.id, x.heading, x.width, tuple(x.successors), tuple(x.features))
        == (y.id, y.heading, y.width, tuple(y.successors), tuple(y.features))
        and np.array_equal(x.position, y.position)
        for x, y in zip(a.topology, b.topology, strict=True)
    )


def test_moved_map_is_the_full_restitch_of_the_fused_tiles_within_the_tolerance(fused):
    before, after, touched, pc, _ = fused
    g0 = _graphs(before, pc)
    map0, mg = stitch_tiles([g for k in sorted(g0) for g in g0[k]], pipeline_config=pc, drive_ids=["a"])
    # stitch_tiles is stitch_graphs with the graph kept: the same map
    assert_maps_equal(map0, stitch_graphs([g for k in sorted(g0) for g in g0[k]], pipeline_config=pc, drive_ids=["a"]))
    moved = []
    for k in touched:
        m = moved_graphs(g0[k], before[k], after[k])
        assert m is not None, k  # a fusion only moves maxima
        assert [g.key for g in m] == [g.key for g in g0[k]]
        # the same graphs from the estimates in columns (the stitcher's: a batch message's as received)
        c = moved_graphs(g0[k], segment_columns(before[k]), segment_columns(after[k]))
        for x, y in zip(m, c, strict=True):
            assert x.drive_ids == y.drive_ids
            for f in ("node_xy", "node_count", "node_std", "node_uid", "node_type"):
                assert np.array_equal(getattr(x, f), getattr(y, f)), f
        moved.extend(m)
    fast, _ = moved_map(mg, moved, drive_ids=["a", "b"])
    assert fast.drive_ids == ("a", "b")
    # the export's decisions kept (the plan stitch_tiles keeps): unmoved, the map exactly as exported;
    # moved, the lines of the full export of the moved graph
    assert_maps_equal(mg.with_geometry([]).to_hdmap_planned(drive_ids=["a"]), mg.to_hdmap(drive_ids=["a"]))
    exported = mg.with_geometry(moved).to_hdmap(drive_ids=["a", "b"])
    assert np.mean(_points_to_lines(fast, exported)) <= 1e-6 and np.mean(_points_to_lines(exported, fast)) <= 1e-6
    g1 = _graphs(after, pc)
    full = stitch_graphs([g for k in sorted(g1) for g in g1[k]], pipeline_config=pc, drive_ids=["a", "b"])
    to_full, from_full = _points_to_lines(fast, full), _points_to_lines(full, fast)
    assert np.mean(to_full) <= MOVED_TOLERANCE_M and np.mean(from_full) <= MOVED_TOLERANCE_M
    assert np.mean(from_full > 0.1) < 0.01  # the full map's lines are in the moved one (coverage)
    # the fusion moved the lines, and the moved map with them: the old map is farther off
    assert np.mean(_points_to_lines(map0, full)) > 2 * max(np.mean(to_full), 1e-4)


def test_an_estimate_remade_by_the_settle_is_not_moved_and_graphs_of_another_map_are_refused(fused):
    before, after, touched, pc, drives = fused
    g0 = _graphs(before, pc)
    keys = sorted(before)
    remade = map_region(drives, keys, tile_config=TC, pipeline_config=pc).segments  # the settle with every drive
    k = next(k for k in touched if g0[k] and not same_structure(before[k], remade[k]))
    assert moved_graphs(g0[k], before[k], remade[k]) is None  # connected again instead
    shorter = [replace(s, steps=s.steps[:-1]) for s in before[k]]
    assert moved_graphs(g0[k], before[k], shorter) is None
    _, mg = stitch_tiles([g for kk in keys for g in g0[kk]], pipeline_config=pc)
    other = connect_tile(remade[k], k, pipeline_config=pc)
    bad = [g for g in other if g.key in set(mg.keys)]
    changed = [
        g
        for g in bad
        if not np.array_equal(g.node_uid, mg.graph(g.key).node_uid)
        or not np.array_equal(g.edges, mg.graph(g.key).edges)
    ]
    assert changed  # the settle made other maxima there
    with pytest.raises(HdmapError, match="same nodes and edges"):
        mg.with_geometry(changed[:1])
    with pytest.raises(HdmapError, match="not a graph of the map"):
        mg.with_geometry([replace(g0[k][0], key="nowhere@0")])


def test_ids_follow_the_raw_ids_of_the_previous_version(fused):
    before, after, touched, pc, _ = fused
    g0 = _graphs(before, pc)
    raw, mg = stitch_tiles([g for k in sorted(g0) for g in g0[k]], pipeline_config=pc)
    # a published version whose ids were renumbered (carried over from an older map)
    published = carry_over_ids(raw, None)
    renamed = replace(
        published,
        features=tuple(
            replace(f, id=int(f.id) + 7, predecessors=tuple(i + 7 for i in f.predecessors), successors=())
            for f in published.features
        ),
    )
    ids = raw_id_map(raw, renamed)
    moved = [g for k in touched for g in moved_graphs(g0[k], before[k], after[k]) or []]
    fast_raw, _ = moved_map(mg, moved)
    fast = remap_ids(fast_raw, ids)
    assert fast is not None
    assert [int(f.id) for f in fast.features] == [int(f.id) + 7 for f in fast_raw.features]
    have = {int(f.id) for f in fast.features}
    assert all(int(i) in have for f in fast.features for i in (*f.predecessors, *f.successors))
    assert all(int(i) in have for t in fast.topology for i in t.features)
    # the moved map keeps the topology (which maxima are nodes, where), not the feature geometry
    kept = remap_ids(fast_raw, raw_id_map(raw, published))
    assert kept is not None and _same_topology(kept, published)
    assert any(not np.array_equal(a.points, b.points) for a, b in zip(kept.features, published.features, strict=True))
    assert not _same_topology(kept, replace(published, topology=published.topology[1:]))
    assert remap_ids(fast_raw, {}) is None  # an id not known: carried over by shape instead
    assert remap_ids(fast_raw, {int(f.id): int(f.id) for f in fast_raw.features}) is fast_raw
