"""Lane-level ground-truth maps: the JSON format of data/maps (see its README).

A ``GroundTruth`` holds the true road features (markings and borders), the lanes with their
centerlines and links, and routes (lane sequences in driving order). The simulator drives along
routes; the evaluator uses the features and the routes' centerlines as reference lines.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hdmap_core.errors import GroundTruthError
from hdmap_core.model import FeatureType

__all__ = ["GTFeature", "GTLane", "GTRoute", "GroundTruth", "load_ground_truth", "save_ground_truth"]


@dataclass(frozen=True)
class GTFeature:
    """A true road feature. points: (N, 2) [m], ordered in driving direction."""

    id: int
    type: FeatureType
    points: np.ndarray


@dataclass(frozen=True)
class GTLane:
    """A lane piece. centerline: (N, 2) [m] in driving direction; left/right: neighbour lane ids."""

    id: str
    centerline: np.ndarray
    successors: tuple[str, ...] = ()
    predecessors: tuple[str, ...] = ()
    left: str | None = None
    right: str | None = None
    highway: bool = True
    junction: bool = False


@dataclass(frozen=True)
class GTRoute:
    """A route: lane ids in driving order; ``lane_changes[i]`` means lanes[i] -> lanes[i+1] is a
    change into the side-by-side lane (all other consecutive pairs are successor links)."""

    id: str
    lanes: tuple[str, ...]
    lane_changes: tuple[int, ...] = ()


@dataclass(frozen=True)
class GroundTruth:
    name: str
    features: tuple[GTFeature, ...]
    lanes: dict[str, GTLane]
    routes: tuple[GTRoute, ...]
    extra: dict = field(default_factory=dict, compare=False)

    def route_centerline(self, route: GTRoute) -> np.ndarray:
        """(N, 2) centerline of a route: its lanes' centerlines joined, duplicate joints removed."""
        parts = [self.lanes[lid].centerline for lid in route.lanes]
        pts = np.concatenate(parts, axis=0)
        keep = np.ones(len(pts), dtype=bool)
        keep[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-3
        return pts[keep]


def _array(points: object, what: str) -> np.ndarray:
    arr = np.asarray(points, dtype=float)
    if arr.ndim != 2 or arr.shape[1] < 2 or len(arr) < 2:
        raise GroundTruthError(f"{what}: expected a list of >= 2 [x, y] points, got shape {arr.shape}")
    return arr[:, :2].copy()


def _parse(doc: dict, source: str) -> GroundTruth:
    try:
        features = tuple(
            GTFeature(int(f["id"]), FeatureType.from_label(f["type"]), _array(f["points"], f"feature {f['id']}"))
            for f in doc["features"]
        )
        lanes = {
            str(lane["id"]): GTLane(
                id=str(lane["id"]),
                centerline=_array(lane["centerline"], f"lane {lane['id']}"),
                successors=tuple(map(str, lane.get("successors", ()))),
                predecessors=tuple(map(str, lane.get("predecessors", ()))),
                left=lane.get("left"),
                right=lane.get("right"),
                highway=bool(lane.get("highway", True)),
                junction=bool(lane.get("junction", False)),
            )
            for lane in doc["lanes"]
        }
        routes = tuple(
            GTRoute(str(r["id"]), tuple(map(str, r["lanes"])), tuple(int(i) for i in r.get("lane_changes", ())))
            for r in doc["routes"]
        )
    except (KeyError, TypeError, ValueError) as err:
        raise GroundTruthError(f"{source}: not a ground-truth map ({err!r})") from err
    for r in routes:
        missing = [lid for lid in r.lanes if lid not in lanes]
        if missing:
            raise GroundTruthError(f"{source}: route {r.id} names unknown lanes {missing[:3]}")
    extra = {k: doc[k] for k in ("source", "frame", "geo_reference") if k in doc}
    return GroundTruth(str(doc.get("name", Path(source).stem)), features, lanes, routes, extra)


def load_ground_truth(path: str | Path) -> GroundTruth:
    """Read a ``*.gt.json`` file.

    Raises:
        GroundTruthError: the file is missing, not JSON, or not of the documented format.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise GroundTruthError(f"cannot read ground truth {path}: {err}") from err
    return _parse(doc, str(path))


def ground_truth_to_dict(gt: GroundTruth) -> dict:
    """The JSON document of ``gt`` in the data/maps format."""
    return {
        "name": gt.name,
        **gt.extra,
        "features": [{"id": f.id, "type": f.type.label, "points": np.round(f.points, 3).tolist()} for f in gt.features],
        "lanes": [
            {
                "id": lane.id,
                "centerline": np.round(lane.centerline, 3).tolist(),
                "successors": list(lane.successors),
                "predecessors": list(lane.predecessors),
                "left": lane.left,
                "right": lane.right,
                "highway": lane.highway,
                "junction": lane.junction,
            }
            for lane in gt.lanes.values()
        ],
        "routes": [{"id": r.id, "lanes": list(r.lanes), "lane_changes": list(r.lane_changes)} for r in gt.routes],
    }


def save_ground_truth(gt: GroundTruth, path: str | Path) -> None:
    """Write ``gt`` as JSON in the data/maps format."""
    Path(path).write_text(json.dumps(ground_truth_to_dict(gt)))
