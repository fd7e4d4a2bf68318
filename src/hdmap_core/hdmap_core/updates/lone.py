"""One drive's misclassified copy of a line, dropped from the rebuilt places.

The changed places are mapped again from the few drives after the change (3 after 3 drives
through). Where one of them saw a line with another type (a dashed divider as a road border,
the simulator's ``marking_to_border_rate``), nothing in the rebuild may outvote it: the other
drives missed the line there, or saw it, and the aggregation's overlap filter
(``pipeline.aggregation``) keeps both copies because a one-drive cluster takes the least
bandwidth (0.15 m) and overlaps a line 0.2-0.3 m beside it by less than half. The splice then
puts the copy beside the line the map keeps there. On ``motorway_ramps`` seed 1 the lane
opened, after 3 drives through: a road border along 150 m of the new divider, 71 of the zone's
~2350 map points, zone precision 94.1 % (the 2.5 m opening 93.9 %).

``lone_copies_dropped``: a feature of the spliced map that lies within the rebuilt places, that
one drive saw (its points' ``drive_count`` at most 1, at least one of them 1: not a modelled
line, whose count is 0) and that lies along a line of another type two or more drives saw
(``_ALONG`` of its points within ``_NEAR_M``) is dropped, with the links to it (its neighbours'
and the topology nodes' references). Not a marking along a road border: an edge line at its curb
is both (a 3 m shift puts the right edge line on the barrier's border; dropped, the zone's recall
after 10 drives through fell by 1.8 points, seed 1). A line one drive
saw with nothing of another type beside it stays: it may be what the others missed.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.geometry import resample_evenly, true_runs
from hdmap_core.model import FeatureType, HDMap, MapFeature
from hdmap_core.updates.places import PlaceKey, Places

__all__ = ["lone_copies_dropped"]

_BORDER = int(FeatureType.ROAD_BORDER)
_NEAR_M = 0.5  # a point this close to the other line lies along it [m]
_ALONG = 0.8  # share of a feature's points that must lie along the other line
_STEP_M = 0.5  # the other lines are looked at this spacing [m]


def _lone(f: MapFeature, places: Places, rebuilt: Collection[PlaceKey]) -> bool:
    count = np.asarray(f.drive_count)
    return (
        len(f.points) >= 2
        and int(count.max(initial=0)) == 1
        and all(k in rebuilt for k in places.keys_along(np.asarray(f.points, dtype=float)))
    )


def lone_copies_dropped(hdmap: HDMap, places: Places, rebuilt: Collection[PlaceKey]) -> tuple[HDMap, tuple[int, ...]]:
    """``hdmap`` without the one-drive copies of a line in the ``rebuilt`` places (module
    docstring), and the ids dropped; ``hdmap`` itself when there is none."""
    lone = [f for f in hdmap.features if _lone(f, places, rebuilt)]
    if not lone:
        return hdmap, ()
    # only the features whose box meets the lone ones' (grown by _NEAR_M): not the whole map
    lone_pts = np.concatenate([np.asarray(f.points, dtype=float) for f in lone])
    lo, hi = lone_pts.min(axis=0) - _NEAR_M, lone_pts.max(axis=0) + _NEAR_M
    seen: dict[int, list[np.ndarray]] = {}  # per type: the stretches two or more drives saw
    for f in hdmap.features:
        pts = np.asarray(f.points, dtype=float)
        if not len(pts) or np.any(pts.min(axis=0) > hi) or np.any(pts.max(axis=0) < lo):
            continue
        for a, b in true_runs(np.asarray(f.drive_count) >= 2):
            if b - a >= 2:
                seen.setdefault(int(f.type), []).append(resample_evenly(pts[a:b], _STEP_M))
    trees = {t: cKDTree(np.concatenate(v)) for t, v in seen.items()}
    drop = set()
    for f in lone:
        pts = np.asarray(f.points, dtype=float)
        along = np.zeros(len(pts), dtype=bool)
        for t, tree in trees.items():
            # a marking along a border is an edge line at its curb: both there
            if t != int(f.type) and not (t == _BORDER and int(f.type) != _BORDER):
                d, _ = tree.query(pts, distance_upper_bound=_NEAR_M)
                along |= np.isfinite(d)
        if np.count_nonzero(along) >= _ALONG * len(pts):
            drop.add(int(f.id))
    if not drop:
        return hdmap, ()
    kept = tuple(
        replace(
            f,
            predecessors=tuple(i for i in f.predecessors if i not in drop),
            successors=tuple(i for i in f.successors if i not in drop),
        )
        for f in hdmap.features
        if int(f.id) not in drop
    )
    topology = tuple(
        replace(n, features=tuple(i for i in n.features if i not in drop)) if set(n.features) & drop else n
        for n in hdmap.topology
    )
    return replace(hdmap, features=kept, topology=topology), tuple(sorted(drop))
