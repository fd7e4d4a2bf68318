"""Pure parts of the node suite, without rclpy: markers, health counters, tile messages."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from hdmap_core.model import FeatureType, HDMap, MapFeature, TopologyNode
from hdmap_core.steps import Segment, StepResult
from hdmap_ros.convert.markers import DELETEALL, LINE_LIST, LINE_STRIP, TYPE_COLORS, MarkerTypes, map_to_markers
from hdmap_ros.nodes.diagnostics import OK, WARN, Health

from segment_samples import assert_same_steps


class _Msg(SimpleNamespace):
    pass


def _marker():
    return _Msg(
        header=None,
        ns="",
        id=0,
        type=0,
        action=0,
        points=[],
        frame_locked=False,
        color=None,
        pose=_Msg(orientation=_Msg(w=0.0)),
        scale=_Msg(x=0.0),
    )


FAKE = MarkerTypes(MarkerArray=lambda: _Msg(markers=[]), Marker=_marker, Point=_Msg, ColorRGBA=_Msg)


def _feat(fid, ftype, pts):
    pts = np.asarray(pts, float)
    return MapFeature(fid, ftype, pts, np.ones(len(pts), int), np.zeros(len(pts)))


def test_markers_one_line_strip_per_feature_coloured_by_type():
    m = HDMap(
        features=(
            _feat(2**64 - 1, FeatureType.SOLID, [[0, 0], [1, 0], [2, 0]]),
            _feat(5, FeatureType.DASHED, [[0, 3], [2, 3]]),
            _feat(6, FeatureType.SOLID, [[0, 6], [2, 6]]),
            _feat(7, FeatureType.ROAD_BORDER, [[0, 9]]),  # one point: not drawable
        ),
        topology=(
            TopologyNode(1, np.array([0.0, 1.5]), 0.0, 3.0, successors=(2,)),
            TopologyNode(2, np.array([2.0, 1.5]), 0.0, 3.0),
        ),
    )
    arr = map_to_markers(m, types=FAKE, header="H")
    kinds = [(mk.action, mk.type, mk.ns, mk.id) for mk in arr.markers]
    assert kinds[0][0] == DELETEALL
    assert kinds[1:] == [
        (0, LINE_STRIP, "features/solid", 0),
        (0, LINE_STRIP, "features/dashed", 0),
        (0, LINE_STRIP, "features/solid", 1),
        (0, LINE_LIST, "topology", 0),
    ]
    assert [(p.x, p.y) for p in arr.markers[1].points] == [(0, 0), (1, 0), (2, 0)]
    c = arr.markers[2].color
    assert (c.r, c.g, c.b, c.a) == TYPE_COLORS[FeatureType.DASHED]
    assert all(mk.header == "H" for mk in arr.markers)
    assert [(p.x, p.y) for p in arr.markers[-1].points] == [(0.0, 1.5), (2.0, 1.5)]


def test_health_counts_and_levels():
    h = Health("hdmap: x", backlog_warn=3)
    h.accept()
    h.accept()
    h.reject("non_finite_coordinates", "d7")
    h.duplicate()
    h.backlog = 2
    kv = dict(h.key_values())
    assert kv["drives_accepted"] == "2" and kv["drives_rejected"] == "1" and kv["drives_duplicate"] == "1"
    assert kv["rejected.non_finite_coordinates"] == "1" and kv["last_update_time"] == "never"
    assert h.level() == OK
    h.backlog = 3
    assert h.level() == WARN
    h.backlog = 0
    h.error("boom")
    assert h.level() == WARN and "1 failed" in h.message()
    h.updated(1_500_000_000_000_000_000)
    assert dict(h.key_values())["last_update_time"] == "1500000000.000"


def _segments():
    def st(i, k):
        return StepResult(
            pivot_id="piv",
            index=i,
            s_m=2.0 * i,
            midpoint=np.array([10.0 + i, -3.25]),
            heading=0.125,
            width_m=12.5,
            valid=i != 1,
            processed_before=i == 2,
            lateral_m=np.linspace(-6, 6, k),
            types=np.array([1, 2, 3, 1, 2][:k]),
            counts=np.arange(k) + 1,
            std_m=np.full(k, 0.05),
            drive_ids=("a", "b")[: i + 1],
            empty_m=[np.array([[-3.25, -1.0], [4.5, 6.0]]), None, np.zeros((0, 2))][i],
            pose=[np.array([10.25, -4.5]), None, np.array([12.0, -1.0])][i],
        )

    return [Segment("piv", tuple(st(i, k) for i, k in enumerate([5, 0, 3]))), Segment("other", ())]


@pytest.mark.parametrize("key", [(2**40, -(2**40)), (-(2**62), 2**62)])
def test_tile_keys_travel_as_int64(key):
    """A tile of a drive at 1e15 m (key ~4e12) once wrapped in the int32 message fields."""
    pytest.importorskip("rosbags")
    from hdmap_ros.convert.tiles import msg_to_tile, rosbags_tile_types, tile_to_msg
    from hdmap_ros.io.msgdefs import make_typestore

    store = make_typestore()
    msg = tile_to_msg(key, [], version=1, drive_ids=[], tile_size_m=256.0, stamp_ns=0, types=rosbags_tile_types(store))
    back = msg_to_tile(
        store.deserialize_cdr(store.serialize_cdr(msg, "hdmap_msgs/msg/TileSegments"), "hdmap_msgs/msg/TileSegments")
    )
    assert back.key == key


def test_tile_msg_round_trip_through_cdr():
    pytest.importorskip("rosbags")
    from hdmap_ros.convert.tiles import msg_to_tile, rosbags_tile_types, tile_to_msg
    from hdmap_ros.io.msgdefs import make_typestore

    store = make_typestore()
    segs = _segments()
    msg = tile_to_msg(
        (3, -2),
        segs,
        version=7,
        drive_ids=["a", "b"],
        tile_size_m=256.0,
        stamp_ns=1_700_000_000_123_456_789,
        types=rosbags_tile_types(store),
    )
    cdr = store.serialize_cdr(msg, "hdmap_msgs/msg/TileSegments")
    back = msg_to_tile(store.deserialize_cdr(cdr, "hdmap_msgs/msg/TileSegments"))
    assert (back.key, back.version, back.drive_ids, back.tile_size_m) == ((3, -2), 7, ("a", "b"), 256.0)
    assert back.stamp_ns == 1_700_000_000_123_456_789
    assert [s.pivot_id for s in back.segments] == ["piv", "other"]
    assert_same_steps(segs[0].steps, back.segments[0].steps)
    assert back.segments[0].steps[0].empty_m.shape == (2, 2)


def test_step_evidence_from_a_malformed_message_is_cut_not_fatal():
    from types import SimpleNamespace

    from hdmap_ros.convert.tiles import _empty_from_msg, _pose_from_msg

    assert _empty_from_msg(SimpleNamespace(judged=False, empty_lo_m=[1.0], empty_hi_m=[2.0])) is None
    got = _empty_from_msg(SimpleNamespace(judged=True, empty_lo_m=[1.0, 4.0], empty_hi_m=[2.0]))
    np.testing.assert_array_equal(got, [[1.0, 2.0]])
    assert _empty_from_msg(SimpleNamespace(judged=True, empty_lo_m=[], empty_hi_m=[])).shape == (0, 2)
    # a step without the pivot's position (a message of an older node, or NaN) just has none
    assert _pose_from_msg(SimpleNamespace()) is None
    assert _pose_from_msg(SimpleNamespace(pose=SimpleNamespace(x=float("nan"), y=1.0))) is None
    np.testing.assert_array_equal(_pose_from_msg(SimpleNamespace(pose=SimpleNamespace(x=2.0, y=-1.5))), [2.0, -1.5])


def test_launch_file_compiles_and_names_every_node():
    from pathlib import Path

    path = Path(__file__).resolve().parents[3] / "src/hdmap_ros/launch/hdmap.launch.py"
    text = path.read_text()
    compile(text, str(path), "exec")
    for node in ("drive_ingestor", "segment_mapper", "map_stitcher", "map_publisher", "bag_player"):
        assert f'"{node}"' in text


def _batch_tiles():
    segs = _segments()
    more = [
        Segment(p, tuple(replace(st, pivot_id=p) for st in steps))
        for p, steps in (("third", segs[0].steps[2:]), ("fourth", segs[0].steps[:1]))
    ]
    return [
        ((3, -2), segs, 7, ["a", "b"], [4, 1], True),
        ((2**40, -(2**40)), [], 1, [], [], False),
        ((4, -2), more, 2, ["b"], [1], True),
    ]


@pytest.mark.parametrize("kind", ["rosbags", "rclpy"])
def test_tile_batch_round_trip_through_cdr_is_each_tile_message(kind):
    """A TileSegmentsBatch carries what one TileSegments per tile carries (the stitcher stores
    either the same), and its columns make the same store blob as the segments."""
    from hdmap_ros.convert.tiles import batch_to_tiles, msg_to_tile, tile_to_msg, tiles_to_batch
    from hdmap_ros.persistence.store import columns_to_blob, segments_to_blob

    if kind == "rosbags":
        pytest.importorskip("rosbags")
        from hdmap_ros.convert.tiles import rosbags_tile_types
        from hdmap_ros.io.msgdefs import make_typestore

        store = make_typestore()
        types = rosbags_tile_types(store)

        def wire(msg, name):
            return store.deserialize_cdr(store.serialize_cdr(msg, f"hdmap_msgs/msg/{name}"), f"hdmap_msgs/msg/{name}")
    else:
        pytest.importorskip("rclpy")
        pytest.importorskip("hdmap_msgs.msg")
        from rclpy.serialization import deserialize_message, serialize_message

        from hdmap_ros.convert.tiles import rclpy_tile_types

        types = rclpy_tile_types()

        def wire(msg, _name):
            return deserialize_message(serialize_message(msg), type(msg))

    tiles = _batch_tiles()
    stamp = 1_700_000_000_123_456_789
    got = batch_to_tiles(
        wire(tiles_to_batch(tiles, tile_size_m=256.0, stamp_ns=stamp, types=types), "TileSegmentsBatch")
    )
    assert len(got) == len(tiles)
    for entry, (key, segs, version, ids, counts, final) in zip(got, tiles, strict=True):
        one = msg_to_tile(
            wire(
                tile_to_msg(
                    key,
                    segs,
                    version=version,
                    drive_ids=ids,
                    tile_size_m=256.0,
                    stamp_ns=stamp,
                    types=types,
                    drive_tile_counts=counts,
                    final=final,
                ),
                "TileSegments",
            )
        )
        # every field, the segments apart (made from the columns on demand)
        assert entry.tile == replace(one, segments=[])
        back = entry.segments()
        assert columns_to_blob(entry.columns) == segments_to_blob(back) == segments_to_blob(segs)
        assert [s.pivot_id for s in back] == [s.pivot_id for s in segs]
        assert_same_steps([st for s in segs for st in s.steps], [st for s in back for st in s.steps])


def test_a_tile_batch_whose_columns_do_not_add_up_is_refused():
    pytest.importorskip("rosbags")
    from hdmap_ros.convert.tiles import batch_to_tiles, rosbags_tile_types, tiles_to_batch
    from hdmap_ros.io.msgdefs import make_typestore

    msg = tiles_to_batch(_batch_tiles(), tile_size_m=256.0, stamp_ns=0, types=rosbags_tile_types(make_typestore()))
    for field, value in [
        ("step_maxima", msg.step_maxima[:-1]),
        ("lateral_m", msg.lateral_m[1:]),
        ("tile_segments", msg.tile_segments + 1),
        ("step_drive_index", msg.step_drive_index + 10),
        ("version", msg.version[:1]),
    ]:
        bad = type(msg)(**{**{f: getattr(msg, f) for f in msg.__dataclass_fields__}, field: value})
        with pytest.raises(ValueError, match="do not add up"):
            batch_to_tiles(bad)
