"""Lanes derived from the map's feature graph.

Cross sections: every topology node (one sampling step, 2 m apart) is a cut line through the road
midpoint, perpendicular to its heading, as wide as the road plus a margin. The map features that
cross it in its direction, sorted from left to right, are the boundaries of that cross section.

RULE 1 (lane): two adjacent boundaries bound a lane when their median distance over a section
lies in [LANE_WIDTH_MIN_M, LANE_WIDTH_MAX_M].
RULE 2 (shoulder): a strip between a solid marking and a road border is a shoulder, not a lane.

Sections are runs of consecutive cross sections with the same boundaries (the same feature ids,
in the same order); a run is cut into lanes at most LANELET_MAX_M long. Where two runs meet (a
new feature, a feature ending, a split or merge of the topology) the boundaries are joined node
by node, so that a lane's successors are the lanes whose boundaries start where its own end:

RULE 3 (continuation): a boundary continues the boundary of the preceding run of the same feature,
of a linked feature (predecessor / successor), or the nearest one within JOIN_TOL_M.
RULE 4 (lane gain, drop, gore): a boundary that starts (ends) without a preceding (following) one
starts (ends) at the node of the nearest boundary that does continue: the new lane opens from a
point beside a through lane (reached by a lane change across a dashed line, or as a split) and a
dropped lane closes onto its neighbour (a merge).
RULE 5 (gaps): a topology chain that ends (starts) is linked to the nearest cross section of the
same direction within GAP_LINK_M ahead (behind), so lanes continue across small gaps of the
topology, ramps joining a road included.
"""

from __future__ import annotations

import hashlib
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from hdmap_core.evaluation.cuts import Cuts, points_on_cuts
from hdmap_core.lanes.model import Boundary, Lane, LaneMap
from hdmap_core.model import FeatureType, HDMap

__all__ = [
    "derive_lanes",
    "LANE_WIDTH_MIN_M",
    "LANE_WIDTH_MAX_M",
    "LANELET_MAX_M",
    "JOIN_TOL_M",
    "GAP_LINK_M",
]

LANE_WIDTH_MIN_M = 2.4  # narrowest lane (3.5-3.9 m motorway lanes, 2.75 m in works zones)
LANE_WIDTH_MAX_M = 5.5  # wider: two lanes with a missing marking, or a taper
LANELET_MAX_M = 300.0  # longest lane piece where nothing changes
JOIN_TOL_M = 1.0  # a boundary continues a boundary this close at the joint
GAP_LINK_M = 15.0  # topology chain ends linked across gaps up to this distance
_CUT_MARGIN_M = 3.0  # cut lines reach this far beyond the estimated road width
_COS_SAME_DIRECTION = 0.7  # features crossing a cut within ~45 deg of its direction
_COS_LINK = np.cos(np.radians(35.0))  # heading agreement of a gap link
_WIDTH_SLACK_M = 0.5  # RULE 7: tolerance of the lane width test per cross section
_DUPLICATE_M = 0.5  # crossings this close on one cut are one line
_TRACK_TOL_M = 0.5  # sideways shift of one line between two stations of a chain (2 m apart)
_TRACK_GAP = 5  # stations a line may be missing (10 m) and still continue


def derive_lanes(hdmap: HDMap) -> LaneMap:
    """The lanes of ``hdmap`` (module docstring): lane pieces, shared boundaries and end nodes.

    A map without topology nodes or features has no lanes (an empty ``LaneMap``).
    """
    st = _Stations.of(hdmap)
    if len(st) == 0 or not hdmap.features:
        return LaneMap((), (), {})
    _bridge_gaps(st)
    sections = _cross_sections(st, hdmap)
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
        i = _nearest_along(st, j, ahead=False)
        if i is not None and j not in st.succ[i]:
            st.succ[i].append(j)
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
    same line seen at consecutive stations (RULE 6), also across a change of feature id."""
    normal = np.stack([-st.tangent[:, 1], st.tangent[:, 0]], axis=1)
    half = st.width / 2.0 + _CUT_MARGIN_M
    cuts = Cuts(st.pos, st.tangent, normal, -half, half, np.zeros(len(st)))
    polylines = [np.asarray(f.points, dtype=float) for f in hdmap.features]
    length = np.array([float(np.hypot(*np.diff(p, axis=0).T).sum()) for p in polylines])
    cp = points_on_cuts(cuts, polylines, cos_min=_COS_SAME_DIRECTION)
    order = np.lexsort((-cp.s, cp.cut))
    cut, owner, s = cp.cut[order], cp.owner[order], cp.s[order]
    bounds = np.searchsorted(cut, np.arange(len(st) + 1))
    types = np.array([int(f.type) for f in hdmap.features])
    raw: list[list[tuple[int, float]]] = []
    for k in range(len(st)):
        sl = slice(bounds[k], bounds[k + 1])
        raw.append(_dedupe(list(zip(owner[sl].tolist(), s[sl].tolist(), strict=True)), length))
    xy_of = [[(f, st.pos[k] + sv * normal[k]) for f, sv in items] for k, items in enumerate(raw)]
    tracks = _track(st, xy_of, types, normal)
    out: list[_Section] = []
    for k in range(len(st)):
        xy = np.array([x[2] for x in tracks[k]], dtype=float).reshape(-1, 2)
        sk = (xy - st.pos[k]) @ normal[k]
        o = np.argsort(-sk, kind="stable")
        o = o[_bounding(sk[o], types[[tracks[k][i][1] for i in o]])]
        out.append(
            _Section(
                tuple(tracks[k][i][0] for i in o),
                tuple(tracks[k][i][1] for i in o),
                sk[o],
                xy[o],
            )
        )
    return out


def _bounding(s: np.ndarray, types: np.ndarray) -> np.ndarray:
    """RULE 7: the boundaries (sorted left to right) next to a plausible lane (RULES 1, 2, with
    _WIDTH_SLACK_M); others (outer borders beyond shoulders, lines of a road beside) are left out
    so that they never cut a lane."""
    gap = s[:-1] - s[1:]
    pair = (gap >= LANE_WIDTH_MIN_M - _WIDTH_SLACK_M) & (gap <= LANE_WIDTH_MAX_M + _WIDTH_SLACK_M)
    border, solid = int(FeatureType.ROAD_BORDER), int(FeatureType.SOLID)
    shoulder = ((types[:-1] == border) & (types[1:] == solid)) | ((types[:-1] == solid) & (types[1:] == border))
    pair &= ~shoulder
    keep = np.zeros(len(s), dtype=bool)
    keep[:-1] |= pair
    keep[1:] |= pair
    return keep


def _dedupe(items: list[tuple[int, float]], length: np.ndarray) -> list[tuple[int, float]]:
    """Crossings closer than _DUPLICATE_M are one line (overlapping pieces): the longer feature stays."""
    out: list[tuple[int, float]] = []
    for f, s in items:  # left to right
        if out and out[-1][1] - s < _DUPLICATE_M:
            if length[f] > length[out[-1][0]]:
                out[-1] = (f, s)
            continue
        out.append((f, s))
    return out


def _track(
    st: _Stations, raw: list[list[tuple[int, np.ndarray]]], types: np.ndarray, normal: np.ndarray
) -> list[list[tuple[int, int, np.ndarray]]]:
    """RULE 6: a crossing continues the line of the previous stations of its chain that crossed
    within _TRACK_TOL_M of it (sideways, in the map frame) with the same type, also after up to
    _TRACK_GAP stations without a crossing (the gap is filled by interpolation). Returns per
    station (track, feature, point)."""
    out: list[list[tuple[int, int, np.ndarray]]] = [[] for _ in range(len(st))]
    next_track = 0
    done = np.zeros(len(st), dtype=bool)

    def single(k: int) -> int | None:
        if len(st.succ[k]) == 1 and len(st.pred[st.succ[k][0]]) == 1:
            return st.succ[k][0]
        return None

    starts = [k for k in range(len(st)) if not (len(st.pred[k]) == 1 and single(st.pred[k][0]) == k)]
    for k0 in starts + list(range(len(st))):
        if done[k0]:
            continue
        chain = [k0]
        done[k0] = True
        nxt = single(k0)
        while nxt is not None and not done[nxt]:
            chain.append(nxt)
            done[nxt] = True
            nxt = single(nxt)
        open_: dict[int, tuple[int, int, np.ndarray]] = {}  # track -> (position in chain, feature, point)
        for i, k in enumerate(chain):
            cands = []
            for j, (f, xy) in enumerate(raw[k]):
                for t, (_oi, of, oxy) in open_.items():
                    d = abs(float((xy - oxy) @ normal[k]))
                    if d <= _TRACK_TOL_M and types[f] == types[of]:
                        cands.append((d, t, j))
            cands.sort()
            taken_t: set[int] = set()
            taken_j: set[int] = set()
            for _, t, j in cands:
                if t in taken_t or j in taken_j:
                    continue
                taken_t.add(t)
                taken_j.add(j)
                f, xy = raw[k][j]
                oi, of, oxy = open_[t]
                for g in range(oi + 1, i):  # fill the gap
                    w = (g - oi) / (i - oi)
                    out[chain[g]].append((t, of, oxy + w * (xy - oxy)))
                out[k].append((t, f, xy))
                open_[t] = (i, f, xy)
            for j, (f, xy) in enumerate(raw[k]):
                if j not in taken_j:
                    out[k].append((next_track, f, xy))
                    open_[next_track] = (i, f, xy)
                    next_track += 1
            open_ = {t: v for t, v in open_.items() if i - v[0] <= _TRACK_GAP}
    return out


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

    starts = [k for k in range(len(st)) if not (len(st.pred[k]) == 1 and continues(st.pred[k][0]) == k)]
    seen = np.zeros(len(st), dtype=bool)
    runs: list[list[int]] = []

    def walk(k: int) -> None:
        run = [k]
        seen[k] = True
        nxt = continues(k)
        while nxt is not None and not seen[nxt]:
            run.append(nxt)
            seen[nxt] = True
            nxt = continues(nxt)
        runs.extend(_chunks(st, run))

    for k in starts:
        walk(k)
    for k in range(len(st)):  # closed loops without any change
        if not seen[k]:
            walk(k)
    return runs


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
    fid = [int(f.id) for f in feats]
    index = {f: i for i, f in enumerate(fid)}
    linked = [
        {index[int(x)] for x in (*f.predecessors, *f.successors) if int(x) in index} for f in feats
    ]
    run_of_first = {run[0]: r for r, run in enumerate(runs)}
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
            prefix[r] = {}
            for t, f, at in zip(sec.features, sec.labels, sec.xy, strict=True):
                prefix[r][t] = (p, match(t, f, at, psec)[0])
        elif len(preds) > 1 and sec.features:  # a merge: the preceding runs end at the joints of a
            for p in preds:
                for q in run_of_last.get(p, []):
                    psec = sections[p]
                    suffix[q] = {
                        t: (a, match(t, f, at, sec)[0])
                        for t, f, at in zip(psec.features, psec.labels, psec.xy, strict=True)
                    }
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
        for i, f in enumerate(sec.features):
            if f not in fs:
                j = keep[int(np.argmin(np.abs(sec.s[keep] - sec.s[i])))]
                uf.alias((k, f), (k, sec.features[j]))

    def node_uid(key: tuple[int, int]) -> int:
        root = uf.find(key)
        return _uid("node", int(st.ids[root[0]]), fid[label(root)])

    nodes: dict[int, np.ndarray] = {}
    boundaries: dict[int, Boundary] = {}
    lanes: list[dict] = []
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
        piece_ids = [_uid("boundary", int(st.ids[run[0]]), fid[f]) for f in lab]
        for b in range(len(lab) - 1):
            fl, fr = lab[b], lab[b + 1]
            tl, tr = feats[fl].type, feats[fr].type
            width = float(np.median(s[:, b] - s[:, b + 1]))
            if not LANE_WIDTH_MIN_M <= width <= LANE_WIDTH_MAX_M:  # RULE 1
                continue
            if {tl, tr} == {FeatureType.SOLID, FeatureType.ROAD_BORDER}:  # RULE 2
                continue
            for bb, f in ((b, fl), (b + 1, fr)):
                if piece_ids[bb] not in boundaries:
                    boundaries[piece_ids[bb]] = Boundary(
                        piece_ids[bb], fid[f], feats[f].type, pts[bb], ends[bb][0], ends[bb][1]
                    )
            center = (pts[b] + pts[b + 1]) / 2.0
            lanes.append(
                dict(
                    id=_uid("lane", int(st.ids[run[0]]), fid[fl], fid[fr]),
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
    return LaneMap(_link(lanes, boundaries), tuple(sorted(boundaries.values(), key=lambda x: x.id)), nodes)


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
