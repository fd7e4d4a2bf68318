"""``hdmap bag2map IN -o OUT``: build the lane-level map of a fleet bag and write it as a map bag.

Reads the drives and the origin of IN (rosbag2 directory or ``.mcap``), reports every rejected
drive with its reason, runs :func:`hdmap_core.pipeline.driver.build_map`, writes OUT (rosbag2 MCAP with
the map on ``/hdmap/map`` and the origin on ``/fleet/origin``) and, with ``--geojson``, the
features and lanes as RFC 7946 GeoJSON; with ``--lanelet2 DIR``, the lanes as an Autoware map
directory (``hdmap export``); with ``--graphml``, the topology graph as GraphML (map frame).
The map is the road as of the last drive (``hdmap_core.updates.follow``; ``--no-follow-changes``:
the consensus of every drive, the map of the first build): changes of the road are detected and
the changed places rebuilt from the drives after the change; the changes and the retired pieces go
to ``OUT.history.json`` (docs/updates.md). Where nothing changed, the map is the same either way.
With ``--tiled`` (or ``--scheduler``) the bag is indexed by tile on disk and built tile by tile
(``hdmap_ros.tiled``, docs/scale.md). A tiled build gives the consensus of
every drive (it does not follow changes yet).
Exit status: 0 done, 1 an error (e.g. no usable drive), 2 usage.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hdmap_core.errors import ConfigError, NoUsableDataError
from hdmap_core.model import GeoOrigin, HDMap
from hdmap_ros.io.bagio import FleetBag, read_fleet_bag, write_map_bag
from hdmap_ros.io.geojson import write_geojson

__all__ = [
    "NAME",
    "HELP",
    "add_arguments",
    "run",
    "override_arg",
    "add_origin_argument",
    "add_set_argument",
    "parse_origin",
    "tile_config_of",
    "TILE_DEFAULTS",
]

NAME = "bag2map"
HELP = "build a lane-level HD map from a fleet bag and write it as a rosbag2 MCAP map bag"
PRESETS = ("default", "paper", "naive")
# Tiles of an offline tiled build (docs/scale.md "How the work is partitioned"): 1 km, four times the live suite's
# 256 m edge (less margin per tile); pivots walk only 32 m beyond their tile (the steps of the
# tile proper are kept anyway): paper_like 1x, tiled 116 s at 1024 m, 140 s at 2048 m, same accuracy.
TILE_DEFAULTS = {"tile_size_m": 1024.0, "margin_m": 128.0, "pivot_margin_m": 32.0}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", metavar="IN", help="fleet bag: rosbag2 directory (MCAP or sqlite3) or .mcap file")
    parser.add_argument("-o", "--output", metavar="OUT", required=True, help="map bag directory to write")
    parser.add_argument("--geojson", metavar="FILE", help="also write the map features and lanes as GeoJSON (WGS84)")
    parser.add_argument(
        "--graphml", metavar="PATH", help="also write the topology graph as GraphML (map frame, metres)"
    )
    parser.add_argument(
        "--lanelet2",
        metavar="DIR",
        help="also write the lanes as an Autoware map directory: DIR/lanelet2_map.osm + DIR/map_projector_info.yaml",
    )
    parser.add_argument("--preset", choices=PRESETS, default="default", help="pipeline preset (default: %(default)s)")
    add_set_argument(
        parser,
        "change one parameter of the preset (repeatable), dotted into PipelineConfig, the value as "
        "JSON, e.g. --set stitching.max_distance_m=8 --set alignment.robust_loss=false",
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed of the pipeline (default: %(default)s)")
    add_origin_argument(parser)
    parser.add_argument(
        "--workers",
        type=_parse_workers,
        default=None,
        metavar="N",
        help="processes for the pivot passes; independent parts of the map (e.g. the two carriageways) "
        "run apart and the map is the same as with 1 (default: the CPUs available); with N > 1 the "
        "drives' side of the change following's comparison is also made ahead, at the lowest priority, "
        "on the CPU time the build leaves idle; with --tiled: Dask "
        "worker processes of a LocalCluster (default: 1, the tiles in this process)",
    )
    parser.add_argument(
        "--follow-changes",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="give the road as of the last drive: detect changes of the road from the drives' time stamps, "
        "rebuild the changed places from the drives after the change, keep what they replaced in OUT.history.json "
        "(default: on with the default preset, off with paper and naive; a road without changes gets the same map "
        "as with --no-follow-changes)",
    )
    tiled = parser.add_argument_group("out of core, by tiles (docs/scale.md)")
    tiled.add_argument(
        "--tiled",
        action="store_true",
        help="index the bag by tile on disk in one pass and build tile by tile: memory bounded by the tiles "
        "in work, not by the bag; with --workers N (N > 1) on a Dask LocalCluster of N processes",
    )
    tiled.add_argument(
        "--scheduler",
        metavar="ADDR",
        help="build by tiles on the running Dask cluster at ADDR (tcp://HOST:8786); implies --tiled",
    )
    tiled.add_argument(
        "--tile-size-m",
        type=float,
        default=None,
        metavar="M",
        help=f"edge of a tile [m] (default: {TILE_DEFAULTS['tile_size_m']:g})",
    )
    tiled.add_argument(
        "--margin-m",
        type=float,
        default=None,
        metavar="M",
        help=f"context mapped around a tile [m] (default: {TILE_DEFAULTS['margin_m']:g})",
    )
    tiled.add_argument(
        "--block-tiles",
        type=int,
        default=None,
        metavar="N",
        help="the offset adjustment block-wise over blocks of N x N tiles with a global coarse solve, as tasks "
        "on the workers (default: one network-wide solve in this process)",
    )
    tiled.add_argument(
        "--stitch-tiles",
        type=int,
        default=None,
        metavar="N",
        help="stitch per region of N x N tiles as tasks on the workers, then join across the region borders "
        "(default: one stitch of all tiles in this process; the same map on the fleets measured, docs/scale.md)",
    )
    tiled.add_argument("--index", metavar="FILE", help="keep the tile index in FILE (default: a temporary file)")
    parser.add_argument("--overwrite", action="store_true", help="replace OUT if it is an existing bag")
    parser.add_argument("--report", metavar="FILE", help="write the input summary and the build report as JSON")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar even on a terminal")


def tile_config_of(args: argparse.Namespace) -> Any:
    """The ``TileConfig`` of ``--tile-size-m``, ``--margin-m`` and ``--seed``.

    Raises:
        ConfigError: a value the tiling does not take, named."""
    from hdmap_core.live.tiles import TileConfig  # noqa: PLC0415

    size = args.tile_size_m if args.tile_size_m is not None else TILE_DEFAULTS["tile_size_m"]
    margin = args.margin_m if args.margin_m is not None else TILE_DEFAULTS["margin_m"]
    return TileConfig(
        tile_size_m=size, margin_m=margin, seed=args.seed, pivot_margin_m=min(TILE_DEFAULTS["pivot_margin_m"], margin)
    )


def parse_origin(text: str) -> GeoOrigin:
    """argparse type of ``--origin LAT,LON[,ALT]``."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not LAT,LON[,ALT]") from None
    if len(values) not in (2, 3) or not np.all(np.isfinite(values)) or abs(values[0]) > 90 or abs(values[1]) > 180:
        raise argparse.ArgumentTypeError(f"{text!r} is not a WGS84 LAT,LON[,ALT]")
    return GeoOrigin(*values)


def add_origin_argument(parser: argparse.ArgumentParser) -> None:
    """``--origin LAT,LON[,ALT]`` (parsed by :func:`parse_origin`) into ``args.origin``."""
    parser.add_argument(
        "--origin",
        metavar="LAT,LON[,ALT]",
        type=parse_origin,
        help="WGS84 origin of the map frame when the bag has no /fleet/origin (or to override it)",
    )


def add_set_argument(parser: argparse.ArgumentParser, help_text: str, dest: str = "overrides") -> None:
    """The repeatable ``--set KEY=VALUE`` of a PipelineConfig change (parsed by :func:`override_arg`)
    into ``args.<dest>``, a list of (key, value)."""
    parser.add_argument(
        "--set", metavar="KEY=VALUE", action="append", type=override_arg, default=[], dest=dest, help=help_text
    )


def override_arg(text: str) -> tuple[str, object]:
    """argparse type of ``--set KEY=VALUE``: ``pipeline.parse_override``, a malformed item a usage error."""
    from hdmap_core.pipeline.overrides import parse_override  # noqa: PLC0415 - heavy; --help stays fast

    try:
        return parse_override(text)
    except ConfigError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _parse_workers(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number >= 1")
    return n


def _fail(message: str) -> int:
    print(f"hdmap {NAME}: error: {message}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    out = Path(args.output)
    if out.exists() and not args.overwrite:
        return _fail(f"{out} exists already (use --overwrite to replace it)")
    if out.exists() and not (out / "metadata.yaml").exists():
        return _fail(f"{out} exists and is not a rosbag2 directory; refusing to replace it")
    if args.lanelet2 and Path(args.lanelet2).is_file():
        return _fail(f"--lanelet2 {args.lanelet2} is a file, not a directory")
    if args.geojson and Path(args.geojson).is_dir():
        return _fail(f"--geojson {args.geojson} is a directory")
    if args.graphml and Path(args.graphml).is_dir():
        return _fail(f"--graphml {args.graphml} is a directory")

    from hdmap_core.parallel import SpareWork, available_cpus  # noqa: PLC0415
    from hdmap_core.pipeline import driver as pipeline  # noqa: PLC0415 - heavy, and only needed for a real run
    from hdmap_core.pipeline.overrides import config_from  # noqa: PLC0415
    from hdmap_core.pipeline.presets import FOLLOWS_CHANGES  # noqa: PLC0415
    from hdmap_core.updates.config import ChangeConfig  # noqa: PLC0415
    from hdmap_core.updates.follow import own_side  # noqa: PLC0415
    from hdmap_core.updates.places import places_of  # noqa: PLC0415

    try:  # a bad --set is named before the bag is read
        config = config_from(args.preset, dict(args.overrides))
    except ConfigError as err:
        return _fail(f"--set {err}")
    if args.overrides:
        print(f"preset {args.preset}, changed: " + ", ".join(f"{k}={json.dumps(v)}" for k, v in args.overrides))

    if args.tiled or args.scheduler:
        return _run_tiled(args, config, out)
    t_start = time.perf_counter()
    fleet = read_fleet_bag(args.bag)
    _report_input(fleet)
    if not fleet.drives:
        reasons = _reason_counts(fleet)
        raise NoUsableDataError(
            f"{args.bag}: no usable drive ({len(fleet.rejected)} rejected{': ' + reasons if reasons else ''})"
            + (f"; {fleet.error}" if fleet.error else "")
        )
    origin = args.origin or fleet.origin
    if args.geojson and origin is None:
        return _fail(f"--geojson needs the map origin: {args.bag} has no /fleet/origin; give --origin LAT,LON")
    if args.lanelet2 and origin is None:
        return _fail(f"--lanelet2 needs the map origin: {args.bag} has no /fleet/origin; give --origin LAT,LON")

    workers = args.workers or available_cpus()
    follow = args.follow_changes if args.follow_changes is not None else FOLLOWS_CHANGES.get(args.preset, False)
    change_config = ChangeConfig()
    # the follow's places and the drives' side of its comparison with the map (their cuts and
    # their own lines on them) need no map: with more than one worker they are made meanwhile, on
    # the CPU time the build leaves idle (its serial stages, the passes' uneven shares)
    ahead = follow and workers > 1
    with (
        _Progress(enabled=not args.no_progress and sys.stderr.isatty()) as progress,
        SpareWork(lambda _: places_of(fleet.drives, cell_m=change_config.cell_m), int(ahead)) as spare_places,
        SpareWork(lambda i: own_side(fleet.drives[i], change_config), len(fleet.drives) if ahead else 0) as spare,
    ):
        result = pipeline.build_map(fleet.drives, config=config, seed=args.seed, progress=progress, workers=workers)
        history = None
        if follow:
            from hdmap_core.updates.follow import follow_changes, history_to_dict  # noqa: PLC0415

            first = result
            # the drives the build used: change detection never sees a drive the build refused
            usable = first.drives

            def build(drives: Any) -> tuple[HDMap, Any]:
                nonlocal result
                if drives is usable:  # the map of every drive: built above
                    return first.map, first.report
                result = pipeline.build_map(
                    list(drives), config=config, seed=args.seed, progress=progress, workers=workers
                )
                return result.map, result.report

            sides = {fleet.drives[i].drive_id: side for i, side in spare.take().items()}
            # the places of every drive read: those of the drives used when the build used every one
            places = spare_places.take().get(0) if len(usable) == len(fleet.drives) else None
            if ahead:
                print(
                    f"made ahead on idle CPU time: {len(sides)} of {len(fleet.drives)} drives' side of the comparison"
                    + (", the places" if places is not None else "")
                )
            followed = follow_changes(
                usable,
                build=build,
                config=change_config,
                bounds=None,
                workers=workers,
                sides=sides,
                places=places,
            )  # usable: checked above
            history = history_to_dict(followed)
            # a local rebuild maps the changed places only: the run's figures are the first build's
            base = first if followed.report is first.report else result
            result = dataclasses.replace(base, map=followed.map) if followed.changes else first
            for c in followed.changes:
                modelled = sum(len(m.points) for m in followed.modelled if m.change_id == c.id)
                print(
                    f"change {c.id}: {', '.join(c.kinds)} at {c.time_ns} ns, {len(c.places)} place(s), "
                    f"{len(c.drives_after)} drive(s) in evidence, confidence {c.confidence:.3f}"
                    + (f", {modelled} unseen marking point(s) moved by its shift (model)" if modelled else "")
                )
            print(f"follow changes: {len(followed.changes)} change(s), {len(followed.retired)} retired piece(s)")
    hdmap: HDMap = result.map

    _write_outputs(args, out, hdmap, origin, history=history, trajectories=[d.xy for d in fleet.drives])
    seconds = time.perf_counter() - t_start
    print(_summary(fleet, hdmap, result, seconds))
    if args.report:
        Path(args.report).write_text(json.dumps(_report_dict(args, fleet, hdmap, result, seconds), indent=1))
        print(f"wrote {args.report}")
    return 0


def _write_outputs(
    args: argparse.Namespace,
    out: Path,
    hdmap: HDMap,
    origin: GeoOrigin | None,
    *,
    history: dict | None = None,
    trajectories: Sequence[np.ndarray] = (),
) -> None:
    """The map bag, the change history (``OUT.history.json``, when changes were followed) and the
    GeoJSON, Lanelet2 and GraphML files asked for; the lanes gain connectors from the drives'
    ``trajectories`` where they lack a connection (:mod:`hdmap_core.lanes.connectors`)."""
    write_map_bag(out, hdmap, origin, overwrite=args.overwrite)
    print(f"wrote {out}: {len(hdmap.features)} features, {len(hdmap.topology)} topology nodes")
    if history is not None:
        hist = out.with_name(out.name + ".history.json")
        hist.write_text(json.dumps(history))
        print(f"wrote {hist}")
    lanes = None
    if args.geojson or args.lanelet2:
        from hdmap_core.lanes.derive import derive_lanes  # noqa: PLC0415 - lanes only when written

        lanes = derive_lanes(hdmap)
        if len(trajectories):
            from hdmap_core.lanes.drivepath import trajectory_lanes  # noqa: PLC0415

            lanes = trajectory_lanes(lanes, trajectories)
    if args.geojson:
        write_geojson(hdmap, origin, args.geojson, lanes=lanes)
        print(f"wrote {args.geojson}")
    if args.lanelet2 and lanes is not None:
        from hdmap_ros.io.lanelet2 import write_lanelet2  # noqa: PLC0415 - lanes only when asked

        write_lanelet2(lanes, origin, args.lanelet2)
        print(f"wrote {args.lanelet2}: {len(lanes.lanes)} lanelets")
    if args.graphml:
        from hdmap_core.graph.topology_graph import write_graphml  # noqa: PLC0415 - networkx only when asked

        g = write_graphml(hdmap, args.graphml)
        print(f"wrote {args.graphml}: {g.number_of_nodes()} nodes, {g.number_of_edges()} links")


def _run_tiled(args: argparse.Namespace, config: Any, out: Path) -> int:
    """``--tiled`` / ``--scheduler``: the bag indexed by tile, the map built tile by tile."""
    from hdmap_ros.tiled import build_from_bag  # noqa: PLC0415 - dask and the pipeline only when asked

    try:
        tile_config = tile_config_of(args)
    except ConfigError as err:
        return _fail(str(err))
    if args.index and Path(args.index).is_dir():
        return _fail(f"--index {args.index} is a directory")
    t_start = time.perf_counter()
    with _Progress(enabled=not args.no_progress and sys.stderr.isatty()) as progress:
        got = build_from_bag(
            args.bag,
            config=config,
            tile_config=tile_config,
            workers=args.workers or 1,
            scheduler=args.scheduler,
            index_path=args.index,
            progress=progress,
            block_tiles=args.block_tiles,
            stitch_tiles=args.stitch_tiles,
            trajectories=bool(args.lanelet2 or args.geojson),
        )
    index, result = got.index, got.result
    for _did, _reason, text in got.rejected:
        print(f"hdmap {NAME}: rejected {text}", file=sys.stderr)
    if index.bag_error:
        print(
            f"hdmap {NAME}: warning: {index.bag_error}; went on with the {index.drive_count} intact drive(s)",
            file=sys.stderr,
        )
    origin = args.origin or index.origin
    for flag, value in (("--geojson", args.geojson), ("--lanelet2", args.lanelet2)):
        if value and origin is None:
            return _fail(f"{flag} needs the map origin: {args.bag} has no /fleet/origin; give --origin LAT,LON")
    hdmap: HDMap = result.map
    _write_outputs(args, out, hdmap, origin, trajectories=got.trajectories)
    seconds = time.perf_counter() - t_start
    rep = result.report
    print(
        "\n".join(
            [
                "summary (tiled):",
                f"  drives indexed   {index.drive_count} ({index.drive_km:.1f} km), rejected {len(got.rejected)}",
                f"  tile index       {got.index_seconds:.1f} s, {index.tile_config.tile_size_m:g} m tiles, "
                f"{index.tile_config.margin_m:g} m margins" + (f", kept in {args.index}" if args.index else ""),
                f"  map              {len(hdmap.features)} features, {len(hdmap.topology)} topology nodes",
                f"  wall time        {seconds:.1f} s (index + build + write)",
                "  build report:",
            ]
            + [f"    {line}" for line in rep.summary().splitlines()]
        )
    )
    if args.report:
        doc = {
            "input": str(args.bag),
            "output": str(args.output),
            "preset": args.preset,
            "overrides": dict(args.overrides),
            "seed": args.seed,
            "tiled": True,
            "scheduler": args.scheduler,
            "drives": index.drive_count,
            "drive_km": index.drive_km,
            "rejected": [{"drive_id": d, "reason": r, "text": t} for d, r, t in got.rejected],
            "bag_error": index.bag_error or None,
            "features": len(hdmap.features),
            "topology_nodes": len(hdmap.topology),
            "wall_s": seconds,
            "index_s": got.index_seconds,
            "build": dataclasses.asdict(rep),
        }
        Path(args.report).write_text(json.dumps(doc, indent=1))
        print(f"wrote {args.report}")
    return 0


def _report_dict(args: argparse.Namespace, fleet: FleetBag, hdmap: HDMap, result: Any, seconds: float) -> dict:
    report = getattr(result, "report", None)
    build = dataclasses.asdict(report) if dataclasses.is_dataclass(report) else {}
    refused = {str(r[0]) for r in getattr(report, "rejected", None) or []}  # by the pipeline (e.g. implausible)
    return {
        "input": str(args.bag),
        "output": str(args.output),
        "preset": args.preset,
        "overrides": dict(args.overrides),
        "seed": args.seed,
        "drives": len(fleet.drives),
        "drive_km": sum(d.length_m for d in fleet.drives if d.drive_id not in refused) / 1000.0,
        "rejected": [dataclasses.asdict(r) for r in fleet.rejected],
        "bag_error": fleet.error,
        "features": len(hdmap.features),
        "topology_nodes": len(hdmap.topology),
        "changes_followed": len(hdmap.extra.get("changes", ())),
        "wall_s": seconds,
        "build": json.loads(json.dumps(build, default=str)),
    }


def _reason_counts(fleet: FleetBag, refused: Sequence[tuple[str, str]] = ()) -> str:
    counts: dict[str, int] = {}
    for reason in [r.reason for r in fleet.rejected] + [reason for _, reason in refused]:
        counts[reason] = counts.get(reason, 0) + 1
    return ", ".join(f"{n} {reason}" for reason, n in sorted(counts.items()))


def _report_input(fleet: FleetBag) -> None:
    for r in fleet.rejected:
        print(f"hdmap {NAME}: rejected {r}", file=sys.stderr)
    if fleet.error and fleet.drives:  # with none, the error that ends the run names the bag's fault
        print(f"hdmap {NAME}: warning: {fleet.error}", file=sys.stderr)
        print(f"hdmap {NAME}: going on with the {len(fleet.drives)} intact drive(s)", file=sys.stderr)


def _summary(fleet: FleetBag, hdmap: HDMap, result: Any, seconds: float) -> str:
    km_features = (
        sum(float(np.linalg.norm(np.diff(np.asarray(f.points), axis=0), axis=1).sum()) for f in hdmap.features) / 1000.0
    )
    report = getattr(result, "report", None)
    # drives the pipeline rejected (e.g. implausible ones: a pose at 1e12 m) count as rejected here too
    refused = [(str(d), str(r).split(":", 1)[0]) for d, r in getattr(report, "rejected", None) or []]
    refused_ids = {d for d, _ in refused}
    used = [d for d in fleet.drives if d.drive_id not in refused_ids]
    drive_km = sum(d.length_m for d in used) / 1000.0
    n_rejected = len(fleet.rejected) + len(refused)
    lines = [
        "summary:",
        f"  drives read      {len(fleet.drives)}, used {len(used)} ({drive_km:.1f} km), rejected {n_rejected}"
        + (f" ({_reason_counts(fleet, refused)})" if n_rejected else ""),
        f"  map              {len(hdmap.features)} features ({km_features:.2f} km of polylines), "
        f"{len(hdmap.topology)} topology nodes",
        f"  wall time        {seconds:.1f} s (read + build + write)",
    ]
    if fleet.error:
        lines.insert(2, "  input bag        DAMAGED, only the intact drives before the damage were used")
    if report is not None:
        text = report.summary() if callable(getattr(report, "summary", None)) else _fields(report)
        lines += ["  pipeline report:"] + [f"    {line}" for line in str(text).splitlines()]
    return "\n".join(lines)


def _fields(report: Any) -> str:
    items = vars(report).items() if hasattr(report, "__dict__") else []
    return "\n".join(f"{k}: {v}" for k, v in items if not k.startswith("_"))


class _Progress:
    """The ``progress(stage, done, total)`` callback of build_map: a tqdm bar on a terminal."""

    def __init__(self, *, enabled: bool) -> None:
        self.enabled = enabled
        self.bar: Any = None
        self.stage: str | None = None
        self.calls = 0

    def __enter__(self) -> _Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.close()

    def __call__(self, stage: str, done: int, total: int) -> None:
        self.calls += 1
        if not self.enabled:
            return
        if self.bar is None or stage != self.stage:
            from tqdm import tqdm  # noqa: PLC0415 - only on a terminal

            if self.bar is not None:
                self.bar.close()
            self.bar = tqdm(total=total, desc=f"{NAME}: {stage}", file=sys.stderr, leave=False, unit="")
            self.stage = stage
        self.bar.total = total
        self.bar.n = done
        self.bar.refresh()
