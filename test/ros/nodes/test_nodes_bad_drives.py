"""Bad drives against the live nodes: rejected with a reason, the node stays up, and a bad drive
stored by an older version never comes back from the store (real rclpy nodes, callbacks called
directly; no spinning needed)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("hdmap_msgs.msg")

from rclpy.parameter import Parameter  # noqa: E402

from hdmap_core.live.tiles import TileConfig, tiles_of_drive  # noqa: E402
from hdmap_ros.convert.messages import drive_to_msg, rclpy_types  # noqa: E402
from hdmap_ros.persistence.store import DriveStore  # noqa: E402

from bag_samples import make_drive  # noqa: E402
from nodes_harness import use_dds, wait_for  # noqa: E402

pytestmark = pytest.mark.ros


def _far_pose(drive, dist):
    xy = np.array(drive.xy, dtype=float)
    xy[len(xy) // 2, 0] += dist
    return replace(drive, xy=xy)


@pytest.mark.parametrize("dist", [1e6, 1e12, 1e200])
def test_mapper_rejects_a_far_pose_and_stores_nothing(ros, tmp_path, dist):
    from hdmap_ros.nodes.segment_mapper import SegmentMapper

    mapper = SegmentMapper(
        context=ros.context, parameter_overrides=[Parameter("db_path", value=str(tmp_path / "m.db"))]
    )
    try:
        t = rclpy_types()
        mapper.on_drive(drive_to_msg(_far_pose(make_drive("bad"), dist), types=t))
        mapper.on_drive(drive_to_msg(make_drive("good"), types=t))
        assert mapper.store.drive_ids() == ["good"]
        assert mapper.health.rejected == {"coordinate_out_of_bounds": 1}
        assert mapper.received == 2
    finally:
        mapper.destroy_node()


def test_a_bad_drive_stored_before_is_removed_at_start(ros, tmp_path):
    from hdmap_ros.nodes.segment_mapper import SegmentMapper

    db = tmp_path / "m.db"
    store = DriveStore(db)
    cfg = TileConfig()
    good, zig = make_drive("good"), make_drive("zig", seed=1)
    xy = np.array(zig.xy, dtype=float)
    xy[1::2, 1] += 50.0  # every other pose +50 m: 500 m/s
    zig = replace(zig, xy=xy)
    for d in (good, zig):
        store.add_drive(d, tiles_of_drive(d, config=cfg))  # as an older version stored them, unchecked
    tile_of_zig = sorted(tiles_of_drive(zig, config=cfg))[0]
    store.put_tile(tile_of_zig, [], ["good", "zig"])
    store.close()
    mapper = SegmentMapper(context=ros.context, parameter_overrides=[Parameter("db_path", value=str(db))])
    try:
        assert mapper.store.drive_ids() == ["good"]
        assert mapper.health.rejected.get("implausible_stored") == 1
        assert tile_of_zig in mapper.store.stale_tiles()  # its estimate counted the removed drive
        assert mapper.store.get_meta("plausible_upto").endswith("|1")  # the last drive kept
    finally:
        mapper.destroy_node()
    again = SegmentMapper(context=ros.context, parameter_overrides=[Parameter("db_path", value=str(db))])
    try:
        assert again.store.drive_ids() == ["good"] and not again.health.rejected
    finally:
        again.destroy_node()


def test_ingestor_rejects_implausible_drives_by_reason(ros):
    from hdmap_ros.nodes.drive_ingestor import DriveIngestor

    ing = DriveIngestor(context=ros.context)
    try:
        t = rclpy_types()
        stamps = make_drive("rev").stamps_ns[::-1].copy()
        for d in (_far_pose(make_drive("far"), 1e9), replace(make_drive("rev"), stamps_ns=stamps), make_drive("ok")):
            ing.on_drive(drive_to_msg(d, types=t))
        assert ing.health.rejected == {"coordinate_out_of_bounds": 1, "stamps_not_increasing": 1}
        assert ing.published == 1 and ing.received == 3
    finally:
        ing.destroy_node()


def test_bag_player_counts_what_it_cannot_send(ros, tmp_path):
    """Undecodable bytes and a Drive of another definition are not sent but counted (hdmap run then
    never waits for them); a damaged chunk is skipped with a warning and the rest played."""
    from hdmap_ros.nodes.bag_player import BagPlayer

    from hostile_bags import bag_without_vehicle_id, small_drives

    bag = bag_without_vehicle_id(tmp_path, small_drives(3))
    player = ros.add(
        BagPlayer(
            context=ros.context,
            parameter_overrides=[
                Parameter("bag", value=str(bag)),
                Parameter("rate", value=0.0),
                Parameter("wait_for_subscribers_s", value=0.0),
            ],
        )
    )
    wait_for(lambda: player.done, 20, what="player done")
    assert player.published == 0 and player.skipped == {"definition_mismatch": 3} and player.played == 3


@pytest.mark.parametrize("rosbag2", [False, True], ids=["mcap", "rosbag2"])
def test_bag_player_sends_the_good_drives_of_a_bag_with_two_definitions(ros, tmp_path, rosbag2):
    """One Drive connection with the contract's definition, one without vehicle_id: the first one's
    drives are sent, the other's counted as definition_mismatch."""
    from hdmap_ros.nodes.bag_player import BagPlayer

    from hostile_bags import small_drives, two_definition_bag

    drives = small_drives(6)
    bag = two_definition_bag(tmp_path / ("two" if rosbag2 else "two.mcap"), drives[0::2], drives[1::2], rosbag2=rosbag2)
    player = ros.add(
        BagPlayer(
            context=ros.context,
            parameter_overrides=[
                Parameter("bag", value=str(bag)),
                Parameter("rate", value=0.0),
                Parameter("wait_for_subscribers_s", value=0.0),
            ],
        )
    )
    wait_for(lambda: player.done, 20, what="player done")
    assert player.published == 3 and player.skipped == {"definition_mismatch": 3} and player.played == 6


@pytest.mark.slow
def test_hdmap_run_settles_on_a_bag_with_undecodable_and_invalid_drives(tmp_path, sample_bags, capsys, monkeypatch):
    """bags/bad_inputs: 4 good drives, 10 invalid ones the ingestor rejects, one undecodable the
    player skips (before: never counted, so `hdmap run` waited forever)."""
    from hdmap_ros import cli

    use_dds(monkeypatch, 74)

    code = cli.main(["run", str(sample_bags / "bad_inputs"), "-o", str(tmp_path / "map"), "--timeout", "300"])
    err = capsys.readouterr().err
    assert code == 0, err[-2000:]
    assert "settled: drives played 15 (skipped 1), accepted 4, rejected 10" in err
