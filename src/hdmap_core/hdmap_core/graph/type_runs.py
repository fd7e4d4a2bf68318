"""Marking types along a polyline: flicker smoothed into runs (beyond the paper; Sec. VI export).

Aggregated types flicker where drives misclassify dashed/solid, and every flicker would close a
polyline (Sec. V, RULE 1 of ``segment_graph.feature_chains``). At export the map's feature types
are smoothed: short runs take their neighbours' type (``smooth_types``), and weakly supported
markings beside a road border become its solid edge line (``edge_lines_solid``).
"""

from __future__ import annotations

import copy

import numpy as np

from hdmap_core.geometry import left_normal, nearest_on_same_cut
from hdmap_core.graph.flat import FlatGraph
from hdmap_core.graph.segment_graph import feature_chains
from hdmap_core.model import FeatureType

__all__ = ["edge_lines_solid", "smooth_types"]

_BORDER_CODE = int(FeatureType.ROAD_BORDER)
_UNKNOWN_CODE = int(FeatureType.UNKNOWN)


def edge_lines_solid(flat: FlatGraph, *, within_m: float, max_drives: int) -> np.ndarray:
    """(N,) node types with weakly supported (or unknown) markings beside a border of their
    cross-section typed solid (``StitchConfig.edge_line_solid_m``)."""
    types = flat.n_type.copy()
    topo = flat.node_topo()
    border = types == _BORDER_CODE
    weak = ~border & ((types == _UNKNOWN_CODE) | (flat.n_count <= max_drives))
    if not (weak.any() and border.any()):
        return types
    h = flat.t_heading[topo]
    nrm = left_normal(h)
    lat = np.einsum("ij,ij->i", flat.n_xy - flat.t_xy[topo], nrm)
    # the laterally nearest border of the same topology node (cut widths are < 1e3 m)
    bi, wi = np.flatnonzero(border), np.flatnonzero(weak)
    _, near = nearest_on_same_cut(topo[wi], lat[wi], topo[bi], lat[bi], width=1e3)
    # RULE edge line: the marking beside the road's border is its solid edge line
    types[wi[near <= within_m]] = int(FeatureType.SOLID)
    return types


def smooth_types(
    flat: FlatGraph,
    uid: np.ndarray,
    *,
    min_run_m: float,
    sparse_run_m: float = 0.0,
    sparse_count: int = 0,
    minority_only: bool = False,
    single_run_m: float = 0.0,
    end_run_m: float = 0.0,
    end_run_through: bool = False,
) -> np.ndarray:
    """Marking types with short runs along a polyline relabelled to their neighbours' type.

    Aggregated types flicker where drives misclassify dashed/solid (5-10 % of stretches), and every
    flicker would close the polyline (RULE 1). A run of one marking type shorter than
    ``min_run_m`` inside a polyline takes the type of its longer neighbouring run; runs are merged
    shortest first. Road borders and markings are never relabelled into each other. A run between
    two runs of one other type (a flicker: A B A) seen by at most ``sparse_count`` drives (median
    over its nodes) is relabelled up to ``sparse_run_m``: with 1-3 drives one drive's
    misclassification decides the type for tens of metres. With ``minority_only`` such a run of
    two or more drives is relabelled only when the better supported of its neighbour runs has
    more drives (median); a flicker run of one drive is relabelled up to ``single_run_m`` when it
    is not longer than both of its neighbour runs. A run at the polyline's end seen by one drive
    is relabelled up to ``end_run_m`` when it is not longer than its one neighbour run and that
    run was seen by more drives. With ``end_run_through`` that end rule alone is judged once more
    afterwards, along chains that go on through leftover edges (1:1): the exported polyline goes
    on there, so the chain's end is no line's end and its neighbour run lies beyond the edge.

    Returns:
        (N,) int type codes.
    """
    types = flat.n_type.copy()
    is_border = (types == _BORDER_CODE).astype(np.int64)
    chains = feature_chains(flat.n_nodes, flat.edges, flat.leftover, is_border, uid)
    for c in chains:
        if len(c) < 3 or is_border[c[0]]:
            continue
        t = types[c]
        cut = np.flatnonzero(t[1:] != t[:-1]) + 1
        if len(cut) == 0:
            continue
        seg = np.r_[0.0, np.hypot(*np.diff(flat.n_xy[c], axis=0).T)]
        bounds = np.r_[0, cut, len(c)].tolist()
        runs = [[bounds[k], bounds[k + 1], int(t[bounds[k]])] for k in range(len(bounds) - 1)]

        def length(r: list[int]) -> float:
            return float(seg[r[0] + 1 : r[1]].sum() + (seg[r[1]] if r[1] < len(c) else 0.0))

        cnt = flat.n_count[c]

        def med(r: list[int]) -> float:
            return float(np.median(cnt[r[0] : r[1]]))

        def short(i: int) -> bool:
            r = runs[i]
            if length(r) < min_run_m or r[2] == _UNKNOWN_CODE:
                # RULE unknown type: a line whose drives disagreed on its type (a type clash kept,
                # hdmap_core.pipeline.alignment) takes the type of the line it continues
                return True
            # RULE flicker: only a run between two runs of one other type (A B A)
            if not (0 < i < len(runs) - 1 and runs[i - 1][2] == runs[i + 1][2]):
                return False
            m = med(r)
            if length(r) < sparse_run_m and m <= sparse_count:
                # RULE minority: a run of >= 2 drives is one drive's misclassification only when
                # the runs beside it were seen by more drives (on 30-drive CARLA fleets 3-drive
                # solid runs between 2-3-drive dashed runs are real: the lines before junctions)
                if not minority_only or m <= 1 or m < max(med(runs[i - 1]), med(runs[i + 1])):
                    return True
            # RULE single drive: one drive's type is no evidence against the line's type before
            # and after it, over a whole misclassified stretch (20-200 m in the simulator) --
            # unless the run is longer than both neighbours (S 78 m, D 145 m, S 77 m of one
            # drive: the two short runs are the likelier misclassification)
            longest = length(r) > max(length(runs[i - 1]), length(runs[i + 1]))
            return length(r) < single_run_m and m <= 1 and not longest

        def end_short(i: int) -> bool:
            # RULE single-drive end: one drive's type at a polyline's end is no evidence against
            # the type better supported drives gave the line before it (the flicker rules want a
            # neighbour on both sides). Judged last, when no other run is to be merged: a
            # neighbour that is itself short or a flicker is no run of its own yet.
            if not (i == 0 or i == len(runs) - 1):
                return False
            r, nb = runs[i], (runs[1] if i == 0 else runs[-2])
            m = med(r)
            return m <= 1 and med(nb) > m and length(r) < end_run_m and length(r) <= length(nb)

        while len(runs) > 1:
            cand = [i for i in range(len(runs)) if short(i)]
            if not cand and end_run_m > 0:
                cand = [i for i in range(len(runs)) if end_short(i)]
            if not cand:
                break
            k = min(cand, key=lambda i: (length(runs[i]), i))
            left = runs[k - 1] if k > 0 else None
            right = runs[k + 1] if k + 1 < len(runs) else None
            into = left if right is None or (left is not None and length(left) >= length(right)) else right
            assert into is not None  # len(runs) > 1: run k has a neighbour
            runs[k][2] = into[2]
            merged: list[list[int]] = []
            for r in runs:  # join neighbours of equal type
                if merged and merged[-1][2] == r[2]:
                    merged[-1][1] = r[1]
                else:
                    merged.append(r)
            runs = merged
        for a, b, ty in runs:
            t[a:b] = ty
        types[c] = t
    if end_run_through and end_run_m > 0:
        # RULE single-drive end across leftover edges: only the end rule (no min run, no flicker:
        # along the longer chains the single-drive flicker rule relabelled true runs)
        g = copy.copy(flat)
        g.n_type = types
        g.leftover = np.zeros_like(flat.leftover)
        types = smooth_types(g, uid, min_run_m=0.0, end_run_m=end_run_m)
    return types
