"""Lanelet2 / Autoware map directory: ``lanelet2_map.osm`` and ``map_projector_info.yaml``.

The lanes of :func:`hdmap_core.lanes.derive.derive_lanes` become lanelets (``type=lanelet``,
``subtype=road``, ``location=nonurban``, ``one_way=yes``); their boundary pieces become ways
(``type=line_thin`` with ``subtype=solid|dashed``, or ``type=road_border``), one way per piece,
shared by the lanelets on both sides, so a lane change crosses one dashed way. Consecutive
lanelets share the end nodes of both bounds, so Lanelet2's routing finds successors, splits and
merges.

Georeferencing: ``map_projector_info.yaml`` says ``projector_type: LocalCartesian`` with the map
frame's WGS84 origin (``/fleet/origin``); node ``lat``/``lon``/``ele`` come from the same
geodetic conversion as the GeoJSON export (the map frame is the ENU tangent plane at the origin,
``ele`` its ellipsoidal height), so Lanelet2's LocalCartesian projector gives back the map frame's
x/y (and z = 0) to well below a millimetre.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from hdmap_core.geometry import rdp_mask_many
from hdmap_core.lanes.derive import derive_lanes
from hdmap_core.lanes.drivepath import trajectory_lanes
from hdmap_core.lanes.model import Boundary, LaneMap
from hdmap_core.model import FeatureType, GeoOrigin, HDMap
from hdmap_ros.io.geojson import enu_to_geodetic

__all__ = ["write_lanelet2", "export_lanelet2", "MAP_FILE", "PROJECTOR_FILE", "THIN_TOLERANCE_M"]

MAP_FILE = "lanelet2_map.osm"
PROJECTOR_FILE = "map_projector_info.yaml"
THIN_TOLERANCE_M = 0.02  # boundary points closer than this to the thinned line are left out
_DECIMALS = 10  # degrees: 1e-10 deg is about 0.01 mm


def write_lanelet2(lane_map: LaneMap, origin: GeoOrigin, directory: str | Path) -> Path:
    """Write the Autoware map directory ``directory`` (created if missing); returns it.

    Lanelets whose two bounds do not span at least two distinct nodes each are left out.
    """
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    (out / MAP_FILE).write_text(_osm(lane_map, origin))
    (out / PROJECTOR_FILE).write_text(
        "projector_type: LocalCartesian\n"
        "vertical_datum: WGS84\n"
        "map_origin:\n"
        f"  latitude: {origin.latitude_deg!r}\n"
        f"  longitude: {origin.longitude_deg!r}\n"
        f"  altitude: {origin.altitude_m!r}\n"
    )
    return out


def export_lanelet2(
    hdmap: HDMap, origin: GeoOrigin, directory: str | Path, *, trajectories: Sequence[np.ndarray] = ()
) -> str:
    """Derive the lanes of ``hdmap`` (with connectors from the drives' (N, 2) ``trajectories``
    where the lanes lack a connection, :mod:`hdmap_core.lanes.connectors`, and drive-path lanes,
    :mod:`hdmap_core.lanes.drivepath`) and write them to
    ``directory``; returns a one-line note."""
    t0 = time.perf_counter()
    lanes = derive_lanes(hdmap)
    n = len(lanes.lanes)
    if len(trajectories):
        lanes = trajectory_lanes(lanes, trajectories)
    out = write_lanelet2(lanes, origin, directory)
    km = sum(ln.length_m for ln in lanes.lanes) / 1000.0
    extra = f", {len(lanes.lanes) - n} connectors from {len(trajectories)} drives" if len(trajectories) else ""
    return f"wrote {out}: {len(lanes.lanes)} lanelets ({km:.2f} km{extra}) in {time.perf_counter() - t0:.2f} s"


def _osm(lane_map: LaneMap, origin: GeoOrigin) -> str:
    bounds = {b.id: b for b in lane_map.boundaries}
    used = sorted({i for ln in lane_map.lanes for i in (ln.left_boundary, ln.right_boundary)})
    pieces = [bounds[i] for i in used]
    thinned = _thin([b.points for b in pieces])
    # node ids: the shared end nodes first (sorted by their stable id), then the inner points
    end_ids = sorted({n for b in pieces for n in (b.start_node, b.end_node)})
    node_no = {n: i + 1 for i, n in enumerate(end_ids)}
    nodes = lane_map.nodes or {}
    xy: list[np.ndarray] = [np.asarray(nodes[n], dtype=float).reshape(1, 2) for n in end_ids]
    next_id = len(end_ids) + 1
    way_nodes: dict[int, list[int]] = {}
    for b, pts in zip(pieces, thinned, strict=True):
        inner = pts[1:-1]
        ids = [node_no[b.start_node], *range(next_id, next_id + len(inner)), node_no[b.end_node]]
        next_id += len(inner)
        xy.append(inner)
        way_nodes[b.id] = ids
    allxy = np.concatenate(xy) if xy else np.zeros((0, 2))
    geo = enu_to_geodetic(allxy, origin)
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', '<osm version="0.6" generator="hdmap">']
    for i, (lon, lat, h) in enumerate(geo, start=1):
        lines.append(
            f'  <node id="{i}" lat="{lat:.{_DECIMALS}f}" lon="{lon:.{_DECIMALS}f}" version="1">'
            f'<tag k="ele" v="{h:.4f}"/></node>'
        )
    way_no: dict[int, int] = {}
    for b in pieces:
        ids = way_nodes[b.id]
        if len(set(ids)) < 2:
            continue
        way_no[b.id] = next_id
        refs = "".join(f'<nd ref="{n}"/>' for n in ids)
        source = (
            '<tag k="hdmap:inferred" v="yes"/>' if b.inferred else f'<tag k="hdmap:feature_id" v="{b.feature_id}"/>'
        )
        lines.append(f'  <way id="{next_id}" version="1">{refs}{_line_tags(b)}{source}</way>')
        next_id += 1
    for ln in lane_map.lanes:
        if ln.left_boundary not in way_no or ln.right_boundary not in way_no:
            continue
        lines.append(
            f'  <relation id="{next_id}" version="1">'
            f'<member type="way" ref="{way_no[ln.left_boundary]}" role="left"/>'
            f'<member type="way" ref="{way_no[ln.right_boundary]}" role="right"/>'
            '<tag k="type" v="lanelet"/><tag k="subtype" v="road"/><tag k="location" v="nonurban"/>'
            f'<tag k="one_way" v="yes"/><tag k="hdmap:lane_id" v={quoteattr(str(ln.id))}/></relation>'
        )
        next_id += 1
    lines.append("</osm>")
    return "\n".join(lines) + "\n"


def _line_tags(b: Boundary) -> str:
    if b.type == FeatureType.UNKNOWN:  # a connector across a junction: no line in the map
        return '<tag k="type" v="virtual"/>'
    if b.type == FeatureType.ROAD_BORDER:
        return '<tag k="type" v="road_border"/>'
    subtype = "dashed" if b.type == FeatureType.DASHED else "solid"
    return f'<tag k="type" v="line_thin"/><tag k="subtype" v="{subtype}"/>'


def _thin(polylines: list[np.ndarray]) -> list[np.ndarray]:
    """Ramer-Douglas-Peucker on every piece at once (end points kept)."""
    if not polylines:
        return []
    sizes = np.array([len(p) for p in polylines])
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    allpts = np.concatenate(polylines)
    keep = rdp_mask_many(allpts, starts, THIN_TOLERANCE_M)
    return [allpts[s : s + n][keep[s : s + n]] for s, n in zip(starts, sizes, strict=True)]
