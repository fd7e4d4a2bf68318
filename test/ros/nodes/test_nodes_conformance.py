"""ROS conformance of the nodes, through the same services the ros2 CLI uses: parameter dump
(get/list/describe), run-time set with validation, read-only parameters, an integer for a float
(`rate:=10`), misspelt keys, one-line parameter errors, namespaces, the origin across QoS, state
under ROS_HOME, diagnostics names, the QoS recorded in bags."""

from __future__ import annotations

import subprocess
import sys

import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("hdmap_msgs.msg")

from rcl_interfaces.srv import DescribeParameters, GetParameters, ListParameters, SetParameters  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from hdmap_ros.nodes import qos  # noqa: E402

from nodes_harness import ROOT, dds_env, wait_for  # noqa: E402

pytestmark = pytest.mark.ros


def _call(ros, node_name, srv_type, suffix, request):
    client = ros.node("cli").create_client(srv_type, f"/{node_name}/{suffix}")
    assert client.wait_for_service(timeout_sec=10), suffix
    future = client.call_async(request)
    return wait_for(lambda: future.done() and future, 10, what=suffix).result()


def test_param_dump_is_complete_and_described(ros, tmp_path):
    """`ros2 param dump /segment_mapper` printed {}: preset_overrides had a type and no value."""
    from hdmap_ros.nodes.segment_mapper import SegmentMapper

    ros.add(
        SegmentMapper(context=ros.context, parameter_overrides=[Parameter("db_path", value=str(tmp_path / "m.db"))])
    )
    names = _call(ros, "segment_mapper", ListParameters, "list_parameters", ListParameters.Request()).result.names
    assert {"preset", "preset_overrides", "tile_size_m", "settle_after_s", "db_path"} <= set(names)
    values = _call(
        ros, "segment_mapper", GetParameters, "get_parameters", GetParameters.Request(names=list(names))
    ).values
    assert len(values) == len(names)  # all of them, not an empty answer
    got = dict(zip(names, values))
    assert got["tile_size_m"].double_value == 256.0 and got["preset"].string_value == "default"
    desc = _call(
        ros,
        "segment_mapper",
        DescribeParameters,
        "describe_parameters",
        DescribeParameters.Request(names=["tile_size_m", "settle_after_s"]),
    ).descriptors
    assert desc[0].read_only and desc[0].description and desc[0].floating_point_range
    assert not desc[1].read_only and desc[1].floating_point_range[0].to_value == 3600.0


def test_run_time_parameters_are_validated_and_applied(ros, tmp_path):
    from hdmap_ros.nodes.segment_mapper import SegmentMapper

    mapper = ros.add(
        SegmentMapper(context=ros.context, parameter_overrides=[Parameter("db_path", value=str(tmp_path / "m.db"))])
    )

    def set_(name, value):
        req = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
        return _call(ros, "segment_mapper", SetParameters, "set_parameters", req).results[0]

    assert set_("settle_after_s", 7.5).successful and mapper.settle_after_s == 7.5
    assert set_("settle_after_s", 9).successful and mapper.settle_after_s == 9.0  # an integer for a float
    bad = set_("settle_after_s", -1.0)
    assert not bad.successful and mapper.settle_after_s == 9.0
    ro = set_("tile_size_m", 512.0)
    assert not ro.successful and "read-only" in ro.reason and mapper.tile_config.tile_size_m == 256.0


def test_an_integer_for_a_float_and_a_misspelt_key(ros):
    """`ros2 launch ... rate:=10` crashed bag_player (INTEGER vs DOUBLE); a misspelt key was silent."""
    from hdmap_ros.nodes._common import warn_unknown_parameters
    from hdmap_ros.nodes.bag_player import BagPlayer

    player = BagPlayer(
        context=ros.context, parameter_overrides=[Parameter("rate", value=10), Parameter("rat", value=2.0)]
    )
    try:
        assert player.rate == 10.0 and isinstance(player.rate, float)
        assert warn_unknown_parameters(player) == ["rat"]
    finally:
        player.destroy_node()


@pytest.mark.slow
def test_an_out_of_range_value_is_one_line(tmp_path):
    env = dds_env(74)
    env["ROS_HOME"] = str(tmp_path)
    res = subprocess.run(
        [sys.executable, "-m", "hdmap_ros.nodes.segment_mapper", "--ros-args", "-p", "tile_size_m:=1.0"],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert "tile_size_m" in lines[0] and "Traceback" not in res.stderr


def test_a_namespace_moves_every_topic(ros, tmp_path):
    from hdmap_ros.nodes.drive_ingestor import DriveIngestor
    from hdmap_ros.nodes.map_publisher import MapPublisher
    from hdmap_ros.nodes.segment_mapper import SegmentMapper

    nodes = [
        ros.add(DriveIngestor(context=ros.context, namespace="/ns2")),
        ros.add(
            SegmentMapper(
                context=ros.context,
                namespace="/ns2",
                parameter_overrides=[Parameter("db_path", value=str(tmp_path / "m.db"))],
            )
        ),
        ros.add(MapPublisher(context=ros.context, namespace="/ns2")),
    ]
    topics = set()
    for n in nodes:
        for fn in (n.get_publisher_names_and_types_by_node, n.get_subscriber_names_and_types_by_node):
            topics |= {t for t, _ in fn(n.get_name(), n.get_namespace())}
    ours = {t for t in topics if t != "/diagnostics" and not t.startswith(("/rosout", "/parameter_events"))}
    ours = {t for t in ours if not t.endswith(("/rosout", "/parameter_events"))}
    assert {
        "/ns2/fleet/drives",
        "/ns2/hdmap/drives_accepted",
        "/ns2/hdmap/segments",
        "/ns2/hdmap/map",
        "/ns2/hdmap/markers",
        "/ns2/fleet/origin",
    } <= ours
    assert all(t.startswith("/ns2/") for t in ours), ours
    services = {s for s, _ in nodes[2].get_service_names_and_types_by_node("map_publisher", "/ns2")}
    assert "/ns2/hdmap/save_map" in services


def test_the_origin_reaches_the_map_publisher_from_a_volatile_publisher(ros):
    """Stock `ros2 bag play` of a bag without recorded QoS offers VOLATILE; the subscription was
    TRANSIENT_LOCAL and never matched it."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import NavSatFix

    from hdmap_ros.nodes.map_publisher import MapPublisher

    pub_node = MapPublisher(context=ros.context)
    ros.add(pub_node)
    volatile = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    pub = ros.node("player").create_publisher(NavSatFix, "/fleet/origin", volatile)
    wait_for(lambda: pub.get_subscription_count() > 0, 10, what="a matched subscription")
    fix = NavSatFix(latitude=48.0, longitude=11.0, altitude=500.0)
    fix.status.status = 0  # STATUS_FIX (the default, -2, is no fix)

    def sent_and_got():  # VOLATILE: what is sent before the reader's side matched is lost; send again
        pub.publish(fix)
        return pub_node.origin is not None

    wait_for(sent_and_got, 10, what="the origin", poll=0.2)
    assert pub_node.origin.latitude_deg == 48.0


def test_bag_player_offers_the_latched_origin_from_its_start(ros, tmp_path):
    from hdmap_ros.io.bagio import write_fleet_bag
    from hdmap_ros.nodes.bag_player import BagPlayer

    from hostile_bags import ORIGIN, small_drives

    bag = write_fleet_bag(tmp_path / "fleet", small_drives(2), ORIGIN)
    player = ros.add(
        BagPlayer(
            context=ros.context,
            parameter_overrides=[Parameter("bag", value=str(bag)), Parameter("wait_for_subscribers_s", value=600.0)],
        )
    )
    probe = ros.node("probe")
    # before any message was played: the latched publisher is there to match
    wait_for(lambda: probe.count_publishers("/fleet/origin") == 1, 10, what="the origin publisher")
    assert player.published == 0


def test_state_paths_honour_ros_home(monkeypatch, tmp_path):
    from hdmap_ros.nodes._common import state_path

    monkeypatch.setenv("ROS_HOME", str(tmp_path / "rh"))
    assert state_path("", "segment_mapper.db") == str(tmp_path / "rh" / "hdmap" / "segment_mapper.db")
    monkeypatch.delenv("ROS_HOME")
    assert state_path("", "x.db").endswith("/.ros/hdmap/x.db")
    assert state_path("/data/m.db", "x.db") == "/data/m.db"


def test_diagnostics_name_what_each_node_counts():
    from hdmap_ros.nodes.diagnostics import Health

    keys = {k for k, _ in Health(name="hdmap: map_publisher", item="maps").key_values()}
    assert {"maps_accepted", "maps_rejected"} <= keys and "drives_accepted" not in keys


def test_bags_record_offered_qos(tmp_path):
    import yaml

    from hdmap_ros.io.bagio import write_fleet_bag

    from hostile_bags import ORIGIN, small_drives

    bag = write_fleet_bag(tmp_path / "fleet", small_drives(1), ORIGIN)
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    qos_of = {
        t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
        for t in meta["topics_with_message_count"]
    }
    origin_qos = qos_of["/fleet/origin"]
    origin_qos = yaml.safe_load(origin_qos) if isinstance(origin_qos, str) else origin_qos
    assert origin_qos[0]["durability"] in ("transient_local", 1)
    assert qos_of["/fleet/drives"]


def test_origin_is_subscribed_latched_and_live():
    from rclpy.qos import DurabilityPolicy

    assert qos.ORIGIN_LIVE.durability == DurabilityPolicy.VOLATILE
    assert qos.LATCHED.durability == DurabilityPolicy.TRANSIENT_LOCAL


@pytest.mark.slow
def test_a_yaml_value_out_of_range_is_one_line_and_a_misspelt_key_a_warning(tmp_path):
    env = dds_env(74)
    env["ROS_HOME"] = str(tmp_path)
    bad = tmp_path / "bad.yaml"
    bad.write_text("/**/drive_ingestor:\n  ros__parameters:\n    rdp_epsilon_m: 50.0\n")
    res = subprocess.run(
        [sys.executable, "-m", "hdmap_ros.nodes.drive_ingestor", "--ros-args", "--params-file", str(bad)],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1 and "rdp_epsilon_m" in lines[0], res.stderr
    typo = tmp_path / "typo.yaml"
    typo.write_text("/**/bag_player:\n  ros__parameters:\n    rat: 2.0\n")
    res = subprocess.run(  # an empty bag name: the player says so and ends at once
        [
            sys.executable,
            "-m",
            "hdmap_ros.nodes.bag_player",
            "--ros-args",
            "--params-file",
            str(typo),
            "-p",
            "linger_s:=0.0",
        ],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert "parameter 'rat' is not a parameter of bag_player" in res.stderr, res.stderr


@pytest.mark.slow
def test_the_origin_reaches_a_reader_in_another_process_after_the_bag(ros, tmp_path):
    """The player in its own process plays a short bag and ends; a reader that matches while it
    lingers still gets the latched origin (it used to exit before late readers matched)."""
    from sensor_msgs.msg import NavSatFix

    from hdmap_ros.io.bagio import write_fleet_bag

    from hostile_bags import ORIGIN, small_drives

    bag = write_fleet_bag(tmp_path / "fleet", small_drives(2), ORIGIN)
    env = dds_env(ros.domain_id)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "hdmap_ros.nodes.bag_player",
            "--ros-args",
            "-p",
            f"bag:={bag}",
            "-p",
            "wait_for_subscribers_s:=0.0",
            "-p",
            "rate:=0",
            "-p",
            "linger_s:=5.0",
        ],
        env=env,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        got = []
        ros.node("late").create_subscription(NavSatFix, "/fleet/origin", got.append, qos.LATCHED)
        wait_for(lambda: got, 20, what="the latched origin from the other process")
        assert got[0].latitude == ORIGIN.latitude_deg
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
