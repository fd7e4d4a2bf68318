"""HDMap -> visualization_msgs/MarkerArray for RViz and Foxglove (pure; no rclpy needed).

One LINE_STRIP per map feature, coloured by type, in namespace ``features/<type label>``; one
LINE_LIST with the topology graph's edges (namespace ``topology``); with lanes, one LINE_STRIP per
lane centerline (namespace ``lanes``) and one LINE_LIST of the lanes' ends across (``lanes/ends``).
The array starts with a DELETEALL marker so that features gone from a new map version disappear from the display.

Message classes come from a :class:`MarkerTypes` namespace: :func:`rclpy_marker_types` for nodes,
or any classes taking keyword arguments (tests).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hdmap_core.lanes.model import LaneMap
from hdmap_core.model import FeatureType, HDMap

__all__ = ["MarkerTypes", "rclpy_marker_types", "map_to_markers", "TYPE_COLORS", "LINE_STRIP", "LINE_LIST", "DELETEALL"]

# visualization_msgs/Marker constants.
LINE_STRIP = 4
LINE_LIST = 5
ADD = 0
DELETEALL = 3

# RGBA per feature type: solid white, dashed yellow, road border red, unknown grey.
TYPE_COLORS: dict[FeatureType, tuple[float, float, float, float]] = {
    FeatureType.SOLID: (1.0, 1.0, 1.0, 1.0),
    FeatureType.DASHED: (1.0, 0.85, 0.1, 1.0),
    FeatureType.ROAD_BORDER: (0.9, 0.2, 0.2, 1.0),
    FeatureType.UNKNOWN: (0.6, 0.6, 0.6, 1.0),
}
TOPOLOGY_COLOR = (0.2, 0.6, 1.0, 0.6)
LANE_COLOR = (0.2, 0.9, 0.4, 0.8)
CHANGE_COLOR = (1.0, 0.5, 0.0, 0.9)  # a road change's zone: orange
RETIRED_COLOR = (0.8, 0.3, 0.9, 0.6)  # what it replaced: violet


@dataclass(frozen=True)
class MarkerTypes:
    """The message classes :func:`map_to_markers` builds."""

    MarkerArray: Any
    Marker: Any
    Point: Any
    ColorRGBA: Any


def rclpy_marker_types() -> MarkerTypes:
    """The rclpy classes (visualization_msgs, geometry_msgs, std_msgs)."""
    from geometry_msgs.msg import Point  # noqa: PLC0415
    from std_msgs.msg import ColorRGBA  # noqa: PLC0415
    from visualization_msgs.msg import Marker, MarkerArray  # noqa: PLC0415

    return MarkerTypes(MarkerArray=MarkerArray, Marker=Marker, Point=Point, ColorRGBA=ColorRGBA)


def _points(types: MarkerTypes, xy: np.ndarray) -> list:
    return [types.Point(x=float(x), y=float(y), z=0.0) for x, y in np.asarray(xy, dtype=float).reshape(-1, 2)]


def _marker(types: MarkerTypes, header: Any, ns: str, mid: int, mtype: int, width_m: float, rgba, pts: list) -> Any:
    m = types.Marker()
    m.header = header
    m.ns = ns
    m.id = mid
    m.type = mtype
    m.action = ADD
    m.pose.orientation.w = 1.0
    m.scale.x = float(width_m)
    r, g, b, a = rgba
    m.color = types.ColorRGBA(r=r, g=g, b=b, a=a)
    m.points = pts
    m.frame_locked = True
    return m


def map_to_markers(
    hdmap: HDMap,
    *,
    types: MarkerTypes,
    header: Any,
    line_width_m: float = 0.2,
    topology: bool = True,
    lanes: LaneMap | None = None,
    changes: Sequence[tuple[np.ndarray, Sequence[np.ndarray]]] = (),
) -> Any:
    """Markers of a map.

    Args:
        hdmap: the map (features' points (N, 2) in the map frame [m]).
        types: message classes.
        header: the std_msgs/Header every marker carries (frame id = the map frame).
        line_width_m: LINE_STRIP width [m].
        topology: also draw the topology graph's edges.
        lanes: also draw these lanes: centerlines, and a line across each lane's start and end.
        changes: road changes the map followed, each (its polygon (N, 2), the pieces it retired
            [(M, 2)]): the polygon closed in namespace ``changes/zone``, the retired pieces in
            ``changes/retired``.

    Returns:
        A MarkerArray: DELETEALL, one LINE_STRIP per feature with >= 2 points (marker id = index
        within its type namespace, since Marker.id is int32 and feature ids are uint64), then the
        topology LINE_LIST, then the lanes' centerlines and their ends, then the changes.
    """
    out = types.MarkerArray()
    clear = types.Marker()
    clear.header = header
    clear.action = DELETEALL
    markers = [clear]
    per_type: dict[FeatureType, int] = {}
    for f in hdmap.features:
        if len(f.points) < 2:
            continue
        ftype = FeatureType(int(f.type))
        mid = per_type.get(ftype, 0)
        per_type[ftype] = mid + 1
        markers.append(
            _marker(
                types,
                header,
                f"features/{ftype.label}",
                mid,
                LINE_STRIP,
                line_width_m,
                TYPE_COLORS[ftype],
                _points(types, f.points),
            )
        )
    if topology and hdmap.topology:
        pos = {n.id: np.asarray(n.position, dtype=float) for n in hdmap.topology}
        edges = [(pos[n.id], pos[s]) for n in hdmap.topology for s in n.successors if s in pos]
        if edges:
            xy = np.array([p for e in edges for p in e])
            markers.append(
                _marker(types, header, "topology", 0, LINE_LIST, line_width_m / 2, TOPOLOGY_COLOR, _points(types, xy))
            )
    if lanes is not None and lanes.lanes:
        for i, ln in enumerate(lanes.lanes):
            markers.append(
                _marker(
                    types, header, "lanes", i, LINE_STRIP, line_width_m / 2, LANE_COLOR, _points(types, ln.centerline)
                )
            )
        bounds = {b.id: b.points for b in lanes.boundaries}
        ends = [
            p
            for ln in lanes.lanes
            for k in (0, -1)
            for p in (bounds[ln.left_boundary][k], bounds[ln.right_boundary][k])
        ]
        markers.append(
            _marker(
                types, header, "lanes/ends", 0, LINE_LIST, line_width_m / 2, LANE_COLOR, _points(types, np.array(ends))
            )
        )
    n_retired = 0
    for i, (polygon, retired) in enumerate(changes):
        poly = np.asarray(polygon, dtype=float).reshape(-1, 2)
        if len(poly) >= 3:
            ring = np.vstack([poly, poly[:1]])
            markers.append(
                _marker(types, header, "changes/zone", i, LINE_STRIP, line_width_m, CHANGE_COLOR, _points(types, ring))
            )
        for pts in retired:
            if len(pts) >= 2:
                markers.append(
                    _marker(
                        types,
                        header,
                        "changes/retired",
                        n_retired,
                        LINE_STRIP,
                        line_width_m / 2,
                        RETIRED_COLOR,
                        _points(types, pts),
                    )
                )
                n_retired += 1
    out.markers = markers
    return out
