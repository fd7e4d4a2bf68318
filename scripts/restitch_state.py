#!/usr/bin/env python3
"""Rebuild the live map offline from a node run's stored tiles, to debug what the live map does.

``hdmap run BAG --state DIR`` keeps the nodes' SQLite stores in DIR. ``map_stitcher.db`` there
holds the latest segments of every tile; the map_stitcher makes the map from them by connecting
each tile's segments (``incremental.connect_tile``) and stitching all the graphs
(``incremental.stitch_graphs``). This script does the same in one process, with the preset and
``--set`` changes of ``hdmap bag2map``. The default preset reproduces the live map
(docs/graph.md "Side steps": carla_town04_100_s2's live run on e6b3f41 and its stored tiles
re-stitched, 83/87 long links in both). With ``--gt`` it
scores the map and lists the false long topology links, so a rule can be tried on the live
map's own tiles in seconds instead of a replay of minutes.

Usage (from the repository root, after ``make setup``):
    .venv/bin/hdmap run out/fleets/carla_town04_100_s2 -o out/live --state out/live_state -q
    .venv/bin/python scripts/restitch_state.py out/live_state --gt out/fleets/carla_town04_100_s2.gt.json
    .venv/bin/python scripts/restitch_state.py out/live_state --gt ... --set stitching.max_distance_m=8
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from hdmap_core.errors import HdmapError
from hdmap_core.evaluation.evaluate import evaluate_map
from hdmap_core.groundtruth import load_ground_truth
from hdmap_core.live.tiles import connect_tile, stitch_graphs
from hdmap_core.pipeline.overrides import config_from
from hdmap_ros.commands.bag2map import add_set_argument
from hdmap_ros.commands.bench import SCORE_COLUMNS, score_line
from hdmap_ros.persistence.store import MapStore, blob_to_segments


def restitch(state_dir: Path, config: object):
    """The map the map_stitcher makes from ``state_dir/map_stitcher.db``, and its tile count."""
    db = Path(state_dir) / "map_stitcher.db"
    if not db.is_file():
        raise HdmapError(f"{db}: no map_stitcher store (run `hdmap run BAG --state {state_dir}` first)")
    graphs, drive_ids, tiles = [], set(), MapStore(db).tiles()
    for key, _version, ids, blob in tiles:
        graphs += connect_tile(blob_to_segments(blob), key, pipeline_config=config)
        drive_ids.update(ids)
    return stitch_graphs(graphs, pipeline_config=config, drive_ids=drive_ids), len(tiles)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("state", type=Path, help="the --state directory of an `hdmap run`")
    parser.add_argument("--gt", type=Path, default=None, help="ground truth (.gt.json) to score the map against")
    parser.add_argument("--preset", default="default", help="pipeline preset (default: default)")
    add_set_argument(parser, "change a preset parameter, as `hdmap bag2map --set` (repeatable)", dest="set")
    args = parser.parse_args(argv)
    try:
        config = config_from(args.preset, dict(args.set))
        t0 = time.perf_counter()
        hdmap, n_tiles = restitch(args.state, config)
        dt = time.perf_counter() - t0
        print(f"{n_tiles} tiles -> {len(hdmap.features)} features, {len(hdmap.topology)} topology nodes ({dt:.1f} s)")
        if args.gt is not None:
            report = evaluate_map(hdmap, load_ground_truth(args.gt))
            print(SCORE_COLUMNS)
            print(score_line(args.state.name, report, dt))
            for t in report.false_topology_links:
                if t.length_m > report.config.link_long_m:
                    print(
                        f"false long link ({t.x:.1f}, {t.y:.1f}) -> ({t.to_x:.1f}, {t.to_y:.1f}) "
                        f"{t.length_m:.1f} m: {t.reason}"
                    )
    except HdmapError as err:
        print(f"restitch_state: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
