#!/usr/bin/env python3
"""Benchmark of the live mapper: one update for a long drive on an existing map, and replay speed.

Runs the real ``segment_mapper`` and ``map_stitcher`` node code in this process (an rclpy
context, no other process needed), feeding drives directly to their callbacks, so the figures are
the node's own work per update (message conversion, SQLite commit, per-tile mapping, stitching):

1. builds a map from ``--drives`` simulated drives on a synthetic motorway, drive by drive;
2. times one more update: a ``--long-km`` drive (receive + commit, tile re-estimates, stitch);
3. "replay at ``--rate``x": from the measured per-drive service times and the bag's drive start
   times (simulator: 10-300 s apart), a single-server queue gives the backlog a live replay at
   that rate would see (max and final); a growing backlog means the mapper cannot keep up.

Prints the figures; no assertions. Example (the default is a small run):

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST .venv/bin/python scripts/bench_incremental.py --drives 100
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "src/hdmap_core"), str(ROOT / "src/hdmap_ros")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", type=int, default=100, help="drives of the existing map (default 100)")
    ap.add_argument("--road-km", type=float, default=11.0, help="length of the synthetic motorway [km]")
    ap.add_argument("--snippet-m", type=float, nargs=2, default=(500.0, 2500.0), help="drive length range [m]")
    ap.add_argument("--long-km", type=float, default=10.0, help="length of the timed drive [km]")
    ap.add_argument("--rate", type=float, default=10.0, help="replay rate of the queue estimate")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_DOMAIN_ID", "79")

    import rclpy
    from rclpy.parameter import Parameter

    from hdmap_core.simulate import SimConfig, simulate_fleet
    from hdmap_core.synthetic import synthetic_highway
    from hdmap_ros.convert import drive_to_msg, rclpy_types
    from hdmap_ros.nodes.map_stitcher import MapStitcher
    from hdmap_ros.nodes.segment_mapper import SegmentMapper
    from hdmap_ros.nodes.tile_msgs import rclpy_tile_types, tile_to_msg

    gt = synthetic_highway("motorway", length_m=args.road_km * 1000.0, seed=args.seed)
    lo, hi = args.snippet_m
    fleet = simulate_fleet(gt, config=SimConfig(n_drives=args.drives, snippet_length_min_m=lo, snippet_length_max_m=hi),
                           seed=args.seed)
    long_m = args.long_km * 1000.0
    longs = simulate_fleet(gt, config=SimConfig(n_drives=20, snippet_length_min_m=long_m, snippet_length_max_m=long_m),
                           seed=args.seed + 1).drives
    long_drive = max(longs, key=lambda d: d.length_m)
    long_drive = replace(long_drive, drive_id="long-" + long_drive.drive_id)
    km = sum(d.length_m for d in fleet.drives) / 1000.0
    print(f"fleet: {len(fleet.drives)} drives, {km:.1f} km on a {args.road_km:.1f} km motorway; "
          f"timed drive {long_drive.length_m / 1000.0:.2f} km")

    tmp = Path(tempfile.mkdtemp(prefix="hdmap-bench-"))
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
    mapper = SegmentMapper(context=ctx, parameter_overrides=[
        Parameter("db_path", value=str(tmp / "m.db")), Parameter("settle_after_s", value=3600.0),
        Parameter("preset", value=args.preset)])
    stitcher = MapStitcher(context=ctx, parameter_overrides=[
        Parameter("db_path", value=str(tmp / "s.db")), Parameter("preset", value=args.preset)])
    types, ttypes = rclpy_types(), rclpy_tile_types()

    # hand the mapper's tile messages straight to the stitcher (what DDS does between processes)
    def forward(est) -> None:
        stitcher.on_tile(tile_to_msg(est.key, est.segments(), version=est.version, drive_ids=est.drive_ids,
                                     tile_size_m=mapper.tile_config.tile_size_m, stamp_ns=0, types=ttypes))

    mapper._publish = forward  # noqa: SLF001 - benchmark wiring, the node's own code otherwise

    def update(drive) -> tuple[float, float, float]:
        msg = drive_to_msg(drive, types=types)
        t0 = time.perf_counter()
        mapper.on_drive(msg)
        t1 = time.perf_counter()
        mapper.work()
        t2 = time.perf_counter()
        stitcher.rebuild()
        t3 = time.perf_counter()
        return t1 - t0, t2 - t1, t3 - t2

    service = []
    t_build = time.perf_counter()
    for i, d in enumerate(sorted(fleet.drives, key=lambda d: d.start_ns)):
        rx, mp, st = update(d)
        service.append(rx + mp + st)
        if (i + 1) % 10 == 0:
            print(f"  {i + 1:4d} drives: last update {service[-1]:.2f} s "
                  f"(tiles {len(mapper.store.tiles())}, features {len(stitcher.map.features) if stitcher.map else 0})",
                  flush=True)
    build_s = time.perf_counter() - t_build
    n_tiles = len(mapper.store.tiles())
    rx, mp, st = update(long_drive)
    print(f"\nbuilt map of {len(fleet.drives)} drives drive by drive in {build_s:.1f} s ({n_tiles} tiles)")
    print(f"one update, {long_drive.length_m / 1000:.2f} km drive: {rx + mp + st:.2f} s "
          f"(receive+commit {rx:.3f} s, tile re-estimates {mp:.2f} s, stitch {st:.2f} s)")

    # single-server queue at the given replay rate: arrivals = drive starts / rate
    starts = sorted(d.start_ns for d in fleet.drives)
    arrive = [(s - starts[0]) / 1e9 / args.rate for s in starts]
    free, backlog_max, done_at = 0.0, 0, []
    for a, s in zip(arrive, service):
        begin = max(a, free)
        free = begin + s
        done_at.append(free)
        backlog_max = max(backlog_max, sum(1 for x in arrive if a <= x < free))
    late = [f - a for a, f in zip(arrive, done_at)]
    gaps = [b - a for a, b in zip(arrive, arrive[1:])] or [0.0]
    print(f"replay at {args.rate:g}x: drives arrive every {min(gaps):.1f}-{max(gaps):.1f} s, "
          f"service {min(service):.2f}-{max(service):.2f} s (mean {sum(service) / len(service):.2f} s); "
          f"max backlog {backlog_max} drive(s), max delay {max(late):.1f} s, last drive done {late[-1]:.1f} s after arrival")
    mapper.destroy_node()
    stitcher.destroy_node()
    rclpy.try_shutdown(context=ctx)
    return 0


if __name__ == "__main__":
    sys.exit(main())
