#!/usr/bin/env python3
"""Where the live suite's settle spends its CPU, against the offline build of the same drives.

    .venv/bin/python scripts/profile_live.py FLEET_BAG [--preset default] [--profile remap]

CPU time (``time.process_time``) in this one process, so the figures hold on a shared machine
(wall times of ``scripts/bench_live.py`` do not). Offline: ``build_map`` stage by stage. Live, with
the segment mapper's default tiling (256 m tiles, 128 m margin, pivots 48 m around the tile) and
every drive already there (``hdmap run --rate 0`` after the bag played): every tile's preview
(``live.jobs.run_job`` MAP), the fleet offset model, every tile's settle job (REMAP), the
connection per tile and one stitch of all tiles (as the map stitcher makes it), the carry-over of
feature ids; then the region settle (``live.region.map_region``: every tile from one offline build
of all drives, ``--region-workers`` processes) and its stitch; with the ground truth
(``BAG.gt.json``) the offline, tile-by-tile and region maps scored. ``--profile KIND``: a
cProfile of that phase (preview, remap, stitch, region), top functions.
Prints figures only; nothing is asserted.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import time
from collections import defaultdict
from typing import Any


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag", help="fleet bag")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--profile", default="", help="cProfile one phase: preview, remap, stitch or region")
    ap.add_argument("--top", type=int, default=20)
    ap.add_argument("--skip-offline", action="store_true")
    ap.add_argument("--tile-size", type=float, default=256.0, help="tile_size_m (the mapper's default 256)")
    ap.add_argument("--margin", type=float, default=128.0, help="margin_m (the mapper's default 128)")
    ap.add_argument("--gt", default="", help="ground truth (default BAG.gt.json if there): score the settled maps")
    ap.add_argument(
        "--region-workers", type=int, default=1, help="processes of the region build (1: CPU in one process)"
    )
    args = ap.parse_args()

    from hdmap_core.live.jobs import JobResult, run_job
    from hdmap_core.live.region import map_region
    from hdmap_core.live.scheduler import MAP, REMAP, Job
    from hdmap_core.live.tiles import (
        TileConfig,
        carry_over_ids,
        connect_tile,
        fleet_offsets,
        stitch_graphs,
        tiles_of_drive,
    )
    from hdmap_core.pipeline.driver import build_map
    from hdmap_core.pipeline.overrides import config_from
    from hdmap_ros.io.bagio import read_fleet_bag

    drives = read_fleet_bag(args.bag).drives
    pc = config_from(args.preset)
    tc = TileConfig(tile_size_m=args.tile_size, margin_m=args.margin, pivot_margin_m=48.0)
    by_id = {d.drive_id: d for d in drives}
    print(f"{args.bag}: {len(drives)} drives, {sum(d.length_m for d in drives) / 1000:.1f} drive-km")

    if not args.skip_offline:
        c0 = time.process_time()
        res = build_map(drives, config=pc)
        cpu = time.process_time() - c0
        stages = ", ".join(f"{k} {v:.2f}" for k, v in res.report.stage_seconds.items())
        print(f"offline build_map CPU {cpu:.2f} s ({stages})")

    tiles: dict[tuple[int, int], list[str]] = defaultdict(list)
    for d in drives:
        for k in tiles_of_drive(d, config=tc):
            tiles[k].append(d.drive_id)
    keys = sorted(tiles)
    kw: dict[str, Any] = {"tile_config": tc, "pipeline_config": pc, "use_fleet_model": True}
    prof = cProfile.Profile()

    def phase(name, fn):
        if args.profile == name:
            prof.enable()
        c0 = time.process_time()
        out = fn()
        cpu = time.process_time() - c0
        if args.profile == name:
            prof.disable()
        return out, cpu

    def jobs(kind, model=None):
        out = {}
        for k in keys:
            ids = tuple(sorted(tiles[k]))
            job = Job(kind, k, ids, "m" if kind == REMAP else "", final=kind == REMAP)
            out[k] = run_job(job, [by_id[i] for i in ids], offset_model=model, **kw)
        return out

    prev, t_prev = phase("preview", lambda: jobs(MAP))
    obs = [o for k in keys for o in (prev[k].observations or [])]
    model, t_model = phase("model", lambda: fleet_offsets(obs, pipeline_config=pc))
    remap, t_remap = phase("remap", lambda: jobs(REMAP, model))

    def stitch(results):
        graphs = [g for k in keys for g in connect_tile(results[k].segments or [], k, pipeline_config=pc)]
        return stitch_graphs(graphs, pipeline_config=pc, drive_ids=by_id)

    m_prev, _ = phase("", lambda: stitch(prev))
    m_new, t_stitch = phase("stitch", lambda: stitch(remap))
    _, t_ids = phase("ids", lambda: carry_over_ids(m_new, m_prev))
    # a version in which one tile changed: the settled map with one tile's preview instead
    one = dict(remap)
    one[keys[len(keys) // 2]] = prev[keys[len(keys) // 2]]
    m_one, t_stitch1 = phase("", lambda: stitch(one))
    _, t_ids1 = phase("", lambda: carry_over_ids(m_new, m_one))
    # the settle as one region (live.region): the offline passes on the whole drives, cut into tiles
    reg, t_region = phase(
        "region",
        lambda: map_region(drives, keys, tile_config=tc, pipeline_config=pc, workers=args.region_workers),
    )
    m_reg, t_stitch_r = phase("", lambda: stitch({k: JobResult(segments=reg.segments[k]) for k in keys}))
    print(
        f"live: {len(keys)} tiles of {tc.tile_size_m:g} m (margin {tc.margin_m:g} m); preview {t_prev:.2f} s, "
        f"model {t_model:.2f} s, remap {t_remap:.2f} s, connect+stitch {t_stitch:.2f} s, ids {t_ids:.2f} s "
        f"(one tile changed: connect+stitch {t_stitch1:.2f} s, ids {t_ids1:.2f} s)"
    )
    print(
        f"region: the whole map as one region: build {t_region:.2f} s CPU (this process; workers "
        f"{args.region_workers}), connect+stitch {t_stitch_r:.2f} s; tile path preview+model+remap "
        f"{t_prev + t_model + t_remap:.2f} s"
    )
    gt_path = args.gt or (args.bag.rstrip("/") + ".gt.json")
    if os.path.exists(gt_path):
        from hdmap_core.evaluation.evaluate import evaluate_map
        from hdmap_core.groundtruth import load_ground_truth

        gt = load_ground_truth(gt_path)
        maps = [("tiles (remap)", m_new), ("region", m_reg)]
        if not args.skip_offline:
            maps.insert(0, ("offline build_map", res.map))
        for name, m in maps:
            rep = evaluate_map(m, gt)
            print(f"  {name}: mean error {rep.overall.mean_m:.3f} m, coverage {100 * rep.overall.coverage:.1f} %")
    if args.profile:
        st = pstats.Stats(prof)
        st.sort_stats("cumulative").print_stats(args.top)
        own: dict[str, float] = defaultdict(float)
        for (file, _line, _fn), (_cc, _nc, tt, _ct, _callers) in st.stats.items():  # type: ignore[attr-defined]
            if "hdmap_core" in file:
                own[file.split("hdmap_core/")[-1]] += tt
        for mod, tt in sorted(own.items(), key=lambda kv: -kv[1])[:15]:
            print(f"  {tt:7.2f} s  {mod}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
