"""``hdmap evaluate MAP GT``: score a map against ground truth with the paper's metric (Sec. VII).

MAP is a map bag (rosbag2 directory or ``.mcap`` with ``/hdmap/map``; the last map is used) or a
``.gt.json`` file (its features then serve as the map: a sanity check that must score 0 m).
GT is a ``.gt.json`` file, the name of a shipped ground-truth map (e.g. ``carla_town04``, searched
in ``$HDMAP_MAPS_DIR`` and in the repository's ``data/maps``, as ``hdmap simulate``
does) or of a built-in
synthetic highway (``motorway``, ...).

``--fleet BAG`` gives the drives for the floor sigma_loc / sqrt(n); sigma_loc comes from
``--sigma-loc``, else from ``BAG.sim.json`` beside the fleet bag (written by ``hdmap simulate``:
sqrt(bias_lateral_sigma_m^2 + drift_sigma_m^2)), else 1.0 m. The same ``BAG.sim.json`` gives the
drives' true errors (the realized floor) and the per-point seen counts (the share of the ground truth
the fleet observed, and recall over it); files without them leave those figures n/a.
Prints the summary; ``--json`` and ``--plot`` write the full report and the figure.
``--changes OUT.changes.json`` (from ``hdmap simulate --change``) also scores the changed zones apart
against GT (accuracy there, ghost lines of the old road); with ``--as-of TIME`` GT is the road
before the changes and the map is scored against it with the changes made by TIME.
Exit status: 0 done, 1 an error (unreadable input), 2 usage.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hdmap_core.errors import ConfigError, HdmapError
from hdmap_core.evaluation.config import EvalConfig
from hdmap_core.evaluation.evaluate import evaluate_map, hdmap_from_ground_truth
from hdmap_core.evaluation.lanes import LaneReport
from hdmap_core.evaluation.plot import plot_evaluation
from hdmap_core.evaluation.report import jsonable
from hdmap_core.evaluation.summary import format_summary
from hdmap_core.groundtruth import GroundTruth, load_ground_truth
from hdmap_core.model import Drive, HDMap

__all__ = [
    "NAME",
    "HELP",
    "add_arguments",
    "run",
    "resolve_ground_truth",
    "sigma_from_sim_json",
    "drive_errors_from_sim_json",
    "seen_counts_from_sim_json",
    "parse_time_ns",
    "load_changes",
]

NAME = "evaluate"
HELP = "score a map (map bag or .gt.json) against ground truth: lateral error, coverage, recall, floor"
GT_SUFFIX = ".gt.json"

# Keys of the simulator's config that hold the per-drive lateral localization sigma, most specific first.
_SIGMA_KEYS = (
    "sigma_loc_m",
    "lateral_bias_sigma_m",
    "bias_lateral_sigma_m",
    "lateral_sigma_m",
    "loc_lateral_sigma_m",
    "bias_sigma_m",
    "loc_bias_sigma_m",
    "localization_sigma_m",
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("map", metavar="MAP", help="map bag (rosbag2 directory or .mcap) or a .gt.json used as map")
    parser.add_argument("gt", metavar="GT", help="ground truth: .gt.json path, shared map name or synthetic name")
    parser.add_argument("--fleet", metavar="BAG", help="fleet bag: its drives give the drive count per cut (floor)")
    parser.add_argument(
        "--sigma-loc",
        metavar="M",
        type=_positive_float,
        help="localization sigma for the floor [m] (default: from BAG.sim.json beside --fleet, else 1.0)",
    )
    parser.add_argument("--json", metavar="OUT.json", help="write the full report (with per-cut arrays) as JSON")
    parser.add_argument(
        "--plot", metavar="OUT.png", help="write the figure: map over ground truth, error along the reference"
    )
    parser.add_argument(
        "--lanes",
        action="store_true",
        help="also derive the map's lanes and score them: centerline coverage, precision, error, lane "
        "count, route reachability (routes driven: from BAG.sim.json beside --fleet, else all)",
    )
    parser.add_argument(
        "--changes",
        metavar="FILE",
        help="road changes (OUT.changes.json of hdmap simulate --change): also score the changed zones apart",
    )
    parser.add_argument(
        "--as-of",
        metavar="TIME",
        help="with --changes: GT is the road before the changes; score against it as of TIME "
        "(ns since epoch or ISO 8601, e.g. 2023-06-02T09:00:00Z)",
    )
    parser.add_argument(
        "--all-lanes", action="store_true", help="evaluate along all route lanes, not only highway lanes"
    )
    parser.add_argument(
        "--step", metavar="M", type=_positive_float, default=2.0, help="cut spacing [m] (default: %(default)s)"
    )
    parser.add_argument(
        "--gate",
        metavar="M",
        type=_positive_float,
        default=EvalConfig().gate_m,
        help="a map point farther than this from every same-type GT point is unmatched [m] (default: %(default)s)",
    )


def _lane_report(
    hdmap: HDMap, gt: GroundTruth, args: argparse.Namespace, config: EvalConfig, drives: Sequence[Drive] = ()
) -> LaneReport:
    from hdmap_core.evaluation.lanes import evaluate_lanes  # noqa: PLC0415 - lanes only when asked
    from hdmap_core.lanes.derive import derive_lanes  # noqa: PLC0415

    doc = _read_json(_sim_json_beside(args.fleet)) if args.fleet else None
    truth = doc.get("truth") if isinstance(doc, dict) else None
    routes = None
    if isinstance(truth, dict):
        routes = {str(t.get("route_id")) for t in truth.values() if isinstance(t, dict)}
    lanes = derive_lanes(hdmap)
    if drives:  # the fleet's trajectories: connectors where the lanes lack one, as bag2map makes them
        from hdmap_core.lanes.drivepath import trajectory_lanes  # noqa: PLC0415

        lanes = trajectory_lanes(lanes, [d.xy for d in drives])
    return evaluate_lanes(lanes, gt, route_ids=routes, config=config)


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number > 0")
    return value


def _fail(message: str) -> int:
    print(f"hdmap {NAME}: error: {message}", file=sys.stderr)
    return 2


def resolve_ground_truth(spec: str) -> GroundTruth:
    """Load ground truth from a path, a shared map name (``carla_town04`` or ``carla_town04.gt.json``)
    or a synthetic highway name, through :func:`hdmap_core.simulation.fleet.load_map` (one resolver for
    ``hdmap simulate`` and ``hdmap evaluate``).

    Raises:
        GroundTruthError: nothing of that name, or the file is not ground truth.
    """
    from hdmap_core.simulation.fleet import load_map

    if Path(spec).exists():
        return load_ground_truth(spec)
    name = spec[: -len(GT_SUFFIX)] if spec.endswith(GT_SUFFIX) else spec
    return load_map(name)


def _load_map(spec: str) -> tuple[HDMap, str]:
    """The map to evaluate and a description of where it came from."""
    if spec.endswith(".json"):
        gt = load_ground_truth(spec)
        return hdmap_from_ground_truth(gt), f"ground truth {spec} used as map"
    from hdmap_ros.io.bagio import read_map_bag

    hdmap = read_map_bag(spec)
    note = f"map bag {spec} (version {hdmap.version}, {len(hdmap.features)} features)"
    if hdmap.extra.get("bag_error"):
        note += f"; bag damaged after the map: {hdmap.extra['bag_error']}"
    return hdmap, note


def _sim_json_beside(bag: str) -> Path | None:
    p = Path(bag.rstrip("/\\"))
    for cand in (p.with_name(p.name + ".sim.json"), p.with_suffix(".sim.json")):
        if cand.is_file():
            return cand
    return None


def _read_json(path: str | Path | None) -> object:
    """The parsed document, or None when there is no path or it cannot be read as JSON."""
    if path is None:
        return None
    try:
        return json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None


def drive_errors_from_sim_json(path: str | Path | None) -> dict[str, float] | None:
    """Per drive id, its mean lateral localization error [m] as ``hdmap simulate`` recorded it
    (``truth.<id>.lateral_error_mean_m``), or None when the file has none."""
    doc = _read_json(path)
    truth = doc.get("truth") if isinstance(doc, dict) else None
    if not isinstance(truth, dict):
        return None
    out = {
        str(k): float(v["lateral_error_mean_m"])
        for k, v in truth.items()
        if isinstance(v, dict) and _number(v.get("lateral_error_mean_m")) is not None
    }
    return out or None


def seen_counts_from_sim_json(path: str | Path | None) -> dict[int, np.ndarray] | None:
    """Per ground-truth feature id, (N,) int64 the number of drives that detected each of its
    points, as ``hdmap simulate`` recorded it (``seen_count``, run-length coded); None when the
    file has none (written before the seen count existed) or it is not readable. Entries that do
    not decode are left out (the evaluator then names those features as skipped)."""
    from hdmap_core.simulation.fleet import decode_runs

    doc = _read_json(path)
    seen = doc.get("seen_count") if isinstance(doc, dict) else None
    if not isinstance(seen, dict):
        return None
    out = {}
    for key, code in seen.items():
        try:
            out[int(key)] = decode_runs(code)
        except (TypeError, ValueError):
            continue
    return out


def sigma_from_sim_json(path: str | Path) -> float | None:
    """The lateral localization sigma [m] of the drives recorded by the simulator, or None.

    ``hdmap simulate`` writes ``config.bias_lateral_sigma_m`` (constant per-drive bias) and
    ``config.drift_sigma_m`` (slow Gauss-Markov drift, independent of the bias); at one cut a drive's
    lateral error is their sum, so sigma_loc = sqrt(bias^2 + drift^2). Other documents: the first of
    ``_SIGMA_KEYS`` found (config first), else a key naming both "sigma" and "lat" ending in "_m".
    """
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(doc, dict):
        return None
    cfg = doc.get("config")
    if isinstance(cfg, dict) and _number(cfg.get("bias_lateral_sigma_m")) is not None:
        bias = _number(cfg["bias_lateral_sigma_m"]) or 0.0
        drift = _number(cfg.get("drift_sigma_m")) or 0.0
        sigma = math.hypot(bias, drift)
        return sigma if sigma > 0 else None
    found: dict[str, float] = {}

    def walk(node: object, depth: int) -> None:
        if depth > 4 or not isinstance(node, dict):
            return
        for key, value in node.items():
            if _number(value) is not None and key not in found:
                found[key] = float(value)
            elif isinstance(value, dict) and key not in ("truth", "drives"):
                walk(value, depth + 1)

    walk(cfg, 0)
    walk(doc, 0)
    for key in _SIGMA_KEYS:
        if key in found and found[key] > 0:
            return found[key]
    for key, value in found.items():
        low = key.lower()
        if "sigma" in low and "lat" in low and low.endswith("_m") and value > 0:
            return value
    return None


def _number(value: object) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


def parse_time_ns(text: str) -> int:
    """ns since epoch from an integer or an ISO 8601 time (UTC when no zone is given).

    Raises:
        ConfigError: neither.
    """
    import datetime as dt  # noqa: PLC0415

    try:
        return int(text)
    except ValueError:
        pass
    try:
        t = dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise ConfigError(f"--as-of {text!r}: not ns since epoch nor an ISO 8601 time") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.UTC)
    return int(round(t.timestamp() * 1e9))


def load_changes(path: str | Path) -> tuple[GroundTruth, list, list]:
    """(road before the changes, changes, zones) of an ``OUT.changes.json`` file.

    Raises:
        ConfigError: unreadable or not such a file; GroundTruthError: its road before is unreadable.
    """
    from hdmap_core.simulation.changes import changes_from_dict  # noqa: PLC0415

    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ConfigError(f"cannot read road changes {path}: {err}") from err
    if not isinstance(doc, dict) or "gt_before" not in doc:
        raise ConfigError(f"{path}: not a road-changes file (no gt_before)")
    changes, zones = changes_from_dict(doc)
    return load_ground_truth(path.with_name(str(doc["gt_before"]))), changes, zones


def run(args: argparse.Namespace) -> int:
    for opt in ("json", "plot"):
        out = getattr(args, opt)
        if out and Path(out).is_dir():
            return _fail(f"--{opt} {out} is a directory")
    if args.as_of and not args.changes:
        return _fail("--as-of needs --changes FILE")
    gt = resolve_ground_truth(args.gt)
    zone_input = None
    if args.changes:
        from hdmap_core.simulation.changes import road_as_of  # noqa: PLC0415

        gt_before, changes, zones = load_changes(args.changes)
        if args.as_of:
            t = parse_time_ns(args.as_of)
            gt = road_as_of(gt, changes, t)
            print(f"road as of {t} ns: {sum(c.time_ns <= t for c in changes)} of {len(changes)} change(s) made")
        first = min(c.time_ns for c in changes) if changes else 0
        zone_input = (road_as_of(gt_before, changes, first - 1), zones)
    hdmap, map_note = _load_map(args.map)
    print(f"map: {map_note}")
    print(f"ground truth: {gt.name} ({len(gt.features)} features, {len(gt.lanes)} lanes, {len(gt.routes)} routes)")

    drives, errors, seen = None, None, None
    sigma, sigma_note = args.sigma_loc, "--sigma-loc"
    if args.fleet:
        from hdmap_ros.io.bagio import read_fleet_bag

        fleet = read_fleet_bag(args.fleet)
        if fleet.error and not fleet.drives:
            raise HdmapError(f"fleet bag {args.fleet}: {fleet.error}")
        drives = fleet.drives
        note = f"fleet: {len(drives)} drives from {args.fleet}"
        if fleet.rejected:
            note += f" ({len(fleet.rejected)} rejected)"
        if fleet.error:
            note += f"; read stopped early: {fleet.error}"
        print(note)
        sim = _sim_json_beside(args.fleet)
        errors = drive_errors_from_sim_json(sim)
        seen = seen_counts_from_sim_json(sim)
        if sigma is None:
            sigma = sigma_from_sim_json(sim) if sim else None
            sigma_note = f"{sim.name}" if sigma is not None else "default"
    if sigma is None:
        sigma, sigma_note = EvalConfig().default_sigma_loc_m, "default"
    print(f"sigma_loc: {sigma:g} m ({sigma_note})")

    config = EvalConfig(step_m=args.step, gate_m=args.gate, highway_only=not args.all_lanes)
    report = evaluate_map(
        hdmap, gt, config=config, drives=drives, sigma_loc_m=sigma, drive_errors=errors, seen_counts=seen
    )
    print()
    print(format_summary(report))
    lanes = _lane_report(hdmap, gt, args, config, drives or ()) if args.lanes else None
    if lanes is not None:
        print(lanes.summary())
    zone_report = zone_lanes = None
    if zone_input is not None:
        from hdmap_core.evaluation.zone import evaluate_zone  # noqa: PLC0415

        zone_report = evaluate_zone(hdmap, gt, zone_input[0], zone_input[1], config=config)
        print(zone_report.line())
        if args.lanes:  # the lane count there against the road's markings now (a closed / opened lane)
            from hdmap_core.evaluation.zone import evaluate_zone_lanes  # noqa: PLC0415
            from hdmap_core.lanes.derive import derive_lanes  # noqa: PLC0415

            zone_lanes = evaluate_zone_lanes(derive_lanes(hdmap), gt, zone_input[1], config=config)
            print(zone_lanes.line())
    if args.json:
        doc = report.to_dict(include_cuts=True)
        if lanes is not None:
            doc["lanes"] = jsonable(lanes.to_dict())
        doc["inputs"] = {"map": args.map, "gt": args.gt, "fleet": args.fleet, "sigma_loc_source": sigma_note}
        if zone_report is not None:
            doc["changed_zone"] = zone_report.to_dict()
            if zone_lanes is not None:
                doc["changed_zone_lanes"] = jsonable(dataclasses.asdict(zone_lanes))
        Path(args.json).write_text(json.dumps(doc, allow_nan=False))
        print(f"wrote {args.json}")
    if args.plot:
        plot_evaluation(report, hdmap, gt, args.plot)
        print(f"wrote {args.plot}")
    return 0
