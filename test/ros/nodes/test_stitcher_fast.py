"""The fast path through the nodes, without spinning: the mapper fuses a drive on settled road in
its own process and hands its tiles over as one batch; the stitcher stores the batch at once and
moves the map in place (``live.restitch``), listing the drive; the full rebuild of the same tiles
follows and is then the map (``stitch_graphs`` of every tile, bit for bit)."""

from __future__ import annotations

import time
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("hdmap_msgs.msg")

from fuse_fleet import fuse_fleet  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from hdmap_core.live.fuse import fuse_drive  # noqa: E402
from hdmap_core.live.region import map_region  # noqa: E402
from hdmap_core.live.restitch import MOVED_TOLERANCE_M  # noqa: E402
from hdmap_core.live.scheduler import FUSE  # noqa: E402
from hdmap_core.live.tiles import TileConfig, connect_tile, stitch_graphs, tiles_of_drive  # noqa: E402
from hdmap_core.pipeline import presets  # noqa: E402
from hdmap_ros.convert.messages import drive_to_msg, map_to_msg, rclpy_types  # noqa: E402
from hdmap_ros.convert.tiles import batch_to_tiles, rclpy_tile_types, tile_to_msg, tiles_to_batch  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]

TC = TileConfig(tile_size_m=256.0, margin_m=128.0, seed=0)


def _msgs(tiles, ids, version, counts):
    t = rclpy_tile_types()
    return [
        tile_to_msg(
            k,
            tiles[k],
            version=version,
            drive_ids=ids[k],
            tile_size_m=TC.tile_size_m,
            stamp_ns=0,
            types=t,
            drive_tile_counts=[counts[d] for d in ids[k]],
            final=True,
        )
        for k in sorted(tiles)
    ]


def _batch(tiles, ids, version, counts):
    return tiles_to_batch(
        [(k, tiles[k], version, ids[k], [counts[d] for d in ids[k]], True) for k in sorted(tiles)],
        tile_size_m=TC.tile_size_m,
        stamp_ns=0,
        types=rclpy_tile_types(),
    )


def test_a_fused_burst_moves_the_map_at_once_and_the_full_rebuild_follows(ros, tmp_path):
    from hdmap_ros.nodes.map_stitcher import MapStitcher

    drives = fuse_fleet()
    pc = presets.preset("default")
    base, new = drives[:-1], drives[-1]
    tiles_of = {d.drive_id: tiles_of_drive(d, config=TC) for d in drives}
    keys = sorted(set().union(*[tiles_of[d.drive_id] for d in base]))
    settled = map_region(base, keys, tile_config=TC, pipeline_config=pc).segments
    res = fuse_drive(new, {k: settled[k] for k in tiles_of[new.drive_id] if k in settled})
    assert res.tiles is not None, res.reason
    counts = {d: len(k) for d, k in tiles_of.items()}
    ids = {k: sorted(d.drive_id for d in base if k in tiles_of[d.drive_id]) for k in keys}
    ids_after = {k: sorted([*ids[k], new.drive_id]) for k in res.tiles}

    st = MapStitcher(  # not spun: this test calls its turns
        context=ros.context,
        parameter_overrides=[
            Parameter("db_path", value=str(tmp_path / "s.db")),
            Parameter("drive_db_path", value=str(tmp_path / "m.db")),
            Parameter("debounce_s", value=0.2),
            Parameter("max_delay_s", value=0.5),
            Parameter("follow_changes", value="off"),
        ],
    )
    try:
        for m in _msgs(settled, ids, 1, counts):
            st.on_tile(m)
        st._work()  # every drive complete: at once
        first = st.map
        assert first is not None and set(first.drive_ids) == {d.drive_id for d in base} and st.is_settled()
        st.on_batch(_batch(res.tiles, ids_after, 2, counts))  # as the mapper sends it: one message
        assert st.store.tiles_signature() == ";".join(f"{x},{y}:{2 if (x, y) in res.tiles else 1}" for x, y in keys)
        st._rested_at = 0.0  # the drive came long after the last rebuild
        st._work()  # the fused burst completes the new drive: moved in place at once
        fast = st.map
        assert fast.version == first.version + 1 and new.drive_id in fast.drive_ids
        assert "last_fast_update_s" in st.health.extra and not st.is_settled()  # the full rebuild is due
        # the map went out as CDR bytes made at once: rclpy reads them as the message map_to_msg makes
        made = map_to_msg(fast, types=rclpy_types())
        assert deserialize_message(st._last_msg, type(made)) == deserialize_message(serialize_message(made), type(made))
        after = dict(settled)
        after.update(res.tiles)
        full = stitch_graphs(
            [g for k in sorted(after) for g in connect_tile(after[k], k, pipeline_config=pc)],
            pipeline_config=pc,
            drive_ids=[d.drive_id for d in drives],
        )
        # within the tolerance of the full re-stitch: the same lines, point for point nearly
        assert len(fast.features) == len(full.features)
        d = [
            np.max(np.linalg.norm(a.points - b.points, axis=1))
            for a, b in zip(fast.features, full.features, strict=True)
            if len(a.points) == len(b.points)
        ]
        assert np.median(d) <= MOVED_TOLERANCE_M
        time.sleep(0.25)  # quiet for debounce_s
        st._rested_at = 0.0
        st._work()
        exact = st.map
        assert exact.version == fast.version + 1 and st.is_settled()
        assert len(exact.features) == len(full.features)
        for a, b in zip(exact.features, full.features, strict=True):
            np.testing.assert_array_equal(a.points, b.points)  # the full rebuild, bit for bit
        assert exact.drive_ids == full.drive_ids
        # on a map whose road changes were followed (another map than the stitch made), no fast
        # update: the same estimates again (a fusion's shape) are rebuilt in full
        st._put_followed(replace(exact, version=exact.version + 1), st._map_sig, [])
        for m in _msgs(res.tiles, ids_after, 3, counts):
            st.on_tile(m)
        st._rested_at = 0.0
        st._work()
        assert st.map.version == exact.version + 2 and st.is_settled()
    finally:
        st.destroy_node()


def test_the_mapper_fuses_in_its_own_process_and_sends_the_tiles_as_one_batch(ros, tmp_path):
    from hdmap_ros.nodes.map_stitcher import MapStitcher
    from hdmap_ros.nodes.segment_mapper import SegmentMapper
    from hdmap_ros.persistence.store import segments_to_blob

    drives = fuse_fleet()
    base, new = drives[:-1], drives[-1]
    t = rclpy_types()
    mapper = SegmentMapper(  # not spun: this test calls its turns
        context=ros.context,
        parameter_overrides=[
            Parameter("db_path", value=str(tmp_path / "m.db")),
            Parameter("workers", value=1),
            Parameter("republish_on_start", value=False),
        ],
    )
    stitcher = MapStitcher(
        context=ros.context,
        parameter_overrides=[
            Parameter("db_path", value=str(tmp_path / "s.db")),
            Parameter("drive_db_path", value=str(tmp_path / "m.db")),
            Parameter("follow_changes", value="off"),
        ],
    )
    batches, singles, pooled = [], [], []
    mapper._batch_pub = SimpleNamespace(publish=batches.append)
    mapper._seg_pub = SimpleNamespace(publish=singles.append)
    submit = mapper._pools[0].submit
    mapper._pools[0].submit = lambda fn, job, *a, **kw: pooled.append(job.kind) or submit(fn, job, *a, **kw)
    try:
        for d in base:
            mapper.on_drive(drive_to_msg(d, types=t))
        mapper.input_done()
        deadline = time.monotonic() + 300
        while not mapper.is_settled() and time.monotonic() < deadline:
            mapper.work()
        assert mapper.is_settled() and len(batches) == 1 and not singles  # the region: one batch
        stitcher.on_batch(batches[0])
        stitcher._work()
        assert set(stitcher.map.drive_ids) == {d.drive_id for d in base}

        mapper.on_drive(drive_to_msg(new, types=t))
        mapper.work()  # takes the drive and fuses it at once, here
        assert mapper.fast_fused == 1 and FUSE not in pooled and not singles
        assert len(batches) == 2
        tiles = batch_to_tiles(batches[1])
        mine = tiles_of_drive(new, config=mapper.tile_config)
        assert {e.tile.key for e in tiles} == mine
        for e in tiles:
            est = mapper.store.tile(e.tile.key)
            assert e.tile.final and e.tile.version == est.version and new.drive_id in e.tile.drive_ids
            assert e.tile.drive_tile_counts[e.tile.drive_ids.index(new.drive_id)] == len(mine)
            assert segments_to_blob(e.segments()) == est.segments_blob  # what the mapper stored
        stitcher.on_batch(batches[1])
        stitcher._rested_at = 0.0
        stitcher._work()  # one batch completes the drive: the map moved in place lists it
        assert new.drive_id in stitcher.map.drive_ids and "last_fast_update_s" in stitcher.health.extra
    finally:
        mapper.destroy_node()
        stitcher.destroy_node()
