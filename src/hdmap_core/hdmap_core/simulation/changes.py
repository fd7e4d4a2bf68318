"""Road changes: the ground truth as it changes over time (construction zones, re-striping).

A ``RoadChange`` acts on one carriageway along one ground-truth route, between two stations
``from_m``..``to_m`` measured along that route's centerline. What belongs to the carriageway: a
point within ``BAND_M`` of the route centerline, beside the piece between its ends, running in
the route's direction (so the opposite carriageway and crossing roads are never touched).

Kinds (``KINDS``):

* ``shift``: lane markings and lane centerlines move ``size`` metres to the right of the driving
  direction (toward the shoulder; negative: toward the median), reached over a smooth ``taper_m``
  ramp at each end inside the zone; in full within ``BAND_M / 2`` of the route, fading out to
  none at ``BAND_M`` (ramps leaving the carriageway). Road borders (barrier, shoulder border) stay, as in a
  construction zone.
* ``restripe``: markings flip dashed <-> solid inside the zone; by default every dashed one (a
  no-overtaking zone), with ``size`` = k the k-th marking from the left only.
* ``remove``: markings disappear inside the zone; by default every dashed one, with ``size`` = k
  the k-th marking from the left only.
* ``add``: a new solid marking ``size`` metres right of the route centerline along the zone.
* ``close``: the rightmost lane is closed: the right edge marking moves onto the lane divider left
  of it (``size`` metres, default the distance between the two), with the tapers; the divider is
  removed along the zone; the closed lane's centerline merges into its left neighbour, so drives
  in it change lanes. Lane ids and links stay (the lane count changes in geometry only).
* ``open``: the shoulder opens as a lane: the right edge marking moves ``size`` metres to the
  right (required), with the tapers, and a dashed marking is drawn where it was, between the
  tapers; there the new lane's centerline is added (``size`` wide, split off the rightmost lane
  and merging back into it, that lane its left neighbour). Simulated drives do not use it. The
  moved edge stays on or inside the road border right of it: a ``size`` larger than the room
  between them is refused (``GroundTruthError`` naming the largest ``size`` there).

Text form (``parse_change``, ``hdmap simulate --change``): ``KIND:FROM_M-TO_M[:SIZE][:ROUTE]@AFTER``,
e.g. ``shift:1000-2000:1.5:fwd_lane1@40``: drives 0..39 see the road as it was, drives 40.. the
changed one. Everything here is pure (no I/O): ``apply_change`` returns a new ``GroundTruth``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.errors import ConfigError, GroundTruthError
from hdmap_core.geometry import arc_length, resample_evenly, turn_left, unit_tangents
from hdmap_core.groundtruth import GroundTruth, GTFeature, GTLane, GTRoute
from hdmap_core.model import FeatureType

__all__ = [
    "KINDS",
    "BAND_M",
    "CHANGE_GAP_S",
    "DEFAULT_TAPER_M",
    "RoadChange",
    "ChangeZone",
    "parse_change",
    "apply_change",
    "apply_changes",
    "road_as_of",
    "changes_from_dict",
    "change_zone",
    "zone_mask",
    "default_route",
]

KINDS = ("shift", "restripe", "remove", "add", "close", "open")
#: Lateral reach of a change from its route's centerline [m]: a whole carriageway of 3-4 lanes
#: with its shoulder from any of its lanes, not the opposite one (that runs the other way).
BAND_M = 20.0
#: Time between the last drive before a change and the first after it [s] ("a day later").
CHANGE_GAP_S = 86_400.0
DEFAULT_TAPER_M = 100.0
_DENSE_M = 0.5  # spacing of the densified route centerline [m]
_COS_SAME = 0.5  # a feature runs with the route when cos(angle) >= this
_TEXT = re.compile(r"^(?P<kind>[a-z]+):(?P<a>-?[0-9.]+)-(?P<b>-?[0-9.]+)(?P<rest>(:[^:@]+){0,2})@(?P<after>[0-9]+)$")


@dataclass(frozen=True)
class RoadChange:
    """One change of the road (module docstring).

    Attributes:
        kind: one of ``KINDS``.
        from_m, to_m: the zone, stations along the route centerline [m], from < to.
        size: shift [m, + = right]; restripe/remove: the marking's 1-based rank from the left
            (None: every dashed one); add: the new marking's offset right of the route [m].
        route_id: the route the stations are measured along ("" = ``default_route``).
        after_drive: index of the first drive that sees the changed road.
        taper_m: length of each end ramp of a shift [m].
        time_ns: when the road changed [ns since epoch] (set by the simulator; 0 = unknown).
    """

    kind: str
    from_m: float
    to_m: float
    size: float | None = None
    route_id: str = ""
    after_drive: int = 0
    taper_m: float = DEFAULT_TAPER_M
    time_ns: int = 0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ConfigError(f"road change: unknown kind {self.kind!r}; choose one of {', '.join(KINDS)}")
        if not (math.isfinite(self.from_m) and math.isfinite(self.to_m) and self.from_m < self.to_m):
            raise ConfigError(f"road change {self.kind}: zone {self.from_m}-{self.to_m} m must have FROM < TO")
        if self.size is not None and not math.isfinite(self.size):
            raise ConfigError(f"road change {self.kind}: size {self.size} is not finite")
        if self.kind == "add" and self.size is None:
            raise ConfigError("road change add: SIZE (offset of the new marking right of the route [m]) is required")
        if self.kind == "open" and (self.size is None or self.size <= 0):
            raise ConfigError("road change open: SIZE (how far the edge marking moves right [m], > 0) is required")
        if self.kind == "close" and self.size is not None and self.size <= 0:
            raise ConfigError(f"road change close: SIZE (the closed lane's width [m]) must be > 0, got {self.size}")
        if (
            self.kind in ("restripe", "remove")
            and self.size is not None
            and (self.size < 1 or self.size != int(self.size))
        ):
            raise ConfigError(
                f"road change {self.kind}: SIZE selects the k-th marking from the left (k >= 1), got {self.size}"
            )
        if self.after_drive < 0:
            raise ConfigError(f"road change {self.kind}: @AFTER must be >= 0, got {self.after_drive}")
        if not (self.taper_m >= 0 and 2 * self.taper_m <= self.to_m - self.from_m):
            raise ConfigError(
                f"road change {self.kind}: tapers of {self.taper_m} m do not fit the zone {self.from_m}-{self.to_m} m"
            )

    @property
    def shift_m(self) -> float:
        """The lateral shift of a ``shift`` change [m, + = right]; 1.5 when no size is given."""
        return 1.5 if self.size is None else float(self.size)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, doc: dict) -> RoadChange:
        """Inverse of ``to_dict``.

        Raises:
            ConfigError: a missing or unknown key, or an invalid value.
        """
        try:
            return cls(**{k: doc[k] for k in doc})
        except TypeError as err:
            raise ConfigError(f"road change: {err}") from err

    def text(self) -> str:
        """The ``--change`` text of this change."""
        size = "" if self.size is None else f":{self.size:g}"
        route = f":{self.route_id}" if self.route_id else ""
        return f"{self.kind}:{self.from_m:g}-{self.to_m:g}{size}{route}@{self.after_drive}"


def parse_change(text: str) -> RoadChange:
    """``KIND:FROM_M-TO_M[:SIZE][:ROUTE]@AFTER`` -> ``RoadChange`` (module docstring).

    Raises:
        ConfigError: the text is not of that form or a value is invalid.
    """
    m = _TEXT.match(text.strip())
    if not m:
        raise ConfigError(
            f"--change {text!r}: expected KIND:FROM_M-TO_M[:SIZE][:ROUTE]@AFTER_DRIVE, e.g. shift:1000-2000:1.5@40"
        )
    size: float | None = None
    route = ""
    for item in [p for p in m["rest"].split(":") if p]:
        try:
            value = float(item)
        except ValueError:
            if route:
                raise ConfigError(f"--change {text!r}: two routes given") from None
            route = item
            continue
        if size is not None or route:
            raise ConfigError(f"--change {text!r}: SIZE comes once, before ROUTE")
        size = value
    return RoadChange(m["kind"], float(m["a"]), float(m["b"]), size, route, int(m["after"]))


# ------------------------------------------------------------------------------ where


def default_route(gt: GroundTruth) -> GTRoute:
    """The longest route of ``gt`` (the first of equal ones): where a change without a route acts.

    Raises:
        GroundTruthError: ``gt`` has no route of >= 2 points.
    """
    best, best_len = None, -1.0
    for r in gt.routes:
        line = gt.route_centerline(r) if r.lanes else np.zeros((0, 2))
        length = float(arc_length(line)[-1]) if len(line) >= 2 else -1.0
        if length > best_len + 1e-6:
            best, best_len = r, length
    if best is None or best_len <= 0:
        raise GroundTruthError(f"ground truth {gt.name!r}: no route to place a road change on")
    return best


@dataclass(frozen=True)
class ChangeZone:
    """Where a change acts: the densified route centerline, its stations and the zone's ends.

    Attributes:
        line: (N, 2) the whole route centerline, every ``_DENSE_M`` [m].
        s: (N,) its stations [m].
        from_m, to_m: the zone [m].
        band_m: lateral reach [m].
    """

    line: np.ndarray
    s: np.ndarray
    from_m: float
    to_m: float
    band_m: float = BAND_M

    @cached_property
    def tree(self) -> cKDTree:
        """Nearest-point index of ``line``."""
        return cKDTree(self.line)

    @cached_property
    def tangents(self) -> np.ndarray:
        """(N, 2) unit tangents of ``line``."""
        return unit_tangents(self.line)

    def piece(self, *, step_m: float = 5.0) -> np.ndarray:
        """(M, 2) the route centerline between the zone's ends, every ~``step_m`` (for files)."""
        keep = (self.s >= self.from_m) & (self.s <= self.to_m)
        pts = self.line[keep]
        return pts[:: max(1, int(round(step_m / _DENSE_M)))] if len(pts) > 2 else pts

    def polygon(self) -> np.ndarray:
        """(P, 2) a closed ring around the zone: the piece offset ``band_m`` to each side."""
        pts = self.piece()
        if len(pts) < 2:
            return np.zeros((0, 2))
        left = turn_left(unit_tangents(pts))
        ring = np.concatenate([pts + self.band_m * left, (pts - self.band_m * left)[::-1]])
        return np.concatenate([ring, ring[:1]])

    def to_dict(self) -> dict:
        return {
            "from_m": self.from_m,
            "to_m": self.to_m,
            "band_m": self.band_m,
            "line": np.round(self.piece(step_m=_DENSE_M * 2), 3).tolist(),
            "line_start_m": float(self.s[np.argmax(self.s >= self.from_m)]) if len(self.s) else 0.0,
        }

    @classmethod
    def from_dict(cls, doc: dict) -> ChangeZone:
        """A zone read back from ``to_dict``: the piece between its ends (enough for ``zone_mask``)."""
        line = np.asarray(doc["line"], dtype=float).reshape(-1, 2)
        dense = resample_evenly(line, _DENSE_M) if len(line) >= 2 else line
        s = float(doc.get("line_start_m", doc["from_m"])) + (
            arc_length(dense) if len(dense) >= 2 else np.zeros(len(dense))
        )
        return cls(dense, s, float(doc["from_m"]), float(doc["to_m"]), float(doc.get("band_m", BAND_M)))


def change_zone(gt: GroundTruth, change: RoadChange) -> ChangeZone:
    """The zone of ``change`` on ``gt``.

    Raises:
        GroundTruthError: the route is unknown or the zone lies beyond its end.
    """
    if change.route_id:
        route = next((r for r in gt.routes if r.id == change.route_id), None)
        if route is None:
            raise GroundTruthError(f"road change {change.text()}: no route {change.route_id!r} in {gt.name!r}")
    else:
        route = default_route(gt)
    line = resample_evenly(gt.route_centerline(route), _DENSE_M)
    s = arc_length(line)
    if change.from_m >= s[-1] or change.to_m <= 0:
        raise GroundTruthError(
            f"road change {change.text()}: route {route.id} is {s[-1]:.0f} m long, the zone lies outside it"
        )
    return ChangeZone(line, s, change.from_m, change.to_m)


def _station(
    zone: ChangeZone, points: np.ndarray, tangents: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(station [m], lateral [m, + = left], member of the carriageway) of each point."""
    if len(points) == 0:
        z = np.zeros(0)
        return z, z, np.zeros(0, dtype=bool)
    _, j = zone.tree.query(points)
    tj = zone.tangents[j]
    v = points - zone.line[j]
    along = np.sum(v * tj, axis=1)
    lat = tj[:, 0] * v[:, 1] - tj[:, 1] * v[:, 0]
    member = (np.abs(lat) <= zone.band_m) & (np.abs(along) <= 2.0 * _DENSE_M)
    if tangents is not None:
        member &= np.sum(tangents * tj, axis=1) >= _COS_SAME
    return zone.s[j] + along, lat, member


def zone_mask(zone: ChangeZone, points: np.ndarray, tangents: np.ndarray | None = None) -> np.ndarray:
    """(N,) True for the points inside the zone: on its carriageway (running its way when
    ``tangents`` (N, 2) are given) and between its ends."""
    s, _, member = _station(zone, np.asarray(points, dtype=float).reshape(-1, 2), tangents)
    return member & (s >= zone.from_m) & (s <= zone.to_m)


# ------------------------------------------------------------------------------ what


def _profile(s: np.ndarray, change: RoadChange) -> np.ndarray:
    """0 outside the zone, 1 inside, smooth ramps of ``taper_m`` at both ends inside it."""
    if change.taper_m <= 0:
        return ((s >= change.from_m) & (s <= change.to_m)).astype(float)

    def ramp(x: np.ndarray) -> np.ndarray:
        x = np.clip(x, 0.0, 1.0)
        return x * x * (3.0 - 2.0 * x)

    return ramp((s - change.from_m) / change.taper_m) * ramp((change.to_m - s) / change.taper_m)


def _shift_weight(zone: ChangeZone, pts: np.ndarray, change: RoadChange) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(station, lateral, weight) of each point: ``_shifted`` moves it ``change.shift_m * weight``."""
    s, lat, member = _station(zone, pts, unit_tangents(pts))
    # Full shift within half the band, fading out smoothly toward its edge (a ramp leaving the
    # carriageway bends back onto its old course rather than jumping there).
    fade = np.clip((zone.band_m - np.abs(lat)) / (zone.band_m / 2.0), 0.0, 1.0)
    return s, lat, np.where(member, _profile(s, change) * fade * fade * (3.0 - 2.0 * fade), 0.0)


def _shifted(zone: ChangeZone, pts: np.ndarray, change: RoadChange) -> np.ndarray:
    _, _, w = _shift_weight(zone, pts, change)
    if not np.any(w > 0):
        return pts
    _, j = zone.tree.query(pts)
    left = turn_left(zone.tangents[j])
    return pts - (change.shift_m * w)[:, None] * left


def _runs(mask: np.ndarray) -> list[tuple[int, int, bool]]:
    """(start, end exclusive, value) of the runs of ``mask``."""
    edges = np.flatnonzero(np.diff(mask.astype(np.int8))) + 1
    bounds = np.concatenate([[0], edges, [len(mask)]])
    return [(int(a), int(b), bool(mask[a])) for a, b in zip(bounds[:-1], bounds[1:])]


def _zone_markings(zone: ChangeZone, gt: GroundTruth, change: RoadChange) -> dict[int, tuple[np.ndarray, float]]:
    """Feature index -> ((N,) in-zone mask, median lateral offset there [m, + = left]) of the
    markings with at least two points in the zone between the change's ends."""
    out: dict[int, tuple[np.ndarray, float]] = {}
    for i, f in enumerate(gt.features):
        if f.type not in (FeatureType.SOLID, FeatureType.DASHED):
            continue
        s, lat, member = _station(zone, f.points, unit_tangents(f.points))
        inside = member & (s >= change.from_m) & (s <= change.to_m)
        if np.count_nonzero(inside) >= 2:
            out[i] = (inside, float(np.median(lat[inside])))
    return out


def _selected(zone: ChangeZone, gt: GroundTruth, change: RoadChange) -> dict[int, np.ndarray]:
    """Feature index -> (N,) in-zone mask of the markings a restripe / remove acts on."""
    cand = _zone_markings(zone, gt, change)
    if change.size is None:
        return {i: m for i, (m, _) in cand.items() if gt.features[i].type == FeatureType.DASHED}
    order = sorted(cand, key=lambda i: -cand[i][1])  # left first
    k = int(change.size) - 1
    if k >= len(order):
        raise GroundTruthError(f"road change {change.text()}: only {len(order)} markings in the zone")
    # One marking may be several features in a row (successive pieces): take all at its offset.
    lat_k = cand[order[k]][1]
    return {i: cand[i][0] for i in order if abs(cand[i][1] - lat_k) < 0.5}


def _markings_by_offset(zone: ChangeZone, gt: GroundTruth, change: RoadChange) -> list[tuple[float, list[int]]]:
    """The carriageway's markings in the zone grouped by lateral offset (0.5 m), rightmost first:
    (median offset [m, + = left], feature indices)."""
    cand = [(lat, i) for i, (_, lat) in _zone_markings(zone, gt, change).items()]
    groups: list[tuple[float, list[int]]] = []
    for offset, i in sorted(cand):
        if groups and abs(offset - groups[-1][0]) < 0.5:
            groups[-1][1].append(i)
        else:
            groups.append((offset, [i]))
    return groups


def _edge_moved(
    zone: ChangeZone, gt: GroundTruth, change: RoadChange, edge: list[int], right_m: float
) -> list[GTFeature]:
    """The features with those of ``edge`` shifted ``right_m`` to the right with the tapers."""
    moved = replace(change, kind="shift", size=right_m)
    return [replace(f, points=_shifted(zone, f.points, moved)) if i in edge else f for i, f in enumerate(gt.features)]


def _lane_changes(zone: ChangeZone, gt: GroundTruth, change: RoadChange) -> GroundTruth:
    groups = _markings_by_offset(zone, gt, change)
    if change.kind == "close":
        if len(groups) < 2:
            raise GroundTruthError(
                f"road change {change.text()}: fewer than two markings in the zone, no lane to close"
            )
        (lat_edge, edge), (lat_div, divider) = groups[0], groups[1]
        width = float(change.size) if change.size is not None else lat_div - lat_edge
        feats = _edge_moved(zone, gt, change, edge, -width)
        # The divider disappears along the zone.
        out: list[GTFeature] = []
        next_id = max((f.id for f in gt.features), default=0) + 1
        for i, f in enumerate(feats):
            if i not in divider:
                out.append(f)
                continue
            s, _, member = _station(zone, f.points, unit_tangents(f.points))
            gone = member & (s >= change.from_m) & (s <= change.to_m)
            pieces = [(a, b) for a, b, kept in _runs(~gone) if kept and b - a >= 2]
            for k, (a, b) in enumerate(pieces):
                out.append(GTFeature(f.id if k == 0 else next_id, f.type, f.points[a:b].copy()))
                next_id += int(k > 0)
        # The closed lane's centerline merges into its left neighbour.
        lanes = {}
        shift_left = replace(change, kind="shift", size=-width)
        for lid, ln in gt.lanes.items():
            s, lat, member = _station(zone, ln.centerline, unit_tangents(ln.centerline))
            inside = member & (s >= change.from_m) & (s <= change.to_m)
            closed = np.count_nonzero(inside) >= 2 and lat_edge < float(np.median(lat[inside])) < lat_div
            lanes[lid] = replace(ln, centerline=_shifted(zone, ln.centerline, shift_left)) if closed else ln
        return replace(gt, features=tuple(out), lanes=lanes)
    if not groups:
        raise GroundTruthError(f"road change {change.text()}: no marking in the zone to open the shoulder beside")
    lat_edge, edge = groups[0]
    size, room = float(change.size or 0.0), _open_room(zone, gt, change, edge)
    if size > room + 1e-9:
        raise GroundTruthError(
            f"road change {change.text()}: the edge marking would move {size:g} m, beyond the road border; "
            f"the shoulder there allows an opening of at most SIZE {room:.2f} m"
        )
    feats = _edge_moved(zone, gt, change, edge, size)
    keep = (zone.s >= change.from_m + change.taper_m) & (zone.s <= change.to_m - change.taper_m)
    piece = zone.line[keep]
    left = turn_left(unit_tangents(piece))
    new_id = max((f.id for f in gt.features), default=0) + 1
    line = GTFeature(new_id, FeatureType.DASHED, resample_evenly(piece + lat_edge * left, 1.0))
    width = float(change.size or 0.0)
    lanes = _opened_lane(zone, gt, change, resample_evenly(piece + (lat_edge - width / 2.0) * left, 1.0), lat_edge)
    return replace(gt, features=(*feats, line), lanes=lanes)


def _open_room(zone: ChangeZone, gt: GroundTruth, change: RoadChange, edge: list[int]) -> float:
    """The largest SIZE an ``open`` of the ``edge`` marking's features may have [m, floored to the
    cm]: where it moves (its shift weight w > 0), the moved edge stays on or inside the nearest road
    border right of it, at that station (lateral room / w); ``inf`` where no border runs beside it."""
    borders = []  # (station, lateral) of each road border's points on the carriageway, by station
    for f in gt.features:
        if f.type != FeatureType.ROAD_BORDER:
            continue
        s, lat, member = _station(zone, f.points, None)
        if np.count_nonzero(member) >= 2:
            order = np.argsort(s[member])
            borders.append((s[member][order], lat[member][order]))
    room = math.inf
    for i in edge:
        s, lat, w = _shift_weight(zone, gt.features[i].points, change)
        moved = w > 1e-3
        if not moved.any():
            continue
        s, lat, w = s[moved], lat[moved], w[moved]
        # the nearest border right of each point, at its station (-inf: none)
        beside = np.full(len(s), -np.inf)
        for bs, blat in borders:
            at = np.interp(s, bs, blat)
            k = np.clip(np.searchsorted(bs, s), 1, len(bs) - 1)
            near = (s >= bs[0]) & (s <= bs[-1]) & (bs[k] - bs[k - 1] <= 5.0)  # not across a gap
            right = near & (at < lat)
            beside = np.where(right, np.maximum(beside, at), beside)
        has = np.isfinite(beside)
        if has.any():
            room = min(room, float(np.min((lat[has] - beside[has]) / w[has])))
    return math.floor(room * 100.0 + 1e-3) / 100.0 if math.isfinite(room) else room


def _opened_lane(
    zone: ChangeZone, gt: GroundTruth, change: RoadChange, centerline: np.ndarray, lat_edge: float
) -> dict[str, GTLane]:
    """``gt``'s lanes with the opened lane: ``centerline`` (between the tapers, where the new
    divider is drawn), split off the rightmost lane beside it and merging back into it (that lane's
    pieces at its two ends get it as a successor / predecessor; it has that lane as its ``left``).
    The rightmost lane does not get it as its ``right``: the simulator's lane changes go to the
    ``left`` / ``right`` neighbours, and the drives after the change do not use the new lane."""
    lanes = dict(gt.lanes)
    if len(centerline) < 2:
        return lanes
    # the lane pieces of the carriageway right next to the old edge, per station
    pieces: list[tuple[float, float, str]] = []
    for lid, ln in gt.lanes.items():
        s, lat, member = _station(zone, ln.centerline, unit_tangents(ln.centerline))
        inside = member & (s >= change.from_m) & (s <= change.to_m) & (lat > lat_edge)
        if np.count_nonzero(inside) >= 2:
            pieces.append((float(np.median(lat[inside])), float(s[inside].min()), lid))
    if not pieces:
        return lanes
    nearest = min(p[0] for p in pieces)
    outer = [lid for lat, _, lid in pieces if lat - nearest < 1.0]

    def piece_at(station: float) -> str | None:
        best, best_d = None, math.inf
        for lid in outer:
            s, _, member = _station(zone, gt.lanes[lid].centerline, None)
            if not member.any():
                continue
            lo, hi = float(s[member].min()), float(s[member].max())
            d = 0.0 if lo <= station <= hi else min(abs(station - lo), abs(station - hi))
            if d < best_d:
                best, best_d = lid, d
        return best

    ids = set(lanes)
    new_id, k = "opened", 1
    while new_id in ids:
        k += 1
        new_id = f"opened{k}"
    a, b = change.from_m + change.taper_m, change.to_m - change.taper_m
    first, last, beside = piece_at(a), piece_at(b), piece_at(0.5 * (a + b))
    if first is not None:
        lanes[first] = replace(lanes[first], successors=(*lanes[first].successors, new_id))
    if last is not None:
        lanes[last] = replace(lanes[last], predecessors=(*lanes[last].predecessors, new_id))
    lanes[new_id] = GTLane(
        new_id,
        centerline,
        successors=() if last is None else (last,),
        predecessors=() if first is None else (first,),
        left=beside,
    )
    return lanes


def apply_change(gt: GroundTruth, change: RoadChange) -> GroundTruth:
    """``gt`` with ``change`` applied (a new object; ``gt`` is not modified). Feature ids stay where
    a feature is kept whole; a feature cut at the zone's ends keeps its id on its first piece and
    the others get new ids above every id of ``gt``.

    Raises:
        GroundTruthError: the route is unknown, the zone lies off it, or the selected marking
            does not exist.
    """
    zone = change_zone(gt, change)
    if change.kind == "shift":
        feats = tuple(
            f if f.type == FeatureType.ROAD_BORDER else replace(f, points=_shifted(zone, f.points, change))
            for f in gt.features
        )
        lanes = {lid: replace(ln, centerline=_shifted(zone, ln.centerline, change)) for lid, ln in gt.lanes.items()}
        return replace(gt, features=feats, lanes=lanes)
    if change.kind in ("close", "open"):
        return _lane_changes(zone, gt, change)
    next_id = max((f.id for f in gt.features), default=0) + 1
    out: list[GTFeature] = []
    if change.kind == "add":
        keep = (zone.s >= change.from_m) & (zone.s <= change.to_m)
        piece = zone.line[keep]
        left = turn_left(unit_tangents(piece))
        pts = resample_evenly(piece - float(change.size or 0.0) * left, 1.0)
        return replace(gt, features=(*gt.features, GTFeature(next_id, FeatureType.SOLID, pts)))
    chosen = _selected(zone, gt, change)
    for i, f in enumerate(gt.features):
        if i not in chosen:
            out.append(f)
            continue
        first = True
        for a, b, inside in _runs(chosen[i]):
            lo, hi = max(0, a - 1) if inside else a, min(len(f.points), b + 1) if inside else b
            if hi - lo < 2 or (inside and change.kind == "remove"):
                continue
            ftype = f.type
            if inside:
                ftype = FeatureType.SOLID if f.type == FeatureType.DASHED else FeatureType.DASHED
            fid = f.id if first else next_id
            if not first:
                next_id += 1
            first = False
            out.append(GTFeature(fid, ftype, f.points[lo:hi].copy()))
    return replace(gt, features=tuple(out))


def apply_changes(gt: GroundTruth, changes: Sequence[RoadChange]) -> GroundTruth:
    """``gt`` with every change applied in order."""
    for c in changes:
        gt = apply_change(gt, c)
    return gt


def changes_from_dict(doc: dict) -> tuple[list[RoadChange], list[ChangeZone]]:
    """The changes and their zones of an ``OUT.changes.json`` document (``hdmap simulate``).

    Raises:
        ConfigError: not such a document.
    """
    try:
        rows = list(doc["changes"])
        changes = [RoadChange.from_dict({k: v for k, v in r.items() if k != "zone"}) for r in rows]
        zones = [ChangeZone.from_dict(r["zone"]) for r in rows]
    except (KeyError, TypeError, ValueError) as err:
        raise ConfigError(f"not a road-changes document ({err!r})") from err
    return changes, zones


def road_as_of(gt_before: GroundTruth, changes: Sequence[RoadChange], time_ns: int) -> GroundTruth:
    """The road as of ``time_ns``: ``gt_before`` with the changes made by then (``time_ns`` of
    each change, in time order)."""
    return apply_changes(gt_before, sorted((c for c in changes if c.time_ns <= time_ns), key=lambda c: c.time_ns))
