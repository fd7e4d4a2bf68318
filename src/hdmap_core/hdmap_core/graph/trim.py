"""Overlap trimming: a new segment gives way where the map already has the place (beyond the paper; Sec. VI).

Pivots of one place map it more than once; before linking, the ends of a new segment's components
that duplicate a place another segment maps are cut off (``StitchConfig.trim_overlap``), so the
link joins one estimate of the place to the next instead of two side by side.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.geometry import heading_frame
from hdmap_core.graph.flat import FlatGraph
from hdmap_core.graph.segment_graph import SegmentGraph
from hdmap_core.graph.stitch_config import StitchConfig

__all__ = ["trim_overlaps"]

# Rules measured and adopted with this stage (docs/graph.md); no preset changes them, so they are
# constants, not settings
#: a topology node this close to another graph's node with a similar heading is the same place
#: [m] ...
_OVERLAP_RADIUS_M = 1.2
#: ... or up to ``overlap_search_m`` away and at most this far along the road, when its features
#: have twins (two pivots' midpoints differ with their cut lines) [m]
_OVERLAP_ALONG_M = 1.2
#: ... a twin: a maximum of the same type within this across the road [m]
_OVERLAP_FEATURE_M = 0.5
#: ... for at least this share of the node's maxima (and 2)
_OVERLAP_SHARE = 0.6


def trim_overlaps(
    flat: FlatGraph,
    graphs: Mapping[str, SegmentGraph],
    alive: Mapping[str, np.ndarray],
    *,
    new_keys: Sequence[str],
    config: StitchConfig,
) -> tuple[dict[str, np.ndarray], int]:
    """Kill component end nodes of new graphs that lie on a place another graph already maps.

    Each new graph's components are walked from both ends inward while the node overlaps a live
    node of another graph: within ``_OVERLAP_RADIUS_M`` (the same road midpoint), or within
    ``_OVERLAP_ALONG_M`` along with most of its features' twins (the same features).

    RULE keep longer (``trim_keep_longer``): a node is not killed for overlapping a shorter piece
    (fewer topology nodes in its component) of another graph; that graph is walked after the new
    ones instead, so its shorter piece gives way (the longer estimate of a place stays).
    RULE lookahead (``trim_lookahead``): nor for a place whose own walk will trim it (for a third).

    Args:
        flat: the map's flat view before trimming (not modified).
        graphs: its segment graphs by key.
        alive: per key, (T_k,) bool: topology nodes in the map (not modified).
        new_keys: keys of the graphs just added.
        config: stitching parameters.

    Returns:
        The new alive masks (every key) and how many nodes were killed.
    """
    alive = {k: v.copy() for k, v in alive.items()}
    cfg = config
    if flat.n_topo == 0:
        return alive, 0
    tree = cKDTree(flat.t_xy)
    cos_max = math.cos(math.radians(cfg.max_heading_diff_deg))
    comps: dict[str, list[np.ndarray]] = {}
    sizes: dict[str, np.ndarray] = {}
    spared: set[str] = set()

    def components(key: str) -> list[np.ndarray]:
        if key not in comps:
            comps[key] = graphs[key].components()
        return comps[key]

    def size_of(key: str) -> np.ndarray:
        if key not in sizes:
            out = np.zeros(graphs[key].n_topo, dtype=np.int64)
            for comp in components(key):
                out[comp] = len(comp)
            sizes[key] = out
        return sizes[key]

    graph_index = {k: i for i, k in enumerate(flat.keys)}
    pending: set[str] = set()  # the new graphs not walked yet

    def overlaps(k: str, t: int, lookahead: bool, skip: int = -1) -> bool:
        """Does node t of graph k lie on a place of another graph (not ``skip``) that it must
        give way to?"""
        g = graphs[k]
        gi = graph_index[k]
        own = size_of(k)[t]
        u, n = heading_frame(float(g.topo_heading[t]))
        fl = g.node_xy[g.topo_start[t] : g.topo_start[t + 1]] @ n
        ft = g.node_type[g.topo_start[t] : g.topo_start[t + 1]]
        radius = max(_OVERLAP_RADIUS_M, cfg.overlap_search_m)
        for j in tree.query_ball_point(g.topo_xy[t], radius):
            if flat.t_graph[j] in (gi, skip):
                continue
            kj = flat.keys[flat.t_graph[j]]
            if not alive[kj][flat.t_local[j]]:
                continue
            if math.cos(g.topo_heading[t] - flat.t_heading[j]) < cos_max:
                continue
            d = flat.t_xy[j] - g.topo_xy[t]
            if math.hypot(*d) <= _OVERLAP_RADIUS_M:
                same = True  # the same road midpoint
            elif abs(float(d @ u)) > _OVERLAP_ALONG_M or len(fl) == 0:
                continue
            else:
                # the same features: most of this step's maxima have a twin of the same type
                other = slice(flat.t_start[j], flat.t_start[j + 1])
                gl, gt = flat.n_xy[other] @ n, flat.n_type[other]
                twin = (np.abs(fl[:, None] - gl[None, :]) <= _OVERLAP_FEATURE_M) & (ft[:, None] == gt[None, :])
                same = int(twin.any(axis=1).sum()) >= max(min(2, len(fl)), _OVERLAP_SHARE * len(fl))
            if not same:
                continue
            if cfg.trim_keep_longer and size_of(kj)[flat.t_local[j]] < own:
                if lookahead:
                    spared.add(kj)
                continue
            if (
                lookahead
                and cfg.trim_lookahead
                and kj in pending
                and overlaps(kj, int(flat.t_local[j]), False, skip=gi)
            ):
                continue  # RULE: not for a place whose own walk will trim it (for a third)
            return True
        return False

    def walk(k: str) -> int:
        live = alive[k]
        killed = 0
        for comp in components(k):
            order = comp.tolist()
            for walk_order in (order, order[::-1]):
                for t in walk_order:
                    if not live[t] or not overlaps(k, t, True):
                        break
                    live[t] = False
                    killed += 1
        pending.discard(k)
        return killed

    pending.update(new_keys)
    killed = sum(walk(k) for k in new_keys)
    killed += sum(walk(k) for k in sorted(spared - set(new_keys)))
    return alive, killed
