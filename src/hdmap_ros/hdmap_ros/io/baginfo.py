"""Inspect a bag without ROS tools: ``python -m hdmap_ros.io.baginfo BAG [--drives]``.

Prints the topics with message types and counts, the origin, the drives (with ``--drives`` one
line each: id, poses, length, detections by type), the maps, every rejected message with its
reason, and any damage to the bag.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from collections.abc import Sequence

from hdmap_core.errors import BagError
from hdmap_core.model import Drive, FeatureType, GeoOrigin
from hdmap_ros.io.bagio import MAP_TOPIC, Rejection, iter_bag, iter_fleet_bag, read_map_bag

__all__ = ["main", "describe"]


def describe(path: str, *, drives: bool = False) -> str:
    """A human-readable description of a bag (see the module docstring)."""
    lines = [f"bag: {path}"]
    topics: Counter[tuple[str, str]] = Counter()
    sizes: Counter[tuple[str, str]] = Counter()
    damage = None
    try:
        for bm in iter_bag(path):
            topics[(bm.topic, bm.msgtype)] += 1
            sizes[(bm.topic, bm.msgtype)] += len(bm.data)
    except BagError as err:
        damage = str(err)
    lines.append("topics:")
    for (topic, msgtype), n in sorted(topics.items()):
        lines.append(f"  {topic:16s} {msgtype:28s} {n:6d} msgs {sizes[(topic, msgtype)] / 1e6:8.2f} MB")
    kept, rejected, origin = [], [], None
    try:
        for item in iter_fleet_bag(path):
            if isinstance(item, Drive):
                kept.append(item)
            elif isinstance(item, Rejection):
                rejected.append(item)
            elif isinstance(item, GeoOrigin):
                origin = item
    except BagError:
        pass  # reported above
    if origin is not None:
        lines.append(
            f"origin: lat {origin.latitude_deg:.8f} lon {origin.longitude_deg:.8f} alt {origin.altitude_m:.2f} m"
        )
    if kept or rejected:
        km = sum(d.length_m for d in kept) / 1000.0
        lines.append(f"drives: {len(kept)} valid ({km:.2f} km), {len(rejected)} rejected")
        if drives:
            for d in kept:
                by_type = Counter(FeatureType(det.type).label for det in d.detections)
                dets = " ".join(f"{k}={v}" for k, v in sorted(by_type.items()))
                lines.append(f"  {d.drive_id:24s} {len(d.xy):6d} poses {d.length_m:8.1f} m  detections {dets}")
        for r in rejected:
            lines.append(f"  rejected {r}")
    if any(t == MAP_TOPIC for t, _ in topics):
        try:
            m = read_map_bag(path)
            by_type = Counter(f.type.label for f in m.features)
            lines.append(
                f"last map: version {m.version}, {len(m.features)} features "
                f"({', '.join(f'{k} {v}' for k, v in sorted(by_type.items()))}), "
                f"{len(m.topology)} topology nodes, {len(m.drive_ids)} drives"
            )
        except BagError as err:
            lines.append(f"map: unreadable: {err}")
    if damage:
        # Nothing read at all: not a bag (or missing); else the bag is damaged after what was read.
        lines.append(f"{'DAMAGED' if topics else 'ERROR'}: {damage}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hdmap_ros.io.baginfo", description=__doc__.splitlines()[0])
    parser.add_argument("bag", help="rosbag2 directory or .mcap file")
    parser.add_argument("--drives", action="store_true", help="one line per drive")
    args = parser.parse_args(argv)
    text = describe(args.bag, drives=args.drives)
    print(text)
    return 1 if "\nDAMAGED: " in text or "\nERROR: " in text else 0


if __name__ == "__main__":
    sys.exit(main())
