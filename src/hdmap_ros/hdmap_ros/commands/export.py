"""``hdmap export MAP_BAG --lanelet2 DIR``: the lanes of a map bag as an Autoware map directory.

Reads the last map on ``/hdmap/map`` and the origin on ``/fleet/origin`` (or ``--origin``),
derives the lanes (:func:`hdmap_core.lanes.derive.derive_lanes`; with ``--fleet BAG`` also the
connectors its drives made where the lanes lack a connection, :mod:`hdmap_core.lanes.connectors`)
and writes ``DIR/lanelet2_map.osm`` and ``DIR/map_projector_info.yaml`` (``hdmap_ros.io.lanelet2``).
Exit status: 0 done, 1 an error (e.g. no map in the bag), 2 usage.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["NAME", "HELP", "add_arguments", "run"]

NAME = "export"
HELP = "write the lanes of a map bag as a Lanelet2 / Autoware map directory"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from hdmap_ros.commands.bag2map import add_origin_argument  # noqa: PLC0415

    parser.add_argument("map", metavar="MAP_BAG", help="map bag (rosbag2 directory or .mcap) with /hdmap/map")
    parser.add_argument(
        "--lanelet2",
        metavar="DIR",
        required=True,
        help="directory to write: DIR/lanelet2_map.osm and DIR/map_projector_info.yaml",
    )
    add_origin_argument(parser)
    parser.add_argument(
        "--fleet",
        metavar="BAG",
        help="fleet bag the map was built from: its drives' trajectories add connector lanes where the "
        "lanes lack a connection (junctions without lines)",
    )


def run(args: argparse.Namespace) -> int:
    from hdmap_ros.io.bagio import read_fleet_bag, read_map_bag  # noqa: PLC0415
    from hdmap_ros.io.lanelet2 import export_lanelet2  # noqa: PLC0415

    if Path(args.lanelet2).is_file():
        print(f"hdmap {NAME}: error: --lanelet2 {args.lanelet2} is a file, not a directory", file=sys.stderr)
        return 2
    hdmap = read_map_bag(args.map)
    origin = args.origin or hdmap.extra.get("origin")
    if origin is None:
        print(f"hdmap {NAME}: error: {args.map} has no /fleet/origin; give --origin LAT,LON", file=sys.stderr)
        return 2
    trajectories = [d.xy for d in read_fleet_bag(args.fleet).drives] if args.fleet else []
    print(export_lanelet2(hdmap, origin, args.lanelet2, trajectories=trajectories))
    return 0
