"""The map as of the last drive: changes of the road found and the changed places rebuilt.

1. The map is built from every drive (``build_map``), as always.
2. Every drive is compared with it place by place (``updates.evidence``) and the changes of the
   road are confirmed with their change points (``updates.detect``).
3. No change: that map is the result, unchanged. Otherwise every drive that passed a changed
   place before the change loses its part there (its trajectory and detections are cut; the
   pieces elsewhere stay, ids ``<drive id>/<k>``); every drive in evidence of a change is moved
   onto the first map by its own offset, estimated on what did not change (its anchor per place,
   ``updates.evidence``, smoothed along it), since a few drives alone would leave their
   localisation error in the rebuilt place; and the map is built again: the changed places come
   from the drives after the change only, everything else from every drive as before.
4. What the changed places held in the first map is retired, not forgotten: ``RetiredFeature``
   (the feature's piece there, valid until the change's time) in ``HDMap.extra["retired"]``;
   the changes are in ``HDMap.extra["changes"]``, and the map's version counts them.

``follow_changes`` is step 1 and then ``follow_map`` (steps 2-4) on the map it built. The node
suite calls ``follow_map`` itself on its settled map (``live.changes.follow_live``), so the live
map follows a change with exactly the code ``bag2map`` uses.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
import shapely
from scipy.ndimage import uniform_filter1d
from scipy.spatial import cKDTree

from hdmap_core.geometry import left_normal, point_headings, true_runs
from hdmap_core.model import Detection, Drive, FeatureType, HDMap, MapFeature
from hdmap_core.parallel import map_balanced
from hdmap_core.plausibility import PhysicalBounds, prepare_drives
from hdmap_core.updates.before import as_before, moved_consensus, with_neighbours
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import DetectedChange, detect_changes
from hdmap_core.updates.edges import (
    EdgeEvidence,
    EdgeSide,
    detect_edge_changes,
    edge_evidence,
    edge_side,
    fleet_edge_evidence,
    merge_changes,
    opened_edge_moved,
    solid_lines,
)
from hdmap_core.updates.evidence import (
    DriveSide,
    PlaceEvidence,
    drive_evidence,
    drive_side,
    fleet_evidence,
    map_lines,
    unwrap_aliases,
)
from hdmap_core.updates.lone import lone_copies_dropped
from hdmap_core.updates.marks import unchanged_marks
from hdmap_core.updates.places import PlaceKey, Places, places_of
from hdmap_core.updates.splice import Reach, border_shift, grow, shifted, splice
from hdmap_core.updates.tapers import taper_moved
from hdmap_core.updates.unseen import ModelledMarking, UnseenMove, measured_moved, unseen_at_ends, unseen_moved

__all__ = [
    "RetiredFeature",
    "FollowResult",
    "follow_changes",
    "follow_map",
    "anchored",
    "cut_before_changes",
    "fleet_comparison",
    "drive_comparisons",
    "OwnSide",
    "own_side",
    "unwrapped",
    "drives_near_changes",
    "recompared",
    "clip_to_places",
    "along_drives",
    "retired_features",
    "history_to_dict",
]

_MIN_POSES = 5  # a drive piece with fewer poses is dropped ...
_MIN_PIECE_M = 20.0  # ... or shorter than this [m] (the pipeline refuses a drive standing still: 5 m)


@dataclass(frozen=True)
class RetiredFeature:
    """A piece of a map feature that a change replaced.

    Attributes:
        feature_id: the feature it was part of (in the map before the change).
        type: its FeatureType code.
        points: (N, 2) the piece inside the changed places [m].
        change_id: the change that retired it.
        valid_from_ns: start of the first drive it was built from; valid_to_ns: the change's time.
    """

    feature_id: int
    type: int
    points: np.ndarray
    change_id: int
    valid_from_ns: int
    valid_to_ns: int


@dataclass(frozen=True)
class FollowResult:
    """The map as of the last drive, and how it came about.

    Attributes:
        map: the map (the first build's when nothing changed).
        changes: the confirmed changes, in time order.
        retired: what they replaced.
        first_map: the map of every drive (before any change was followed).
        rebuilt: with a local rebuild, the places taken from it (the changed ones and their
            ends along the drives); the map is the first map's everywhere else.
        seconds: wall time per stage: ``build`` (the first map), ``detect`` (evidence and change
            points), ``rebuild`` (the second build), ``apply`` (alignment and splice); and the
            CPU time of this process in ``detect_cpu``, ``rebuild_cpu``, ``apply_cpu`` (worker
            processes not counted).
        report: the build's report: the first (whole) build's with a local rebuild, else the
            rebuild's (``follow_changes``; None from ``follow_map``, whose build gives none).
        places: the places the drives were compared in (None when nothing was compared).
        modelled: the first map's markings no drive after a shift saw, moved by the shift the
            drives measured (``updates.unseen``; with a local rebuild only).
    """

    map: HDMap
    changes: tuple[DetectedChange, ...]
    retired: tuple[RetiredFeature, ...]
    first_map: HDMap
    report: object
    rebuilt: frozenset[PlaceKey] = frozenset()
    seconds: dict[str, float] = field(default_factory=dict, compare=False)
    places: Places | None = field(default=None, compare=False)
    modelled: tuple[ModelledMarking, ...] = ()


def _change_times(changes: Sequence[DetectedChange]) -> dict[PlaceKey, int]:
    """Per changed place, the time of its change (the latest, where two changes meet)."""
    out: dict[PlaceKey, int] = {}
    for c in changes:
        for p in c.places:
            out[p.key] = max(out.get(p.key, c.time_ns), c.time_ns)
    return out


def _cut_drive(drive: Drive, keep: np.ndarray) -> list[Drive]:
    """The pieces of ``drive`` on its kept poses, each with the detections nearest to it."""
    xy = np.asarray(drive.xy, dtype=float)
    runs = [
        (a, b)
        for a, b in true_runs(keep)
        if b - a >= _MIN_POSES and float(np.linalg.norm(np.diff(xy[a:b], axis=0), axis=1).sum()) >= _MIN_PIECE_M
    ]
    if len(runs) == 1 and runs[0] == (0, len(keep)):
        return [drive]
    if not runs:
        return []
    piece_of_pose = np.full(len(keep), -1)
    for k, (a, b) in enumerate(runs):
        piece_of_pose[a:b] = k
    tree = cKDTree(drive.xy)
    dets: list[list[Detection]] = [[] for _ in runs]
    for det in drive.detections:
        pts = np.asarray(det.points, dtype=float)
        _, j = tree.query(pts)
        owner = piece_of_pose[j]
        starts = np.flatnonzero(np.diff(np.concatenate([[-2], owner])) != 0)
        ends = np.concatenate([starts[1:], [len(owner)]])
        for s0, s1 in zip(starts, ends):
            if owner[s0] >= 0 and s1 - s0 >= 2:
                dets[int(owner[s0])].append(Detection(det.type, pts[s0:s1].copy()))
    out = []
    for k, (a, b) in enumerate(runs):
        out.append(
            replace(
                drive,
                drive_id=f"{drive.drive_id}/{k}",
                xy=drive.xy[a:b].copy(),
                yaw=drive.yaw[a:b].copy(),
                stamps_ns=drive.stamps_ns[a:b].copy(),
                detections=tuple(dets[k]),
            )
        )
    return out


def anchored(drive: Drive, anchors: dict[PlaceKey, float], places: Places, *, smooth_m: float = 100.0) -> Drive:
    """``drive`` moved left by its anchor offset of each place (smoothed over ``smooth_m``)."""
    keys = places.keys(drive.xy, drive.yaw)
    a = np.array([anchors.get(k, np.nan) for k in keys])
    if not np.isfinite(a).any():
        return drive
    idx = np.arange(len(a))
    ok = np.isfinite(a)
    a = np.interp(idx, idx[ok], a[ok])
    step = max(drive.length_m / max(len(a) - 1, 1), 1e-3)
    a = uniform_filter1d(a, size=max(1, int(round(smooth_m / step))) | 1, mode="nearest")
    left = left_normal(drive.yaw)
    move = a[:, None] * left
    tree = cKDTree(drive.xy)
    dets = []
    for det in drive.detections:
        _, j = tree.query(np.asarray(det.points, dtype=float))
        dets.append(Detection(det.type, np.asarray(det.points, dtype=float) + move[j]))
    return replace(drive, xy=drive.xy + move, detections=tuple(dets))


def along_drives(
    drives: Sequence[Drive], places: Places, times: dict[PlaceKey, int], steps: int
) -> dict[PlaceKey, int]:
    """``times`` with the places up to ``steps`` places before and after them along ``drives``
    (the change's time of the place they lead to): the tapers and stretches detection left out.
    A place a drive crosses for less than half a cell (a cell's corner) does not count as one
    of the ``steps``, it is taken with the next: else a 100 m taper beyond a corner of 20 m
    would be left out."""
    out = dict(times)
    short = 0.5 * places.cell_m
    for d in drives:
        keys = places.keys(d.xy, d.yaw)
        if not keys:
            continue
        step = np.r_[0.0, np.linalg.norm(np.diff(np.asarray(d.xy, dtype=float), axis=0), axis=1)]
        starts = [i for i in range(len(keys)) if i == 0 or keys[i] != keys[i - 1]]
        seq = [keys[i] for i in starts]
        length = np.add.reduceat(step, starts)
        for i, k in enumerate(seq):
            if k not in times:
                continue
            for way in (-1, 1):
                j, counted = i + way, 0
                while 0 <= j < len(seq) and counted < steps:
                    if seq[j] not in times:
                        out[seq[j]] = max(out.get(seq[j], times[k]), times[k])
                    counted += int(length[j] >= short)
                    j += way
    return out


def _ids_unique(drives: Sequence[Drive]) -> bool:
    return len({d.drive_id for d in drives}) == len(drives)


Records = list[tuple[list[PlaceEvidence], list[EdgeEvidence]]]


class OwnSide(NamedTuple):
    """A drive's own side of its comparison with a map (its cuts and its detections on them),
    which no map changes: it can be made before the map is there (``bag2map`` makes it on a
    spare core while the map is built)."""

    places: DriveSide
    edges: EdgeSide


def own_side(drive: Drive, config: ChangeConfig = ChangeConfig()) -> OwnSide:
    """``drive``'s ``OwnSide`` (``drive_side`` and ``edge_side``)."""
    return OwnSide(drive_side(drive, config), edge_side(drive, config))


def drive_comparisons(
    drives: Sequence[Drive],
    hdmap: HDMap,
    places: Places,
    *,
    config: ChangeConfig,
    workers: int = 1,
    only: Sequence[int] | None = None,
    sides: Mapping[str, OwnSide] | None = None,
) -> Records:
    """Per drive (those at the indices ``only``, else every one) its comparison with ``hdmap``
    alone: its place evidence before ``unwrap_aliases`` and its edge evidence anchored on it.

    With ``workers`` > 1 the drives are shared out by length over that many processes
    (``parallel.map_balanced``: the map's lines indexed once here, inherited by the forked
    workers), the records in drive order: the same records as one process. ``sides``: drives'
    ``own_side`` made before, by drive id (the others' are made here; the same records)."""
    lines, solids = map_lines(hdmap), solid_lines(hdmap)
    at = list(range(len(drives))) if only is None else list(only)
    sides = sides or {}

    def one(i: int) -> tuple[list[PlaceEvidence], list[EdgeEvidence]]:
        drive = drives[at[i]]
        side = sides.get(drive.drive_id)
        ev = drive_evidence(drive, lines, places, config=config, side=side.places if side else None)
        anchors = {e.key: e.anchor_m for e in ev if np.isfinite(e.anchor_m)}
        return ev, edge_evidence(drive, solids, places, anchors, config=config, side=side.edges if side else None)

    return map_balanced(one, [max(drives[i].length_m, 1.0) for i in at], workers)


def unwrapped(records: Records, config: ChangeConfig) -> tuple[list[PlaceEvidence], list[EdgeEvidence]]:
    """The fleet's evidence of per-drive ``records``: ``unwrap_aliases`` over every drive's place
    evidence (as ``fleet_evidence``), the edge evidence in drive order."""
    evidence = unwrap_aliases([e for ev, _ in records for e in ev], config)
    return evidence, [x for _, xs in records for x in xs]


def fleet_comparison(
    drives: Sequence[Drive], hdmap: HDMap, places: Places, *, config: ChangeConfig, workers: int = 1
) -> tuple[list[PlaceEvidence], list[EdgeEvidence]]:
    """Every drive compared with ``hdmap``: ``fleet_evidence`` and ``fleet_edge_evidence``, in
    drive order.

    Each drive's comparison is its own (its edge evidence is anchored on its own place evidence):
    ``drive_comparisons``, on ``workers`` processes. Drives with a shared id (their anchors mix in
    ``fleet_edge_evidence``) are compared as one fleet in this process.
    """
    if not _ids_unique(drives):
        evidence = fleet_evidence(drives, hdmap, places, config=config)
        return evidence, fleet_edge_evidence(drives, hdmap, places, evidence, config=config)
    return unwrapped(drive_comparisons(drives, hdmap, places, config=config, workers=workers), config)


class _Compared(NamedTuple):
    """The drives compared with a map: the fleet's place and edge evidence, and each drive's own
    records where the drive ids are unique (None otherwise: compared as one fleet)."""

    evidence: list[PlaceEvidence]
    edges: list[EdgeEvidence]
    records: Records | None


def _compared(
    drives: Sequence[Drive],
    hdmap: HDMap,
    places: Places,
    *,
    config: ChangeConfig,
    workers: int,
    sides: Mapping[str, OwnSide] | None,
) -> _Compared:
    """Every drive compared with ``hdmap``, each drive's records kept where the ids are unique
    (:func:`drive_comparisons`; else :func:`fleet_comparison`)."""
    if not _ids_unique(drives):
        return _Compared(*fleet_comparison(drives, hdmap, places, config=config, workers=workers), None)
    records = drive_comparisons(drives, hdmap, places, config=config, workers=workers, sides=sides)
    return _Compared(*unwrapped(records, config), records)


def _compared_again(
    compared: _Compared,
    drives: Sequence[Drive],
    first: HDMap,
    reference: HDMap,
    places: Places,
    *,
    config: ChangeConfig,
    workers: int,
    sides: Mapping[str, OwnSide] | None,
) -> _Compared:
    """``compared`` (the drives against ``first``) as against ``reference`` instead: with records,
    only the drives near where the two maps differ are compared again (:func:`recompared`)."""
    if compared.records is None:
        return _Compared(*fleet_comparison(drives, reference, places, config=config, workers=workers), None)
    records = recompared(
        compared.records, drives, first, reference, places, config=config, workers=workers, sides=sides
    )
    return _Compared(*unwrapped(records, config), records)


def _detected(compared: _Compared, places: Places, *, config: ChangeConfig, workers: int) -> list[DetectedChange]:
    """The changes ``compared`` shows: the places' (``detect_changes``) and the edge line's
    (``detect_edge_changes``), merged."""
    changes = detect_changes(compared.evidence, places, config=config, workers=workers)
    return merge_changes(changes, detect_edge_changes(compared.edges, places, config=config), places)


def _segment_rows(features: Sequence[MapFeature]) -> Counter[tuple[float, ...]]:
    """The features' line segments as (type, ax, ay, bx, by) rows, counted (``map_lines``')."""
    rows: Counter[tuple[float, ...]] = Counter()
    for f in features:
        pts = np.asarray(f.points, dtype=float)
        if len(pts) >= 2:
            rows.update(map(tuple, np.c_[np.full(len(pts) - 1, float(f.type)), pts[:-1], pts[1:]].tolist()))
    return rows


def drives_near_changes(drives: Sequence[Drive], first: HDMap, other: HDMap, reach_m: float) -> list[int]:
    """Indices of the ``drives`` with a pose within ``reach_m`` of a line segment one of the maps
    holds more often than the other. A drive's comparison meets the map only on its cuts, each
    through one of its poses and ``view_m`` long to either side: with ``reach_m`` >= ``view_m``,
    every other drive meets the same segments in both maps, in the same order (``updates.splice``
    keeps the first map's features in order), and its records are the same. Features both maps
    hold (their very points, as ``splice`` keeps them) are not looked at."""

    def own(a: HDMap, b: HDMap) -> list[MapFeature]:
        shared = {(id(f.points), int(f.type)) for f in b.features}
        return [f for f in a.features if (id(f.points), int(f.type)) not in shared]

    a, b = _segment_rows(own(first, other)), _segment_rows(own(other, first))
    differ = (a - b) + (b - a)
    if not differ:
        return []
    ends = np.array(sorted(differ))[:, 1:].reshape(-1, 2, 2)
    lo, hi = ends.min(axis=(0, 1)) - reach_m, ends.max(axis=(0, 1)) + reach_m
    lines = shapely.multilinestrings(shapely.linestrings(ends))
    out = []
    for i, d in enumerate(drives):
        xy = np.asarray(d.xy, dtype=float)
        xy = xy[((xy >= lo) & (xy <= hi)).all(axis=1)]  # a pose farther out than the box is no nearer
        if len(xy) and shapely.dwithin(shapely.multipoints(xy), lines, reach_m):
            out.append(i)
    return out


def recompared(
    records: Records,
    drives: Sequence[Drive],
    first: HDMap,
    reference: HDMap,
    places: Places,
    *,
    config: ChangeConfig,
    workers: int = 1,
    sides: Mapping[str, OwnSide] | None = None,
) -> Records:
    """``records`` (``drive_comparisons`` of ``drives`` with ``first``) as compared with
    ``reference`` instead: only the drives near where the two maps differ are compared again
    (``drives_near_changes``, within the cuts' reach plus a metre), the others keep theirs."""
    again = drives_near_changes(drives, first, reference, config.view_m + 1.0)
    out = list(records)
    redone = drive_comparisons(drives, reference, places, config=config, workers=workers, only=again, sides=sides)
    for i, r in zip(again, redone):
        out[i] = r
    return out


def cut_before_changes(
    drives: Sequence[Drive],
    places: Places,
    changes: Sequence[DetectedChange],
    *,
    times: dict[PlaceKey, int] | None = None,
    before: bool = False,
) -> list[Drive]:
    """``drives`` without their parts in a changed place from before its change (module docstring);
    ``times``: the change time per place, instead of ``changes``'. ``before``: the other way, without
    their parts in a changed place from its change on (the road as it was, ``updates.before``)."""
    times = _change_times(changes) if times is None else times
    out: list[Drive] = []
    for d in drives:
        keys = places.keys(d.xy, d.yaw)
        stamps = np.asarray(d.stamps_ns, dtype=np.int64)
        if before:
            keep = stamps < np.array([times.get(k, np.iinfo(np.int64).max) for k in keys], dtype=np.int64)
        else:
            keep = stamps >= np.array([times.get(k, np.iinfo(np.int64).min) for k in keys], dtype=np.int64)
        out.extend(_cut_drive(d, keep) if not keep.all() else [d])
    return out


def clip_to_places(drives: Sequence[Drive], places: Places, keys: set[PlaceKey]) -> list[Drive]:
    """The pieces of ``drives`` in the places ``keys`` (ids ``<drive id>/<k>`` where cut)."""
    out: list[Drive] = []
    for d in drives:
        keep = np.array([k in keys for k in places.keys(d.xy, d.yaw)], dtype=bool)
        if keep.any():
            out.extend(_cut_drive(d, keep) if not keep.all() else [d])
    return out


def retired_features(
    hdmap: HDMap,
    places: Places,
    changes: Sequence[DetectedChange],
    *,
    valid_from_ns: int,
    reach: Reach | None = None,
) -> list[RetiredFeature]:
    """The pieces of ``hdmap``'s features inside the changed places (with ``reach``: and within it,
    as ``updates.splice.splice`` replaces them)."""
    owner: dict[PlaceKey, DetectedChange] = {}
    for c in changes:
        for p in c.places:
            owner[p.key] = c
    out = []
    for f in hdmap.features:
        pts = np.asarray(f.points, dtype=float)
        if len(pts) < 2:
            continue
        yaw = point_headings(pts)
        keys = places.keys(pts, yaw)
        inside = np.array([k in owner for k in keys])
        if reach is not None and inside.any():
            inside[inside] = reach.replaced(pts[inside], yaw[inside], int(f.type))
        for a, b in true_runs(inside):
            if b - a >= 2:
                c = owner[keys[a]]
                out.append(RetiredFeature(int(f.id), int(f.type), pts[a:b].copy(), c.id, valid_from_ns, c.time_ns))
    return out


_BOUNDS = PhysicalBounds()
_BORDER = int(FeatureType.ROAD_BORDER)
_MARKINGS = (int(FeatureType.SOLID), int(FeatureType.DASHED))
# A first map's border in a changed place stays unless the (aligned) local map has a border this
# close (updates.splice.Reach): the same barrier seen again. Not ChangeConfig.pair_max_m (3 m):
# on motorway_ramps the opposite carriageway's barrier, 2.5 m beyond the median one, which the
# drives after the change saw and the local map holds, then took the median barrier's place
# (shift10 seed 1: zone recall 93.8 % with 3 m, 97.4 % with 1.5 m; docs/updates.md, "How `bag2map` follows a change").
_BORDER_SAME_M = 1.5
_NOT_SHIFTED = {"lane_closed", "lane_opened", "type", "marking_gone"}


def follow_changes(
    drives: Sequence[Drive],
    *,
    build: Callable[[Sequence[Drive]], tuple[HDMap, object]],
    config: ChangeConfig = ChangeConfig(),
    bounds: PhysicalBounds | None = _BOUNDS,
    local: bool = True,
    margin_places: int = 2,
    taper_places: int = 1,
    workers: int = 1,
    sides: Mapping[str, OwnSide] | None = None,
    places: Places | None = None,
) -> FollowResult:
    """The map of ``drives`` as of the last of them: the map of every drive (``build``), then
    :func:`follow_map` on it (module docstring).

    Args:
        drives: the fleet's drives (their time stamps order them).
        build: drives -> (map, build report): the pipeline as configured (``build_map``).
        config: change detection settings.
        bounds: the physical bounds of the build (``PipelineConfig.plausibility``): a drive outside
            them (or malformed) is left out here as the build leaves it out, so that no evidence
            is computed on it (a pose at 1e12 m would ask for terabytes). ``drives`` is passed
            to ``build`` as given when every drive keeps them.
        local, margin_places, taper_places, workers, sides, places: as :func:`follow_map` (``places``
            of the drives as given, used only when every drive keeps the bounds).
    """
    usable, rejected = prepare_drives(drives, bounds=bounds)
    if rejected:
        drives = usable
    reports: list[object] = []

    def map_only(ds: Sequence[Drive]) -> HDMap:
        hdmap, report = build(ds)
        reports.append(report)
        return hdmap

    t0 = time.perf_counter()
    first_map = map_only(drives)
    build_s = time.perf_counter() - t0
    result = follow_map(
        first_map,
        drives,
        build=map_only,
        config=config,
        local=local,
        margin_places=margin_places,
        taper_places=taper_places,
        workers=workers,
        sides=sides,
        places=None if rejected else places,
    )
    # the first (whole) build's report, unless the whole map was built again
    report = reports[-1] if result.changes and not local else reports[0]
    return replace(result, report=report, seconds={"build": build_s, **result.seconds})


def follow_map(
    first_map: HDMap,
    drives: Sequence[Drive],
    *,
    build: Callable[[Sequence[Drive]], HDMap],
    config: ChangeConfig = ChangeConfig(),
    local: bool = True,
    margin_places: int = 2,
    taper_places: int = 1,
    workers: int = 1,
    sides: Mapping[str, OwnSide] | None = None,
    places: Places | None = None,
) -> FollowResult:
    """An existing map of ``drives`` made to follow the changes of the road they show.

    This is :func:`follow_changes` after its first build, shared by ``bag2map`` (its first build)
    and the node suite (the stitcher's settled map, ``live.changes.follow_live``), steps 2-4 of the
    module docstring: every drive is compared with ``first_map`` place by place, the changes are
    confirmed (markings moved, re-striped, gone or new; an edge line moved: a lane closed or
    opened), and only when there is one the changed places are mapped again and put into it.

    Args:
        first_map: the consensus of every drive in ``drives`` (the map to follow the changes on).
        drives: every drive it was built from, usable as they are (within the physical bounds);
            their time stamps order them.
        build: drives -> map: the pipeline as configured (``build_map(...).map``); called once,
            and only when a change is confirmed.
        config: change detection settings.
        local: rebuild only the changed places (grown by ``margin_places`` places for context),
            aligned on ``first_map``'s road borders and spliced into it (``updates.splice``);
            False: rebuild the whole map from every drive (cut and moved as above).
        margin_places: places around the changed ones mapped with them and thrown away.
        taper_places: with ``local``, the places this many before and after the changed ones
            along the drives after the change are rebuilt with them (from those drives only):
            the ends of a change (tapers) that detection left out.
        workers: processes the drives' comparison with ``first_map`` runs on
            (:func:`fleet_comparison`) and the places' change tests (:func:`detect_changes`); the
            result is the same with any number.
        sides: the drives' ``own_side`` (their side of the comparison, which no map changes),
            made before, by drive id; the others' are made here (the same result).
        places: ``places_of(drives, cell_m=config.cell_m)`` made before (else made here).

    Returns:
        The followed map (``first_map`` itself when nothing changed, its version grown by the
        number of changes otherwise), the changes, the retired pieces, the places compared in,
        ``rebuilt`` (with ``local``) and the stages' wall time (``detect``, ``rebuild``, ``apply``).
        ``report`` is None: ``build`` gives none.
    """
    t1, c1 = time.perf_counter(), time.process_time()
    if places is None or places.cell_m != config.cell_m:
        places = places_of(drives, cell_m=config.cell_m)
    compared = _compared(drives, first_map, places, config=config, workers=workers, sides=sides)
    changes = _detected(compared, places, config=config, workers=workers)
    # where the consensus has taken the new road (updates.before): the map as it was there, and
    # the drives compared with that instead (those near it again, the others keep their records)
    changed = {p.key for c in changes for p in c.places}
    taken = with_neighbours(moved_consensus(compared.evidence, config, skip=changed, edges=compared.edges), places)
    taken = {k: t for k, t in taken.items() if k not in changed}
    old_road: HDMap | None = None
    if taken:
        pieces = clip_to_places(
            cut_before_changes(drives, places, (), times=taken, before=True), places, grow(places, taken, margin_places)
        )
        old_road = as_before(first_map, build(pieces), pieces, places, set(taken), config=config)
        reference = splice(first_map, old_road, places, set(taken))
        compared = _compared_again(
            compared, drives, first_map, reference, places, config=config, workers=workers, sides=sides
        )
        changes = _detected(compared, places, config=config, workers=workers)
    evidence, edges = compared.evidence, compared.edges
    t0, c0 = time.perf_counter(), time.process_time()
    seconds = {"detect": t0 - t1, "detect_cpu": c0 - c1}
    if not changes:
        return FollowResult(first_map, (), (), first_map, None, seconds=seconds, places=places)
    in_evidence = {d for c in changes for d in c.drives_after}
    anchors: dict[str, dict[PlaceKey, float]] = {}
    for e in evidence:
        if e.drive_id in in_evidence and np.isfinite(e.anchor_m):
            anchors.setdefault(e.drive_id, {})[e.key] = e.anchor_m
    moved = [anchored(d, anchors[d.drive_id], places) if d.drive_id in anchors else d for d in drives]
    if local:
        first_change = min(c.time_ns for c in changes)
        after = [d for d in moved if d.start_ns >= first_change]
        times = along_drives(after, places, _change_times(changes), taper_places)
        after = [d for d in after if d.drive_id in in_evidence]
        cut = cut_before_changes(moved, places, changes, times=times)
        core = set(times)
        # the map the rebuilt places replace: the road as it was where the consensus had taken the new
        base = first_map if old_road is None else splice(first_map, old_road, places, set(taken) & core)
        region = grow(places, core, margin_places)
        clipped = clip_to_places(cut, places, region)
        t1, c1 = time.perf_counter(), time.process_time()
        local_map = build(clipped)
        seconds["rebuild"], seconds["rebuild_cpu"] = time.perf_counter() - t1, time.process_time() - c1
        local_map = shifted(local_map, border_shift(local_map, base, after, places, core, config=config), places)
        # what the rebuilt places were mapped from: beyond the sensors' reach of every such pose
        # the first map stays (updates.splice)
        poses = [d.xy[np.array([k in core for k in places.keys(d.xy, d.yaw)], dtype=bool)] for d in clipped]
        borders = [np.asarray(f.points, dtype=float) for f in local_map.features if int(f.type) == _BORDER]
        marks = [np.asarray(f.points, dtype=float) for f in local_map.features if int(f.type) in _MARKINGS]
        # what no drive after a shift saw of the first map's markings: moved by the shift
        unseen = unseen_moved(base, local_map, places, changes, evidence, core, config=config)
        # an opened shoulder's edge line no drive after the change saw: moved by the edge's move
        # and the other lines of a lane opened, which it left alone, where those drives missed them
        edge, opened_kept = opened_edge_moved(
            unseen.map, local_map, places, changes, core, evidence=edges, config=config
        )
        unseen = UnseenMove(edge.map, unseen.pieces + edge.pieces)
        modelled = unseen.pieces
        # lines no drive after a shift saw, where the lines they saw had not moved yet (the
        # tapers' ends): not where a line went or changed type, which the few drives cannot tell
        # from a line they did not see
        shifts = all("geometry" in c.kinds and not set(c.kinds) & _NOT_SHIFTED for c in changes)
        # ... and not in a place where the drives after the change measured the lines moved
        moved_places = measured_moved(changes, config)
        if shifts:
            # along the tapers, where the lines moved less than the shift: moved as the lines
            # the drives saw beside them
            unseen = taper_moved(base, unseen, local_map, places, changes, core, config=config)
            modelled = unseen.pieces
        ends = unseen_at_ends(unseen.map, local_map, places, core, moved_places) if shifts else np.zeros((0, 2))
        keep = [unseen.moved_to, ends]
        # a re-striping or a marking gone leaves the other lines: those the drives after it had
        # no evidence of stay (updates.marks)
        kept = unchanged_marks(base, local_map, places, changes, after, core, config=config)
        reach = Reach(
            np.concatenate([np.zeros((0, 2)), *poses]),
            config.view_m,
            np.concatenate([np.zeros((0, 2)), *borders]),
            _BORDER_SAME_M,
            np.concatenate([np.zeros((0, 2)), *marks]),
            keep=np.concatenate([*keep, kept, opened_kept]),
            take=unseen.moved_from,
        )
        new_map = splice(unseen.map, local_map, places, core, reach=reach)
        # one drive's copy of a line with another type, beside the line the map has there
        new_map, _ = lone_copies_dropped(new_map, places, core)
    else:
        core = set()
        base = first_map
        reach = None
        modelled = ()
        cut = cut_before_changes(moved, places, changes)
        t1, c1 = time.perf_counter(), time.process_time()
        new_map = build(cut)
        seconds["rebuild"], seconds["rebuild_cpu"] = time.perf_counter() - t1, time.process_time() - c1
    start = min((d.start_ns for d in drives), default=0)
    retired = tuple(retired_features(base, places, changes, valid_from_ns=start, reach=reach))
    extra = {**new_map.extra, "changes": list(changes), "retired": list(retired), "modelled": list(modelled)}
    new_map = replace(new_map, version=first_map.version + len(changes), extra=extra)
    seconds["apply"] = time.perf_counter() - t0 - seconds["rebuild"]
    seconds["apply_cpu"] = time.process_time() - c0 - seconds["rebuild_cpu"]
    return FollowResult(
        new_map, tuple(changes), retired, first_map, None, frozenset(core), seconds, places=places, modelled=modelled
    )


def history_to_dict(result: FollowResult) -> dict:
    """The changes and retired pieces as a JSON document (``bag2map`` writes ``OUT.history.json``)."""
    return {
        "changes": [
            {
                "id": c.id,
                "time_ns": c.time_ns,
                "kinds": list(c.kinds),
                "confidence": round(c.confidence, 4),
                "drives_after": list(c.drives_after),
                "places": [
                    {"key": list(p.key), "kind": p.kind, "effect": round(p.effect, 4), "extended": p.extended}
                    for p in c.places
                ],
                "modelled_points": sum(len(m.points) for m in result.modelled if m.change_id == c.id),
            }
            for c in result.changes
        ],
        "retired": [
            {
                "feature_id": r.feature_id,
                "type": r.type,
                "change_id": r.change_id,
                "valid_from_ns": r.valid_from_ns,
                "valid_to_ns": r.valid_to_ns,
                "points": np.round(r.points, 3).tolist(),
            }
            for r in result.retired
        ],
        # the first map's markings no drive after a shift saw, moved by the measured shift
        # (updates.unseen): a model, not an observation (their points' drive_count is 0)
        "modelled": [
            {
                "feature_id": m.feature_id,
                "type": m.type,
                "change_id": m.change_id,
                "move_m": round(float(np.median(m.move_m)), 3),
                "points": np.round(m.points, 3).tolist(),
            }
            for m in result.modelled
        ],
    }
