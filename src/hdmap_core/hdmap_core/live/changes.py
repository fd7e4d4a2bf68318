"""Road changes followed by the live map: the offline rule (``hdmap_core.updates``) on the settled map.

The stitcher's map is the consensus of every drive, as ``bag2map``'s first build. Once the map has
settled (every drive mapped and stitched), :func:`follow_live` compares every stored drive with it
place by place (``updates.evidence``) and confirms the changes of the road with their change
points (``updates.detect``), the same functions and settings as offline. Where a change is
confirmed only the changed region is rebuilt, not the whole map: the drives are cut and anchored
as offline (``updates.follow``), clipped to the changed places' cells grown by ``margin_m``, and
mapped by the pipeline (``build``); of that map the pieces inside the changed places replace the
consensus map's pieces there (:func:`splice`), which are retired with the change's time as their
valid-to (``updates.follow.retired_features``).

The result is a function of the drive set only, as the settled map is: a restart on the same
store finds the same changes with the same ids (``DetectedChange.id`` hashes its places and
time), so :func:`new_changes` tells the ones already announced (the stitcher's history) from new
ones. :class:`LiveChange` is what a ``hdmap_msgs/MapChange`` carries.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import ConvexHull

from hdmap_core.live.tiles import clip_drive
from hdmap_core.model import Drive, HDMap, MapFeature
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import DetectedChange, detect_changes
from hdmap_core.updates.evidence import fleet_evidence
from hdmap_core.updates.follow import RetiredFeature, anchored, cut_before_changes, retired_features
from hdmap_core.updates.places import PlaceKey, Places, places_of

__all__ = [
    "LiveChange",
    "LiveFollow",
    "follow_live",
    "splice",
    "live_changes",
    "new_changes",
    "change_polygon",
    "change_to_dict",
    "change_from_dict",
]


@dataclass(frozen=True)
class LiveFollow:
    """The live map as of the last drive.

    Attributes:
        map: the consensus map with the changed places rebuilt (the consensus map itself when
            nothing changed).
        changes: the confirmed changes, in time order.
        retired: the consensus map's pieces they replaced.
        places: the places the drives were compared in.
    """

    map: HDMap
    changes: tuple[DetectedChange, ...]
    retired: tuple[RetiredFeature, ...]
    places: Places | None


@dataclass(frozen=True)
class LiveChange:
    """One confirmed change as announced (``hdmap_msgs/MapChange``) and kept in the history.

    Attributes:
        id: the change's stable id (``DetectedChange.id``).
        time_ns: the change point; the new road is valid from it, the retired pieces until it.
        kinds: geometry (markings moved), type (re-striped), marking_gone, marking_new.
        places: its places ``(ix, iy, side)`` of ``cell_m`` cells.
        cell_m: the places' cell size [m].
        polygon: (N, 2) convex hull of its places' cells [m], counter-clockwise.
        tiles: the live tiles ``(tx, ty)`` its cells touch.
        drive_ids: the drives in evidence (after the change).
        confidence: in (0, 1).
        retired_feature_ids: features of the map before it whose pieces inside it were retired.
        retired: the retired pieces (``RetiredFeature``).
        map_version: the first map version that follows it.
        confirmed_ns: wall time it was first confirmed.
    """

    id: int
    time_ns: int
    kinds: tuple[str, ...]
    places: tuple[PlaceKey, ...]
    cell_m: float
    polygon: np.ndarray
    tiles: tuple[tuple[int, int], ...]
    drive_ids: tuple[str, ...]
    confidence: float
    retired_feature_ids: tuple[int, ...]
    retired: tuple[RetiredFeature, ...]
    map_version: int
    confirmed_ns: int


def _region(changes: Iterable[DetectedChange], cell_m: float, margin_m: float) -> tuple[float, float, float, float]:
    ij = np.array([p.key[:2] for c in changes for p in c.places], dtype=float)
    lo = ij.min(axis=0) * cell_m - margin_m
    hi = (ij.max(axis=0) + 1) * cell_m + margin_m
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def _pieces(f: MapFeature, keep: np.ndarray) -> list[tuple[int, int]]:
    """[a, b) runs of ``keep`` with at least 2 points."""
    edges = np.flatnonzero(np.diff(keep.astype(np.int8))) + 1
    bounds = np.concatenate([[0], edges, [len(keep)]])
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if keep[a] and b - a >= 2]


def _in_places(points: np.ndarray, places: Places, keys: set[PlaceKey]) -> np.ndarray:
    if len(points) < 2:
        return np.zeros(len(points), dtype=bool)
    tang = np.gradient(points, axis=0)
    ks = places.keys(points, np.arctan2(tang[:, 1], tang[:, 0]))
    return np.array([k in keys for k in ks], dtype=bool)


def _cut(f: MapFeature, a: int, b: int, new_id: int) -> MapFeature:
    return replace(
        f,
        id=new_id,
        points=np.asarray(f.points)[a:b].copy(),
        drive_count=np.asarray(f.drive_count)[a:b].copy(),
        lateral_std=np.asarray(f.lateral_std)[a:b].copy(),
        predecessors=f.predecessors if a == 0 else (),
        successors=f.successors if b == len(f.points) else (),
    )


def splice(consensus: HDMap, rebuilt: HDMap, places: Places, keys: set[PlaceKey]) -> HDMap:
    """``consensus`` with its features inside the places ``keys`` replaced by ``rebuilt``'s there.

    A consensus feature keeps its id on its piece that starts where it started (else on its first
    piece outside); its other pieces, and ``rebuilt``'s pieces inside, get new ids (above every
    consensus id). Links stay where a feature's end is kept: a predecessor link goes to the piece
    that kept the predecessor's last point, a successor link to the piece that kept the
    successor's first point; links to an end inside the changed places are dropped. Pieces cut at
    the places' edge have no link there. The topology is the consensus map's (not rebuilt)."""
    next_id = max((int(f.id) for f in consensus.features), default=0) + 1
    out: list[MapFeature] = []
    start_of: dict[int, int] = {}  # consensus id -> id of the piece holding its first point
    end_of: dict[int, int] = {}  # ... its last point
    for f in consensus.features:
        pts = np.asarray(f.points, dtype=float)
        runs = _pieces(f, ~_in_places(pts, places, keys))
        keeper = next((k for k, (a, _) in enumerate(runs) if a == 0), 0)
        for k, (a, b) in enumerate(runs):
            fid = int(f.id) if k == keeper else next_id
            next_id += k != keeper
            out.append(_cut(f, a, b, fid))
            if a == 0:
                start_of[int(f.id)] = fid
            if b == len(pts):
                end_of[int(f.id)] = fid
    out = [
        replace(
            f,
            predecessors=tuple(end_of[i] for i in f.predecessors if i in end_of),
            successors=tuple(start_of[i] for i in f.successors if i in start_of),
        )
        for f in out
    ]
    for f in rebuilt.features:
        inside = _in_places(np.asarray(f.points, dtype=float), places, keys)
        for a, b in _pieces(f, inside):
            out.append(replace(_cut(f, a, b, next_id), predecessors=(), successors=()))
            next_id += 1
    return replace(consensus, features=tuple(out))


def follow_live(
    consensus: HDMap,
    drives: Sequence[Drive],
    *,
    build: Callable[[Sequence[Drive]], HDMap],
    config: ChangeConfig = ChangeConfig(),
    margin_m: float = 128.0,
) -> LiveFollow:
    """The live map as of the last of ``drives`` (module docstring).

    Args:
        consensus: the settled map of every drive (the stitcher's).
        drives: every stored drive (checked against the physical bounds by the mapper).
        build: drives -> map (the pipeline as the nodes are configured).
        config: change detection settings (as offline).
        margin_m: the changed places' cells grown by this for the rebuild [m] (context for the
            alignment; only the pieces inside the changed places are kept).
    """
    if not drives or not consensus.features:
        return LiveFollow(consensus, (), (), None)
    places = places_of(drives, cell_m=config.cell_m)
    evidence = fleet_evidence(drives, consensus, places, config=config)
    changes = detect_changes(evidence, places, config=config)
    if not changes:
        return LiveFollow(consensus, (), (), places)
    in_evidence = {d for c in changes for d in c.drives_after}
    anchors: dict[str, dict[PlaceKey, float]] = {}
    for e in evidence:
        if e.drive_id in in_evidence and np.isfinite(e.anchor_m):
            anchors.setdefault(e.drive_id, {})[e.key] = e.anchor_m
    moved = [anchored(d, anchors[d.drive_id], places) if d.drive_id in anchors else d for d in drives]
    bounds = _region(changes, places.cell_m, margin_m)
    region = [c for c in (clip_drive(d, bounds) for d in cut_before_changes(moved, places, changes)) if c is not None]
    rebuilt = build(region)
    keys = {k for c in changes for k in c.keys}
    start = min((d.start_ns for d in drives), default=0)
    retired = tuple(retired_features(consensus, places, changes, valid_from_ns=start))
    spliced = splice(consensus, rebuilt, places, keys)
    extra = {**consensus.extra, "changes": list(changes), "retired": list(retired)}
    return LiveFollow(replace(spliced, extra=extra), tuple(changes), retired, places)


def change_polygon(keys: Iterable[PlaceKey], cell_m: float) -> np.ndarray:
    """(N, 2) convex hull of the cells of ``keys``, counter-clockwise [m]."""
    ij = np.array(sorted({k[:2] for k in keys}), dtype=float).reshape(-1, 2)
    corners = np.concatenate([ij + d for d in ((0, 0), (1, 0), (1, 1), (0, 1))]) * cell_m
    if len(corners) < 3:
        return corners
    hull = ConvexHull(corners)
    return corners[hull.vertices]


def _tiles(keys: Iterable[PlaceKey], cell_m: float, tile_size_m: float) -> tuple[tuple[int, int], ...]:
    out = set()
    for ix, iy, _ in keys:
        x0, y0 = ix * cell_m, iy * cell_m
        for tx in range(int(np.floor(x0 / tile_size_m)), int(np.floor((x0 + cell_m - 1e-9) / tile_size_m)) + 1):
            for ty in range(int(np.floor(y0 / tile_size_m)), int(np.floor((y0 + cell_m - 1e-9) / tile_size_m)) + 1):
                out.add((tx, ty))
    return tuple(sorted(out))


def live_changes(result: LiveFollow, *, tile_size_m: float, map_version: int, confirmed_ns: int) -> list[LiveChange]:
    """The changes of ``result`` as announced with map version ``map_version``."""
    cell_m = result.places.cell_m if result.places is not None else ChangeConfig().cell_m
    out = []
    for c in result.changes:
        keys = tuple(sorted(c.keys))
        retired = tuple(r for r in result.retired if r.change_id == c.id)
        out.append(
            LiveChange(
                id=int(c.id),
                time_ns=int(c.time_ns),
                kinds=tuple(c.kinds),
                places=keys,
                cell_m=float(cell_m),
                polygon=change_polygon(keys, cell_m),
                tiles=_tiles(keys, cell_m, tile_size_m),
                drive_ids=tuple(c.drives_after),
                confidence=float(c.confidence),
                retired_feature_ids=tuple(sorted({r.feature_id for r in retired})),
                retired=retired,
                map_version=int(map_version),
                confirmed_ns=int(confirmed_ns),
            )
        )
    return out


def new_changes(known: Iterable[int], changes: Sequence[DetectedChange]) -> list[DetectedChange]:
    """Those of ``changes`` not in the history ``known`` (ids)."""
    ids = set(known)
    return [c for c in changes if int(c.id) not in ids]


def change_to_dict(c: LiveChange) -> dict:
    """A JSON document of ``c`` (the stitcher's history store)."""
    return {
        "id": c.id,
        "time_ns": c.time_ns,
        "kinds": list(c.kinds),
        "places": [list(k) for k in c.places],
        "cell_m": c.cell_m,
        "polygon": np.asarray(c.polygon, dtype=float).tolist(),
        "tiles": [list(t) for t in c.tiles],
        "drive_ids": list(c.drive_ids),
        "confidence": c.confidence,
        "retired_feature_ids": list(c.retired_feature_ids),
        "retired": [
            {
                "feature_id": r.feature_id,
                "type": r.type,
                "points": np.asarray(r.points, dtype=float).tolist(),
                "change_id": r.change_id,
                "valid_from_ns": r.valid_from_ns,
                "valid_to_ns": r.valid_to_ns,
            }
            for r in c.retired
        ],
        "map_version": c.map_version,
        "confirmed_ns": c.confirmed_ns,
    }


def change_from_dict(d: dict) -> LiveChange:
    """The inverse of :func:`change_to_dict`."""
    return LiveChange(
        id=int(d["id"]),
        time_ns=int(d["time_ns"]),
        kinds=tuple(d["kinds"]),
        places=tuple((int(a), int(b), int(s)) for a, b, s in d["places"]),
        cell_m=float(d["cell_m"]),
        polygon=np.asarray(d["polygon"], dtype=float).reshape(-1, 2),
        tiles=tuple((int(a), int(b)) for a, b in d["tiles"]),
        drive_ids=tuple(d["drive_ids"]),
        confidence=float(d["confidence"]),
        retired_feature_ids=tuple(int(i) for i in d["retired_feature_ids"]),
        retired=tuple(
            RetiredFeature(
                int(r["feature_id"]),
                int(r["type"]),
                np.asarray(r["points"], dtype=float).reshape(-1, 2),
                int(r["change_id"]),
                int(r["valid_from_ns"]),
                int(r["valid_to_ns"]),
            )
            for r in d["retired"]
        ),
        map_version=int(d["map_version"]),
        confirmed_ns=int(d["confirmed_ns"]),
    )


def dumps(c: LiveChange) -> str:
    """``change_to_dict`` as a JSON string."""
    return json.dumps(change_to_dict(c))
