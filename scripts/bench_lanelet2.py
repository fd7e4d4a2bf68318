#!/usr/bin/env python3
"""Benchmark of the Lanelet2 export: lanes derived from a map bag and written, timed.

Times each part (cross sections, runs and joints, writing the .osm) ``--repeat`` times and
prints the best wall time and the CPU time (``time.process_time``: less sensitive to other jobs
on a shared machine). Prints figures; no assertions. Example:

    .venv/bin/python scripts/bench_lanelet2.py MAP_BAG [--repeat 3]
"""

from __future__ import annotations

import argparse
import tempfile
import time

from hdmap_core.lanes.derive import derive_lanes
from hdmap_ros.io.bagio import read_map_bag
from hdmap_ros.io.lanelet2 import write_lanelet2


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("map", help="map bag with /hdmap/map and /fleet/origin")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    hdmap = read_map_bag(args.map)
    origin = hdmap.extra.get("origin")
    if origin is None:
        raise SystemExit(f"{args.map} has no /fleet/origin")
    best: dict[str, tuple[float, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.repeat):
            w0, c0 = time.perf_counter(), time.process_time()
            lanes = derive_lanes(hdmap)
            w1, c1 = time.perf_counter(), time.process_time()
            write_lanelet2(lanes, origin, tmp)
            w2, c2 = time.perf_counter(), time.process_time()
            for name, w, c in (("derive", w1 - w0, c1 - c0), ("write", w2 - w1, c2 - c1), ("total", w2 - w0, c2 - c0)):
                bw, bc = best.get(name, (float("inf"), float("inf")))
                best[name] = (min(bw, w), min(bc, c))
    km = sum(ln.length_m for ln in lanes.lanes) / 1000.0
    print(
        f"{args.map}: {len(hdmap.features)} features, {len(hdmap.topology)} topology nodes -> "
        f"{len(lanes.lanes)} lanelets ({km:.1f} km)"
    )
    for name, (w, c) in best.items():
        print(f"  {name:7s} wall {w:6.2f} s   cpu {c:6.2f} s   (best of {args.repeat})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
