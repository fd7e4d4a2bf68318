#!/usr/bin/env python3
"""CPU time of the live fast path, stage by stage: one drive fused into settled tiles until the map
that lists it is serialised, with the full re-stitch (before) and the map moved in place (now).

    .venv/bin/python scripts/profile_fast_path.py STATE FLEET_BAG DRIVE_ID [--repeat 2]

STATE: a live state folder with a settled map (``hdmap run --state``, e.g. the ``state`` folder a
``scripts/bench_live.py --latency --out DIR`` run leaves); FLEET_BAG: the fleet bag; DRIVE_ID: a
drive of it on mapped road (``bench_live.py`` prints the one it fuses). The map's tiles are those
the fleet's drives cover (tiles of other drives in the store are left out); the drive is fused
into its tiles' stored estimates (a stand-in for the settled map without it: a drive already in
the settle is fused again, the same work). Stages, in one process (``time.process_time``, so the
figures hold on a shared machine; DDS transport, SQLite fsyncs and scheduling are not in them):

- the hand-over from the mapper to the stitcher, **per tile** (before 2026-12-07 live-fast3: the
  tiles' segments pickled to a worker process and the fused ones back, one TileSegments per tile
  made, serialised, deserialised and read, each tile's segments encoded for the stitcher's store)
  against **batch** (now: the fusion in the mapper's process on its decoded segments, one
  TileSegmentsBatch in columns, the store's blobs made from the columns, the segments made from
  them for the moved graphs);
- common to both: ``fuse_drive`` and the mapper's store encoding (``segments_to_blob``);
- stitcher: **before** (main until 2026-12-07 live-stitch): ``connect_tile`` of the touched tiles,
  ``stitch_graphs`` of all, ``carry_over_ids``, ``map_to_msg``; **now** (``live.restitch``):
  ``moved_graphs``, ``moved_map``, ``remap_ids``, ``map_to_msg`` with the last map's messages of
  unchanged topology nodes reused; and the CDR serialisation of the map.

Prints figures only; nothing is asserted.
"""

from __future__ import annotations

import argparse
import pickle
import time


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("state")
    ap.add_argument("fleet")
    ap.add_argument("drive_id")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()

    from rclpy.serialization import deserialize_message, serialize_message

    from hdmap_core.live.fuse import fuse_drive
    from hdmap_core.live.restitch import moved_graphs, moved_map, raw_id_map, remap_ids, stitch_tiles
    from hdmap_core.live.tiles import TileConfig, carry_over_ids, connect_tile, stitch_graphs, tiles_of_drive
    from hdmap_core.pipeline.overrides import config_from
    from hdmap_ros.convert.messages import map_to_msg, rclpy_types
    from hdmap_ros.convert.tiles import batch_to_tiles, msg_to_tile, rclpy_tile_types, tile_to_msg, tiles_to_batch
    from hdmap_ros.io.bagio import read_fleet_bag
    from hdmap_ros.io.cdr import encode_map
    from hdmap_ros.persistence.store import MapStore, blob_to_segments, columns_to_blob, segments_to_blob

    cfg = config_from(args.preset, {})
    tc = TileConfig()
    P = time.process_time
    drives = read_fleet_bag(args.fleet).drives
    drive = next(d for d in drives if d.drive_id == args.drive_id)
    fleet_tiles = set().union(*[tiles_of_drive(d, config=tc) for d in drives])
    store = MapStore(f"{args.state}/map_stitcher.db")
    blobs = {k: b for k, _, _, b in store.tiles() if k in fleet_tiles}
    store.close()
    touched = sorted(tiles_of_drive(drive, config=tc) & set(blobs))
    segs = {k: blob_to_segments(b) for k, b in blobs.items()}
    graphs = {k: connect_tile(segs[k], k, pipeline_config=cfg) for k in sorted(segs)}
    raw0, mg = stitch_tiles([g for k in sorted(graphs) for g in graphs[k]], pipeline_config=cfg)
    types, tile_types = rclpy_types(), rclpy_tile_types()
    pub0 = carry_over_ids(raw0, None)
    ids0 = raw_id_map(raw0, pub0)
    print(f"{len(segs)} tiles in the map ({len(pub0.features)} features), {len(touched)} touched by {drive.drive_id}")
    for _ in range(max(1, args.repeat)):
        st: dict[str, float] = {}
        per_tile: dict[str, float] = {}
        batch: dict[str, float] = {}
        mine = {k: segs[k] for k in touched}
        t = P()
        res = fuse_drive(drive, mine)
        st["mapper: fuse_drive"] = P() - t
        if res.tiles is None:
            print(f"the drive is refused: {res.reason}")
            return 1
        fused = res.tiles
        t = P()
        for k in touched:
            segments_to_blob(fused[k])
        st["mapper: encode the estimates (store)"] = P() - t
        # per tile (before)
        t = P()
        pickle.loads(pickle.dumps((drive, mine)))
        pickle.loads(pickle.dumps(fused))
        per_tile["mapper: job input and result pickled"] = P() - t
        t = P()
        msgs = [
            tile_to_msg(k, fused[k], version=2, drive_ids=[], tile_size_m=tc.tile_size_m, stamp_ns=0, types=tile_types)
            for k in touched
        ]
        wire = [serialize_message(m) for m in msgs]
        per_tile["mapper: tile messages + CDR"] = P() - t
        t = P()
        got = {}
        for b in wire:
            tile = msg_to_tile(deserialize_message(b, type(msgs[0])))
            got[tile.key] = list(tile.segments)
        per_tile["stitcher: CDR + msg_to_tile"] = P() - t
        t = P()
        for k in touched:
            segments_to_blob(got[k])
        per_tile["stitcher: encode for the store"] = P() - t
        # batch (now)
        t = P()
        bmsg = tiles_to_batch(
            [(k, fused[k], 2, [drive.drive_id], [len(touched)], True) for k in touched],
            tile_size_m=tc.tile_size_m,
            stamp_ns=0,
            types=tile_types,
        )
        bwire = serialize_message(bmsg)
        batch["mapper: batch message + CDR"] = P() - t
        t = P()
        entries = batch_to_tiles(deserialize_message(bwire, type(bmsg)))
        batch["stitcher: CDR + batch_to_tiles"] = P() - t
        t = P()
        for e in entries:
            columns_to_blob(e.columns)
        batch["stitcher: blobs from the columns"] = P() - t
        t = P()
        got = {e.tile.key: e.segments() for e in entries}
        batch["stitcher: segments from the columns"] = P() - t
        print(f"  batch message: {len(bwire) / 1e6:.2f} MB; tile messages: {sum(len(b) for b in wire) / 1e6:.2f} MB")
        for name, v in per_tile.items():
            print(f"  per tile  {name:38s} {v:6.3f} s")
        print(f"  per tile  {'= hand-over':38s} {sum(per_tile.values()):6.3f} s")
        for name, v in batch.items():
            print(f"  batch     {name:38s} {v:6.3f} s")
        print(f"  batch     {'= hand-over':38s} {sum(batch.values()):6.3f} s")
        common_before = sum(st.values()) + sum(per_tile.values())
        common = sum(st.values()) + sum(batch.values())
        t = P()
        g2 = dict(graphs)
        g2.update({k: connect_tile(got[k], k, pipeline_config=cfg) for k in touched})
        b_connect = P() - t
        t = P()
        raw = stitch_graphs([g for k in sorted(g2) for g in g2[k]], pipeline_config=cfg)
        b_stitch = P() - t
        t = P()
        new = carry_over_ids(raw, pub0)
        b_ids = P() - t
        t = P()
        serialize_message(map_to_msg(new, types=types))
        b_msg = P() - t
        before = b_connect + b_stitch + b_ids + b_msg
        t = P()
        moved = [g for k in touched for g in moved_graphs(graphs[k], segs[k], got[k]) or []]
        n_move = P() - t
        t = P()
        raw1, _ = moved_map(mg, moved)
        n_export = P() - t
        t = P()
        new1 = remap_ids(raw1, ids0) or carry_over_ids(raw1, pub0)
        n_ids = P() - t
        t = P()
        encode_map(new1)
        n_msg = P() - t
        now = n_move + n_export + n_ids + n_msg
        for name, v in st.items():
            print(f"  {name:48s} {v:6.3f} s")
        print(
            f"  stitcher before: connect {b_connect:.3f} + stitch {b_stitch:.3f} + ids {b_ids:.3f} + map message "
            f"{b_msg:.3f} = {before:.3f} s"
        )
        print(
            f"  stitcher now:    move {n_move:.3f} + export {n_export:.3f} + ids {n_ids:.3f} + map message "
            f"{n_msg:.3f} (encode_map) = {now:.3f} s  ({before / now:.1f}x less)"
        )
        print(
            f"  chain CPU (mapper + hand-over + stitcher): main before live-stitch {common_before + before:.2f} s, "
            f"per tile + moved {common_before + now:.2f} s, now {common + now:.2f} s"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
