"""GeoJSON export: RFC 7946 structure and georeferencing accuracy."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from pyproj import Geod

from hdmap_core.errors import InvalidMessageError
from hdmap_core.model import FeatureType, GeoOrigin, HDMap, MapFeature
from hdmap_ros.io.geojson import enu_to_lonlat, map_to_geojson, write_geojson

from bag_samples import make_map

WGS84_A = 6378137.0
WGS84_E2 = 6.69437999014e-3


def _prime_vertical_radius(lat_deg: float) -> float:
    s = math.sin(math.radians(lat_deg))
    return WGS84_A / math.sqrt(1.0 - WGS84_E2 * s * s)


@pytest.mark.parametrize("origin", [GeoOrigin(48.137154, 11.576124, 0.0), GeoOrigin(-33.9, 151.2, 0.0)])
def test_100_m_east_is_100_m_on_the_ellipsoid(origin):
    ((lon, lat),) = enu_to_lonlat(np.array([[100.0, 0.0]]), origin)
    az, _, dist = Geod(ellps="WGS84").inv(origin.longitude_deg, origin.latitude_deg, lon, lat)
    assert dist == pytest.approx(100.0, abs=0.01)
    assert az == pytest.approx(90.0, abs=1e-3)
    # independent check: an arc of the parallel circle, radius N cos(lat)
    dlon = math.degrees(
        100.0 / (_prime_vertical_radius(origin.latitude_deg) * math.cos(math.radians(origin.latitude_deg)))
    )
    metres_per_deg = 100.0 / dlon
    assert (lon - origin.longitude_deg - dlon) * metres_per_deg == pytest.approx(0.0, abs=0.01)


def test_origin_altitude_is_respected():
    # The tangent plane lies at the origin's altitude: 100 m there spans a slightly smaller angle.
    origin = GeoOrigin(48.0, 11.0, 500.0)
    ((lon, _lat),) = enu_to_lonlat(np.array([[100.0, 0.0]]), origin)
    radius = (_prime_vertical_radius(48.0) + 500.0) * math.cos(math.radians(48.0))
    expected = 11.0 + math.degrees(100.0 / radius)
    assert (lon - expected) * 100.0 / (expected - 11.0) == pytest.approx(0.0, abs=0.01)


def test_north_and_origin_points():
    origin = GeoOrigin(10.0, 20.0, 0.0)
    ll = enu_to_lonlat(np.array([[0.0, 0.0], [0.0, 250.0]]), origin)
    np.testing.assert_allclose(ll[0], [20.0, 10.0], atol=1e-12)
    az, _, dist = Geod(ellps="WGS84").inv(20.0, 10.0, ll[1, 0], ll[1, 1])
    assert dist == pytest.approx(250.0, abs=0.01) and az == pytest.approx(0.0, abs=1e-3)


def test_feature_collection_structure(tmp_path):
    hdmap = make_map(n_features=3, n_points=6)
    origin = GeoOrigin(57.7, 11.97, 10.0)
    gj = map_to_geojson(hdmap, origin)
    assert gj["type"] == "FeatureCollection" and len(gj["features"]) == 3
    for f, feat in zip(hdmap.features, gj["features"]):
        assert feat["geometry"]["type"] == "LineString"
        coords = feat["geometry"]["coordinates"]
        assert len(coords) == len(f.points) and all(len(c) == 2 for c in coords)
        # RFC 7946: [lon, lat]; <= 8 decimals
        assert abs(coords[0][0] - 11.97) < 0.01 and abs(coords[0][1] - 57.7) < 0.01
        assert all(round(v, 8) == v for c in coords for v in c)
        props = feat["properties"]
        assert props["id"] == str(f.id) and feat["id"] == str(f.id)
        assert props["type"] == f.type.label
        assert props["drive_count"] == f.drive_count.tolist()
        assert props["drive_count_min"] == f.drive_count.min()
        assert props["drive_count_mean"] == pytest.approx(f.drive_count.mean(), abs=1e-3)
        np.testing.assert_allclose(props["lateral_std"], f.lateral_std, atol=1e-4)
        assert props["successors"] == [str(i) for i in f.successors]
    back = json.loads(write_geojson(hdmap, origin, tmp_path / "m.geojson").read_text())
    assert back == json.loads(json.dumps(gj))


def test_topology_nodes_optional_and_short_features_skipped():
    hdmap = make_map(n_features=1, n_points=4)
    stub = MapFeature(
        id=5, type=FeatureType.SOLID, points=np.zeros((1, 2)), drive_count=np.ones(1), lateral_std=np.ones(1)
    )
    hdmap = HDMap(features=hdmap.features + (stub,), topology=hdmap.topology)
    origin = GeoOrigin(0.0, 0.0, 0.0)
    assert len(map_to_geojson(hdmap, origin)["features"]) == 1
    gj = map_to_geojson(hdmap, origin, include_topology=True)
    kinds = [f["properties"]["kind"] for f in gj["features"]]
    assert kinds.count("topology_node") == len(hdmap.topology)
    node = gj["features"][1]
    assert node["geometry"]["type"] == "Point" and len(node["geometry"]["coordinates"]) == 2


def test_invalid_origin():
    with pytest.raises(InvalidMessageError, match="WGS84"):
        map_to_geojson(make_map(n_features=1), GeoOrigin(float("nan"), 0.0))


def test_retired_pieces_of_a_followed_change_are_shown_apart():
    from hdmap_core.updates.follow import RetiredFeature

    origin = GeoOrigin(48.0, 9.0, 0.0)
    feat = MapFeature(7, FeatureType.SOLID, np.array([[0.0, 0.0], [50.0, 0.0]]), np.array([3, 3]), np.array([0.1, 0.1]))
    old = RetiredFeature(5, int(FeatureType.DASHED), np.array([[0.0, 1.5], [25.0, 1.5], [50.0, 1.5]]), 99, 10, 20)
    plain = map_to_geojson(HDMap(features=(feat,)), origin)
    followed = map_to_geojson(HDMap(features=(feat,), extra={"retired": [old]}), origin)
    assert [f["properties"]["kind"] for f in plain["features"]] == ["road_feature"]
    kinds = [f["properties"]["kind"] for f in followed["features"]]
    assert kinds == ["road_feature", "retired"]
    props = followed["features"][1]["properties"]
    assert props["type"] == "dashed" and props["change_id"] == "99" and props["valid_to_ns"] == 20
    coords = np.array(followed["features"][1]["geometry"]["coordinates"])
    np.testing.assert_allclose(coords, enu_to_lonlat(old.points, origin), atol=1e-9)
