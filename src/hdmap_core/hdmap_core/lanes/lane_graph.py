"""The lane graph for users who query it: routes from lane to lane, reachable sets, lanes at a place.

Edges of the ``networkx.DiGraph``: ``kind="successor"`` (weight: the lane's length) and
``kind="change"`` into a neighbour across a dashed boundary (weight: half the lane's length, the
usual cost of a change in Lanelet2's routing is of the same order).
"""

from __future__ import annotations

import networkx as nx
import numpy as np
import shapely

from hdmap_core.lanes.model import LaneMap

__all__ = ["lane_graph", "lane_route", "reachable_lanes", "lanes_at"]


def lane_graph(lane_map: LaneMap) -> nx.DiGraph:
    """Nodes: lane ids with ``length_m``, ``left``, ``right``; edges: successors and lane changes."""
    g = nx.DiGraph()
    for ln in lane_map.lanes:
        g.add_node(ln.id, length_m=ln.length_m, left=ln.left, right=ln.right)
    for ln in lane_map.lanes:
        for s in ln.successors:
            g.add_edge(ln.id, s, kind="successor", weight=ln.length_m)
        for other, ok in ((ln.left, ln.change_left), (ln.right, ln.change_right)):
            if ok and other is not None and not g.has_edge(ln.id, other):
                g.add_edge(ln.id, other, kind="change", weight=ln.length_m / 2.0)
    return g


def lane_route(graph: nx.DiGraph, start: int, end: int) -> list[int] | None:
    """The shortest lane sequence from ``start`` to ``end`` (lane changes included), None if none."""
    try:
        return list(nx.shortest_path(graph, start, end, weight="weight"))
    except (nx.NetworkXNoPath, nx.NodeNotFound):
        return None


def reachable_lanes(graph: nx.DiGraph, start: int) -> set[int]:
    """Every lane reachable from ``start`` (itself included)."""
    return set(nx.descendants(graph, start)) | {start} if start in graph else set()


def lanes_at(lane_map: LaneMap, xy: np.ndarray, yaw: np.ndarray, *, max_angle_rad: float = 0.6) -> np.ndarray:
    """For each (N, 2) point with heading ``yaw`` (N,) [rad], the id of a lane containing it whose
    direction there agrees within ``max_angle_rad``; 0 where none."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    out = np.zeros(len(xy), dtype=np.int64)
    if not lane_map.lanes or not len(xy):
        return out
    polys = np.array([shapely.Polygon(lane_map.polygon(ln)) for ln in lane_map.lanes], dtype=object)
    polys = shapely.make_valid(polys)
    tree = shapely.STRtree(polys)
    pi, li = tree.query(shapely.points(xy), predicate="intersects")
    for p, i in zip(pi, li, strict=True):
        if out[p]:
            continue
        c = lane_map.lanes[i].centerline
        j = int(np.argmin(np.hypot(*(c - xy[p]).T)))
        d = c[min(j + 1, len(c) - 1)] - c[max(j - 1, 0)]
        dyaw = np.arctan2(d[1], d[0]) - yaw[p]
        if abs((dyaw + np.pi) % (2 * np.pi) - np.pi) <= max_angle_rad:
            out[p] = lane_map.lanes[i].id
    return out
