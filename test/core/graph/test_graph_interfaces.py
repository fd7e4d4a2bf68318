"""Sec. VI as functions with plain data in and out: the flat view, linking, loose ends, trimming,
export, the Dijkstra reach of a node and the map's topology graph in networkx.

Roads run east (heading 0); segments are built with the helpers of ``segment_samples`` (test/support).
"""

from __future__ import annotations

import dataclasses
import heapq
import math

import networkx as nx
import numpy as np
import pytest

from hdmap_core.graph.export import export_map
from hdmap_core.graph.flat import flatten, link_key
from hdmap_core.graph.linking import link_segments
from hdmap_core.graph.links import Adjacency, reached_within
from hdmap_core.graph.loose_ends import join_loose_ends
from hdmap_core.graph.map_graph import stitch
from hdmap_core.graph.stitch_config import StitchConfig
from hdmap_core.graph.topology_graph import topology_graph, write_graphml
from hdmap_core.graph.trim import trim_overlaps
from hdmap_core.model import HDMap, TopologyNode

from former_configs import former
from segment_samples import LINES, conn, road


def _flat_of(*graphs):
    gs = {g.key: g for g in graphs}
    alive = {k: np.ones(g.n_topo, dtype=bool) for k, g in gs.items()}
    return gs, alive, flatten(gs, alive, node_dead={})


def test_flatten_concatenates_graphs_in_key_order_with_their_links():
    r"""b: x 100..118 | a: x 0..18  ->  a's nodes first; a stored link a:9 -> b:0 becomes one edge."""
    ga, gb = conn(road("a", 0.0, 10)), conn(road("b", 100.0, 10))
    gs = {gb.key: gb, ga.key: ga}
    alive = {k: np.ones(g.n_topo, dtype=bool) for k, g in gs.items()}
    alive[gb.key][0] = False  # b's first node trimmed: a link to it is dropped
    link_ok = (ga.key, 9, gb.key, 1)
    link_gone = (ga.key, 9, gb.key, 0)
    flat = flatten(gs, alive, node_dead={}, topo_links=[link_ok, link_gone])
    assert flat.keys == sorted([ga.key, gb.key]) and flat.n_topo == 19
    np.testing.assert_allclose(flat.t_xy[:10, 0], 2.0 * np.arange(10))
    assert flat.n_nodes == 19 * 3 and flat.t_start[-1] == flat.n_nodes
    te = {tuple(e) for e in flat.topo_edges.tolist()}
    assert (9, 10) in te and len(te) == 9 + 8 + 1
    assert link_key(flat, 9, 10, topo=True) == link_ok


def test_link_segments_joins_two_segments_in_a_row():
    r"""a: x 0..98 | b: x 100..198  ->  one topology link a -> b and one feature link per line."""
    gs, _, flat = _flat_of(conn(road("a", 0.0, 50)), conn(road("b", 100.0, 50)))
    before = flat.topo_edges.copy()
    links = link_segments(flat, gs, config=former(StitchConfig))
    assert links.topo == [(49, 50)]
    assert len(links.features) == len(LINES[0])
    for x, y in links.features:
        assert flat.n_xy[x, 0] == pytest.approx(98.0) and flat.n_xy[y, 0] == pytest.approx(100.0)
        assert flat.n_xy[x, 1] == pytest.approx(flat.n_xy[y, 1])
    np.testing.assert_array_equal(flat.topo_edges, before)  # the input is not modified


def test_link_segments_of_parallel_roads_links_nothing():
    r"""a: y 0, x 0..98;  b: y 40, x 100..198  ->  too far across: no link."""
    gs, _, flat = _flat_of(
        conn(road("a", 0.0, 50)), conn(road("b", 100.0, 50, y_mid=40.0, lines=([36.5, 40.0, 43.5], LINES[1])))
    )
    links = link_segments(flat, gs, config=former(StitchConfig))
    assert links.topo == [] and links.features == []


def test_join_loose_ends_joins_a_line_across_a_gap_between_segments():
    r"""a: x 0..98 | (gap 10 m) | b: x 108..206, topology not linked  ->  one join per line."""
    gs, _, flat = _flat_of(conn(road("a", 0.0, 50)), conn(road("b", 108.0, 50)))
    joins = join_loose_ends(flat, config=former(StitchConfig))
    assert len(joins.links) == 3 and not joins.dropped.any()
    for a, b in joins.links:
        assert flat.n_xy[a, 0] == pytest.approx(98.0) and flat.n_xy[b, 0] == pytest.approx(108.0)
    off = join_loose_ends(flat, config=dataclasses.replace(former(StitchConfig), join_radius_m=5.0))
    assert off.links == []


def test_trim_overlaps_returns_new_masks_and_leaves_its_input():
    """b maps x 60..98 again (no processed_before): its overlapping start is trimmed, not a's."""
    ga, gb = conn(road("a", 0.0, 50)), conn(road("b", 60.0, 50, y_mid=0.4))
    gs, alive, flat = _flat_of(ga, gb)
    new, killed = trim_overlaps(flat, gs, alive, new_keys=[gb.key], config=former(StitchConfig))
    assert all(v.all() for v in alive.values())  # not modified
    assert new[ga.key].all() and killed == int((~new[gb.key]).sum()) > 0
    assert not new[gb.key][0] and new[gb.key][-1]


def test_export_map_leaves_the_flat_view_unchanged():
    _, _, flat = _flat_of(conn(road("a", 0.0, 30)))
    types, edges = flat.n_type.copy(), flat.edges.copy()
    cfg = former(StitchConfig, min_type_run_m=10.0, edge_line_solid_m=1.5)
    features, topology = export_map(flat, config=cfg)
    assert len(features) == 3 and len(topology) == 30
    np.testing.assert_array_equal(flat.n_type, types)
    np.testing.assert_array_equal(flat.edges, edges)


def _heap_reach(succ: dict[int, list[int]], xy: np.ndarray, i: int, limit: float) -> set[int]:
    """The reach by hand (a textbook Dijkstra), to check the library's against."""
    best, heap = {i: 0.0}, [(0.0, i)]
    while heap:
        d, k = heapq.heappop(heap)
        if d > best[k]:
            continue
        for n in succ.get(k, []):
            dn = d + float(np.hypot(*(xy[n] - xy[k])))
            if dn <= limit and dn < best.get(n, math.inf):
                best[n] = dn
                heapq.heappush(heap, (dn, n))
    return set(best)


def test_reached_within_matches_a_textbook_dijkstra_with_added_edges():
    """Random nodes (some at one place: zero-length edges), repeated edges and edges added after
    construction: csgraph's bounded Dijkstra reaches exactly the nodes the textbook one does."""
    rng = np.random.default_rng(3)
    n = 200
    xy = rng.uniform(0, 100, (n, 2))
    xy[1] = xy[0]
    src, dst = rng.integers(0, n, 700), rng.integers(0, n, 700)
    src, dst = np.r_[src, 0, 0, 5], np.r_[dst, 1, 1, 5]  # a zero-length edge twice, a loop
    walk = Adjacency(src, dst, n)
    flat = type("F", (), {"t_xy": xy})()
    succ: dict[int, list[int]] = {}
    for a, b in zip(src.tolist(), dst.tolist()):
        succ.setdefault(a, []).append(b)
    for i in range(0, n, 7):
        for limit in (0.0, 15.0, 60.0):
            assert reached_within(flat, walk, i, limit) == _heap_reach(succ, xy, i, limit)
    assert 1 in reached_within(flat, walk, 0, 0.0)
    walk.add(2, 3)
    succ.setdefault(2, []).append(3)
    far = float(np.hypot(*(xy[3] - xy[2])))
    assert 3 in reached_within(flat, walk, 2, far + 1e-9)
    assert reached_within(flat, walk, 2, 80.0) == _heap_reach(succ, xy, 2, 80.0)


# --- the topology graph in networkx -----------------------------------------------------------------------


def _split_map() -> HDMap:
    r"""0 -> 1 -> 2 -> 3        a road that splits at node 1 (node 4 on the ramp);
    \-> 4           node 3 names a successor 99 that is not in the map."""
    pos = {0: (0.0, 0.0), 1: (2.0, 0.0), 2: (4.0, 0.0), 3: (6.0, 0.0), 4: (3.6, -1.2)}
    succ = {0: (1,), 1: (2, 4), 2: (3,), 3: (99,), 4: ()}
    nodes = tuple(
        TopologyNode(
            id=2**63 + k,
            position=np.array(p),
            heading=0.1 * k,
            width=7.0 + k,
            successors=tuple(2**63 + s for s in succ[k]),
            features=(2**64 - 1, k + 1),
        )
        for k, p in pos.items()
    )
    return HDMap(topology=nodes, version=4)


def test_topology_graph_has_the_nodes_links_and_attributes_of_the_map():
    g = topology_graph(_split_map())
    base = 2**63
    assert isinstance(g, nx.DiGraph) and g.graph["version"] == 4
    assert sorted(g.nodes) == [base + k for k in range(5)]
    assert sorted(g.edges) == sorted(
        [(base, base + 1), (base + 1, base + 2), (base + 1, base + 4), (base + 2, base + 3)]
    )
    assert g.nodes[base + 4] == {
        "x": 3.6,
        "y": -1.2,
        "heading": pytest.approx(0.4),
        "width": 11.0,
        "features": (2**64 - 1, 5),
    }
    assert g.edges[base + 1, base + 4]["length_m"] == pytest.approx(math.hypot(1.6, 1.2))
    # a user's query: the ramp is reached from the start, over 2 + 2 m of road
    assert nx.shortest_path_length(g, base, base + 4, weight="length_m") == pytest.approx(4.0)
    assert not nx.has_path(g, base + 4, base)


def test_graphml_round_trip_keeps_ids_positions_and_features(tmp_path):
    path = tmp_path / "topo.graphml"
    written = write_graphml(_split_map(), path)
    g = nx.read_graphml(path, node_type=int)
    assert sorted(g.nodes) == sorted(written.nodes) and sorted(g.edges) == sorted(written.edges)
    n = g.nodes[2**63 + 4]
    assert (n["x"], n["y"], n["width"], n["n_features"]) == (3.6, -1.2, 11.0, 2)
    assert [int(f) for f in n["features"].split()] == [2**64 - 1, 5]


def test_topology_graph_of_a_stitched_map_is_one_chain():
    r"""a: x 0..98 | b: x 100..198 stitched  ->  100 nodes in one chain, 99 links of ~2 m."""
    g = topology_graph(stitch([conn(road("a", 0.0, 50)), conn(road("b", 100.0, 50))]))
    assert g.number_of_nodes() == 100 and g.number_of_edges() == 99
    assert nx.is_weakly_connected(g) and nx.is_directed_acyclic_graph(g)
    lengths = [d["length_m"] for _, _, d in g.edges(data=True)]
    np.testing.assert_allclose(lengths, 2.0, atol=1e-9)
    assert len(nx.dag_longest_path(g)) == 100
