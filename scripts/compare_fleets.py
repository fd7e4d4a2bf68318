#!/usr/bin/env python3
"""Build maps of fleet bags with a preset and parameter overrides, score them, one line per fleet.

The tool behind the "measured on the 28 fleets" tables of docs/graph.md and docs/pipeline.md: a
rule or parameter is measured by running this twice on the same bags, without and with the
override (``--set``), and comparing the lines. It builds in this process (no peak-memory
figure; ``hdmap bench`` is the side-by-side comparison of the presets with time and memory).

Each SCENARIO is a fleet bag with ``BAG.gt.json`` beside it (and ``BAG.sim.json`` for the
floor and the observed share), or ``MAP:DRIVES[:SEEDS]`` to simulate into ``--work-dir``, as
``hdmap bench`` takes them. Columns: mean and offset-corrected mean lateral error [m],
coverage, recall, observed share, recall over the observed points, precision [%],
fragmentation, road splits,merges found/in GT, long topology links supported/evaluable,
build time [s].

Usage (from the repository root, after ``make setup``):
    .venv/bin/python scripts/compare_fleets.py bags/ramps_20 bags/e6mini_20
    .venv/bin/python scripts/compare_fleets.py bags/ramps_20 --set stitching.max_distance_m=8
    .venv/bin/python scripts/compare_fleets.py carla_town04:30:1-3 --work-dir out/fleets --save out/maps
"""

from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path

from hdmap_core.errors import ConfigError, HdmapError
from hdmap_core.pipeline.overrides import config_from
from hdmap_ros.commands.bag2map import add_set_argument
from hdmap_ros.commands.bench import SCORE_COLUMNS, build_and_evaluate, prepare_scenarios, score_line


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenarios", nargs="+", metavar="SCENARIO")
    parser.add_argument("--preset", default="default", help="pipeline preset (default: default)")
    add_set_argument(parser, "change a preset parameter, as `hdmap bag2map --set` (repeatable)", dest="set")
    parser.add_argument("--seed", type=int, default=0, help="pipeline seed (default: 0)")
    parser.add_argument("--workers", type=int, default=None, help="processes per build (default: the CPUs)")
    parser.add_argument("--work-dir", type=Path, default=Path("out/fleets"), help="simulated bags go here")
    parser.add_argument("--save", type=Path, default=None, help="pickle each map and report to DIR/NAME.pkl")
    args = parser.parse_args(argv)
    try:
        config = config_from(args.preset, dict(args.set))
    except ConfigError as err:
        print(f"compare_fleets: --set {err}", file=sys.stderr)
        return 2
    try:
        scenarios = prepare_scenarios(args.scenarios, scales=[1.0], work_dir=args.work_dir)
    except HdmapError as err:  # a spec that is no bag and no MAP:DRIVES, an unknown map
        print(f"compare_fleets: {err}", file=sys.stderr)
        return 2
    print(SCORE_COLUMNS, flush=True)
    failed = 0
    for sc in scenarios:
        try:
            line = _score(sc, config, args)
        except HdmapError as err:  # a bag or ground truth that cannot be used: named, the rest goes on
            print(f"compare_fleets: {sc.name}: {err}", file=sys.stderr)
            failed += 1
            continue
        print(line, flush=True)
    return 1 if failed else 0


def _score(sc: object, config: object, args: argparse.Namespace) -> str:
    """Build and score one scenario (as ``hdmap bench`` does): its ``SCORE_COLUMNS`` line (and the
    pickle with ``--save``)."""
    _fleet, result, report, build_s, _workers = build_and_evaluate(sc, config, args.seed, args.workers)
    if args.save is not None:
        args.save.mkdir(parents=True, exist_ok=True)
        with open(args.save / f"{sc.name}.pkl", "wb") as f:
            pickle.dump({"map": result.map, "rep": report}, f)
    return score_line(sc.name, report, build_s)


if __name__ == "__main__":
    sys.exit(main())
