"""``hdmap run BAG``: the whole node suite in one process, fed drive by drive from a bag.

``ros2 launch`` is not there on wheel installs, so this runs drive_ingestor, segment_mapper,
map_stitcher, map_publisher and bag_player in one single-threaded rclpy executor (real DDS
topics between them: ``ros2 topic echo /hdmap/map`` from another process works). It exits when the bag is done and
the map has settled (every drive mapped, every tile re-estimated from all its drives with the
fleet offset model, every estimate stitched),
or stays up with ``--keep-alive``. The settled map can be written with ``--out``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

from hdmap_core.errors import HdmapError, NoUsableDataError

NAME = "run"
# RULE: the loop checks for the end at most this often: the check reads both stores (SQLite), and
# spin_once returns after every callback (py-spy, 30-drive ramps: 3 % of
# the suite's process samples went to this check)
CHECK_PERIOD_S = 0.05
HELP = "run the node suite in one process on a fleet bag (drive by drive) and write the settled map"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", help="fleet bag (rosbag2 directory or .mcap) to replay onto /fleet/drives")
    parser.add_argument(
        "--rate",
        type=float,
        default=0.0,
        help="replay speed factor of the bag's log times; 0 = as fast as possible (default)",
    )
    parser.add_argument("--out", "-o", help="write the settled map here (rosbag2 MCAP directory)")
    parser.add_argument("--geojson", help="also write the settled map as GeoJSON (needs /fleet/origin in the bag)")
    parser.add_argument(
        "--state",
        help="directory of the SQLite stores (default: a fresh temporary one); "
        "an existing state continues where it stopped",
    )
    parser.add_argument("--preset", default=None, help="pipeline preset (default: the params file's, 'default')")
    parser.add_argument(
        "--set",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        dest="overrides",
        help="change one preset parameter (repeatable), as `hdmap bag2map --set`; sets the "
        "mapper's and the stitcher's preset_overrides",
    )
    parser.add_argument("--params-file", help="node parameters (YAML), applied over the package defaults")
    parser.add_argument(
        "--namespace",
        default="",
        help="namespace of every node and topic (e.g. /ns2: "
        "/ns2/fleet/drives, /ns2/hdmap/map), so two suites can share a ROS domain",
    )
    parser.add_argument(
        "--keep-alive", action="store_true", help="keep serving /hdmap/map after settling (Ctrl-C ends)"
    )
    parser.add_argument("--timeout", type=float, default=0.0, help="give up after this many seconds (0 = never)")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress lines")


class _Suite:
    """The five nodes in one executor."""

    def __init__(self, args: argparse.Namespace, state: Path) -> None:
        import rclpy  # noqa: PLC0415
        from rclpy.executors import SingleThreadedExecutor  # noqa: PLC0415
        from rclpy.parameter import Parameter  # noqa: PLC0415

        from hdmap_ros.nodes._common import warn_unknown_parameters, with_default_params  # noqa: PLC0415
        from hdmap_ros.nodes.bag_player import BagPlayer  # noqa: PLC0415
        from hdmap_ros.nodes.drive_ingestor import DriveIngestor  # noqa: PLC0415
        from hdmap_ros.nodes.map_publisher import MapPublisher  # noqa: PLC0415
        from hdmap_ros.nodes.map_stitcher import MapStitcher  # noqa: PLC0415
        from hdmap_ros.nodes.segment_mapper import SegmentMapper  # noqa: PLC0415

        ros_args = ["hdmap-run", "--ros-args"]
        if args.params_file:
            ros_args += ["--params-file", str(args.params_file)]
        if getattr(args, "namespace", ""):
            ros_args += ["-r", f"__ns:=/{args.namespace.strip('/')}"]
        self.context = rclpy.Context()
        rclpy.init(args=with_default_params(ros_args), context=self.context)

        def p(**kw):
            return [Parameter(k, value=v) for k, v in kw.items()]

        preset = {"preset": args.preset} if args.preset else {}
        if args.overrides:
            preset["preset_overrides"] = list(args.overrides)
        c = {"context": self.context}
        self.nodes = []
        try:  # a parameter a node rejects (e.g. a bad --set) ends the run with its message, cleanly
            self.ingestor = DriveIngestor(**c)
            self.nodes.append(self.ingestor)
            self.mapper = SegmentMapper(parameter_overrides=p(db_path=str(state / "segment_mapper.db"), **preset), **c)
            self.nodes.append(self.mapper)
            self.stitcher = MapStitcher(
                parameter_overrides=p(
                    db_path=str(state / "map_stitcher.db"), drive_db_path=str(state / "segment_mapper.db"), **preset
                ),
                **c,
            )
            self.nodes.append(self.stitcher)
            self.publisher = MapPublisher(**c)
            self.nodes.append(self.publisher)
            self.player = BagPlayer(parameter_overrides=p(bag=str(args.bag), rate=float(args.rate)), **c)
            self.nodes.append(self.player)
        except BaseException:
            for n in self.nodes:
                n.destroy_node()
            rclpy.try_shutdown(context=self.context)
            raise
        # RULE: one thread for the five nodes: they share one GIL, the heavy work runs in worker
        # processes, and threads only made the callbacks compete (134-drive paper_like, idle: the
        # ingest 3.7 s against 5-6 s with the repaired thread pool of nodes/executor.py and
        # 18 s with rclpy's own; the settle 1.4x bag2map against 1.6x and 2.0-2.4x)
        self.executor = SingleThreadedExecutor(context=self.context)
        for n in self.nodes:
            warn_unknown_parameters(n)  # a misspelt key of --params-file is named, not ignored
            self.executor.add_node(n)

    def input_in(self) -> bool:
        """The bag is done and every drive of it has reached the mapper (stored or refused)."""
        return (
            self.player.done
            and self.ingestor.received >= self.player.published
            and self.mapper.received >= self.ingestor.published
        )

    def settled(self) -> bool:
        """The bag is done and everything it caused has reached the map (messages the player
        skipped as unreadable are counted there and never awaited)."""
        if not self.input_in() or not self.mapper.is_settled():
            return False
        return (
            self.mapper.store.tiles_signature() == self.stitcher.store.tiles_signature()
            and self.stitcher.is_settled()
            and self.stitcher.changes_followed()
        )

    def status(self) -> str:
        m = self.stitcher.map
        return (
            f"drives played {self.player.played} (skipped {sum(self.player.skipped.values())}), "
            f"accepted {self.ingestor.health.accepted}, "
            f"rejected {self.ingestor.health.rejected_total}, tiles pending {self.mapper.scheduler.pending_tiles()} "
            f"(of {self.mapper.scheduler.tile_count}), map version {m.version if m else 0} "
            f"({len(m.features) if m else 0} features, {len(m.drive_ids) if m else 0} drives)"
        )

    def close(self) -> None:
        import rclpy  # noqa: PLC0415

        self.executor.shutdown()
        for n in self.nodes:
            n.destroy_node()
        rclpy.try_shutdown(context=self.context)


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # never leave the machine by default
    if not Path(args.bag).exists():
        raise HdmapError(f"{args.bag}: no such bag")
    tmp = None
    if args.state:
        state = Path(args.state)
        state.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="hdmap-run-")
        state = Path(tmp.name)
    try:
        suite = _Suite(args, state)
    except BaseException:
        if tmp is not None:
            tmp.cleanup()
        raise
    t0 = time.monotonic()
    last_print = last_check = 0.0
    # RULE: the bag is on its way: no previews or one-drive maps while it plays (the settle after
    # it makes every tile; they cost the ingest its time in this process)
    suite.mapper.input_open()
    told = False
    try:
        while True:
            suite.executor.spin_once(timeout_sec=0.1)
            now = time.monotonic()
            if not args.quiet and now - last_print >= 2.0:
                print(f"[{now - t0:6.1f} s] {suite.status()}", file=sys.stderr)
                last_print = now
            if now - last_check < CHECK_PERIOD_S:
                continue
            last_check = now
            if not told and suite.input_in():
                # RULE: the bag is the only input: once it is in, the mapper settles at once
                # instead of waiting settle_after_s for drives that cannot come
                suite.mapper.input_done()
                told = True
            if not args.keep_alive and suite.settled():
                break
            if args.timeout and now - t0 > args.timeout:
                print(f"hdmap run: not settled after {args.timeout:.0f} s: {suite.status()}", file=sys.stderr)
                return 1
        hdmap = suite.stitcher.map
        if not args.quiet:
            print(f"[{time.monotonic() - t0:6.1f} s] settled: {suite.status()}", file=sys.stderr)
        if hdmap is None:
            raise NoUsableDataError(f"{args.bag}: no usable drive, no map")
        _write(args, hdmap)
        return 0
    finally:
        suite.close()
        if tmp is not None:
            tmp.cleanup()


def _write(args: argparse.Namespace, hdmap) -> None:
    from hdmap_ros.io.bagio import read_bag_origin, write_map_bag  # noqa: PLC0415

    origin = read_bag_origin(args.bag) if (args.out or args.geojson) else None
    if args.out:
        write_map_bag(args.out, hdmap, origin, overwrite=True)
        print(f"map version {hdmap.version} ({len(hdmap.features)} features) written to {args.out}")
    if args.geojson:
        if origin is None:
            raise HdmapError(f"{args.bag} has no /fleet/origin: cannot write GeoJSON")
        from hdmap_core.lanes.derive import derive_lanes  # noqa: PLC0415
        from hdmap_ros.io.geojson import write_geojson  # noqa: PLC0415

        write_geojson(hdmap, origin, args.geojson, lanes=derive_lanes(hdmap))
        print(f"GeoJSON written to {args.geojson}")
