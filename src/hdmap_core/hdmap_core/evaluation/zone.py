"""The changed zone scored apart: a map against the road as it is now, inside the zones of road
changes, and its ghost lines (map lines that match only the road as it was).

The same cut lines and matching rules as ``evaluate_map`` (Sec. VII, docs/evaluation.md), on the
cuts of the current road whose centre lies in a zone (``simulation.changes.zone_mask``, running the
zone's way):

* recall: share of the current road's points with a map point of their type within
  ``recall_radius_m`` on their cut; precision: share of the map points with such a partner;
* mean error: mean |lateral error| of the map points matched (same type, within ``gate_m``);
* type accuracy: of the map points with any current point within ``gate_m``, the share whose
  nearest point of their own type is no farther than the nearest of any type + ``type_tie_m``;
* ghost share: share of the map points with a point of the old road (any type) within
  ``recall_radius_m`` and none of the current road: what is left of the road as it was;
* old recall: recall against the old road (how much of the map still shows it).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import networkx as nx
import numpy as np

from hdmap_core.evaluation.config import EVAL_TYPES, EvalConfig
from hdmap_core.evaluation.cuts import Cuts, configured_cuts, nearest_on_same_cut, nearest_same_type, points_on_cuts
from hdmap_core.geometry import arc_length
from hdmap_core.groundtruth import GroundTruth, GTLane
from hdmap_core.lanes.lane_graph import lane_graph, lanes_at
from hdmap_core.lanes.model import LaneMap
from hdmap_core.model import HDMap
from hdmap_core.simulation.changes import ChangeZone, zone_mask

__all__ = ["ZoneReport", "evaluate_zone", "ZoneLanes", "evaluate_zone_lanes"]

_EVAL_TYPES = tuple(int(t) for t in EVAL_TYPES)
_SAME_LANE_M = 1.0  # two ground-truth lane centerlines this close on a cut are one lane [m]
_LINK_PROBE_M = 15.0  # a lane link is probed this far before / after its joint [m]
_LINK_REACH_M = 1000.0  # the map's successor path between the two probes may be this long [m]


@dataclass(frozen=True)
class ZoneReport:
    """What ``evaluate_zone`` measured (module docstring); shares in [0, 1], NaN when undefined."""

    n_cuts: int
    n_gt_points: int
    n_map_points: int
    recall: float
    precision: float
    mean_m: float
    type_accuracy: float
    ghost_share: float
    old_recall: float

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in asdict(self).items()}

    def line(self) -> str:
        """One line of text."""

        def pct(x: float) -> str:
            return "n/a" if math.isnan(x) else f"{100 * x:.1f} %"

        mean = "n/a" if math.isnan(self.mean_m) else f"{self.mean_m:.3f} m"
        return (
            f"changed zone ({self.n_cuts} cuts): recall {pct(self.recall)}, precision {pct(self.precision)}, "
            f"mean error {mean}, type accuracy {pct(self.type_accuracy)}, ghost share {pct(self.ghost_share)}, "
            f"recall of the old road {pct(self.old_recall)}"
        )


def _share(num: int, den: int) -> float:
    return num / den if den else math.nan


def _zone_cuts(gt_now: GroundTruth, zones: Sequence[ChangeZone], config: EvalConfig) -> tuple[Cuts, float]:
    """The metric's cut lines of ``gt_now`` inside ``zones``, and the cosine of the largest angle
    between a feature and a cut's road direction."""
    cos_feat = math.cos(math.radians(config.max_feature_angle_deg))
    cuts = configured_cuts(gt_now, config, cos_feature=cos_feat)
    inside = np.zeros(len(cuts), dtype=bool)
    for z in zones:
        inside |= zone_mask(z, cuts.center, cuts.tangent)
    return cuts.take(inside), cos_feat


def evaluate_zone(
    hdmap: HDMap,
    gt_now: GroundTruth,
    gt_before: GroundTruth,
    zones: Sequence[ChangeZone],
    *,
    config: EvalConfig = EvalConfig(),
) -> ZoneReport:
    """Score ``hdmap`` inside ``zones`` against ``gt_now``; ghosts against ``gt_before``."""
    cuts, cos_feat = _zone_cuts(gt_now, zones, config)
    width = 4.0 * (config.max_half_length_m + config.border_margin_m) + 10.0

    def on_cuts(feats: Sequence) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        feats = [f for f in feats if int(f.type) in _EVAL_TYPES and len(f.points) >= 2]
        p = points_on_cuts(cuts, [np.asarray(f.points, dtype=float) for f in feats], cos_min=cos_feat)
        types = np.array([int(f.type) for f in feats], dtype=np.int64)[p.owner] if feats else p.owner
        return p.cut, p.s, types

    g_cut, g_s, g_t = on_cuts(gt_now.features)
    o_cut, o_s, o_t = on_cuts(gt_before.features)
    m_cut, m_s, m_t = on_cuts(hdmap.features)
    if len(cuts) == 0:
        nan = math.nan
        return ZoneReport(0, 0, len(m_cut), nan, nan, nan, nan, nan, nan)
    gi, gd = nearest_same_type(m_cut, m_s, m_t, g_cut, g_s, g_t, width=width)
    _, g_to_m = nearest_same_type(g_cut, g_s, g_t, m_cut, m_s, m_t, width=width)
    _, o_to_m = nearest_same_type(o_cut, o_s, o_t, m_cut, m_s, m_t, width=width)
    _, any_now = nearest_on_same_cut(m_cut, m_s, g_cut, g_s, width=width)
    _, any_old = nearest_on_same_cut(m_cut, m_s, o_cut, o_s, width=width)
    matched = gd <= config.gate_m
    err = np.abs(m_s[matched] - g_s[gi[matched]]) if matched.any() else np.zeros(0)
    typed = any_now <= config.gate_m
    type_ok = typed & (gd <= any_now + config.type_tie_m)
    ghost = (any_old <= config.recall_radius_m) & (any_now > config.recall_radius_m)
    return ZoneReport(
        n_cuts=len(cuts),
        n_gt_points=len(g_cut),
        n_map_points=len(m_cut),
        recall=_share(int(np.count_nonzero(g_to_m <= config.recall_radius_m)), len(g_cut)),
        precision=_share(int(np.count_nonzero(gd <= config.recall_radius_m)), len(m_cut)),
        mean_m=float(np.mean(err)) if len(err) else math.nan,
        type_accuracy=_share(int(np.count_nonzero(type_ok)), int(np.count_nonzero(typed))),
        ghost_share=_share(int(np.count_nonzero(ghost)), len(m_cut)),
        old_recall=_share(int(np.count_nonzero(o_to_m <= config.recall_radius_m)), len(o_cut)),
    )


@dataclass(frozen=True)
class ZoneLanes:
    """Lanes in the changed zone (``evaluate_zone_lanes``): the share of the zone's cuts where the
    map has as many lanes as the road has now, the mean counts, and the road's lane links there
    (successor links whose joint lies in the zone: a lane opened splits off its neighbour and
    merges back) that the map's lane graph has."""

    n_cuts: int
    count_accuracy: float
    mean_map_lanes: float
    mean_gt_lanes: float
    n_links: int = 0
    links_ok: int = 0

    @property
    def link_share(self) -> float:
        return self.links_ok / self.n_links if self.n_links else math.nan

    def line(self) -> str:
        links = f", lane links {self.links_ok}/{self.n_links}" if self.n_links else ""
        return (
            f"changed zone lanes ({self.n_cuts} cuts): lane count right at {100 * self.count_accuracy:.1f} % "
            f"(mean {self.mean_map_lanes:.2f} lanes in the map, {self.mean_gt_lanes:.2f} on the road){links}"
        )


def _distinct_per_cut(cut: np.ndarray, s: np.ndarray, n_cuts: int, apart_m: float) -> np.ndarray:
    """Per cut, the number of crossings at least ``apart_m`` from the previous one along it."""
    if not len(cut):
        return np.zeros(n_cuts, dtype=np.int64)
    order = np.lexsort((s, cut))
    c, x = cut[order], s[order]
    new = np.ones(len(c), dtype=bool)
    new[1:] = (c[1:] != c[:-1]) | (np.diff(x) >= apart_m)
    return np.bincount(c[new], minlength=n_cuts)


def _zone_links(lane_map: LaneMap, gt_now: GroundTruth, zones: Sequence[ChangeZone]) -> tuple[int, int]:
    """(GT successor links A -> B whose joint lies in a zone, those the map has): the map lane at
    A's centerline ``_LINK_PROBE_M`` before the joint reaches the map lane at B's centerline that far
    after it in the map's lane graph (successors and lane changes across dashed lines, as a route
    does: a lane gained may open beside a through lane) within ``_LINK_REACH_M``. The joint is
    where the two lanes part or join (``_joint``)."""
    probes: list[tuple[np.ndarray, float, np.ndarray, float]] = []
    for a in gt_now.lanes.values():
        for bid in a.successors:
            b = gt_now.lanes.get(bid)
            if b is None or len(a.centerline) < 2 or len(b.centerline) < 2:
                continue
            on_a, on_b, at, heading = _joint(a, b, gt_now)
            if not any(zone_mask(z, at[None, :], heading[None, :]).any() for z in zones):
                continue
            pa, ya = _probe(a.centerline, on_a - _LINK_PROBE_M)
            pb, yb = _probe(b.centerline, on_b + _LINK_PROBE_M)
            probes.append((pa, ya, pb, yb))
    if not probes:
        return 0, 0
    xy = np.array([p for pa, _, pb, _ in probes for p in (pa, pb)])
    yaw = np.array([y for _, ya, _, yb in probes for y in (ya, yb)])
    found = lanes_at(lane_map, xy, yaw).reshape(-1, 2)
    graph = lane_graph(lane_map)
    ok = 0
    for la, lb in found:
        if la == 0 or lb == 0:
            continue
        try:
            ok += int(la == lb or nx.shortest_path_length(graph, int(la), int(lb), weight="weight") <= _LINK_REACH_M)
        except (nx.NetworkXNoPath, nx.NodeNotFound):
            pass
    return len(probes), ok


def _joint(a: GTLane, b: GTLane, gt_now: GroundTruth) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Where GT lane ``a`` hands over to its successor ``b``: (the joint's station along ``a``,
    along ``b`` [m], its position, a's heading there). Where ``a`` ends at ``b``'s start (within
    ``_SAME_LANE_M``), there. Where they do not meet, a lane split off or merged into the side
    of another lane's piece (the road's lane model may link a lane opened beside a through lane
    to the through lane's pieces at its two ends): where ``a`` runs on (one of its successors
    starts at its end), ``b`` splits off its side at ``b``'s start; else ``a`` merges into
    ``b``'s side at ``a``'s end. Probing at ``a``'s end and ``b``'s start there would look for
    the lane before the joint after the one behind it."""
    ca, cb = np.asarray(a.centerline, dtype=float), np.asarray(b.centerline, dtype=float)
    len_a = float(arc_length(ca)[-1])
    if np.hypot(*(ca[-1] - cb[0])) <= _SAME_LANE_M:
        return len_a, 0.0, ca[-1], ca[-1] - ca[-2]
    runs_on = any(
        np.hypot(*(ca[-1] - np.asarray(gt_now.lanes[c].centerline[0], dtype=float))) <= _SAME_LANE_M
        for c in a.successors
        if c != b.id and c in gt_now.lanes and len(gt_now.lanes[c].centerline)
    )
    if runs_on:  # a split: b starts beside a
        s_a = _station_on(ca, cb[0])
        return s_a, 0.0, cb[0], cb[1] - cb[0]
    s_b = _station_on(cb, ca[-1])  # a merge: a ends beside b
    return len_a, s_b, ca[-1], ca[-1] - ca[-2]


def _station_on(line: np.ndarray, p: np.ndarray) -> float:
    """Arc length along ``line`` of the point of ``line`` nearest to ``p`` [m]."""
    a, d = line[:-1], np.diff(line, axis=0)
    t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
    dist = np.hypot(*(a + t[:, None] * d - p).T)
    i = int(np.argmin(dist))
    return float(arc_length(line)[i] + t[i] * np.hypot(*d[i]))


def _probe(line: np.ndarray, at_m: float) -> tuple[np.ndarray, float]:
    """The point ``at_m`` along ``line`` (clipped to its ends) and its heading."""
    s = arc_length(line)
    q = float(np.clip(at_m, 0.0, s[-1]))
    j = int(np.clip(np.searchsorted(s, q), 1, len(line) - 1))
    d = line[j] - line[j - 1]
    w = (q - s[j - 1]) / max(s[j] - s[j - 1], 1e-9)
    return line[j - 1] + w * d, float(np.arctan2(d[1], d[0]))


def evaluate_zone_lanes(
    lane_map: LaneMap, gt_now: GroundTruth, zones: Sequence[ChangeZone], *, config: EvalConfig = EvalConfig()
) -> ZoneLanes:
    """Lanes of ``lane_map`` (``hdmap_core.lanes.derive_lanes``) in the zones against the road as
    it is now (``ZoneLanes``). The road's lane count on a cut: its lane centerlines crossing it, two
    within ``_SAME_LANE_M`` one lane (a closed lane's centerline runs on its neighbour's,
    ``simulation.changes``; an opened lane has its own)."""
    cuts, cos_feat = _zone_cuts(gt_now, zones, config)
    if len(cuts) == 0:
        return ZoneLanes(0, math.nan, math.nan, math.nan)
    g = points_on_cuts(cuts, [ln.centerline for ln in gt_now.lanes.values()], cos_min=cos_feat)
    m = points_on_cuts(cuts, [ln.centerline for ln in lane_map.lanes], cos_min=cos_feat)
    n_gt = _distinct_per_cut(g.cut, g.s, len(cuts), _SAME_LANE_M)
    n_map = np.bincount(m.cut, minlength=len(cuts))
    n_links, links_ok = _zone_links(lane_map, gt_now, zones)
    return ZoneLanes(
        len(cuts), float(np.mean(n_gt == n_map)), float(n_map.mean()), float(n_gt.mean()), n_links, links_ok
    )
