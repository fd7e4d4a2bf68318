"""Where the time of one map build goes: stage times and a cProfile of ``pipeline.build_map``.

    .venv/bin/python scripts/profile_build.py out/bench/fleets/paper_like_134_s1 [--preset default] [--top 25]

The bag is a fleet bag as ``hdmap simulate`` / ``hdmap bench --work-dir`` write them. Prints the
pipeline's own stage times (``BuildReport.stage_seconds``, measured without the profiler), then the
same build under cProfile: the functions with the largest cumulative time, and the own time summed
per ``hdmap_core`` module. Run by hand on an otherwise idle machine; nothing here is asserted.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time
from collections import defaultdict


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag", help="fleet bag")
    ap.add_argument("--preset", default="default", help="pipeline preset (default: %(default)s)")
    ap.add_argument("--top", type=int, default=25, help="functions to list (default: %(default)s)")
    args = ap.parse_args()

    from hdmap_core.pipeline import driver as pipeline
    from hdmap_core.pipeline.overrides import config_from
    from hdmap_ros.io.bagio import read_fleet_bag

    drives = read_fleet_bag(args.bag).drives
    config = config_from(args.preset)
    t0 = time.perf_counter()
    result = pipeline.build_map(drives, config=config, seed=0)
    wall = time.perf_counter() - t0
    km = sum(d.length_m for d in drives) / 1000.0
    print(f"{args.bag}: {len(drives)} drives, {km:.1f} drive-km, preset {args.preset}: build {wall:.1f} s")
    for stage, sec in result.report.stage_seconds.items():
        print(f"  {stage:<14} {sec:7.2f} s  {100.0 * sec / wall:5.1f} %")

    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.runcall(pipeline.build_map, drives, config=config, seed=0)
    print(f"\nunder cProfile: {time.perf_counter() - t0:.1f} s; largest cumulative times:")
    stats = pstats.Stats(prof)
    stats.sort_stats("cumulative").print_stats(r"hdmap_core", args.top)
    per_module: dict[str, float] = defaultdict(float)
    for (path, _line, _name), (_cc, _nc, own, _cum, _callers) in stats.stats.items():  # type: ignore[attr-defined]
        key = path.split("hdmap_core/")[-1] if "hdmap_core/" in path else "(numpy, scipy, other)"
        per_module[key] += own
    print("own time per module:")
    for key, own in sorted(per_module.items(), key=lambda kv: -kv[1])[:15]:
        print(f"  {key:<28} {own:7.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
