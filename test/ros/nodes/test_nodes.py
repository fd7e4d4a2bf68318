"""Node tests over real DDS (Fast DDS on loopback, an own ROS_DOMAIN_ID per test).

Quick ones: the ingestor's validation and diagnostics, the bag player, the map publisher's markers
and save service, parameter declarations. The end-to-end ones (whole suite on a bag, late joiner,
SIGKILL/restart) are in test_nodes_e2e.py and marked slow.
"""

from __future__ import annotations

from concurrent.futures import Future

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("hdmap_msgs.msg")

from dataclasses import replace  # noqa: E402

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from hdmap_core.model import GeoOrigin  # noqa: E402
from hdmap_ros.convert.messages import drive_to_msg, map_to_msg, msg_to_drive, rclpy_types  # noqa: E402
from hdmap_ros.io.bagio import read_map_bag, write_fleet_bag  # noqa: E402
from hdmap_ros.nodes import qos  # noqa: E402

from bag_samples import make_drive, make_map  # noqa: E402
from nodes_harness import wait_for  # noqa: E402

pytestmark = pytest.mark.ros


def _collect(node, msg_type, topic, profile):
    got = []
    node.create_subscription(msg_type, topic, got.append, profile)
    return got


def _diag_values(arrays, name):
    """Key/values of the latest status called ``name``."""
    for arr in reversed(arrays):
        for st in arr.status:
            if st.name == name:
                return {kv.key: kv.value for kv in st.values}
    return None


def test_ingestor_rejects_malformed_drives_and_stays_up(ros):
    from hdmap_ros.nodes.drive_ingestor import DriveIngestor

    ing = ros.add(
        DriveIngestor(context=ros.context, parameter_overrides=[Parameter("diagnostics_period_s", value=0.2)])
    )
    t = rclpy_types()
    probe = ros.node("probe")
    accepted = _collect(probe, t.Drive, "/hdmap/drives_accepted", qos.replay(100))
    diags = _collect(probe, DiagnosticArray, "/diagnostics", qos.DIAGNOSTICS)
    pub = probe.create_publisher(t.Drive, "/fleet/drives", qos.DRIVES)
    wait_for(lambda: pub.get_subscription_count() > 0, 10, what="ingestor subscription")

    good = make_drive("good", n=40)
    nan = make_drive("nan", n=40)
    nan.xy[5, 0] = np.nan
    short = replace(make_drive("short"), xy=np.zeros((1, 2)), yaw=np.zeros(1), stamps_ns=np.zeros(1, np.int64))
    wrong = replace(make_drive("wrong"), frame_id="odom")
    for d in (good, nan, short, wrong, good, make_drive("good2", n=30)):
        pub.publish(drive_to_msg(d, types=t))

    wait_for(lambda: len(accepted) >= 2, 10, what="two accepted drives")
    vals = wait_for(
        # both counts: the last rejection (the duplicate) comes before good2 is accepted
        lambda: (
            (v := _diag_values(diags, "hdmap: drive_ingestor"))
            and v["drives_rejected"] == "4"
            and v["drives_accepted"] == "2"
            and v
        ),
        10,
        what="diagnostics with 4 rejections and 2 drives accepted",
    )
    assert [m.drive_id for m in accepted] == ["good", "good2"]
    assert vals["drives_accepted"] == "2"
    assert vals["rejected.non_finite_coordinates"] == "1"
    assert vals["rejected.too_few_points"] == "1"
    assert vals["rejected.wrong_frame"] == "1"
    assert vals["rejected.duplicate_drive_id"] == "1"
    # accepted drives come out cleaned: the 3-point road border (< 3 m) is gone
    back = msg_to_drive(accepted[0])
    assert len(back.detections) == 2 and len(good.detections) == 3
    assert ing.health.accepted == 2


def test_bag_player_replays_drives_in_order_and_latches_origin(ros, tmp_path):
    from hdmap_ros.nodes.bag_player import BagPlayer

    drives = [make_drive(f"d{i:02d}", n=20, seed=i, start_ns=10**18 + i * 10**8) for i in range(8)]
    bag = write_fleet_bag(tmp_path / "fleet", drives, GeoOrigin(48.0, 11.0, 500.0))
    t = rclpy_types()
    probe = ros.node("probe")
    got = _collect(probe, t.Drive, "/fleet/drives", qos.DRIVES)
    player = ros.add(
        BagPlayer(
            context=ros.context,
            parameter_overrides=[
                Parameter("bag", value=str(bag)),
                Parameter("rate", value=2.0),
                Parameter("start_offset_s", value=0.15),
            ],
        )
    )
    wait_for(lambda: player.done, 20, what="player done")
    wait_for(lambda: len(got) >= 6, 10, what="six drives")
    # offset 0.15 s skips d00 and d01 (at 0 and 0.1 s); rate 2: 0.5 s of bag in ~0.25 s
    assert [m.drive_id for m in got] == [f"d{i:02d}" for i in range(2, 8)]
    np.testing.assert_array_equal(msg_to_drive(got[0]).xy, drives[2].xy)
    late = ros.node("late")
    from sensor_msgs.msg import NavSatFix

    origin = _collect(late, NavSatFix, "/fleet/origin", qos.LATCHED)
    wait_for(lambda: origin, 10, what="latched origin for a late subscriber")
    assert origin[0].latitude == 48.0


def test_map_publisher_markers_and_save_service(ros, tmp_path):
    from visualization_msgs.msg import MarkerArray

    from hdmap_msgs.srv import SaveMap
    from hdmap_ros.nodes.map_publisher import MapPublisher

    node = ros.add(MapPublisher(context=ros.context))
    hdmap = make_map(n_features=3)
    t = rclpy_types()
    src = ros.node("source")
    map_pub = src.create_publisher(t.Map, "/hdmap/map", qos.LATCHED)
    from sensor_msgs.msg import NavSatFix, NavSatStatus

    origin_pub = src.create_publisher(NavSatFix, "/fleet/origin", qos.LATCHED)
    fix = NavSatStatus(status=NavSatStatus.STATUS_FIX)
    origin_pub.publish(NavSatFix(status=fix, latitude=48.1, longitude=11.5, altitude=520.0))
    map_pub.publish(map_to_msg(hdmap, types=t))
    wait_for(lambda: node.map is not None, 10, what="the map at the publisher")
    assert node.lanes is None  # no reader of the markers yet: nothing drawn, no lanes derived

    viewer = ros.node("viewer")  # joins after the map was published: drawn then, and latched
    markers = _collect(viewer, MarkerArray, "/hdmap/markers", qos.LATCHED)
    arr = wait_for(lambda: markers and markers[-1], 10, what="markers")
    strips = [m for m in arr.markers if m.type == 4 and m.ns.startswith("features/")]
    assert len(strips) == 3 and {m.ns for m in strips} == {"features/solid", "features/dashed", "features/road_border"}

    client = viewer.create_client(SaveMap, "/hdmap/save_map")
    assert client.wait_for_service(timeout_sec=10)
    out = tmp_path / "saved"
    resp = _call(client, SaveMap.Request(path=str(out)))
    assert resp.success, resp.message
    back = read_map_bag(out)
    assert [f.id for f in back.features] == [f.id for f in hdmap.features]
    assert (tmp_path / "saved.geojson").is_file()
    assert (tmp_path / "saved.lanelet2" / "lanelet2_map.osm").is_file()
    assert "saved.lanelet2" in resp.message
    bad = _call(client, SaveMap.Request(path=""))
    assert not bad.success and "empty" in bad.message


def _call(client, request, timeout=20.0):
    fut = client.call_async(request)
    wait_for(fut.done, timeout, what="service response")
    return fut.result()


def test_parameters_have_descriptions_ranges_and_reject_out_of_range(ros):
    from rclpy.exceptions import InvalidParameterValueException

    from hdmap_ros.nodes.drive_ingestor import DriveIngestor

    ing = ros.add(DriveIngestor(context=ros.context))
    desc = ing.describe_parameter("min_detection_length_m")
    assert desc.description and desc.floating_point_range[0].to_value == 100.0
    assert ing.get_parameter("min_detection_length_m").value == 3.0
    with pytest.raises(InvalidParameterValueException, match="rdp_epsilon_m"):
        DriveIngestor(context=ros.context, parameter_overrides=[Parameter("rdp_epsilon_m", value=50.0)])


@pytest.mark.parametrize(
    "module,cls",
    [
        ("drive_ingestor", "DriveIngestor"),
        ("segment_mapper", "SegmentMapper"),
        ("map_stitcher", "MapStitcher"),
        ("map_publisher", "MapPublisher"),
        ("bag_player", "BagPlayer"),
    ],
)
def test_config_yaml_names_only_declared_parameters(ros, tmp_path, module, cls):
    import importlib

    import yaml

    from hdmap_ros.nodes._common import params_file

    spec = yaml.safe_load(params_file().read_text())[f"/**/{module}"]["ros__parameters"]  # any namespace
    overrides = [Parameter("db_path", value=str(tmp_path / "x.db"))] if "db_path" in spec else []
    node = ros.add(
        getattr(importlib.import_module(f"hdmap_ros.nodes.{module}"), cls)(
            context=ros.context, parameter_overrides=overrides
        )
    )
    undeclared = [k for k in spec if not node.has_parameter(k)]
    assert not undeclared, f"{module}: {undeclared} in config/hdmap.yaml but not declared"
    for k, v in spec.items():  # the YAML states the declared defaults (paths aside)
        if k != "db_path":
            assert node.get_parameter(k).value == v, k


def test_bag_player_loops(ros, tmp_path):
    from hdmap_ros.nodes.bag_player import BagPlayer

    drives = [make_drive(f"L{i}", n=10, seed=i, start_ns=10**18 + i * 10**7) for i in range(3)]
    bag = write_fleet_bag(tmp_path / "fleet", drives, None)
    t = rclpy_types()
    got = _collect(ros.node("probe"), t.Drive, "/fleet/drives", qos.DRIVES)
    player = ros.add(
        BagPlayer(
            context=ros.context,
            parameter_overrides=[
                Parameter("bag", value=str(bag)),
                Parameter("rate", value=0.0),
                Parameter("loop", value=True),
            ],
        )
    )
    wait_for(lambda: len(got) >= 7, 20, what="a second pass over the bag")
    assert [m.drive_id for m in got[:7]] == ["L0", "L1", "L2", "L0", "L1", "L2", "L0"]
    assert not player.done


def test_mapper_refuses_a_store_made_with_another_tiling(ros, tmp_path):
    from hdmap_core.errors import ConfigError
    from hdmap_ros.nodes.segment_mapper import SegmentMapper

    db = Parameter("db_path", value=str(tmp_path / "m.db"))
    first = SegmentMapper(context=ros.context, parameter_overrides=[db])
    first.destroy_node()
    with pytest.raises(ConfigError, match="tile_size_m=256.0"):
        SegmentMapper(context=ros.context, parameter_overrides=[db, Parameter("tile_size_m", value=512.0)])


@pytest.mark.parametrize("module,cls", [("segment_mapper", "SegmentMapper"), ("map_stitcher", "MapStitcher")])
def test_preset_overrides_change_the_pipeline_config_and_a_bad_one_is_named(ros, tmp_path, module, cls):
    import importlib

    from hdmap_core.errors import ConfigError
    from hdmap_core.pipeline import presets

    node_cls = getattr(importlib.import_module(f"hdmap_ros.nodes.{module}"), cls)
    db = Parameter("db_path", value=str(tmp_path / "x.db"))
    plain = node_cls(context=ros.context, parameter_overrides=[db])  # not spun: only its config is read
    assert plain.pipeline_config == presets.preset("default")  # unset: the preset as it is
    plain.destroy_node()
    changed = node_cls(
        context=ros.context,
        parameter_overrides=[
            db,
            Parameter("preset_overrides", value=["stitching.max_distance_m=8", "alignment.n_iterations=2"]),
        ],
    )
    cfg = changed.pipeline_config
    changed.destroy_node()
    assert cfg.stitching.max_distance_m == 8 and cfg.alignment.n_iterations == 2 and cfg.name == "default+"
    with pytest.raises(ConfigError, match="preset_overrides: stitching.nope: StitchConfig has no field 'nope'"):
        node_cls(
            context=ros.context, parameter_overrides=[db, Parameter("preset_overrides", value=["stitching.nope=1"])]
        )
    with pytest.raises(ConfigError, match="preset_overrides: 'nokey' is not KEY=VALUE"):
        node_cls(context=ros.context, parameter_overrides=[db, Parameter("preset_overrides", value=["nokey"])])


def _unspun_stitcher(ros, tmp_path, *, debounce_s: float, max_delay_s: float):
    """A map stitcher on stores in ``tmp_path``, not spun: only the test calls its turn
    (``_work``); the caller destroys it."""
    from hdmap_ros.nodes.map_stitcher import MapStitcher

    return MapStitcher(
        context=ros.context,
        parameter_overrides=[
            Parameter("db_path", value=str(tmp_path / "s.db")),
            Parameter("drive_db_path", value=str(tmp_path / "m.db")),
            Parameter("debounce_s", value=debounce_s),
            Parameter("max_delay_s", value=max_delay_s),
        ],
    )


def test_a_restarted_stitcher_reports_its_stored_map_on_diagnostics(ros, tmp_path):
    """A stitcher restarted on a store whose map is made from every stored estimate rebuilds
    nothing, so its /diagnostics must name the stored map's version from the start (they named
    none: the e2e SIGKILL test then waited for a map version forever when the mapper had settled
    and the stitcher had every estimate before they were killed)."""
    from hdmap_ros.persistence.store import segments_to_blob

    st = _unspun_stitcher(ros, tmp_path, debounce_s=0.2, max_delay_s=0.5)
    st.store.put_tile((0, 0), 1, segments_to_blob([]), ["d"])
    st.store.put_map(replace(make_map(n_features=3), version=7), st.store.tiles_signature())
    st.destroy_node()
    st = _unspun_stitcher(ros, tmp_path, debounce_s=0.2, max_delay_s=0.5)
    try:
        kv = dict(st.health.key_values())
        assert (kv["map_version"], kv["features"]) == ("7", "3")
        assert st.is_settled()  # nothing to rebuild: the map stays version 7
    finally:
        st.destroy_node()


def test_the_stitcher_follows_road_changes_only_with_every_estimate_the_mapper_announced(ros, tmp_path, monkeypatch):
    """The mapper's status (settled, N estimates made) may come before its estimates (another
    topic; a restart republishes them): the map of the estimates here so far is not the settled
    map, and road changes are followed only once every announced estimate is in the map."""
    from hdmap_core.live.progress import LiveStatus
    from hdmap_ros.nodes import change_following
    from hdmap_ros.persistence.store import segments_to_blob

    class InProcess:  # the follow's process pool, run here: the patched read_drives is seen
        def submit(self, fn, *args, **kwargs):
            fut: Future = Future()
            fut.set_result(fn(*args, **kwargs))
            return fut

    reads: list[str] = []
    monkeypatch.setattr(change_following, "read_drives", lambda path: reads.append(str(path)) or [])
    st = _unspun_stitcher(ros, tmp_path, debounce_s=0.2, max_delay_s=0.5)
    monkeypatch.setattr(st, "_follow_pool", InProcess)
    try:
        assert st.follow_changes  # the default preset follows road changes
        st._mapper_status = LiveStatus(tile_versions=2, settled=True)  # 2 estimates made, 1 here
        st.store.put_tile((0, 0), 1, segments_to_blob([]), ["d"])
        st.rebuild()
        assert st.is_settled() and st.map.version == 1
        st._follow()
        assert reads == []  # the other estimate is on its way
        st.store.put_tile((1, 0), 1, segments_to_blob([]), ["d"])
        st.rebuild()
        st._follow()  # submits the follow
        st._follow()  # takes its result
        assert reads == [str(tmp_path / "m.db")] and st.changes_followed()
    finally:
        st.destroy_node()


def test_stitcher_waits_for_the_estimates_the_mapper_announced_and_then_rebuilds_at_once(ros, tmp_path, monkeypatch):
    """The mapper's status names more estimates than have come (the region's burst): no map of a
    part of them, even past max_delay_s; once every one is here and the mapper settled, the map is
    made at once, without waiting debounce_s."""
    import time

    from hdmap_core.live.progress import LiveStatus
    from hdmap_ros.persistence.store import segments_to_blob

    st = _unspun_stitcher(ros, tmp_path, debounce_s=0.2, max_delay_s=0.5)
    starts: list[float] = []
    monkeypatch.setattr(st, "rebuild", lambda: starts.append(time.monotonic()))
    try:
        st._mapper_status = LiveStatus(tile_versions=3, settled=True)  # 3 estimates made, 2 here
        for i in range(2):
            st.store.put_tile((i, 0), 1, segments_to_blob([]), ["d"])
        st._first_dirty = time.monotonic() - 10.0  # max_delay_s long past
        st._last_rx = time.monotonic() - 0.3  # quiet for more than debounce_s
        st._work()
        assert starts == []  # the third is on its way
        st.store.put_tile((2, 0), 1, segments_to_blob([]), ["d"])
        st._last_rx = time.monotonic()  # it just came: not quiet, yet nothing more can come
        st._work()
        assert len(starts) == 1
        # an announced estimate that never comes holds the map at most max_delay_s after the last one
        st._mapper_status = LiveStatus(tile_versions=4, settled=True)
        st._first_dirty = st._last_rx = time.monotonic() - 0.3
        st._work()
        assert len(starts) == 1
        st._last_rx = time.monotonic() - 0.6
        st._work()
        assert len(starts) == 2
    finally:
        st.destroy_node()


def test_stitcher_paces_rebuilds_while_estimates_stream_and_rebuilds_at_once_when_quiet(ros, tmp_path, monkeypatch):
    """While estimates keep coming (never a quiet debounce_s), a rebuild forced by max_delay_s
    waits at least as long as the last rebuild took (REBUILD_SHARE 0.5); once quiet, at once."""
    import time

    from hdmap_ros.nodes.map_stitcher import REBUILD_SHARE

    assert REBUILD_SHARE == 0.5
    st = _unspun_stitcher(ros, tmp_path, debounce_s=0.5, max_delay_s=0.0)
    starts: list[float] = []

    def rebuild() -> None:  # a rebuild that takes 0.3 s
        starts.append(time.monotonic())
        time.sleep(0.3)

    monkeypatch.setattr(st, "rebuild", rebuild)
    try:
        end = time.monotonic() + 1.5
        while time.monotonic() < end:  # an estimate every 20 ms
            now = time.monotonic()
            st._last_rx = now
            if st._first_dirty is None:
                st._first_dirty = now
            st._work()
            time.sleep(0.02)
        assert len(starts) >= 2
        # each rebuild started at least 0.3 s (the last one's duration) after the last one ended
        assert all(b - a >= 0.6 - 1e-3 for a, b in zip(starts, starts[1:]))
        n = len(starts)
        st._first_dirty = st._last_rx = time.monotonic() - 0.6  # quiet for more than debounce_s
        st._rested_at = time.monotonic() + 100.0
        st._work()
        assert len(starts) == n + 1  # a quiet debounce rebuilds at once, paced or not
    finally:
        st.destroy_node()
