"""RFC 7946 GeoJSON export of a map, georeferenced through the map frame's WGS84 origin.

Georeferencing: the map frame is the local east-north-up tangent plane at the origin (as
hdmap_msgs/Drive.msg says), so map coordinates (x east, y north, z = 0) are converted exactly back
to WGS84 with PROJ's topocentric conversion: ENU -> ECEF (``+inv +proj=topocentric``) -> geodetic
(``+inv +proj=cart``). On the tangent plane a point 10 km from the origin lies about 8 m above the
ellipsoid; its geodetic position is taken along the ellipsoid normal, which differs from a
transverse-Mercator reading of the same x/y by less than 1 cm within 10 km.

Coordinates are [longitude, latitude] in degrees rounded to 8 decimals (about 1 mm), no altitude.
Ids are uint64 and exceed JavaScript's exact integers (2**53), so they are written as decimal strings.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import Transformer

from hdmap_core.errors import InvalidMessageError
from hdmap_core.lanes.model import Lane, LaneMap
from hdmap_core.model import FeatureType, GeoOrigin, HDMap, MapFeature, TopologyNode

__all__ = ["enu_to_lonlat", "enu_to_geodetic", "map_to_geojson", "write_geojson", "COORD_DECIMALS"]

COORD_DECIMALS = 8


def _transformer(origin: GeoOrigin) -> Transformer:
    lat, lon, h = origin.latitude_deg, origin.longitude_deg, origin.altitude_m
    if not (np.isfinite(lat) and np.isfinite(lon) and np.isfinite(h)) or abs(lat) > 90 or abs(lon) > 180:
        raise InvalidMessageError(f"origin ({lat}, {lon}, {h}) is not a valid WGS84 position")
    pipeline = (
        "+proj=pipeline"
        f" +step +inv +proj=topocentric +ellps=WGS84 +lat_0={lat!r} +lon_0={lon!r} +h_0={h!r}"
        " +step +inv +proj=cart +ellps=WGS84"
        " +step +proj=unitconvert +xy_in=rad +xy_out=deg"
    )
    return Transformer.from_pipeline(pipeline)


def enu_to_lonlat(xy: np.ndarray, origin: GeoOrigin) -> np.ndarray:
    """(N, 2) map-frame east/north [m] on the tangent plane -> (N, 2) WGS84 [lon, lat] [deg]."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    lon, lat, _h = _transformer(origin).transform(xy[:, 0], xy[:, 1], np.zeros(len(xy)))
    return np.stack([np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64)], axis=1)


def enu_to_geodetic(xy: np.ndarray, origin: GeoOrigin) -> np.ndarray:
    """(N, 2) map-frame east/north [m] on the tangent plane (z = 0) -> (N, 3) WGS84 [lon, lat]
    [deg] and ellipsoidal height [m] (the height of the tangent plane there)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    lon, lat, h = _transformer(origin).transform(xy[:, 0], xy[:, 1], np.zeros(len(xy)))
    return np.stack([np.asarray(v, dtype=np.float64) for v in (lon, lat, h)], axis=1)


def _coords(lonlat: np.ndarray) -> list[list[float]]:
    return np.round(lonlat, COORD_DECIMALS).tolist()


def _feature_json(f: MapFeature, lonlat: np.ndarray) -> dict[str, Any]:
    counts = np.asarray(f.drive_count, dtype=np.int64)
    std = np.asarray(f.lateral_std, dtype=np.float64)
    return {
        "type": "Feature",
        "id": str(int(f.id)),
        "geometry": {"type": "LineString", "coordinates": _coords(lonlat)},
        "properties": {
            "kind": "road_feature",
            "id": str(int(f.id)),
            "type": f.type.label,
            "drive_count": counts.tolist(),
            "drive_count_min": int(counts.min()) if counts.size else 0,
            "drive_count_mean": round(float(counts.mean()), 3) if counts.size else 0.0,
            "lateral_std": np.round(std, 4).tolist(),
            "lateral_std_mean": round(float(std.mean()), 4) if std.size else None,
            "predecessors": [str(int(i)) for i in f.predecessors],
            "successors": [str(int(i)) for i in f.successors],
        },
    }


def _node_json(n: TopologyNode, lonlat: np.ndarray) -> dict[str, Any]:
    return {
        "type": "Feature",
        "id": str(int(n.id)),
        "geometry": {"type": "Point", "coordinates": _coords(lonlat)[0]},
        "properties": {
            "kind": "topology_node",
            "id": str(int(n.id)),
            "heading_rad": round(float(n.heading), 6),
            "width_m": round(float(n.width), 3),
            "successors": [str(int(i)) for i in n.successors],
            "features": [str(int(i)) for i in n.features],
        },
    }


def _lane_json(lane: Lane, lonlat: np.ndarray) -> dict[str, Any]:
    ring = _coords(lonlat)
    ring.append(ring[0])
    return {
        "type": "Feature",
        "id": str(int(lane.id)),
        "geometry": {"type": "Polygon", "coordinates": [ring]},
        "properties": {
            "kind": "lane",
            "id": str(int(lane.id)),
            "left_feature": str(int(lane.left_feature)),
            "right_feature": str(int(lane.right_feature)),
            "left_type": lane.left_type.label,
            "right_type": lane.right_type.label,
            "width_mean_m": round(float(np.mean(lane.width)), 3) if len(lane.width) else None,
            "length_m": round(lane.length_m, 3),
            "successors": [str(int(i)) for i in lane.successors],
            "predecessors": [str(int(i)) for i in lane.predecessors],
            "left": str(int(lane.left)) if lane.left is not None else None,
            "right": str(int(lane.right)) if lane.right is not None else None,
        },
    }


def _retired_json(r: Any, lonlat: np.ndarray) -> dict[str, Any]:
    return {
        "type": "Feature",
        "geometry": {"type": "LineString", "coordinates": _coords(lonlat)},
        "properties": {
            "kind": "retired",
            "feature_id": str(int(r.feature_id)),
            "type": FeatureType(int(r.type)).label,
            "change_id": str(int(r.change_id)),
            "valid_from_ns": int(r.valid_from_ns),
            "valid_to_ns": int(r.valid_to_ns),
        },
    }


def map_to_geojson(
    hdmap: HDMap, origin: GeoOrigin, *, include_topology: bool = False, lanes: LaneMap | None = None
) -> dict[str, Any]:
    """The map's road features as an RFC 7946 FeatureCollection of WGS84 LineStrings.

    Args:
        hdmap: the map (map-frame coordinates [m]).
        origin: WGS84 origin of the map frame.
        include_topology: also add the topology nodes as Point features (``kind`` tells them apart).
        lanes: also add these lanes (``hdmap_core.lanes.derive.derive_lanes``) as Polygon features
            (``kind: "lane"``: the left boundary forward, the right one back) with their boundary
            feature ids and types, width, length, successors, predecessors and neighbours.
        A map that followed a change of the road (``HDMap.extra["retired"]``) also has the pieces
        it replaced, ``kind`` "retired", with ``change_id``, ``valid_from_ns`` and ``valid_to_ns``.

    Returns:
        A JSON-ready dict. Each LineString has properties ``id`` (string), ``type`` (label),
        ``drive_count`` (per point) with ``drive_count_min`` / ``drive_count_mean``,
        ``lateral_std`` [m] (per point) with ``lateral_std_mean``, ``predecessors``, ``successors``.
        Foreign member ``hdmap`` holds version, frame, drive count and the origin.

    Raises:
        InvalidMessageError: the origin is not a valid WGS84 position.
    """
    features = [f for f in hdmap.features if len(f.points) >= 2]
    nodes = list(hdmap.topology) if include_topology else []
    # One vectorised transform for every point of the map.
    parts = [np.asarray(f.points, dtype=np.float64).reshape(-1, 2) for f in features]
    parts += [np.asarray(n.position, dtype=np.float64).reshape(1, 2) for n in nodes]
    lane_list = list(lanes.lanes) if lanes is not None else []
    rings = [lanes.polygon(ln) for ln in lane_list] if lanes is not None else []
    parts += rings
    retired = [r for r in hdmap.extra.get("retired", ()) if len(getattr(r, "points", ())) >= 2]
    parts += [np.asarray(r.points, dtype=np.float64).reshape(-1, 2) for r in retired]
    lonlat = enu_to_lonlat(np.concatenate(parts) if parts else np.zeros((0, 2)), origin)
    out: list[dict[str, Any]] = []
    start = 0
    for f, pts in zip(features, parts, strict=False):
        out.append(_feature_json(f, lonlat[start : start + len(pts)]))
        start += len(pts)
    for n in nodes:
        out.append(_node_json(n, lonlat[start : start + 1]))
        start += 1
    for ln, ring in zip(lane_list, rings, strict=True):
        out.append(_lane_json(ln, lonlat[start : start + len(ring)]))
        start += len(ring)
    for r in retired:  # what a change of the road replaced (hdmap_core.updates.follow)
        n_pts = len(r.points)
        out.append(_retired_json(r, lonlat[start : start + n_pts]))
        start += n_pts
    return {
        "type": "FeatureCollection",
        "features": out,
        "hdmap": {
            "version": int(hdmap.version),
            "frame_id": hdmap.frame_id,
            "n_drives": len(hdmap.drive_ids),
            "origin": {
                "latitude_deg": origin.latitude_deg,
                "longitude_deg": origin.longitude_deg,
                "altitude_m": origin.altitude_m,
            },
            "georeference": "map frame = ENU tangent plane at the origin (PROJ topocentric), WGS84",
        },
    }


def write_geojson(hdmap: HDMap, origin: GeoOrigin, path: str | Path, **options: Any) -> Path:
    """Write :func:`map_to_geojson` to ``path`` (compact JSON); returns the path."""
    path = Path(path)
    path.write_text(json.dumps(map_to_geojson(hdmap, origin, **options), separators=(",", ":")))
    return path
