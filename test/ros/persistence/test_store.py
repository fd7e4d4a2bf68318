"""Tests of hdmap_ros.persistence.store: exact blob round trips, transactional drive and map stores."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from hdmap_core.model import Detection, Drive, FeatureType, HDMap, MapFeature, TopologyNode
from hdmap_core.segment_columns import segment_columns
from hdmap_core.steps import Segment, StepResult
from hdmap_ros.persistence.store import (
    DriveStore,
    MapStore,
    blob_to_drive,
    blob_to_map,
    blob_to_observations,
    blob_to_segments,
    drive_to_blob,
    map_to_blob,
    observations_to_blob,
    segments_to_blob,
)

from segment_samples import assert_same_steps


def _drive(drive_id="d1", n=5, x0=0.0):
    rng = np.random.default_rng(abs(hash(drive_id)) % 1000)
    xy = np.stack([x0 + np.arange(n, dtype=float), rng.normal(size=n)], axis=1)
    return Drive(
        drive_id=drive_id,
        xy=xy,
        yaw=rng.normal(size=n),
        stamps_ns=np.arange(n, dtype=np.int64) * 10**8 + 1_700_000_000 * 10**9,
        detections=(
            Detection(FeatureType.SOLID, rng.normal(size=(3, 2))),
            Detection(FeatureType.ROAD_BORDER, rng.normal(size=(2, 2))),
        ),
        vehicle_id="veh",
    )


def _assert_drive_equal(a: Drive, b: Drive):
    assert (a.drive_id, a.vehicle_id, a.frame_id) == (b.drive_id, b.vehicle_id, b.frame_id)
    np.testing.assert_array_equal(a.xy, b.xy)
    np.testing.assert_array_equal(a.yaw, b.yaw)
    np.testing.assert_array_equal(a.stamps_ns, b.stamps_ns)
    assert [d.type for d in a.detections] == [d.type for d in b.detections]
    for da, db in zip(a.detections, b.detections):
        np.testing.assert_array_equal(da.points, db.points)


def test_drive_blob_round_trip_is_exact():
    d = _drive()
    _assert_drive_equal(blob_to_drive(drive_to_blob(d)), d)
    empty = Drive("e", np.zeros((2, 2)), np.zeros(2), np.zeros(2, np.int64))
    _assert_drive_equal(blob_to_drive(drive_to_blob(empty)), empty)


def _segments():
    def step(pivot, i, k):
        return StepResult(
            pivot_id=pivot,
            index=i,
            s_m=2.0 * i + 0.1,
            midpoint=np.array([i * 2.0, 1.5]),
            heading=0.3,
            width_m=11.5,
            valid=bool(i % 2 == 0),
            processed_before=bool(i == 1),
            lateral_m=np.linspace(-5, 5, k),
            types=np.arange(k) % 4,
            counts=np.arange(k) + 2,
            std_m=np.full(k, 0.07),
            drive_ids=tuple(f"x{j}" for j in range(i + 1)),
            # negative evidence: judged with two intervals, not judged, judged with none
            empty_m=[np.array([[-3.25, -1.0], [4.5, 6.0]]), None, np.zeros((0, 2))][i],
            # the pivot's own position: known, not known (stored before poses were kept), known
            pose=[np.array([0.25, 3.0]), None, np.array([4.0, -0.5])][i],
        )

    return [Segment("p1", tuple(step("p1", i, k) for i, k in enumerate([3, 0, 5]))), Segment("p2", ())]


def test_segments_blob_round_trip_is_exact():
    segs = _segments()
    back = blob_to_segments(segments_to_blob(segs))
    assert [s.pivot_id for s in back] == ["p1", "p2"]
    assert len(back[1].steps) == 0
    assert_same_steps(segs[0].steps, back[0].steps)
    assert back[0].steps[0].empty_m.shape == (2, 2)
    assert blob_to_segments(segments_to_blob([])) == []


def _map():
    f1 = MapFeature(
        id=2**63 + 5,
        type=FeatureType.DASHED,
        points=np.array([[0.0, 0], [10, 0.5]]),
        drive_count=np.array([3, 4]),
        lateral_std=np.array([0.1, 0.2]),
        successors=(7,),
    )
    f2 = MapFeature(
        id=7,
        type=FeatureType.SOLID,
        points=np.array([[10.0, 0.5], [20, 1], [30, 1]]),
        drive_count=np.array([1, 2, 3]),
        lateral_std=np.zeros(3),
        predecessors=(2**63 + 5,),
    )
    t = TopologyNode(id=99, position=np.array([1.0, 2.0]), heading=0.5, width=7.25, successors=(100,), features=(7,))
    return HDMap(features=(f1, f2), topology=(t,), drive_ids=("a", "b"), version=12, stamp_ns=123, extra={"k": 1})


def test_map_blob_round_trip_is_exact():
    m = _map()
    b = blob_to_map(map_to_blob(m))
    assert (b.drive_ids, b.version, b.frame_id, b.stamp_ns, b.extra) == (m.drive_ids, 12, "map", 123, {"k": 1})
    for fa, fb in zip(m.features, b.features):
        assert (fa.id, fa.type, fa.predecessors, fa.successors) == (fb.id, fb.type, fb.predecessors, fb.successors)
        np.testing.assert_array_equal(fa.points, fb.points)
        np.testing.assert_array_equal(fa.drive_count, fb.drive_count)
        np.testing.assert_array_equal(fa.lateral_std, fb.lateral_std)
    (ta,), (tb,) = m.topology, b.topology
    assert (ta.id, ta.heading, ta.width, ta.successors, ta.features) == (
        tb.id,
        tb.heading,
        tb.width,
        tb.successors,
        tb.features,
    )
    assert blob_to_map(map_to_blob(HDMap())).features == ()


def _observations():
    from hdmap_core.steps import StepObservations

    rng = np.random.default_rng(5)
    return [
        StepObservations(
            pivot_id="p#0,0",
            index=3,
            midpoint=np.array([1.5, -2.25]),
            heading=0.3,
            drive_ids=("a", "b", "a"),
            drive_s_m=rng.normal(size=3) * 1e3,
            lateral_m=rng.normal(size=3),
            types=np.array([1, 2, 3]),
            cluster=np.array([0, -1, 1]),
            offsets_m=rng.normal(size=3),
        ),
        StepObservations(
            pivot_id="q#1,0",
            index=0,
            midpoint=np.array([7.0, 8.0]),
            heading=-1.0,
            drive_ids=("c",),
            drive_s_m=np.array([np.pi]),
            lateral_m=np.array([1 / 3]),
            types=np.array([2]),
            cluster=np.array([0]),
        ),
    ]


def test_observations_blob_round_trip_is_exact():
    obs = _observations()
    back = blob_to_observations(observations_to_blob(obs))
    assert len(back) == 2
    for a, b in zip(obs, back):
        assert (a.pivot_id, a.index, a.heading, a.drive_ids) == (b.pivot_id, b.index, b.heading, b.drive_ids)
        for f in ("midpoint", "drive_s_m", "lateral_m", "types", "cluster", "offsets_m"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
            assert getattr(a, f).dtype.kind == getattr(b, f).dtype.kind
    assert blob_to_observations(observations_to_blob([])) == []


def test_drive_store_keeps_observations_and_the_fleet_model(tmp_path):
    st = DriveStore(tmp_path / "m.db")
    st.add_drive(_drive("a"), [(0, 0), (1, 0)])
    st.add_drive(_drive("b"), [(1, 0)])
    assert st.stale_observations() == [(0, 0), (1, 0)] and st.observation_sets() == []
    assert st.model() == (None, "")
    # an estimate made with the tile's own adjustment stores its observations in the same transaction
    st.put_tile((1, 0), _segments(), ["a", "b"], observations=_observations())
    st.put_observations((0, 0), _observations()[1:], ["a"])
    assert st.stale_observations() == []
    assert st.observation_sets() == [((0, 0), ["a"]), ((1, 0), ["a", "b"])]
    assert [o.pivot_id for o in st.observations()] == ["q#1,0", "p#0,0", "q#1,0"]  # by tile
    st.put_model({"format": "x", "v": [0.1, None]}, "sig1")
    st.put_tile((0, 0), [], ["a"], model_sig="sig1")
    # (1, 0) was made with its own adjustment; (0, 0) with the model
    assert st.tiles_off_model("sig1") == [(1, 0)] and st.tiles_off_model("sig2") == [(0, 0), (1, 0)]
    st.add_drive(_drive("c"), [(0, 0)])  # (0, 0) is stale now: not "made from all its drives"
    assert st.tiles_off_model("sig1") == [(1, 0)] and st.stale_observations() == [(0, 0)]
    st.close()
    st2 = DriveStore(tmp_path / "m.db")
    assert st2.model() == ({"format": "x", "v": [0.1, None]}, "sig1")
    assert st2.observation_sets()[1] == ((1, 0), ["a", "b"])
    st2.close()


def test_drive_store_of_before_the_fleet_model_is_migrated(tmp_path):
    import sqlite3

    con = sqlite3.connect(tmp_path / "old.db")
    con.execute(
        "CREATE TABLE tiles (tx INTEGER NOT NULL, ty INTEGER NOT NULL, version INTEGER NOT NULL, "
        "drive_count INTEGER NOT NULL, drive_ids TEXT NOT NULL, segments BLOB, PRIMARY KEY (tx, ty))"
    )
    con.execute("INSERT INTO tiles VALUES (0, 0, 4, 1, '[\"a\"]', NULL)")
    con.commit()
    con.close()
    st = DriveStore(tmp_path / "old.db")
    st.add_drive(_drive("a"), [(0, 0)])
    assert st.tile((0, 0)).version == 4 and st.tiles_off_model("s") == [(0, 0)]
    assert st.put_tile((0, 0), [], ["a"], model_sig="s").version == 5 and st.tiles_off_model("s") == []
    st.close()


def test_drive_store_acknowledges_once_and_indexes_tiles(tmp_path):
    st = DriveStore(tmp_path / "m.db")
    assert st.add_drive(_drive("a"), [(0, 0), (1, 0)])
    assert st.add_drive(_drive("b"), [(1, 0)])
    assert not st.add_drive(_drive("a"), [(5, 5)])  # duplicate id: nothing stored
    assert st.drive_ids() == ["a", "b"] and st.pending() == ["a", "b"]
    assert st.tile_drive_count((1, 0)) == 2 and st.tile_drive_count((5, 5)) == 0
    assert [d.drive_id for d in st.drives_covering((1, 0))] == ["a", "b"]
    assert st.tiles_of(["b"]) == {(1, 0)}
    assert {d: sorted(k) for d, k in st.tiles_per_drive(["a", "b", "x"]).items()} == {
        "a": [(0, 0), (1, 0)],
        "b": [(1, 0)],
        "x": [],
    }
    assert st.tile_drive_sets() == {(0, 0): ["a"], (1, 0): ["a", "b"]}
    assert [d.drive_id for d in st.drives(["b", "a", "x"])] == ["a", "b"]
    assert st.stale_tiles() == [(0, 0), (1, 0)]
    est = st.put_tile((1, 0), _segments(), ["a", "b"])
    assert est.version == 1 and st.put_tile((1, 0), [], ["a", "b"], model_sig="m").version == 2
    assert st.estimates() == [((1, 0), ["a", "b"], "m")] and st.tile((1, 0)).model_sig == "m"
    assert st.stale_tiles() == [(0, 0)]
    # many tiles in one commit (the region settle): each gets its next version
    many = st.put_tiles([((0, 0), _segments(), ["a"]), ((1, 0), [], ["a", "b"])], model_sig="r")
    assert [(e.key, e.version, e.model_sig) for e in many] == [((0, 0), 1, "r"), ((1, 0), 3, "r")]
    assert st.estimates() == [((0, 0), ["a"], "r"), ((1, 0), ["a", "b"], "r")]
    assert st.tile((0, 0)).segments_blob == many[0].segments_blob == segments_to_blob(_segments())
    # the same blobs cut from the tiles' segments in columns (made once for the store and the batch)
    other = DriveStore(tmp_path / "columns.db")
    tiles = [((5, 0), [], ["a"]), ((6, 0), _segments(), ["a"]), ((7, 0), _segments(), ["b"])]
    cols = segment_columns([seg for _, segs, _ in tiles for seg in segs])
    blobs = [e.segments_blob for e in other.put_tiles(tiles, model_sig="f", columns=cols)]
    assert blobs == [segments_to_blob(segs) for _, segs, _ in tiles]
    with pytest.raises(ValueError):
        other.put_tiles([((8, 0), _segments(), ["a"])], columns=cols)  # columns of other segments
    other.close()
    assert st.stale_tiles() == []
    st.put_tile((1, 0), [], ["a", "b"], model_sig="m")
    st.mark_processed(["a"])
    assert st.pending() == ["b"]
    st.close()
    # everything survives reopening
    st2 = DriveStore(tmp_path / "m.db")
    assert st2.pending() == ["b"] and st2.tile((1, 0)).version == 4 and st2.tile((1, 0)).segments() == []
    assert st2.tile((1, 0)).drive_ids == ("a", "b") and st2.tile((1, 0)).drive_count == 2
    _assert_drive_equal(st2.drives_covering((0, 0))[0], _drive("a"))


def test_map_store_ignores_old_tile_versions(tmp_path):
    st = MapStore(tmp_path / "s.db")
    blob = segments_to_blob(_segments())
    assert st.put_tile((0, 0), 2, blob, ["a"])
    assert not st.put_tile((0, 0), 2, blob, ["a"])
    assert not st.put_tile((0, 0), 1, b"junk", ["a"])
    assert st.tile_version((0, 0)) == 2 and st.tiles_signature() == "0,0:2"
    assert st.map() == (None, "")
    st.put_map(_map(), st.tiles_signature())
    m, sig = st.map()
    assert m.version == 12 and sig == "0,0:2"


def test_map_store_stores_a_batch_in_one_transaction_newer_versions_only(tmp_path):
    st = MapStore(tmp_path / "s.db")
    blob = segments_to_blob(_segments())
    assert st.put_tile((0, 0), 2, blob, ["a"])
    got = st.put_tiles([((0, 0), 2, b"junk", ["a"], [1], True), ((1, 0), 1, blob, ["a", "b"], [2, 1], False)])
    assert got == [False, True]  # the same version again is ignored, the new tile stored
    assert st.tiles_signature() == "0,0:2;1,0:1"
    with pytest.raises(sqlite3.Error):  # one bad tile: none of the batch is stored
        st.put_tiles([((2, 0), 1, blob, ["a"], [1], True), ((3,), 1, blob, ["a"], [1], True)])
    assert st.tiles_signature() == "0,0:2;1,0:1"
    assert st.tile_progress()[(1, 0)] == ([2, 1], False)
    assert [b for k, _, _, b in st.tiles() if k == (0, 0)] == [blob]


def test_sigkill_mid_transaction_keeps_committed_drives(tmp_path):
    """A process killed inside a transaction leaves exactly the committed drives."""
    db = tmp_path / "k.db"
    script = textwrap.dedent(
        f"""
        import os, signal, numpy as np
        from hdmap_core.model import Drive
        from hdmap_ros.persistence.store import DriveStore
        st = DriveStore({str(db)!r})
        d = lambda i: Drive(f"d{{i}}", np.zeros((2, 2)), np.zeros(2), np.zeros(2, np.int64))
        for i in range(3):
            st.add_drive(d(i), [(0, i)])
        st._con.execute("BEGIN IMMEDIATE")
        st._con.execute("INSERT INTO drives(drive_id, blob) VALUES ('half', x'00')")
        os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], cwd=str(tmp_path), env=_env(), capture_output=True)
    assert proc.returncode == -9, proc.stderr.decode()
    st = DriveStore(db)
    assert st.drive_ids() == ["d0", "d1", "d2"]


def _env():
    import os
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(root / "src/hdmap_core"), str(root / "src/hdmap_ros"), env.get("PYTHONPATH", "")]
    )
    return env


def test_map_store_keeps_each_tiles_drive_counts_and_finality_and_migrates_an_old_store(tmp_path):
    import sqlite3

    st = MapStore(tmp_path / "s.db")
    blob = segments_to_blob(_segments())
    assert st.put_tile((0, 0), 1, blob, ["a", "b"], [2, 1], final=False)
    assert st.put_tile((1, 0), 1, blob, ["a"], [2])
    assert st.tile_progress() == {(0, 0): ([2, 1], False), (1, 0): ([2], True)}
    st.close()
    old = tmp_path / "old.db"  # a map store of before the counts: its tiles vouch for themselves
    con = sqlite3.connect(old)
    con.execute(
        "CREATE TABLE tiles (tx INTEGER NOT NULL, ty INTEGER NOT NULL, version INTEGER NOT NULL, "
        "drive_ids TEXT NOT NULL, segments BLOB NOT NULL, PRIMARY KEY (tx, ty))"
    )
    con.execute("INSERT INTO tiles VALUES (0, 0, 3, '[\"a\"]', ?)", (blob,))
    con.commit()
    con.close()
    st = MapStore(old)
    assert st.tile_progress() == {(0, 0): ([], True)} and st.tile_version((0, 0)) == 3
    st.close()
