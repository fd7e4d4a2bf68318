#!/usr/bin/env python3
"""Benchmark of the live mapper: one update for a long drive on an existing map, and replay speed.

Runs the real ``segment_mapper`` and ``map_stitcher`` node code in this process (an rclpy
context, no other process needed), feeding drives directly to their callbacks, so the figures are
the node's own work per update (message conversion, SQLite commit, per-tile mapping, stitching):

1. feeds the first ``--replay-drives`` drives one by one (each fully mapped and stitched) and keeps
   the per-drive service times; then adds the rest and settles, so the map holds ``--drives``
   drives with every tile estimated from all of its drives;
2. times one more update, a ``--long-km`` drive, in phases: the update (receive + commit =
   acknowledged; the stretches it adds mapped + stitched = on the map), then, measured apart, the
   background work (the debounced re-estimates + stitch; ``--profile N`` profiles it);
3. the long drive alone on an empty map (all its road new; ``--no-new-road`` skips it);
4. "replay at ``--rate``x": from the service times of step 1 and those drives' start times
   (simulator: 10-300 s apart), a single-server queue gives the backlog a live replay at that
   rate would see; a growing backlog means the mapper cannot keep up.

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
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "src/hdmap_core"), str(ROOT / "src/hdmap_ros")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", type=int, default=100, help="drives of the existing map (default 100)")
    ap.add_argument("--road-km", type=float, default=11.0, help="length of the synthetic motorway [km]")
    ap.add_argument("--snippet-m", type=float, nargs=2, default=(500.0, 2500.0), help="drive length range [m]")
    ap.add_argument("--long-km", type=float, default=10.0, help="length of the timed drive [km]")
    ap.add_argument("--rate", type=float, default=10.0, help="replay rate of the queue estimate")
    ap.add_argument("--replay-drives", type=int, default=20, help="drives fed one by one for the replay estimate")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=0, help="mapper processes (0: every CPU, 1: in this process)")
    ap.add_argument(
        "--min-growth-drives",
        type=int,
        default=None,
        help="override the mapper's min_growth_drives (default: the node's default)",
    )
    ap.add_argument(
        "--pivot-margin-m",
        type=float,
        default=None,
        help="override the mapper's pivot_margin_m (>= margin_m: walk the whole grown tile)",
    )
    ap.add_argument("--no-new-road", action="store_true", help="skip timing the long drive on an empty map")
    ap.add_argument(
        "--profile",
        type=int,
        default=0,
        metavar="N",
        help="print the N costliest functions (cProfile, cumulative) of the re-estimate phase",
    )
    args = ap.parse_args()
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_DOMAIN_ID", "79")

    import rclpy
    from rclpy.parameter import Parameter

    from hdmap_core.live.tiles import tiles_of_drive
    from hdmap_core.simulation.fleet import SimConfig, simulate_fleet
    from hdmap_core.simulation.synthetic import synthetic_highway
    from hdmap_ros.convert.messages import drive_to_msg, rclpy_types
    from hdmap_ros.convert.tiles import rclpy_tile_types, tile_to_msg
    from hdmap_ros.nodes.map_stitcher import MapStitcher
    from hdmap_ros.nodes.segment_mapper import SegmentMapper

    gt = synthetic_highway("motorway", length_m=args.road_km * 1000.0, seed=args.seed)
    lo, hi = args.snippet_m
    fleet = simulate_fleet(
        gt, config=SimConfig(n_drives=args.drives, snippet_length_min_m=lo, snippet_length_max_m=hi), seed=args.seed
    )
    long_m = args.long_km * 1000.0
    longs = simulate_fleet(
        gt, config=SimConfig(n_drives=20, snippet_length_min_m=long_m, snippet_length_max_m=long_m), seed=args.seed + 1
    ).drives
    long_drive = max(longs, key=lambda d: d.length_m)
    long_drive = replace(long_drive, drive_id="long-" + long_drive.drive_id)
    km = sum(d.length_m for d in fleet.drives) / 1000.0
    print(
        f"fleet: {len(fleet.drives)} drives, {km:.1f} km on a {args.road_km:.1f} km motorway; "
        f"timed drive {long_drive.length_m / 1000.0:.2f} km"
    )

    tmp = Path(tempfile.mkdtemp(prefix="hdmap-bench-"))
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
    mapper_overrides = (
        [Parameter("preset", value=args.preset), Parameter("workers", value=args.workers)]
        + ([Parameter("min_growth_drives", value=args.min_growth_drives)] if args.min_growth_drives else [])
        + ([Parameter("pivot_margin_m", value=args.pivot_margin_m)] if args.pivot_margin_m is not None else [])
    )
    mapper = SegmentMapper(
        context=ctx,
        parameter_overrides=[Parameter("db_path", value=str(tmp / "m.db")), Parameter("settle_after_s", value=3600.0)]
        + mapper_overrides,
    )
    stitcher = MapStitcher(
        context=ctx,
        parameter_overrides=[Parameter("db_path", value=str(tmp / "s.db")), Parameter("preset", value=args.preset)],
    )
    types, ttypes = rclpy_types(), rclpy_tile_types()

    # hand the mapper's tile messages straight to the stitcher (what DDS does between processes)
    def forward(est, *, final: bool | None = None, segments=None) -> None:
        counts = [mapper.scheduler.drive_tile_count(d) for d in est.drive_ids]
        stitcher.on_tile(
            tile_to_msg(
                est.key,
                list(segments) if segments is not None else est.segments(),
                version=est.version,
                drive_ids=est.drive_ids,
                tile_size_m=mapper.tile_config.tile_size_m,
                stamp_ns=0,
                types=ttypes,
                drive_tile_counts=counts,
                final=bool(final),
            )
        )

    mapper._publish = forward  # noqa: SLF001 - benchmark wiring, the node's own code otherwise
    mapper._batch_pub = SimpleNamespace(publish=stitcher.on_batch)  # noqa: SLF001 - the same for its batches

    def receive(drive) -> float:
        msg = drive_to_msg(drive, types=types)
        t0 = time.perf_counter()
        mapper.on_drive(msg)
        return time.perf_counter() - t0

    def run_until(pred, node=None) -> None:
        node = node or mapper
        while not pred():
            node.work()
            if node.scheduler.busy and node.workers > 1:
                time.sleep(0.002)  # the pool works; do not spin a core away from it

    def stitch() -> float:
        t0 = time.perf_counter()
        stitcher.rebuild()
        stitcher._first_dirty = None  # noqa: SLF001 - what the node's timer does before rebuilding
        return time.perf_counter() - t0

    def fresh_left() -> bool:
        sched = mapper.scheduler
        return bool(mapper.store.pending()) or any(not sched.is_mapped(k) for k in sched.queued())

    drives = sorted(fleet.drives, key=lambda d: d.start_ns)
    # 1. replay prefix drive by drive: per-drive service time = receive + every due tile + stitch,
    #    split into the update (receive, new tiles mapped, stitch) and the background re-estimates
    service, upd, first = [], [], None
    for d in drives[: args.replay_drives]:
        t0 = time.perf_counter()
        n_new = sum(not mapper.scheduler.is_mapped(k) for k in tiles_of_drive(d, config=mapper.tile_config))
        receive(d)
        run_until(lambda: not fresh_left())
        stitch()
        upd.append(time.perf_counter() - t0)
        if first is None:
            first = (d.length_m / 1000.0, n_new, upd[-1])
        run_until(lambda: not mapper.scheduler.queued() and not mapper.store.pending())
        stitch()
        service.append(time.perf_counter() - t0)
    # 2. the rest of the map: all drives in, every tile estimated once from all its drives
    t0 = time.perf_counter()
    for d in drives[args.replay_drives :]:
        receive(d)
    mapper.work()  # the drives handed to the schedule
    mapper.scheduler.settle_after_s = 0.0  # settle now
    run_until(mapper.is_settled)
    stitch()
    mapper.scheduler.settle_after_s = 3600.0
    build_s = time.perf_counter() - t0
    n_tiles = len(mapper.store.tiles())
    counts = [mapper.store.tile_drive_count(t.key) for t in mapper.store.tiles()]
    print(
        f"\nmap of {len(drives)} drives: {n_tiles} tiles, {len(stitcher.map.features)} features, "
        f"drives per tile median {sorted(counts)[len(counts) // 2]} (settled build {build_s:.1f} s)"
    )

    # 3. one update with the long drive
    def stitch_if_changed() -> float:
        return stitch() if stitcher._first_dirty is not None else 0.0  # noqa: SLF001 - the node rebuilds only then

    stitch_if_changed()
    new = tiles_of_drive(long_drive, config=mapper.tile_config) - {t.key for t in mapper.store.tiles()}
    updates0 = mapper.health.updates
    t_rx = receive(long_drive)
    slice_s, mapper.work_slice_s = mapper.work_slice_s, 0.0
    t0 = time.perf_counter()
    mapper.work()  # a turn without mapping time (workers=1): the drive's tiles are queued
    mapper.work_slice_s = slice_s
    run_until(lambda: not (new & mapper.scheduler.queued()))  # the stretches it adds are mapped
    t_new = time.perf_counter() - t0
    s_new = stitch_if_changed()
    queued, updates1 = len(mapper.scheduler.queued()), mapper.health.updates
    prof = None
    if args.profile:
        import cProfile

        prof = cProfile.Profile()
        prof.enable()
    t1 = time.perf_counter()
    run_until(lambda: not mapper.scheduler.queued())
    t_due = time.perf_counter() - t1
    if prof is not None:
        prof.disable()
    s_all = stitch_if_changed()
    n_re = mapper.health.updates - updates1
    print(
        f"one update, {long_drive.length_m / 1000:.2f} km drive over "
        f"{len(tiles_of_drive(long_drive, config=mapper.tile_config))} tiles ({len(new)} new, "
        f"{updates1 - updates0} mapped for it):"
    )
    print(f"  update: receive + commit (acknowledged)   {t_rx:7.3f} s")
    print(
        f"  update: new stretches mapped + stitched   {t_new + s_new:7.3f} s  (mapping {t_new:.3f}, stitch {s_new:.3f})"
    )
    print(f"  update total                              {t_rx + t_new + s_new:7.3f} s")
    print(
        f"  background: {queued} queued tiles checked, {n_re} due re-estimated + stitch {t_due + s_all:7.3f} s "
        f"(mapping {t_due:.3f}, stitch {s_all:.3f})"
    )
    print(f"  update + background                       {t_rx + t_new + s_new + t_due + s_all:7.3f} s")
    print(f"  last map rebuild: {stitcher.health.extra.get('last_rebuild_parts_s')}")
    if prof is not None:
        import pstats

        pstats.Stats(prof).sort_stats("cumulative").print_stats(args.profile)

    # 4. the long drive alone on an empty map: every stretch it covers is new road
    if not args.no_new_road:
        fresh = SegmentMapper(
            context=ctx,
            parameter_overrides=[
                Parameter("db_path", value=str(tmp / "m2.db")),
                Parameter("settle_after_s", value=3600.0),
                Parameter("republish_on_start", value=False),
            ]
            + mapper_overrides,
        )
        fresh._publish = lambda est, final=None, segments=None: None  # noqa: SLF001 - mapping only; the stitch is timed above
        fresh._batch_pub = SimpleNamespace(publish=lambda msg: None)  # noqa: SLF001
        msg = drive_to_msg(long_drive, types=types)
        t0 = time.perf_counter()
        fresh.on_drive(msg)
        fresh.work()
        run_until(lambda: not fresh.scheduler.queued() and not fresh.store.pending(), fresh)
        t_fresh = time.perf_counter() - t0
        n_fresh = len(fresh.store.tiles())
        print(
            f"the {long_drive.length_m / 1000:.2f} km drive on an empty map (all road new): {n_fresh} tiles "
            f"mapped in {t_fresh:.2f} s ({t_fresh / max(n_fresh, 1):.3f} s per tile), without the stitch"
        )
        fresh.destroy_node()
    # 5. single-server queue at the given replay rate over the drive-by-drive prefix
    if first is not None:
        print(
            f"first drive (all road new): {first[0]:.2f} km, {first[1]} tiles, update {first[2]:.2f} s "
            f"({first[2] / max(first[1], 1):.2f} s per tile)"
        )
    if upd:
        print(
            f"drive-by-drive prefix: update (ack + new tiles + stitch) {min(upd):.2f}-{max(upd):.2f} s "
            f"(mean {sum(upd) / len(upd):.2f} s); with background re-estimates {min(service):.2f}-{max(service):.2f} s"
        )
    if service:
        starts = [d.start_ns for d in drives[: len(service)]]
        arrive = [(s - starts[0]) / 1e9 / args.rate for s in starts]
        free, backlog_max, late = 0.0, 0, []
        for a, s in zip(arrive, service):
            free = max(a, free) + s
            late.append(free - a)
            backlog_max = max(backlog_max, sum(1 for x in arrive if a <= x < free))
        gaps = [b - a for a, b in zip(arrive, arrive[1:])] or [0.0]
        print(
            f"replay at {args.rate:g}x, first {len(service)} drives one by one: arrivals every "
            f"{min(gaps):.1f}-{max(gaps):.1f} s (mean {sum(gaps) / len(gaps):.1f} s), "
            f"service {min(service):.2f}-{max(service):.2f} s "
            f"(mean {sum(service) / len(service):.2f} s): max backlog {backlog_max}, max delay {max(late):.1f} s, "
            f"last {late[-1]:.1f} s"
        )
    mapper.destroy_node()
    stitcher.destroy_node()
    rclpy.try_shutdown(context=ctx)
    return 0


if __name__ == "__main__":
    sys.exit(main())
