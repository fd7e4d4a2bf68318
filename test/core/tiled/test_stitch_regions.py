"""The stitch per region of tiles, joined across the region borders (``tiled.stitch``), gives the
map of the one global stitch: on a synthetic road through several regions, whose lines run on
only if the links across every border are made."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.errors import HdmapError
from hdmap_core.graph.map_graph import MapGraph, stitch
from hdmap_core.model import HDMap
from hdmap_core.pipeline import presets
from hdmap_core.tiled.stitch import halo_tiles_for, join_regions, stitch_by_regions, stitch_region

from segment_samples import LINES, B, S, conn, road

TILE_M = 200.0  # the tiles of these tests (each graph lies in one, as a tiled build's do)
DEFAULT = presets.preset("default").stitching


def _network():
    """An eastward road through tiles 0..4 (x 0..1000) and a second one 60 m north (tiles 0..2),
    in pieces of one pivot each: pieces meet at the tile borders (a link across them), two
    overlap at x 600 (one gives way), one ends 30 m short of the next (a loose-end join), and a
    dashed line turns solid in tile 3 (a type change inside a polyline's run)."""
    pieces = [
        road("a0", 0.0, 50),
        road("a1", 100.0, 50),
        road("a2", 200.0, 50),
        road("a3", 300.0, 50),
        road("a4", 400.0, 50),
        road("a5", 500.0, 50),
        road("a6", 600.0, 40, y_mid=0.3),  # x 600..678 overlaps a5's continuation a6b
        road("a6b", 600.0, 50, processed=set(range(5))),
        road("a7", 730.0, 35),  # after a 30 m gap: no step saw x 700..728
        road("a8", 800.0, 50, ([-3.5, 0.0, 3.5], [S, S, B])),
        road("a9", 900.0, 50, ([-3.5, 0.0, 3.5], [S, S, B])),
        road("n0", 0.0, 50, ([56.5, 60.0, 63.5], LINES[1]), y_mid=60.0),
        road("n1", 100.0, 50, ([56.5, 60.0, 63.5], LINES[1]), y_mid=60.0),
        road("n2", 200.0, 100, ([56.5, 60.0, 63.5], LINES[1]), y_mid=60.0),
        road("n3", 400.0, 50, ([56.5, 60.0, 63.5], LINES[1]), y_mid=60.0),
    ]
    graphs = [conn(p) for p in pieces]
    by_tile: dict[tuple[int, int], list] = {}
    for g in graphs:
        x = g.topo_xy[:, 0]
        ix = int(x[0] // TILE_M)
        assert int(x[-1] // TILE_M) == ix or x[-1] % TILE_M == 0  # each graph in one tile
        by_tile.setdefault((ix, 0), []).append(g)
    return graphs, sorted(by_tile.items())


def _same(a: HDMap, b: HDMap) -> None:
    assert [f.id for f in a.features] == [f.id for f in b.features]
    for fa, fb in zip(a.features, b.features):
        assert fa.type == fb.type
        assert fa.predecessors == fb.predecessors and fa.successors == fb.successors
        np.testing.assert_array_equal(fa.points, fb.points)
        np.testing.assert_array_equal(fa.drive_count, fb.drive_count)
        np.testing.assert_array_equal(fa.lateral_std, fb.lateral_std)
    assert [t.id for t in a.topology] == [t.id for t in b.topology]
    for ta, tb in zip(a.topology, b.topology):
        np.testing.assert_array_equal(ta.position, tb.position)
        assert (ta.heading, ta.width, ta.successors, ta.features) == (tb.heading, tb.width, tb.successors, tb.features)
    assert a.drive_ids == b.drive_ids and a.version == b.version


@pytest.mark.parametrize("region_tiles", [1, 2])
def test_regional_stitch_is_the_global_stitch(region_tiles):
    graphs, parts = _network()
    ref = stitch(graphs, config=DEFAULT)
    # the lines run through the regions: one polyline per line of each road, so every border's
    # link (and the loose-end join across the gap, the overlap's trim) is in the map
    south = [f for f in ref.features if f.points[:, 1].max() < 30.0]
    north = [f for f in ref.features if f.points[:, 1].min() > 30.0]
    assert len(north) == 3 and all(f.points[0, 0] == 0.0 and f.points[-1, 0] == 498.0 for f in north)
    border = [f for f in south if f.type == B]
    assert len(border) == 1 and border[0].points[0, 0] == 0.0 and border[0].points[-1, 0] == 998.0
    assert len({ix for (ix, _), _ in parts}) == 5
    got = stitch_by_regions(parts, DEFAULT, region_tiles=region_tiles)
    _same(ref, got)


def test_without_the_halo_the_border_links_are_missing():
    """The join needs each region to see across its border: with no tile around a region, the
    links that start at its last piece find no partner and the lines break at every border."""
    graphs, parts = _network()
    ref = stitch(graphs, config=DEFAULT)
    got = stitch_by_regions(parts, DEFAULT, region_tiles=1, halo_tiles=0)
    assert len(got.features) > len(ref.features)


def test_a_link_across_a_border_is_kept_once_by_the_region_it_starts_in():
    graphs, parts = _network()
    regions = [stitch_region((ix, 0), [p for p in parts if abs(p[0][0] - ix) <= 1], DEFAULT, 1) for (ix, _), _ in parts]
    links = [ln for r in regions for ln in r.state.topo_links]
    assert len(links) == len(set(links))  # no region states another's link
    own = {r.region: {g.key for g in r.graphs} for r in regions}
    assert all(ln[0] in own[r.region] for r in regions for ln in r.state.topo_links)
    crossing = [ln for r in regions for ln in r.state.topo_links if ln[2] not in own[r.region]]
    assert crossing  # the join across the borders is made of these
    _same(stitch(graphs, config=DEFAULT), join_regions(regions, DEFAULT))
    with pytest.raises(HdmapError, match="no stitch state"):
        MapGraph.from_states(graphs, [r.state for r in regions[1:]], config=DEFAULT)


def test_the_halo_covers_a_kilometre_of_tiles_of_any_size():
    assert [halo_tiles_for(m) for m in (1024.0, 1000.0, 512.0, 384.0, 256.0, 4000.0)] == [1, 1, 2, 3, 4, 1]
