"""Lanes derived from the map's feature graph.

Cross sections: every topology node (one sampling step, 2 m apart) is a cut line through the road
midpoint, perpendicular to its heading, as wide as the road plus a margin. The map features that
cross it in its direction, sorted from left to right, are the boundaries of that cross section.

RULE 1 (lane): two adjacent boundaries bound a lane when their median distance over a section
lies in [LANE_WIDTH_MIN_M, LANE_WIDTH_MAX_M].
RULE 2 (shoulder): a strip between a solid marking and a road border is a shoulder, not a lane.
RULE 6 (tracks): a line crossing consecutive cross sections of a topology chain within
_TRACK_TOL_M sideways, of the same kind (dashed, or not: solid and road border are one kind), is
one boundary (also across a change of feature id,
and across up to _TRACK_GAP cross sections without it: the gap is interpolated).
RULE 7 (relevant lines): only lines next to a plausible lane take part (an outer border beyond a
shoulder, or a line of a road beside, never cuts a lane).
RULE 9 (missing marking): a strip between two markings n >= 2 lanes wide gets n - 1 inferred
dashed lines (``Boundary.inferred``).
RULE 15 (tapers): a lane gained in a taper (the edge line moves out over a ramp, then a divider
starts) is born narrow beside the through lane and widens, and a lane dropped narrows beside it
(Lanelet2, OpenDRIVE): a marking that starts (ends) between two lines bounding a lane on each side,
where the strip just before (after) it is wider than one lane (LANE_WIDTH_MAX_M) and narrows to one
lane within _TAPER_MAX_M, is continued back (on) as an inferred dashed line at its distance from
the side that runs on (the one whose distance to its own outer line stays, median over the
strip; alike: the one beside the wider lane), until the widening lane is narrower than
_DUPLICATE_M; RULE 9's lines give way to it there (a marking RULE 9's line runs into, a strip of
two lanes' width, is left to RULE 9). The through lane keeps its width; the narrow strip beside
it is a lane only where RULE 1 finds one (its median width); the lane gained starts where the
divider does, beside the through lane (RULE 4): a split or merge across the dashed line.
RULE 16 (reach): a cut line reaches at least as far as the shorter of the farthest reaches of its
chain's stations up to _REACH_STATIONS before and after it: where the map's road width dips for a
few stations the lines there are still crossed.
RULE 10 (hand-over): along a chain, a boundary that ends is continued by one of any kind starting
within _HANDOVER_M of it at the next cross section (the map hands a line over from one feature to
an overlapping one, or flickers between dashed and solid); a boundary is cut where its kind changes
for at least _KIND_MIN cross sections. Lanes are cut only where the lane structure changes.
RULE 11 (groups): a cross section falls apart into groups of boundaries where no lane can lie
between two neighbours (wider than a lane, a shoulder, or two road borders closer than
_BARRIER_M: a ramp beside the carriageway); each group is a station of its own, linked to the
groups of the next station that overlap it sideways, so that a line starting or ending in one
group (a ramp beside) does not cut the lanes of another.
RULE 12 (two-way roads): left of all the lines crossing a cut in its direction, the nearest line
crossing against it counts as a boundary when it is a marking inside the road within a lane's
width: the centre line of a two-way road, mapped in one direction only, bounds the lane beside
it in the other.

Sections are runs of consecutive cross sections with the same boundaries; a run is cut into lanes
at most LANELET_MAX_M long. Where two runs meet (a line starting or ending, a split or merge of
the topology) the boundaries are joined node by node, so that a lane's successors are the lanes
whose boundaries start where its own end (Lanelet2's rule):

RULE 3 (continuation): a boundary continues the boundary of the preceding run of the same track,
of the same or a linked feature (predecessor / successor), or the nearest one within JOIN_TOL_M.
RULE 4 (lane gain, drop, gore): a boundary that starts (ends) without a preceding (following) one
starts (ends) at the node of the nearest boundary that does continue: the new lane opens from a
point beside a through lane (reached by a lane change across a dashed line, or as a split) and a
dropped lane closes onto its neighbour (a merge). RULE 4b (markings stop): where two or more
lines whose map features end at the cut (within _STOP_M) would end at the same continuing line
on the same side, the lanes between them stop (a junction where the markings stop, not one
dropped lane): they end where their lines end, a lane wide, so that the drives' connectors
(``lanes.connectors``) start where the drives leave them.
RULE 13 (far joints): two runs are not joined where a boundary's joint lies more than
_JOINT_MAX_M from its own crossing (the cut lines of a turn reach across the lines of another
road: the nearest of those is no continuation).
RULE 5 (topology gaps): a topology chain that ends (starts) is linked to the nearest cross section
of the same direction within GAP_LINK_M ahead (behind).
RULE 8 (junctions without markings): a lane without successor is joined by a connector lane with
virtual sides to a lane that starts in its line within BRIDGE_MAX_M; where none starts straight
ahead (a curve), to one that starts along the topology within BRIDGE_MAX_M at the same offsets
from the road middle, the connector a cubic Hermite curve between the two lanes' directions;
where no lane lies at those offsets (a turn into a road of another width), to the one starting
along the topology whose middle is within BRIDGE_TURN_M of the dead end's offset. A lane end that
a gore closes (narrow at its very end, wide within its last _END_POINTS points) is joined only
to a lane starting within _GORE_BRIDGE_M.
RULE 14 (degenerate pieces): no lane (connectors included) whose side runs from a node to the
same node, or whose sides' middles do not lie on their own side of the other side: Lanelet2
turns such a lanelet round on loading, and its routing then disagrees with the lane graph.

Ids are stable: hashes of the topology node id where a piece starts, the feature ids and the
boundary's slot in the cross section.
"""

from __future__ import annotations

import hashlib
from bisect import bisect_left, bisect_right
from collections import Counter, defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from hdmap_core.evaluation.cuts import CutPoints, Cuts, points_on_cuts
from hdmap_core.lanes.model import Boundary, Lane, LaneMap
from hdmap_core.model import FeatureType, HDMap, MapFeature

__all__ = [
    "derive_lanes",
    "LANE_WIDTH_MIN_M",
    "LANE_WIDTH_MAX_M",
    "LANELET_MAX_M",
    "JOIN_TOL_M",
    "GAP_LINK_M",
    "BRIDGE_MAX_M",
    "proper_sides",
]

LANE_WIDTH_MIN_M = 2.4  # narrowest lane (3.5-3.9 m motorway lanes, 2.75 m in works zones)
LANE_WIDTH_MAX_M = 5.5  # wider: two lanes with a missing marking, or a taper
LANELET_MAX_M = 300.0  # longest lane piece where nothing changes
JOIN_TOL_M = 1.0  # a boundary continues a boundary this close at the joint
_STOP_M = 3.0  # RULE 4b: a line stops at a cut when its feature ends this close to the crossing
GAP_LINK_M = 15.0  # topology chain ends linked across gaps up to this distance
BRIDGE_MAX_M = 60.0  # RULE 8: longest connector across a junction without markings
BRIDGE_LATERAL_M = 1.0  # RULE 8: sideways offset of the lane ahead
BRIDGE_TURN_M = 4.0  # RULE 8 turns: offset of the lane ahead where none lies in line
_SIDE_EPS_M = 0.05  # RULE 14: a side's middle lies this far off the other side at least
_GORE_BRIDGE_M = 15.0  # RULE 8: longest connector from a lane end that a gore closes
_END_POINTS = 5  # RULE 8: a lane end is wide enough when any of its last (first) points is (a gore closes it)
BRIDGE_ANGLE_DEG = 20.0  # RULE 8: heading difference of the lane ahead
_CUT_MARGIN_M = 3.0  # cut lines reach this far beyond the estimated road width
_COS_SAME_DIRECTION = 0.7  # features crossing a cut within ~45 deg of its direction
_COS_LINK = np.cos(np.radians(35.0))  # heading agreement of a gap link
_WIDTH_SLACK_M = 0.5  # RULE 7: tolerance of the lane width test per cross section
_SPLIT_WIDTH_M = (3.0, 4.2)  # RULE 9: width of each lane of a strip split by inferred lines
_DUPLICATE_M = 0.5
_BARRIER_M = 3.0  # RULE 11: two road borders closer than this are a barrier between roads, not a lane
_GROUP_OVERLAP_M = 0.0  # RULE 11: groups of consecutive stations that overlap sideways are linked
# RULE 6: the line kinds a track keeps: dashed (crossable) or not; a line the map calls solid in
# one place and road border in the next is one line (its pieces take the most common type)
_KIND = {
    int(FeatureType.DASHED): 0,
    int(FeatureType.SOLID): 1,
    int(FeatureType.ROAD_BORDER): 1,
    int(FeatureType.UNKNOWN): 2,
}  # crossings this close on one cut are one line
_TRACK_TOL_M = 0.5  # sideways shift of one line between two stations of a chain (2 m apart)
_TRACK_GAP = 5  # stations a line may be missing (10 m) and still continue
_HANDOVER_M = 1.0  # RULE 10: a boundary that ends continues one starting this close at the next station
_JOINT_MAX_M = 15.0  # RULE 13: farthest joint of a boundary (the fans reached 40 m; 6 m lost 5 of 15 routes)
_REACH_STATIONS = 15  # RULE 16: stations (30 m) each way whose cut reach a cut line takes
_TAPER_MAX_M = 250.0  # RULE 15: longest continuation of a divider through a taper
_KIND_MIN = 10  # RULE 10: stations (20 m): a shorter stretch of another kind along a boundary is noise


def derive_lanes(hdmap: HDMap) -> LaneMap:
    """The lanes of ``hdmap`` (module docstring): lane pieces, shared boundaries and end nodes.

    A map without topology nodes or features has no lanes (an empty ``LaneMap``).
    """
    st = _Stations.of(hdmap)
    if len(st) == 0 or not hdmap.features:
        return LaneMap((), (), {})
    _bridge_gaps(st)
    sections = _cross_sections(st, hdmap)
    st, sections = _groups(st, sections, [int(f.type) for f in hdmap.features] + [int(FeatureType.DASHED)])
    runs = _runs(st, sections)
    return _build(st, sections, runs, hdmap)


# --------------------------------------------------------------------------------------------
# Stations (cross sections) and their boundaries


@dataclass
class _Stations:
    ids: np.ndarray  # (K,) topology node ids
    pos: np.ndarray  # (K, 2)
    tangent: np.ndarray  # (K, 2)
    width: np.ndarray  # (K,)
    succ: list[list[int]]
    pred: list[list[int]] = field(default_factory=list)

    @classmethod
    def of(cls, hdmap: HDMap) -> _Stations:
        nodes = sorted(hdmap.topology, key=lambda t: t.id)
        index = {int(t.id): i for i, t in enumerate(nodes)}
        k = len(nodes)
        pos = np.array([np.asarray(t.position, dtype=float)[:2] for t in nodes]).reshape(k, 2)
        yaw = np.array([float(t.heading) for t in nodes])
        tangent = np.stack([np.cos(yaw), np.sin(yaw)], axis=1).reshape(k, 2)
        width = np.array([float(t.width) for t in nodes])
        succ = [[index[int(s)] for s in t.successors if int(s) in index] for t in nodes]
        st = cls(np.array([int(t.id) for t in nodes], dtype=np.int64), pos, tangent, width, succ)
        st.relink()
        return st

    def relink(self) -> None:
        self.pred = [[] for _ in range(len(self.ids))]
        for a, ss in enumerate(self.succ):
            for b in ss:
                self.pred[b].append(a)

    def __len__(self) -> int:
        return len(self.ids)


def _bridge_gaps(st: _Stations) -> None:
    """RULE 5: chain ends linked to the nearest station ahead, chain starts to the one behind."""
    ends = [i for i in range(len(st)) if not st.succ[i]]
    starts = [i for i in range(len(st)) if not st.pred[i]]
    for i in ends:
        j = _nearest_along(st, i, ahead=True)
        if j is not None and j not in st.succ[i]:
            st.succ[i].append(j)
    for j in starts:
        back = _nearest_along(st, j, ahead=False)
        if back is not None and j not in st.succ[back]:
            st.succ[back].append(j)
    st.relink()


def _nearest_along(st: _Stations, i: int, *, ahead: bool) -> int | None:
    d = st.pos - st.pos[i]
    along = d @ st.tangent[i] * (1.0 if ahead else -1.0)
    dist = np.hypot(d[:, 0], d[:, 1])
    same = st.tangent @ st.tangent[i] >= _COS_LINK
    ok = same & (along > 0.5) & (dist <= GAP_LINK_M)
    ok[i] = False
    # not a station of the own chain close by (the chain itself continues there)
    for n in st.succ[i] + st.pred[i]:
        ok[n] = False
    if not ok.any():
        return None
    cand = np.flatnonzero(ok)
    return int(cand[np.argmin(dist[cand])])


@dataclass(frozen=True)
class _Section:
    features: tuple[int, ...]  # track ids, left to right (the run key)
    labels: tuple[int, ...]  # feature index of each boundary
    s: np.ndarray  # (B,) lateral position on the cut, + = left [m]
    xy: np.ndarray  # (B, 2) crossing points [m]


def _cross_sections(st: _Stations, hdmap: HDMap) -> list[_Section]:
    """Per station the boundaries crossing it, left to right, each labelled with a track: the
    same line seen at consecutive stations (RULE 6), also across a change of feature id.
    (Per station a handful of lines: plain Python floats are faster here than numpy.)"""
    normal = np.stack([-st.tangent[:, 1], st.tangent[:, 0]], axis=1)
    chains = _chains(st)
    half = _reach(chains, st.width / 2.0 + _CUT_MARGIN_M)
    cuts = Cuts(st.pos, st.tangent, normal, -half, half, np.zeros(len(st)))
    polylines = [np.asarray(f.points, dtype=float) for f in hdmap.features]
    length = [float(np.hypot(*np.diff(p, axis=0).T).sum()) for p in polylines]
    cp = points_on_cuts(cuts, polylines, cos_min=_COS_SAME_DIRECTION)
    cut, owner, s = _with_centre_lines(cp, cuts, polylines, [f.type for f in hdmap.features], half - _CUT_MARGIN_M)
    order = np.lexsort((-s, cut))
    cut, owner, s = cut[order], owner[order], s[order]
    xy = st.pos[cut] + s[:, None] * normal[cut]
    bounds = np.searchsorted(cut, np.arange(len(st) + 1)).tolist()
    rows = list(zip(owner.tolist(), s.tolist(), xy[:, 0].tolist(), xy[:, 1].tolist(), strict=True))
    virtual = len(hdmap.features)  # index of the inferred lines (RULE 9)
    # an inferred line continues a mapped dashed line (a separate type cuts the lanes into pieces
    # wherever the split flickers); a piece is inferred where most of it is
    types = [int(f.type) for f in hdmap.features] + [int(FeatureType.DASHED)]
    length.append(0.0)
    pos, nrm = st.pos.tolist(), normal.tolist()
    raw = [
        _split_wide(_dedupe(rows[bounds[k] : bounds[k + 1]], length), types, virtual, pos[k], nrm[k])
        for k in range(len(st))
    ]
    tracks = _track(st, raw, types, nrm)
    tracks, continued = _tapers(st, chains, tracks, types, virtual, pos, nrm)
    size: dict[int, int] = defaultdict(int)  # track -> stations
    for row in tracks:
        for t, *_ in row:
            size[t] += 1
    out: list[_Section] = []
    for k in range(len(st)):
        (px, py), (nx, ny) = pos[k], nrm[k]
        items = sorted(((x - px) * nx + (y - py) * ny, t, f, x, y) for t, f, x, y in tracks[k])
        items.reverse()  # left to right
        # a line tracked across a gap beside one crossing there (one line mapped twice): the
        # longer track stays
        kept: list[tuple] = []
        for it in items:
            if kept and kept[-1][0] - it[0] < _DUPLICATE_M:
                if (size[it[1]], it[1]) > (size[kept[-1][1]], kept[-1][1]):
                    kept[-1] = it
                continue
            kept.append(it)
        items = kept
        items = [it for it, keep in zip(items, _bounding(items, types, continued), strict=True) if keep]
        out.append(
            _Section(
                tuple(it[1] for it in items),
                tuple(it[2] for it in items),
                np.array([it[0] for it in items], dtype=float),
                np.array([(it[3], it[4]) for it in items], dtype=float).reshape(-1, 2),
            )
        )
    return _handover(st, out, types, continued)


def _reach(chains: list[list[int]], half: np.ndarray) -> np.ndarray:
    """RULE 16 (reach): a cut line reaches to each side at least as far as the shorter of the
    farthest reaches of its chain's stations within _REACH_STATIONS before it and after it: where
    the map's road width dips for a few stations (in a taper, where the lines move apart) no line
    is cut off; a road that narrows for good (a ramp parted, a lane dropped) keeps its cuts.
    Returns the (K,) half lengths [m]."""
    before, after = half.copy(), half.copy()
    for chain in chains:
        c = np.asarray(chain)
        for d in range(1, min(_REACH_STATIONS, len(c) - 1) + 1):
            before[c[d:]] = np.maximum(before[c[d:]], half[c[:-d]])
            after[c[:-d]] = np.maximum(after[c[:-d]], half[c[d:]])
    return np.maximum(half, np.minimum(before, after))


def _with_centre_lines(
    cp: CutPoints, cuts: Cuts, polylines: list[np.ndarray], types: list[FeatureType], half_road: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RULE 12 (two-way roads): per cut, the crossings of its direction ``(cut, owner, s)`` and,
    left of all of them, the nearest crossing against its direction if that is a marking (not a
    road border) inside the road (``|s| <= half_road``) within a lane's width of the leftmost own
    crossing: the centre line of a two-way road, mapped in the other direction only, bounds the
    lane beside it on the left."""
    back = points_on_cuts(cuts, [p[::-1] for p in polylines], cos_min=_COS_SAME_DIRECTION)
    if not len(back.cut):
        return cp.cut, cp.owner, cp.s
    k = len(cuts.center)
    left = np.full(k, -np.inf)  # leftmost own crossing per cut
    np.maximum.at(left, cp.cut, cp.s)
    ahead = (back.s > left[back.cut]) & np.isfinite(left[back.cut])
    c, o, sb = back.cut[ahead], back.owner[ahead], back.s[ahead]
    order = np.lexsort((sb, c))
    c, o, sb = c[order], o[order], sb[order]
    first = np.flatnonzero(np.r_[True, c[1:] != c[:-1]]) if len(c) else np.zeros(0, dtype=np.int64)
    c, o, sb = c[first], o[first], sb[first]
    marking = np.array([types[i] in (FeatureType.SOLID, FeatureType.DASHED) for i in o.tolist()], dtype=bool)
    gap = sb - left[c]
    ok = marking & (np.abs(sb) <= half_road[c]) & (gap >= LANE_WIDTH_MIN_M - _WIDTH_SLACK_M)
    ok &= gap <= LANE_WIDTH_MAX_M + _WIDTH_SLACK_M
    return np.r_[cp.cut, c[ok]], np.r_[cp.owner, o[ok]], np.r_[cp.s, sb[ok]]


def _groups(st: _Stations, sections: list[_Section], types: list[int]) -> tuple[_Stations, list[_Section]]:
    """RULE 11: stations split into groups of boundaries; returns the stations of the groups
    (the first group keeps the station's id) and their sections."""
    border, shoulder = int(FeatureType.ROAD_BORDER), {int(FeatureType.ROAD_BORDER), int(FeatureType.SOLID)}
    wide = LANE_WIDTH_MAX_M + _WIDTH_SLACK_M
    first: list[int] = []  # station -> index of its first group
    ids: list[int] = []
    origin: list[int] = []
    out: list[_Section] = []
    span: list[tuple[float, float] | None] = []  # group -> (right, left) s on its station
    for k, sec in enumerate(sections):
        first.append(len(out))
        n = len(sec.features)
        s = sec.s.tolist()
        cuts = [0]
        for i in range(n - 1):
            ta, tb = types[sec.labels[i]], types[sec.labels[i + 1]]
            w = s[i] - s[i + 1]
            if w > wide or {ta, tb} == shoulder or (ta == tb == border and w < _BARRIER_M):
                cuts.append(i + 1)
        cuts.append(n)
        parts = list(zip(cuts[:-1], cuts[1:], strict=True))
        if len(parts) > 1:  # a lone line beside a group bounds no lane
            parts = [p for p in parts if p[1] - p[0] > 1] or parts[:1]
        for g, (lo, hi) in enumerate(parts):
            ids.append(int(st.ids[k]) if g == 0 else _uid("group", int(st.ids[k]), g))
            origin.append(k)
            if hi - lo == n:
                out.append(sec)
            else:
                out.append(_Section(sec.features[lo:hi], sec.labels[lo:hi], sec.s[lo:hi], sec.xy[lo:hi]))
            span.append((s[hi - 1], s[lo]) if n else None)
    first.append(len(out))
    if len(out) == len(sections):
        return st, sections
    o = np.asarray(origin)
    succ: list[list[int]] = [[] for _ in out]
    normal = np.stack([-st.tangent[:, 1], st.tangent[:, 0]], axis=1)
    for k in range(len(st)):
        mine = range(first[k], first[k + 1])
        for k2 in st.succ[k]:
            theirs = range(first[k2], first[k2 + 1])
            if len(mine) == 1 and len(theirs) == 1:
                succ[mine[0]].append(theirs[0])
                continue
            links = set()
            for v2 in theirs:
                xy = out[v2].xy
                rng = None
                if len(xy):
                    proj = (xy - st.pos[k]) @ normal[k]
                    rng = (float(proj.min()), float(proj.max()))
                for v in mine:
                    a = span[v]
                    if a is None or rng is None or max(a[0], rng[0]) <= min(a[1], rng[1]) + _GROUP_OVERLAP_M:
                        links.add((v, v2))
            for v in mine:  # a group without any overlapping group ahead keeps all links
                if not any(x == v for x, _ in links):
                    links.update((v, v2) for v2 in theirs)
            for v2 in theirs:
                if not any(y == v2 for _, y in links):
                    links.update((v, v2) for v in mine)
            for v, v2 in sorted(links):
                succ[v].append(v2)
    st2 = _Stations(np.array(ids, dtype=np.int64), st.pos[o], st.tangent[o], st.width[o], succ)
    st2.relink()
    return st2, out


def _chains(st: _Stations) -> list[list[int]]:
    """Maximal chains of stations joined by single links (a station with one successor that has
    one predecessor), in order; every station in exactly one chain."""

    def single(k: int) -> int | None:
        if len(st.succ[k]) == 1 and len(st.pred[st.succ[k][0]]) == 1:
            return st.succ[k][0]
        return None

    return _walks(st, single)


def _walks(st: _Stations, follow: Callable[[int], int | None]) -> list[list[int]]:
    """Maximal chains of stations along ``follow`` (a station's one next station, or None), in
    order: first from every station no other one follows to, then the closed loops; every station
    in exactly one chain."""
    starts = [k for k in range(len(st)) if not (len(st.pred[k]) == 1 and follow(st.pred[k][0]) == k)]
    done = [False] * len(st)
    chains = []
    for k0 in starts + list(range(len(st))):
        if done[k0]:
            continue
        chain = [k0]
        done[k0] = True
        nxt = follow(k0)
        while nxt is not None and not done[nxt]:
            chain.append(nxt)
            done[nxt] = True
            nxt = follow(nxt)
        chains.append(chain)
    return chains


def _handover(
    st: _Stations, sections: list[_Section], types: list[int], continued: frozenset[int] = frozenset()
) -> list[_Section]:
    """RULE 10: relabel the boundaries (tracks) of ``sections`` along each chain so that a
    boundary handed over to another line keeps its track, and a track whose kind changes for
    _KIND_MIN stations or more gets a new one there. A divider continued through a taper
    (RULE 15, the tracks ``continued``) is no hand-over: it stays a boundary of its own."""
    orig = [sec.features for sec in sections]
    feats = [list(f) for f in orig]
    next_track = 1 + max((t for f in orig for t in f), default=0)
    for chain in _chains(st):
        alias: dict[int, int] = {}  # original track -> track
        for i, k in enumerate(chain):
            row = [alias.get(t, t) for t in orig[k]]
            for n, t in enumerate(orig[k]):  # a line handed over that comes back beside its heir
                if t not in alias and row.count(t) > 1:
                    alias[t] = next_track
                    row[n] = next_track
                    next_track += 1
            taken_ids: set[int] = set()
            for n, t in enumerate(row):  # two lines handed over to one heir: the later one apart
                if t in taken_ids:
                    alias[orig[k][n]] = next_track
                    row[n] = next_track
                    next_track += 1
                taken_ids.add(row[n])
            if i > 0 and not set(row).issubset(feats[chain[i - 1]]):
                prev = chain[i - 1]
                pf, ps, s = feats[prev], sections[prev].s, sections[k].s
                gone = [(float(ps[n]), t) for n, t in enumerate(pf) if t not in row and t not in continued]
                pairs = sorted(
                    (abs(float(s[n]) - s0), n, t0)
                    for n, t in enumerate(row)
                    if t not in pf and t not in continued
                    for s0, t0 in gone
                    if abs(float(s[n]) - s0) <= _HANDOVER_M
                )
                taken: set[int] = set()
                for _, n, t0 in pairs:
                    if n in taken or t0 in row:
                        continue
                    taken.add(n)
                    alias[orig[k][n]] = t0
                    row[n] = t0
            feats[k] = row
        # kind stretches along each track of the chain
        seen: dict[int, list[tuple[int, int, int]]] = defaultdict(list)  # track -> (station, slot, kind)
        for k in chain:
            for n, t in enumerate(feats[k]):
                seen[t].append((k, n, _KIND[types[sections[k].labels[n]]]))
        for t, items in seen.items():
            kinds = [kd for _, _, kd in items]
            if len(set(kinds)) < 2:
                continue
            spans: list[list[int]] = []  # [kind, first, end)
            for n, kd in enumerate(kinds):
                if spans and spans[-1][0] == kd:
                    spans[-1][2] = n + 1
                else:
                    spans.append([kd, n, n + 1])
            long_ = [sp for sp in spans if sp[2] - sp[1] >= _KIND_MIN]
            cuts = [b[1] for a, b in zip(long_, long_[1:], strict=False) if a[0] != b[0]]
            new_id = t
            for n, (k, slot, _) in enumerate(items):
                if cuts and n >= cuts[0]:
                    cuts.pop(0)
                    new_id = next_track
                    next_track += 1
                feats[k][slot] = new_id
    return [
        _Section(tuple(f), sec.labels, sec.s, sec.xy) if tuple(f) != sec.features else sec
        for f, sec in zip(feats, sections, strict=True)
    ]


def _bounding(items: list[tuple], types: list[int], continued: frozenset[int] = frozenset()) -> list[bool]:
    """RULE 7: the boundaries (``(s, track, feature, x, y)``, left to right) next to a plausible
    lane (RULES 1, 2, with _WIDTH_SLACK_M); others (outer borders beyond shoulders, lines of a road
    beside) are left out so that they never cut a lane. A divider continued through a taper
    (RULE 15, the tracks ``continued``) and the line beside it bound the lane widening there."""
    keep = [False] * len(items)
    lo, hi = LANE_WIDTH_MIN_M - _WIDTH_SLACK_M, LANE_WIDTH_MAX_M + _WIDTH_SLACK_M
    shoulder = {int(FeatureType.ROAD_BORDER), int(FeatureType.SOLID)}
    for i in range(len(items) - 1):
        a, b = items[i], items[i + 1]
        taper = a[1] in continued or b[1] in continued
        if (taper or lo <= a[0] - b[0] <= hi) and {types[a[2]], types[b[2]]} != shoulder:
            keep[i] = keep[i + 1] = True
    return keep


def _split_wide(
    items: list[tuple[int, float, float]], types: list[int], virtual: int, pos: list[float], normal: list[float]
) -> list[tuple[int, float, float]]:
    """RULE 9 (missing marking): a strip between two markings that is n >= 2 lanes wide (each
    _SPLIT_WIDTH_M) gets n - 1 inferred dashed lines at equal spacing (feature ``virtual``)."""
    out: list[tuple[int, float, float]] = []
    border = int(FeatureType.ROAD_BORDER)
    for i, it in enumerate(items):
        out.append(it)
        if i + 1 == len(items):
            break
        nxt = items[i + 1]
        if border in (types[it[0]], types[nxt[0]]):
            continue
        gap = (it[1] - nxt[1]) * normal[0] + (it[2] - nxt[2]) * normal[1]
        n = round(gap / _SPLIT_WIDTH_M[1] + 0.5)  # the fewest lanes not wider than the widest
        if n < 2 or not _SPLIT_WIDTH_M[0] <= gap / n <= _SPLIT_WIDTH_M[1]:
            continue
        for j in range(1, n):
            w = j / n
            out.append((virtual, it[1] + w * (nxt[1] - it[1]), it[2] + w * (nxt[2] - it[2])))
    return out


def _dedupe(items: list[tuple[int, float, float, float]], length: list[float]) -> list[tuple[int, float, float]]:
    """Crossings ``(feature, s, x, y)`` (left to right) closer than _DUPLICATE_M are one line
    (overlapping pieces): the longer feature stays. Returns ``(feature, x, y)``."""
    out: list[tuple[int, float, float, float]] = []
    for it in items:
        if out and out[-1][1] - it[1] < _DUPLICATE_M:
            if length[it[0]] > length[out[-1][0]]:
                out[-1] = it
            continue
        out.append(it)
    return [(f, x, y) for f, _, x, y in out]


def _track(
    st: _Stations, raw: list[list[tuple[int, float, float]]], types: list[int], normal: list[list[float]]
) -> list[list[tuple[int, int, float, float]]]:
    """RULE 6: a crossing continues the line of the previous stations of its chain that crossed
    within _TRACK_TOL_M of it (sideways, in the map frame) with the same type, also after up to
    _TRACK_GAP stations without a crossing (the gap is filled by interpolation). Returns per
    station (track, feature, x, y)."""
    out: list[list[tuple[int, int, float, float]]] = [[] for _ in range(len(st))]
    next_track = 0
    for chain in _chains(st):
        open_: dict[int, tuple[int, int, float, float]] = {}  # track -> (position in chain, feature, x, y)
        for i, k in enumerate(chain):
            nx, ny = normal[k]
            # the open tracks' last points across this cut, sorted: candidates by bisection
            across = sorted((ox * nx + oy * ny, t) for t, (_, _, ox, oy) in open_.items())
            keys = [a for a, _ in across]
            cands = []
            for j, (f, x, y) in enumerate(raw[k]):
                s = x * nx + y * ny
                for a, t in across[bisect_left(keys, s - _TRACK_TOL_M) : bisect_right(keys, s + _TRACK_TOL_M)]:
                    if _KIND[types[f]] == _KIND[types[open_[t][1]]]:
                        cands.append((abs(s - a), t, j))
            cands.sort()
            taken_t: set[int] = set()
            taken_j: set[int] = set()
            for d, t, j in cands:
                if d > _TRACK_TOL_M:
                    break
                if t in taken_t or j in taken_j:
                    continue
                taken_t.add(t)
                taken_j.add(j)
                f, x, y = raw[k][j]
                oi, of, ox, oy = open_[t]
                for g in range(oi + 1, i):  # fill the gap
                    w = (g - oi) / (i - oi)
                    out[chain[g]].append((t, of, ox + w * (x - ox), oy + w * (y - oy)))
                out[k].append((t, f, x, y))
                open_[t] = (i, f, x, y)
            for j, (f, x, y) in enumerate(raw[k]):
                if j not in taken_j:
                    out[k].append((next_track, f, x, y))
                    open_[next_track] = (i, f, x, y)
                    next_track += 1
            open_ = {t: v for t, v in open_.items() if i - v[0] <= _TRACK_GAP}
    return out


# --------------------------------------------------------------------------------------------
# RULE 15: dividers continued through tapers

_Row = dict[int, tuple[float, int]]  # a station's crossings: track -> (s along its normal [m], feature)
_Walk = list[tuple[int, float, float]]  # along a strip: (station, s of its left line, s of its right line)
_MARKINGS = frozenset({int(FeatureType.DASHED), int(FeatureType.SOLID)})  # what RULE 15 continues


@dataclass(frozen=True)
class _Divider:
    """A marking that starts (ends) at a station between two lines, a lane away on each side."""

    left_m: float  # s of the line left of it [m]
    right_m: float  # s of the line right of it [m]
    lane_left_m: float  # width of the lane left of it [m]
    lane_right_m: float  # width of the lane right of it [m]


class _Crossings:
    """The tracks at every station while RULE 15 adds its lines: ``lines[k]`` are station k's
    ``(track, feature, x, y)``; ``row(k)`` gives them as offsets along its cut, computed when first
    asked and again after ``infer`` changed the station (the walks read the same stations many
    times)."""

    def __init__(
        self, tracks: list[list[tuple[int, int, float, float]]], pos: list[list[float]], normal: list[list[float]]
    ) -> None:
        self.lines = [list(row) for row in tracks]
        self.pos, self.normal = pos, normal
        self._rows: dict[int, _Row] = {}

    def row(self, k: int) -> _Row:
        if k not in self._rows:
            (px, py), (nx, ny) = self.pos[k], self.normal[k]
            self._rows[k] = {t: ((x - px) * nx + (y - py) * ny, f) for t, f, x, y in self.lines[k]}
        return self._rows[k]

    def infer(self, k: int, track: int, virtual: int, s_m: float, left_m: float, right_m: float) -> None:
        """An inferred line ``track`` at ``s_m`` on station k, in place of the inferred lines
        (RULE 9's) strictly between ``right_m`` and ``left_m``."""
        (px, py), (nx, ny) = self.pos[k], self.normal[k]
        row = self.row(k)
        self.lines[k] = [it for it in self.lines[k] if not (it[1] == virtual and right_m < row[it[0]][0] < left_m)]
        self.lines[k].append((track, virtual, px + s_m * nx, py + s_m * ny))
        self._rows.pop(k, None)


def _tapers(
    st: _Stations,
    chains: list[list[int]],
    tracks: list[list[tuple[int, int, float, float]]],
    types: list[int],
    virtual: int,
    pos: list[list[float]],
    normal: list[list[float]],
) -> tuple[list[list[tuple[int, int, float, float]]], frozenset[int]]:
    """RULE 15 (tapers): a marking that starts (ends) between two lines of a chain, bounding a
    lane on each side, where the strip between those lines just before (after) it is wider than
    one lane, is continued back (on) through the strip as an inferred line (feature ``virtual``,
    a track of its own, replacing RULE 9's lines there) at its distance from the neighbour line
    that runs on beside it, as far as the strip holds the widening lane (at least _DUPLICATE_M
    wide) and at most _TAPER_MAX_M: a lane born in a taper starts narrow beside the through lane
    and widens (Lanelet2, OpenDRIVE), and the through lane keeps its width. The side held: the
    neighbour whose distance to its own outer neighbour changes least along the strip (median;
    the other one moves); alike, the one beside the wider lane. Returns the tracks and the ids of the continued ones.

    Chains are walked forward for the markings that start (each continued back through the
    stations already passed), then backward for those that end; the lines placed by one walk are
    seen by the later ones (``_Crossings``)."""
    crossings = _Crossings(tracks, pos, normal)
    ids = [{t for t, *_ in row} for row in tracks]  # the tracks of each station, before any is continued
    next_track = 1 + max((t for row in tracks for t, *_ in row), default=-1)
    continued: set[int] = set()
    for chain in chains:
        for stations, along in _both_ways(st, chain):  # starts (walking back), then ends (walking on)
            for n in range(1, len(stations)):
                k, prev = stations[n], stations[n - 1]
                if ids[k] <= ids[prev]:
                    continue  # no line starts here
                row = crossings.row(k)
                for divider in _new_dividers(row, ids[prev], types, virtual):
                    walk = _strip_behind(crossings, stations, along, n, divider, virtual)
                    # RULE 15: only a strip wider than one lane just behind the divider that
                    # narrows to one lane is a taper (two lanes' width all along: RULE 9's)
                    if not _is_taper(walk):
                        continue
                    hold_left = _held_side(crossings, row, divider, walk, virtual)
                    track = next_track
                    next_track += 1
                    if _continue_divider(crossings, walk, divider, track, virtual, hold_left=hold_left):
                        continued.add(track)
    return crossings.lines, frozenset(continued)


def _both_ways(st: _Stations, chain: list[int]) -> list[tuple[list[int], np.ndarray]]:
    """A chain's stations with their distances along it [m], in its direction, then against it:
    walking on, a line that starts at station n is continued back through stations n-1 .. 0 (a
    lane gained); walking against it, one that ends (a lane dropped)."""
    step = np.hypot(*np.diff(st.pos[chain], axis=0).T) if len(chain) > 1 else np.zeros(0)
    along = np.concatenate([[0.0], np.cumsum(step)])
    forward = list(range(len(chain)))
    return [([chain[i] for i in order], along[order]) for order in (forward, forward[::-1])]


def _new_dividers(row: _Row, before: set[int], types: list[int], virtual: int) -> list[_Divider]:
    """The markings of a station (``row``) that are not among the tracks ``before`` (they start
    here) with a line on each side a lane away (RULE 7's width test): the dividers RULE 15 may
    continue, in the order of their track ids."""
    lo, hi = LANE_WIDTH_MIN_M - _WIDTH_SLACK_M, LANE_WIDTH_MAX_M + _WIDTH_SLACK_M
    out = []
    for t, (s_t, f) in sorted(row.items()):
        if t in before or f == virtual or types[f] not in _MARKINGS:
            continue
        left, right = _beside(row, t, virtual)
        if left is None or right is None:
            continue
        a, b = row[left][0] - s_t, s_t - row[right][0]
        if not (lo <= a <= hi and lo <= b <= hi):
            continue  # no divider between two lanes
        out.append(_Divider(row[left][0], row[right][0], a, b))
    return out


def _beside(row: _Row, t: int, virtual: int) -> tuple[int | None, int | None]:
    """The tracks of the lines (no inferred one) next to track ``t`` on its left and right."""
    s = row[t][0]
    left = [(v[0], u) for u, v in row.items() if v[0] > s and v[1] != virtual]
    right = [(v[0], u) for u, v in row.items() if v[0] < s and v[1] != virtual]
    return (min(left)[1] if left else None), (max(right)[1] if right else None)


def _strip_behind(
    crossings: _Crossings, stations: list[int], along: np.ndarray, n: int, divider: _Divider, virtual: int
) -> _Walk:
    """The strip between ``divider``'s two neighbour lines, walked back from ``stations[n]``
    (toward ``stations[0]``) while both lines run on (RULE 10's hand-over distance), no mapped line
    lies between them and for at most _TAPER_MAX_M: per station its two sides."""
    walk: _Walk = []
    sl, sr = divider.left_m, divider.right_m
    for m in range(n - 1, -1, -1):
        if abs(along[m] - along[n]) > _TAPER_MAX_M:
            break
        q = stations[m]
        rq = crossings.row(q)
        sl2, sr2 = _line_near(rq, sl, -1.0, virtual), _line_near(rq, sr, 1.0, virtual)
        if sl2 is None or sr2 is None or not _only_inferred_between(rq, sl2, sr2, virtual):
            break
        sl, sr = sl2, sr2
        walk.append((q, sl, sr))
    return walk


def _line_near(row: _Row, s: float, inward: float, virtual: int) -> float | None:
    """The line of ``row`` (no inferred one) within _HANDOVER_M of ``s`` (RULE 10) farthest
    toward ``inward`` (+1: left): a strip's side is the line next to it (an edge line leaving
    the road border beside it)."""
    cands = [v[0] for v in row.values() if v[1] != virtual and abs(v[0] - s) <= _HANDOVER_M]
    return max(cands, key=lambda x: inward * x) if cands else None


def _only_inferred_between(row: _Row, sl: float, sr: float, virtual: int) -> bool:
    """Lines at ``sl`` and ``sr`` (left of it) apart, with only inferred lines between them."""
    if sl - sr <= _DUPLICATE_M:
        return False
    return all(v[1] == virtual for v in row.values() if sr + _DUPLICATE_M / 2 < v[0] < sl - _DUPLICATE_M / 2)


def _is_taper(walk: _Walk) -> bool:
    """The strip behind a divider is wider than one lane where it starts (ends) and one lane
    wide somewhere along ``walk``: it narrows, a taper."""
    if not walk or walk[0][1] - walk[0][2] <= LANE_WIDTH_MAX_M:
        return False  # the strip before it is one lane (or not there)
    return not all(wl - wr > LANE_WIDTH_MAX_M for _, wl, wr in walk)  # (all wider: never one lane)


def _held_side(crossings: _Crossings, row: _Row, divider: _Divider, walk: _Walk, virtual: int) -> bool:
    """Whether the divider keeps its distance to its left neighbour line through the strip (else
    to its right one): the side that runs on is the one whose distance to its own outer line
    changes less along ``walk`` (by more than _TRACK_TOL_M); alike, or not measured on either
    side, the side of the wider lane."""
    rows = [crossings.row(q) for q, _, _ in walk]
    drift = [
        _outer_drift(row, divider.left_m, rows, [wl for _, wl, _ in walk], 1.0, virtual),
        _outer_drift(row, divider.right_m, rows, [wr for _, _, wr in walk], -1.0, virtual),
    ]
    if np.isfinite(drift).any() and abs(drift[0] - drift[1]) > _TRACK_TOL_M:
        return drift[0] < drift[1]
    return divider.lane_left_m >= divider.lane_right_m


def _outer_drift(row: _Row, s_m: float, rows: list[_Row], sides_m: list[float], sign: float, virtual: int) -> float:
    """How much the distance from a strip's side to its own outer line (toward ``sign``, +1:
    left) changes along the strip: median over ``rows`` (the side at ``sides_m`` there) of its
    difference to the distance at the divider (``row``, side at ``s_m``) [m]; inf: not measured."""
    o_k = _outer_line(row, s_m, sign, virtual)
    d = []
    for rq, s in zip(rows, sides_m, strict=True):
        o = _outer_line(rq, s, sign, virtual)
        if o is not None and o_k is not None:
            d.append(abs((o - s) - (o_k - s_m)))
    return float(np.median(d)) if d else np.inf


def _outer_line(row: _Row, s: float, sign: float, virtual: int) -> float | None:
    """The nearest line of ``row`` (no inferred one) beyond ``s`` on the side of ``sign``."""
    cands = [v[0] for v in row.values() if v[1] != virtual and sign * (v[0] - s) > _DUPLICATE_M]
    return min(cands, key=lambda x: abs(x - s)) if cands else None


def _continue_divider(
    crossings: _Crossings, walk: _Walk, divider: _Divider, track: int, virtual: int, *, hold_left: bool
) -> bool:
    """``divider`` continued through the strip of ``walk`` as the inferred line ``track``, at its
    distance from the held side, as long as the widening lane beside it is at least _DUPLICATE_M
    wide. Returns whether it was placed anywhere."""
    placed = False
    for q, wl, wr in walk:
        s_v = wl - divider.lane_left_m if hold_left else wr + divider.lane_right_m
        if (s_v - wr if hold_left else wl - s_v) < _DUPLICATE_M:
            break
        crossings.infer(q, track, virtual, s_v, wl, wr)
        placed = True
    return placed


# --------------------------------------------------------------------------------------------
# Runs of equal cross sections


def _runs(st: _Stations, sections: list[_Section]) -> list[list[int]]:
    """Maximal chains of stations with one link between them and the same boundaries, cut to
    pieces of at most LANELET_MAX_M."""

    def continues(a: int) -> int | None:
        if len(st.succ[a]) != 1:
            return None
        b = st.succ[a][0]
        if len(st.pred[b]) != 1 or sections[b].features != sections[a].features:
            return None
        return b

    return [piece for run in _walks(st, continues) for piece in _chunks(st, run)]


def _chunks(st: _Stations, run: list[int]) -> list[list[int]]:
    if len(run) < 2:
        return [run]
    step = np.hypot(*np.diff(st.pos[run], axis=0).T)
    length = float(step.sum())
    n = int(np.ceil(length / LANELET_MAX_M))
    if n <= 1:
        return [run]
    cum = np.concatenate([[0.0], np.cumsum(step)])
    cut = np.searchsorted(cum, np.arange(1, n) * length / n)
    return [list(p) for p in np.split(np.asarray(run), cut) if len(p)]


# --------------------------------------------------------------------------------------------
# Joints and lanes


class _Union:
    def __init__(self) -> None:
        self.parent: dict[tuple[int, int], tuple[int, int]] = {}

    def find(self, x: tuple[int, int]) -> tuple[int, int]:
        root = x
        while self.parent.get(root, root) != root:
            root = self.parent[root]
        while self.parent.get(x, x) != root:
            self.parent[x], x = root, self.parent[x]
        return root

    def alias(self, x: tuple[int, int], onto: tuple[int, int]) -> None:
        rx, ro = self.find(x), self.find(onto)
        if rx != ro:
            self.parent[rx] = ro


def _build(st: _Stations, sections: list[_Section], runs: list[list[int]], hdmap: HDMap) -> LaneMap:
    feats = hdmap.features
    index = {int(f.id): i for i, f in enumerate(feats)}
    linked = [{index[int(x)] for x in (*f.predecessors, *f.successors) if int(x) in index} for f in feats] + [set()]
    fid = [int(f.id) for f in feats] + [0]  # the last: inferred lines (RULE 9)
    ftype = [f.type for f in feats] + [FeatureType.DASHED]
    run_of_last: dict[int, list[int]] = defaultdict(list)
    for r, run in enumerate(runs):
        run_of_last[run[-1]].append(r)

    def point(key: tuple[int, int]) -> np.ndarray:
        sec = sections[key[0]]
        return sec.xy[sec.features.index(key[1])]

    def label(key: tuple[int, int]) -> int:
        sec = sections[key[0]]
        return sec.labels[sec.features.index(key[1])]

    def match(t: int, f: int, at: np.ndarray, other: _Section) -> tuple[int, bool]:
        """RULE 3 / 4: the boundary (track) of ``other`` that track ``t`` (feature ``f``, crossing
        at ``at``) continues; and whether it truly continues (False: the nearest one)."""
        if t in other.features:
            return t, True
        for g, h in zip(other.features, other.labels, strict=True):
            if h == f or h in linked[f]:
                return g, True
        d = np.hypot(*(other.xy - at).T)
        i = int(np.argmin(d))
        return other.features[i], bool(d[i] <= JOIN_TOL_M)

    uf = _Union()
    prefix: dict[int, dict[int, tuple[int, int]]] = {}  # run -> feature -> key of its first node
    suffix: dict[int, dict[int, tuple[int, int]]] = {}  # run -> feature -> key of its last node
    for r, run in enumerate(runs):
        a = run[0]
        preds = st.pred[a]
        sec = sections[a]
        if len(preds) == 1:  # a continuation or one branch of a split: start at the joints of p
            p = preds[0]
            psec = sections[p]
            if not psec.features:
                continue
            joints = [(p, match(t, f, at, psec)[0]) for t, f, at in zip(sec.features, sec.labels, sec.xy, strict=True)]
            if _near(joints, sec, point):
                prefix[r] = dict(zip(sec.features, joints, strict=True))
        elif len(preds) > 1 and sec.features:  # a merge: the preceding runs end at the joints of a
            for p in preds:
                for q in run_of_last.get(p, []):
                    psec = sections[p]
                    joints = [
                        (a, match(t, f, at, sec)[0])
                        for t, f, at in zip(psec.features, psec.labels, psec.xy, strict=True)
                    ]
                    if _near(joints, psec, point):
                        suffix[q] = dict(zip(psec.features, joints, strict=True))
    # RULE 4 for lines that end before a split / continuation or start after a merge
    used: dict[int, set[int]] = defaultdict(set)  # station -> features a neighbouring run joins at
    for mapping in list(prefix.values()) + list(suffix.values()):
        for key in mapping.values():
            used[key[0]].add(key[1])
    for k, fs in used.items():
        sec = sections[k]
        keep = [i for i, f in enumerate(sec.features) if f in fs]
        if not keep:
            continue
        nearest = {
            i: keep[int(np.argmin(np.abs(sec.s[keep] - sec.s[i])))] for i, f in enumerate(sec.features) if f not in fs
        }
        # RULE 4b: two or more lines that stop here (their map feature ends at the cut) beside
        # the same continuing line, on the same side, are lanes that stop (a junction where the
        # markings stop), not one dropped lane: they end where they are
        stop = {i for i in nearest if _ends_at(feats, sec.labels[i], sec.xy[i])}
        side = Counter((j, bool(sec.s[i] > sec.s[j])) for i, j in nearest.items() if i in stop)
        for i, j in nearest.items():
            if i not in stop or side[(j, bool(sec.s[i] > sec.s[j]))] < 2:
                uf.alias((k, sec.features[i]), (k, sec.features[j]))

    def node_uid(key: tuple[int, int]) -> int:
        root = uf.find(key)
        slot = sections[root[0]].features.index(root[1])
        return _uid("node", int(st.ids[root[0]]), fid[label(root)], slot)

    nodes: dict[int, np.ndarray] = {}
    boundaries: dict[int, Boundary] = {}
    lanes: list[dict] = []
    where: dict[int, tuple[int, int, tuple[float, float], tuple[float, float]]] = {}  # RULE 8
    for r, run in enumerate(runs):
        sec0 = sections[run[0]]
        if not sec0.features:
            continue
        ways: list[list[tuple[int, int]]] = []
        for f in sec0.features:
            keys = [(k, f) for k in run]
            if r in prefix:
                keys.insert(0, prefix[r][f])
            if r in suffix:
                keys.append(suffix[r][f])
            ways.append(keys)
        if len(ways[0]) < 2:
            continue
        pts = []
        ends = []
        for keys in ways:
            xy = np.array([point(k) for k in keys])
            first, last = uf.find(keys[0]), uf.find(keys[-1])
            xy[0], xy[-1] = point(first), point(last)
            pts.append(xy)
            ends.append((node_uid(keys[0]), node_uid(keys[-1])))
            nodes[ends[-1][0]] = xy[0]
            nodes[ends[-1][1]] = xy[-1]
        s = np.array([sections[k].s for k in run])  # (n, B)
        labels = np.array([sections[k].labels for k in run])  # (n, B)
        lab = [int(np.bincount(labels[:, b]).argmax()) for b in range(labels.shape[1])]  # most common
        # the slot b keeps two pieces apart that carry the same feature (a feature crossing twice)
        piece_ids = [_uid("boundary", int(st.ids[run[0]]), fid[f], b) for b, f in enumerate(lab)]
        for b in range(len(lab) - 1):
            fl, fr = lab[b], lab[b + 1]
            tl, tr = ftype[fl], ftype[fr]
            width = float(np.median(s[:, b] - s[:, b + 1]))
            if not LANE_WIDTH_MIN_M <= width <= LANE_WIDTH_MAX_M:  # RULE 1
                continue
            if {tl, tr} == {FeatureType.SOLID, FeatureType.ROAD_BORDER}:  # RULE 2
                continue
            if not _proper(pts[b], pts[b + 1], ends[b], ends[b + 1]):  # RULE 14
                continue
            for bb, f in ((b, fl), (b + 1, fr)):
                if piece_ids[bb] not in boundaries:
                    boundaries[piece_ids[bb]] = Boundary(
                        piece_ids[bb],
                        fid[f],
                        ftype[f],
                        pts[bb],
                        ends[bb][0],
                        ends[bb][1],
                        inferred=f == len(feats),
                    )
            center = (pts[b] + pts[b + 1]) / 2.0
            lane_id = _uid("lane", int(st.ids[run[0]]), fid[fl], fid[fr], b)
            where[lane_id] = (run[0], run[-1], (s[0, b], s[0, b + 1]), (s[-1, b], s[-1, b + 1]))
            lanes.append(
                dict(
                    id=lane_id,
                    centerline=center,
                    width=np.hypot(*(pts[b] - pts[b + 1]).T),
                    left_boundary=piece_ids[b],
                    right_boundary=piece_ids[b + 1],
                    left_feature=fid[fl],
                    right_feature=fid[fr],
                    left_type=tl,
                    right_type=tr,
                )
            )
    lanes += _bridges(lanes, boundaries, st, where)
    return LaneMap(_link(lanes, boundaries), tuple(sorted(boundaries.values(), key=lambda x: x.id)), nodes)


def _ends_at(feats: Sequence[MapFeature], label: int, at: np.ndarray) -> bool:
    """RULE 4b: the map feature ``label`` (an inferred line: no) ends within _STOP_M of ``at``."""
    if label >= len(feats) or len(feats[label].points) == 0:
        return False
    pts = np.asarray(feats[label].points, dtype=float)
    return bool(min(np.hypot(*(pts[0, :2] - at)), np.hypot(*(pts[-1, :2] - at))) <= _STOP_M)


def _proper(left: np.ndarray, right: np.ndarray, left_ends: tuple[int, int], right_ends: tuple[int, int]) -> bool:
    """RULE 14 (degenerate pieces): a lane needs sides that run from one node to another, each
    with its middle off the other side on its own side (left of the right side, right of the left
    side, by more than _SIDE_EPS_M) and no point on the wrong side. Lanelet2's loader aligns the
    bounds of a lanelet by the side the other bound's middle point lies on
    (``geometry::align``): a side whose ends are joined into one node, a strip of width 0, or
    sides crossed over come out turned round, and its routing disagrees with the lane graph."""
    if left_ends[0] == left_ends[1] or right_ends[0] == right_ends[1]:
        return False
    for a, b, sign in ((left, right, -1.0), (right, left, 1.0)):  # b's points as seen from a
        if len(a) < 2 or float(np.hypot(*(a[-1] - a[0]))) < _SIDE_EPS_M:
            return False
        if sign * _signed_distance(a, _middle(b)[None])[0] <= _SIDE_EPS_M:  # + = left of a
            return False
    return True


def proper_sides(left: np.ndarray, right: np.ndarray, left_ends: tuple[int, int], right_ends: tuple[int, int]) -> bool:
    """RULE 14 for a lane made elsewhere (trajectory connectors): its (N, 2) sides and their
    (start, end) node ids are those of a lane that Lanelet2 loads the right way round."""
    return _proper(left, right, left_ends, right_ends)


def _middle(line: np.ndarray) -> np.ndarray:
    """The point halfway along a polyline."""
    step = np.hypot(*np.diff(line, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(step)])
    half = cum[-1] / 2.0
    return np.array([np.interp(half, cum, line[:, 0]), np.interp(half, cum, line[:, 1])])


def _signed_distance(line: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Distance of each (M, 2) point to the polyline (N, 2), + on its left (the nearest segment's)."""
    a, b = line[:-1], line[1:]
    ab = b - a
    len2 = np.maximum((ab**2).sum(axis=1), 1e-12)
    rel = pts[:, None, :] - a[None]  # (M, S, 2)
    t = np.clip((rel * ab[None]).sum(axis=2) / len2[None], 0.0, 1.0)
    near = a[None] + t[..., None] * ab[None]
    dist = np.hypot(*(pts[:, None, :] - near).transpose(2, 0, 1))
    k = np.argmin(dist, axis=1)
    r = rel[np.arange(len(pts)), k]
    side = np.sign(ab[k, 0] * r[:, 1] - ab[k, 1] * r[:, 0])
    return side * dist[np.arange(len(pts)), k]


def _near(joints: list[tuple[int, int]], sec: _Section, point: Callable[[tuple[int, int]], np.ndarray]) -> bool:
    """RULE 13 (far joints): every boundary of ``sec`` joins a node (``joints``, one per boundary)
    within _JOINT_MAX_M of its own crossing; else the runs are not joined there (the cut lines of a
    turn reach across the lines of another road, and the nearest of those is no continuation)."""
    return all(float(np.hypot(*(point(key) - xy))) <= _JOINT_MAX_M for key, xy in zip(joints, sec.xy, strict=True))


def _bridges(
    lanes: list[dict],
    boundaries: dict[int, Boundary],
    st: _Stations,
    where: dict[int, tuple[int, int, tuple[float, float], tuple[float, float]]],
) -> list[dict]:
    """RULE 8: a lane without successor is joined to a lane that starts within BRIDGE_MAX_M
    ahead in its line (both sides at most BRIDGE_LATERAL_M + 2 % of the gap
    aside, heading within BRIDGE_ANGLE_DEG, both ends at least LANE_WIDTH_MIN_M - _WIDTH_SLACK_M
    wide) by a connector lane with virtual sides (``FeatureType.UNKNOWN``): the junctions of a road
    where the markings stop. Each lane ahead takes one connector, the closest."""

    def ends(ln: dict, k: int) -> tuple[int, int]:
        lb, rb = boundaries[ln["left_boundary"]], boundaries[ln["right_boundary"]]
        return (lb.start_node, rb.start_node) if k == 0 else (lb.end_node, rb.end_node)

    starts = {ends(ln, 0) for ln in lanes}
    narrow = LANE_WIDTH_MIN_M - _WIDTH_SLACK_M
    dead = [ln for ln in lanes if ends(ln, -1) not in starts and ln["width"][-_END_POINTS:].max() >= narrow]
    fresh = [j for j, ln in enumerate(lanes) if ln["width"][:_END_POINTS].max() >= narrow]
    if not dead or not fresh:
        return []

    def side(ln: dict, k: int) -> np.ndarray:  # (2, 2): left and right boundary point at end k
        return np.stack([boundaries[ln["left_boundary"]].points[k], boundaries[ln["right_boundary"]].points[k]])

    head = np.array([side(lanes[j], 0) for j in fresh])  # (F, 2, 2)
    head_dir = np.array([_direction(lanes[j]["centerline"], first=True) for j in fresh])
    cands: list[tuple[float, int, int, np.ndarray | None]] = []
    for a in dead:
        tail, d = side(a, -1), _direction(a["centerline"], first=False)
        rel = head - tail[None]  # (F, 2, 2)
        along = rel @ d  # (F, 2)
        aside = np.abs(rel[..., 0] * d[1] - rel[..., 1] * d[0])
        ok = np.all((along > 0.5) & (along <= BRIDGE_MAX_M) & (aside <= BRIDGE_LATERAL_M + 0.02 * along), axis=1)
        ok &= head_dir @ d >= np.cos(np.radians(BRIDGE_ANGLE_DEG))
        straight = [
            (float(aside[i].sum() + 0.01 * along[i].mean()), int(a["id"]), fresh[i], None)
            for i in np.flatnonzero(ok).tolist()
            if lanes[fresh[i]]["id"] != a["id"]
        ]
        # the topology's path only where no lane starts straight ahead (curves)
        more: list[tuple[float, int, int, np.ndarray | None]] = []
        more += straight or _along_topology(a, lanes, fresh, st, where)
        if a["width"][-1] < narrow:  # a gore closes it: only a short way on to the lane ahead
            tip = a["centerline"][-1]
            more = [c for c in more if np.hypot(*(lanes[c[2]]["centerline"][0] - tip)) <= _GORE_BRIDGE_M]
        cands += more
    by_id = {ln["id"]: ln for ln in lanes}
    used_a: set[int] = set()
    used_b: set[int] = set()
    out: list[dict] = []
    for _, aid, j, path in sorted(cands, key=lambda c: c[:3]):
        if aid in used_a or j in used_b:
            continue
        used_a.add(aid)
        used_b.add(j)
        con = _connector(by_id[aid], lanes[j], boundaries, path)
        lb, rb = boundaries[con["left_boundary"]], boundaries[con["right_boundary"]]
        if not _proper(lb.points, rb.points, (lb.start_node, lb.end_node), (rb.start_node, rb.end_node)):
            used_a.discard(aid)  # RULE 14: the dead end may take its next candidate
            used_b.discard(j)
            for bid in (con["left_boundary"], con["right_boundary"]):
                if not any(bid in (x["left_boundary"], x["right_boundary"]) for x in out):
                    boundaries.pop(bid, None)
            continue
        out.append(con)
    return out


def _along_topology(
    a: dict,
    lanes: list[dict],
    fresh: list[int],
    st: _Stations,
    where: dict[int, tuple[int, int, tuple[float, float], tuple[float, float]]],
) -> list[tuple[float, int, int, np.ndarray]]:
    """RULE 8 through curves: lanes that start on a station reached from the dead end's last
    station along the topology within BRIDGE_MAX_M, both sides within BRIDGE_LATERAL_M of the
    dead end's offsets from the road middle; each with the connector's (N, 2, 2) side points along
    that path (offsets interpolated)."""
    if a["id"] not in where:
        return []
    _, e, _, (sl, sr) = where[a["id"]]
    starts: dict[int, list[int]] = defaultdict(list)
    for j in fresh:
        if lanes[j]["id"] in where:
            starts[where[lanes[j]["id"]][0]].append(j)
    dist, parent = {e: 0.0}, {e: -1}
    todo = [e]
    while todo:
        k = todo.pop()
        for q in st.succ[k]:
            d = dist[k] + float(np.hypot(*(st.pos[q] - st.pos[k])))
            if d <= BRIDGE_MAX_M and d < dist.get(q, np.inf):
                dist[q], parent[q] = d, k
                todo.append(q)
    out = []
    turns = []  # RULE 8 turns: the lane ahead nearest to the dead end's offset, within BRIDGE_TURN_M
    for k, d in dist.items():
        for j in starts.get(k, []) if k != e else []:
            bl, br = where[lanes[j]["id"]][2]
            if lanes[j]["id"] == a["id"]:
                continue
            if max(abs(bl - sl), abs(br - sr)) > BRIDGE_LATERAL_M:
                if abs((bl + br) - (sl + sr)) / 2.0 <= BRIDGE_TURN_M:
                    turns.append((k, d, j))
                continue
            path = [k]
            while parent[path[-1]] != -1:
                path.append(parent[path[-1]])
            path.reverse()
            w = np.array([dist[q] for q in path]) / max(d, 1e-9)
            normal = np.stack([-st.tangent[path, 1], st.tangent[path, 0]], axis=1)
            sides = [st.pos[path] + ((1 - w) * s0 + w * s1)[:, None] * normal for s0, s1 in ((sl, bl), (sr, br))]
            out.append((abs(bl - sl) + abs(br - sr) + 0.01 * d, int(a["id"]), j, np.stack(sides, axis=1)))
    if out or not turns:
        return out
    for k, d, j in turns:
        bl, br = where[lanes[j]["id"]][2]
        path = [k]
        while parent[path[-1]] != -1:
            path.append(parent[path[-1]])
        path.reverse()
        w = np.array([dist[q] for q in path]) / max(d, 1e-9)
        normal = np.stack([-st.tangent[path, 1], st.tangent[path, 0]], axis=1)
        sides = [st.pos[path] + ((1 - w) * s0 + w * s1)[:, None] * normal for s0, s1 in ((sl, bl), (sr, br))]
        score = 2.0 * BRIDGE_LATERAL_M + abs(bl - sl) + abs(br - sr) + 0.01 * d  # after every lane in line
        out.append((score, int(a["id"]), j, np.stack(sides, axis=1)))
    return out


def _direction(line: np.ndarray, *, first: bool) -> np.ndarray:
    """Unit direction of a polyline over its first (last) ~10 m."""
    n = len(line)
    k = min(n - 1, 5)
    d = line[k] - line[0] if first else line[-1] - line[n - 1 - k]
    return d / max(float(np.hypot(*d)), 1e-9)


def _connector(a: dict, b: dict, boundaries: dict[int, Boundary], path: np.ndarray | None = None) -> dict:
    """The connector lane from ``a``'s end to ``b``'s start: straight, or, given the (N, 2, 2) side
    points ``path`` along the topology, a cubic Hermite curve per side from ``a``'s end direction to
    ``b``'s start direction (tangents as long as the path), N points."""
    sides = []
    n = int(np.hypot(*(b["centerline"][0] - a["centerline"][-1])) // 2.0) + 2  # a point every ~2 m
    for i, side in enumerate(("left_boundary", "right_boundary")):
        pa, pb = boundaries[a[side]], boundaries[b[side]]
        if path is None or len(path) < 2:
            pts = np.linspace(pa.points[-1], pb.points[0], n)
        else:  # a curve: cubic Hermite from a's end direction to b's start direction
            length = float(np.hypot(*np.diff(path[:, i], axis=0).T).sum())
            t = np.linspace(0.0, 1.0, max(len(path), 3))[:, None]  # both sides: as many points
            p0, p1 = pa.points[-1], pb.points[0]
            d0 = _direction(pa.points, first=False) * length
            d1 = _direction(pb.points, first=True) * length
            h00, h10, h01, h11 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2
            pts = h00 * p0 + h10 * d0 + h01 * p1 + h11 * d1
        bid = _uid("connector", pa.id, pb.id)
        boundaries[bid] = Boundary(bid, 0, FeatureType.UNKNOWN, pts, pa.end_node, pb.start_node)
        sides.append((bid, pts))
    (lb, lp), (rb, rp) = sides
    return dict(
        id=_uid("connector_lane", a["id"], b["id"]),
        centerline=(lp + rp) / 2.0,
        width=np.hypot(*(lp - rp).T),
        left_boundary=lb,
        right_boundary=rb,
        left_feature=0,
        right_feature=0,
        left_type=FeatureType.UNKNOWN,
        right_type=FeatureType.UNKNOWN,
    )


def _link(lanes: list[dict], boundaries: dict[int, Boundary]) -> tuple[Lane, ...]:
    """Successors by shared end nodes of both sides, neighbours by a shared boundary piece."""
    by_start: dict[tuple[int, int], list[int]] = defaultdict(list)
    by_left: dict[int, int] = {}
    by_right: dict[int, int] = {}
    for i, ln in enumerate(lanes):
        lb, rb = boundaries[ln["left_boundary"]], boundaries[ln["right_boundary"]]
        by_start[(lb.start_node, rb.start_node)].append(i)
        by_left[ln["left_boundary"]] = i
        by_right[ln["right_boundary"]] = i
    succ: list[list[int]] = [[] for _ in lanes]
    pred: list[list[int]] = [[] for _ in lanes]
    for i, ln in enumerate(lanes):
        lb, rb = boundaries[ln["left_boundary"]], boundaries[ln["right_boundary"]]
        for j in by_start.get((lb.end_node, rb.end_node), []):
            if j != i:
                succ[i].append(lanes[j]["id"])
                pred[j].append(ln["id"])
    out = []
    for i, ln in enumerate(lanes):
        left = by_right.get(ln["left_boundary"])
        right = by_left.get(ln["right_boundary"])
        out.append(
            Lane(
                **ln,
                successors=tuple(sorted(succ[i])),
                predecessors=tuple(sorted(pred[i])),
                left=lanes[left]["id"] if left is not None else None,
                right=lanes[right]["id"] if right is not None else None,
            )
        )
    return tuple(sorted(out, key=lambda x: x.id))


def _uid(name: str, *keys: int) -> int:
    """A stable 63-bit id (never 0) from a name and integer keys."""
    raw = name.encode() + b"".join(int(k).to_bytes(8, "little", signed=False) for k in keys)
    x = int.from_bytes(hashlib.blake2b(raw, digest_size=8).digest(), "little") & ((1 << 63) - 1)
    return x or 1
