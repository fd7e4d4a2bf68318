"""map_stitcher follows road changes (docs/updates.md, "Live"): on a settled map of a fleet whose road
moved, it publishes the change on hdmap/changes (hdmap_msgs/MapChange), a new map version, the
figures on /diagnostics, and keeps the history in its store: a restart on the same store publishes
the same change again (same id) and announces nothing new."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("hdmap_msgs.msg")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from hdmap_core.live.tiles import TileConfig, tiles_of_drive  # noqa: E402
from hdmap_core.pipeline.driver import PipelineConfig, build_map  # noqa: E402
from hdmap_core.simulation.changes import parse_change  # noqa: E402
from hdmap_core.simulation.config import SimConfig  # noqa: E402
from hdmap_core.simulation.fleet import simulate_fleet  # noqa: E402
from hdmap_core.simulation.synthetic import synthetic_highway  # noqa: E402
from hdmap_ros.convert.messages import rclpy_change_class, rclpy_status_class, rclpy_types  # noqa: E402
from hdmap_ros.nodes import qos  # noqa: E402
from hdmap_ros.persistence.store import DriveStore, MapStore, segments_to_blob  # noqa: E402

from nodes_harness import wait_for  # noqa: E402

pytestmark = pytest.mark.ros

N_BEFORE, N_AFTER = 14, 4
SIM = SimConfig(
    n_drives=N_BEFORE + N_AFTER, snippet_length_min_m=1300.0, snippet_length_max_m=1500.0, direction_bias=1.0
)
CHANGE = f"shift:400-1100:1.5:fwd_lane2@{N_BEFORE}"


def _diag_values(arrays, name, since_ns=0):
    """The latest status ``name``'s key/values among arrays stamped at or after ``since_ns``."""
    for arr in reversed(arrays):
        if arr.header.stamp.sec * 1_000_000_000 + arr.header.stamp.nanosec < since_ns:
            continue
        for st in arr.status:
            if st.name == name:
                return {kv.key: kv.value for kv in st.values}
    return None


@pytest.fixture(scope="module")
def settled_state(tmp_path_factory):
    """A mapper store holding the fleet's drives and a stitcher store holding the settled map of
    every drive (the consensus map, as the stitcher has it before following changes)."""
    road = synthetic_highway("motorway", length_m=1500.0)
    fleet = simulate_fleet(road, config=SIM, seed=5, changes=[parse_change(CHANGE)])
    first = build_map(list(fleet.drives), config=PipelineConfig(), seed=0, workers=1).map
    d = tmp_path_factory.mktemp("state")
    drives = DriveStore(d / "segment_mapper.db")
    for drive in fleet.drives:
        drives.add_drive(drive, tiles_of_drive(drive, config=TileConfig()))
    drives.close()
    maps = MapStore(d / "map_stitcher.db")
    maps.put_tile((0, 0), 1, segments_to_blob([]), [])
    maps.put_map(replace(first, version=1), maps.tiles_signature())
    maps.close()
    return d, fleet


def _stitcher(ros, d):
    from hdmap_ros.nodes.map_stitcher import MapStitcher

    return ros.add(
        MapStitcher(
            context=ros.context,
            parameter_overrides=[
                Parameter("db_path", value=str(d / "map_stitcher.db")),
                Parameter("drive_db_path", value=str(d / "segment_mapper.db")),
                Parameter("diagnostics_period_s", value=0.2),
            ],
        )
    )


def test_stitcher_announces_a_change_once_and_keeps_its_history_across_a_restart(ros, settled_state):
    from hdmap_ros.nodes.change_following import CHANGES_QOS, CHANGES_TOPIC
    from hdmap_ros.nodes.map_stitcher import MAP_TOPIC

    d, fleet = settled_state
    probe = ros.node("probe")
    changes, maps, diags = [], [], []
    probe.create_subscription(rclpy_change_class(), CHANGES_TOPIC, changes.append, CHANGES_QOS)
    probe.create_subscription(rclpy_types().Map, MAP_TOPIC, maps.append, qos.LATCHED)
    probe.create_subscription(DiagnosticArray, "/diagnostics", diags.append, qos.DIAGNOSTICS)
    status = probe.create_publisher(rclpy_status_class(), "hdmap/mapper_status", qos.LATCHED)

    from hdmap_ros.convert.markers import rclpy_marker_types
    from hdmap_ros.nodes.map_publisher import MARKERS_TOPIC, MapPublisher

    markers = []
    probe.create_subscription(rclpy_marker_types().MarkerArray, MARKERS_TOPIC, markers.append, qos.LATCHED)
    ros.add(MapPublisher(context=ros.context))
    stitcher = _stitcher(ros, d)
    wait_for(lambda: maps and maps[-1].version == 1, 20, what="the stored map")
    assert not changes and not stitcher.changes_followed()  # nothing announced before the map settled
    status.publish(rclpy_status_class()(settled=True))  # the mapper settled: follow the changes
    wait_for(lambda: changes, 120, what="a MapChange")
    (c,) = changes
    after = {dr.drive_id for dr in fleet.drives[N_BEFORE:]}
    assert "geometry" in c.kinds and 0.0 < c.confidence < 1.0
    assert set(c.drive_ids) <= after and len(c.drive_ids) >= 2
    assert c.valid_from_ns == c.time_ns == c.retired_valid_to_ns and c.retired_valid_from_ns < c.time_ns
    # the change point lies after the last drive on the old road, by the first one on the new
    assert (
        min(dr.start_ns for dr in fleet.drives[N_BEFORE:])
        >= c.time_ns
        > max(dr.start_ns for dr in fleet.drives[:N_BEFORE])
    )
    assert len(c.polygon.points) >= 4 and c.tile_x and len(c.tile_x) == len(c.tile_y)
    assert len(c.place_x) == len(c.place_y) == len(c.place_side) > 0 and c.place_cell_m == 100.0
    assert c.retired and {f.id for f in c.retired} == set(c.retired_feature_ids)
    poly = np.array([[p.x, p.y] for p in c.polygon.points])
    pts = np.concatenate([[[p.x, p.y] for p in f.points] for f in c.retired])
    assert (pts >= poly.min(axis=0) - 1e-3).all() and (pts <= poly.max(axis=0) + 1e-3).all()
    # a new map version follows it, the figures are on /diagnostics, the history in the store
    wait_for(lambda: maps[-1].version == c.map_version == 2, 20, what="the map following the change")
    values = wait_for(
        lambda: (v := _diag_values(diags, "hdmap: map_stitcher")) and v.get("changes_new") == "1" and v,
        20,
        what="changes on /diagnostics",
    )
    assert values["changes_known"] == "1" and values["changes_in_map"] == "1"
    assert stitcher.changes_followed() and len(stitcher.store.changes()) == 1
    # the publisher draws the zone (closed) and the retired pieces in their own namespaces
    ns = wait_for(
        lambda: markers and (n := {m.ns for m in markers[-1].markers}) >= {"changes/zone", "changes/retired"} and n,
        20,
        what="change markers",
    )
    assert any(n.startswith("features/") for n in ns)
    zone = next(m for m in markers[-1].markers if m.ns == "changes/zone")
    assert (zone.points[0].x, zone.points[0].y) == (zone.points[-1].x, zone.points[-1].y)
    assert sum(m.ns == "changes/retired" for m in markers[-1].markers) == len(c.retired)
    ros.nodes.remove(stitcher)
    ros.executor.remove_node(stitcher)
    stitcher.destroy_node()

    # restart on the same store: the history comes back (same id, latched), nothing is new
    late = ros.node("late")
    again = []
    late.create_subscription(rclpy_change_class(), CHANGES_TOPIC, again.append, CHANGES_QOS)
    # the stopped node's last /diagnostics may still be in flight: only the restarted node's count
    restarted_ns = time.time_ns()
    stitcher = _stitcher(ros, d)
    wait_for(lambda: again, 20, what="the stored history on hdmap/changes")
    values = wait_for(
        lambda: (v := _diag_values(diags, "hdmap: map_stitcher", restarted_ns)) and "changes_known" in v and v,
        20,
        what="diagnostics after the restart",
    )
    assert [m.id for m in again] == [c.id] and again[0].map_version == c.map_version
    assert values["changes_known"] == "1" and values["changes_new"] == "0"
    assert stitcher.map.version == 2 and stitcher.changes_followed()  # the stored followed map, not re-followed


def test_a_destroyed_stitcher_does_no_more_work_on_its_closed_store(ros, tmp_path):
    """An executor spinning in another thread may still run the stitcher's timer or take a tile
    after ``destroy_node`` (a test harness, a composed process): that pass must not touch the
    closed store (it raised sqlite3.ProgrammingError in the spinner thread, which then stopped)."""
    stitcher = _stitcher(ros, tmp_path)
    ros.nodes.remove(stitcher)
    ros.executor.remove_node(stitcher)
    stitcher.destroy_node()
    stitcher.work()  # no exception: nothing to do after destroy
    stitcher._on_mapper_status(rclpy_status_class()())
