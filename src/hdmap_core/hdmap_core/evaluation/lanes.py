"""Lane metrics: the map's lanes (``hdmap_core.lanes``) against the ground truth's lanes.

- coverage: share of the ground-truth lane centerline (lanes of the routes, sampled every
  SAMPLE_STEP_M) within MATCH_RADIUS_M of a map lane centerline of the same direction;
- precision: share of the map lane centerline within MATCH_RADIUS_M of a ground-truth lane
  centerline (any lane) of the same direction;
- mean centerline error: mean distance of the covered ground-truth samples [m];
- lane count accuracy: share of the evaluator's cuts (``reference_cuts``) where the map has as
  many lanes crossing the cut as the ground truth;
- route reachability: share of the ground-truth routes (those driven, when known) whose first
  and last map lane (the lanes found at the route's centerline, in its direction) are joined by a
  path of the lane graph (successors and lane changes across dashed lines).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.evaluation.config import EvalConfig
from hdmap_core.evaluation.cuts import configured_cuts, points_on_cuts
from hdmap_core.geometry import resample_evenly
from hdmap_core.groundtruth import GroundTruth, GTRoute
from hdmap_core.lanes.lane_graph import lane_graph, lane_route, lanes_at
from hdmap_core.lanes.model import LaneMap

__all__ = ["LaneReport", "evaluate_lanes", "route_ends", "MATCH_RADIUS_M", "SAMPLE_STEP_M"]

MATCH_RADIUS_M = 1.0
SAMPLE_STEP_M = 1.0
_DENSE_M = 0.2  # reference polylines densified to this spacing for the nearest-point search
_COS_SAME_DIRECTION = 0.7
_NEIGHBOURS = 32  # reference points within 1 m at 0.2 m spacing: ~10 per line, 2-3 lines


@dataclass(frozen=True)
class LaneReport:
    """What :func:`evaluate_lanes` measured (fractions in [0, 1], NaN where undefined)."""

    n_lanes: int
    lane_km: float
    coverage: float
    precision: float
    mean_error_m: float
    lane_count_accuracy: float
    n_cuts: int
    routes: int
    routes_routable: int
    unroutable: tuple[str, ...]

    @property
    def route_reachability(self) -> float:
        return self.routes_routable / self.routes if self.routes else float("nan")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["unroutable"] = list(self.unroutable)
        d["route_reachability"] = self.route_reachability
        return d

    def summary(self) -> str:
        return (
            f"lanes: {self.n_lanes} ({self.lane_km:.2f} km); centerline coverage {self.coverage:.1%}, "
            f"precision {self.precision:.1%}, mean error {self.mean_error_m:.3f} m; lane count right at "
            f"{self.lane_count_accuracy:.1%} of {self.n_cuts} cuts; routes routable "
            f"{self.routes_routable}/{self.routes}"
        )


def evaluate_lanes(
    lane_map: LaneMap, gt: GroundTruth, *, route_ids: set[str] | None = None, config: EvalConfig | None = None
) -> LaneReport:
    """Score ``lane_map`` against ``gt`` (module docstring). ``route_ids``: the routes driven
    (all routes when None)."""
    config = config or EvalConfig()
    routes = [r for r in gt.routes if route_ids is None or r.id in route_ids]
    route_lanes = sorted({lid for r in gt.routes for lid in r.lanes})
    gt_ref = [gt.lanes[lid].centerline for lid in route_lanes]
    gt_all = [ln.centerline for ln in gt.lanes.values()]
    map_lines = [ln.centerline for ln in lane_map.lanes]
    cov, err = _match(gt_ref, map_lines)
    prec, _ = _match(map_lines, gt_all)
    acc, n_cuts = _count_accuracy(lane_map, gt, config)
    graph = lane_graph(lane_map)
    bad = []
    for r, ends in zip(routes, _route_ends(lane_map, gt, routes), strict=True):
        if ends is None or lane_route(graph, *ends) is None:
            bad.append(r.id)
    return LaneReport(
        n_lanes=len(lane_map.lanes),
        lane_km=sum(ln.length_m for ln in lane_map.lanes) / 1000.0,
        coverage=cov,
        precision=prec,
        mean_error_m=err,
        lane_count_accuracy=acc,
        n_cuts=n_cuts,
        routes=len(routes),
        routes_routable=len(routes) - len(bad),
        unroutable=tuple(bad),
    )


def route_ends(lane_map: LaneMap, gt: GroundTruth, route_id: str) -> tuple[int, int] | None:
    """The first and the last map lane along the centerline of ground-truth route ``route_id``
    (sampled every 5 m, in its direction); None when the map has no lane on the route."""
    return _route_ends(lane_map, gt, [next(r for r in gt.routes if r.id == route_id)])[0]


def _route_ends(lane_map: LaneMap, gt: GroundTruth, routes: list[GTRoute]) -> list[tuple[int, int] | None]:
    pts, yaw, owner = [], [], []
    for i, route in enumerate(routes):
        p = resample_evenly(gt.route_centerline(route), 5.0)
        d = np.diff(p, axis=0)
        pts.append(p[:-1])
        yaw.append(np.arctan2(d[:, 1], d[:, 0]))
        owner.append(np.full(len(d), i))
    if not pts:
        return []
    found = lanes_at(lane_map, np.concatenate(pts), np.concatenate(yaw))  # one spatial index for all
    own = np.concatenate(owner)
    out: list[tuple[int, int] | None] = []
    for i in range(len(routes)):
        hit = found[(own == i) & (found != 0)]
        out.append((int(hit[0]), int(hit[-1])) if len(hit) else None)
    return out


def _samples(lines: list[np.ndarray], step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``step_m`` on every polyline and their unit directions."""
    pts, dirs = [], []
    for line in lines:
        if len(line) < 2:
            continue
        p = resample_evenly(np.asarray(line, dtype=float), step_m)
        d = np.gradient(p, axis=0)
        n = np.hypot(d[:, 0], d[:, 1])
        ok = n > 1e-9
        pts.append(p[ok])
        dirs.append(d[ok] / n[ok, None])
    if not pts:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(pts), np.concatenate(dirs)


def _match(query: list[np.ndarray], reference: list[np.ndarray]) -> tuple[float, float]:
    """Share of the query lines within MATCH_RADIUS_M of a same-direction reference line, and the
    mean distance of the matched samples [m]."""
    qp, qd = _samples(query, SAMPLE_STEP_M)
    rp, rd = _samples(reference, _DENSE_M)
    if not len(qp):
        return float("nan"), float("nan")
    if not len(rp):
        return 0.0, float("nan")
    # the nearest _NEIGHBOURS reference points within the radius; other directions left out
    d, idx = cKDTree(rp).query(qp, k=_NEIGHBOURS, distance_upper_bound=MATCH_RADIUS_M)
    found = idx < len(rp)
    safe = np.where(found, idx, 0)
    same = np.einsum("qkd,qd->qk", rd[safe], qd) >= _COS_SAME_DIRECTION
    dist = np.where(found & same, d, np.inf).min(axis=1)
    ok = np.isfinite(dist)
    return float(ok.mean()), float(dist[ok].mean()) if ok.any() else float("nan")


def _count_accuracy(lane_map: LaneMap, gt: GroundTruth, config: EvalConfig) -> tuple[float, int]:
    cuts = configured_cuts(gt, config, cos_feature=_COS_SAME_DIRECTION)
    if not len(cuts):
        return float("nan"), 0
    gt_cp = points_on_cuts(cuts, [ln.centerline for ln in gt.lanes.values()], cos_min=_COS_SAME_DIRECTION)
    map_cp = points_on_cuts(cuts, [ln.centerline for ln in lane_map.lanes], cos_min=_COS_SAME_DIRECTION)
    n_gt = np.bincount(gt_cp.cut, minlength=len(cuts))
    n_map = np.bincount(map_cp.cut, minlength=len(cuts))
    return float(np.mean(n_gt == n_map)), len(cuts)
