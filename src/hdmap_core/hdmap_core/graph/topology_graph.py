"""The map's topology graph as a ``networkx.DiGraph`` for users who query it (Sec. VI).

The hierarchical map keeps a topology graph with one node per sampling step (road midpoint,
heading, width) whose successors say where the road goes; ``topology_graph`` hands it to networkx
(shortest paths, reachability, components, drawing) and ``write_graphml`` saves it for tools such
as Gephi or yEd.
"""

from __future__ import annotations

import math
from os import PathLike

import networkx as nx

from hdmap_core.model import HDMap

__all__ = ["topology_graph", "write_graphml"]


def topology_graph(hdmap: HDMap) -> nx.DiGraph:
    """The topology nodes of ``hdmap`` and their successor links as a directed graph.

    Nodes are keyed by ``TopologyNode.id`` (int) with attributes ``x``, ``y`` (road midpoint
    [m], map frame), ``heading`` (ENU yaw [rad]), ``width`` (road width [m]) and ``features`` (ids
    of the features crossing the step, in lateral order, a tuple). An edge a -> b is a successor
    link, with ``length_m`` (straight distance between the midpoints [m]); a successor id that
    names no node of the map is left out. Graph attributes: ``version``, ``frame_id``.
    """
    g = nx.DiGraph(version=int(hdmap.version), frame_id=str(hdmap.frame_id))
    xy: dict[int, tuple[float, float]] = {}
    for t in hdmap.topology:
        x, y = float(t.position[0]), float(t.position[1])
        xy[int(t.id)] = (x, y)
        g.add_node(
            int(t.id),
            x=x,
            y=y,
            heading=float(t.heading),
            width=float(t.width),
            features=tuple(int(f) for f in t.features),
        )
    for t in hdmap.topology:
        a = int(t.id)
        for s in t.successors:
            b = int(s)
            if b in xy:
                g.add_edge(a, b, length_m=math.dist(xy[a], xy[b]))
    return g


def write_graphml(hdmap: HDMap, path: str | PathLike[str]) -> nx.DiGraph:
    """Write the topology graph of ``hdmap`` (``topology_graph``) to a GraphML file.

    GraphML attributes are scalars: ``features`` is written as the feature ids separated by
    spaces (a string), beside ``n_features`` (int). Returns the graph as written.
    """
    g = topology_graph(hdmap)
    out = nx.DiGraph(**g.graph)
    for n, attrs in g.nodes(data=True):
        feats = attrs["features"]
        out.add_node(n, **{**attrs, "features": " ".join(str(f) for f in feats), "n_features": len(feats)})
    out.add_edges_from(g.edges(data=True))
    nx.write_graphml(out, path)
    return out
