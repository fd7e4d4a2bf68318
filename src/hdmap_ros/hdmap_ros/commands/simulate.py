"""``hdmap simulate --map NAME -o OUT``: simulate a vehicle fleet over a ground-truth map.

Writes OUT (rosbag2 MCAP directory with ``/fleet/drives`` and ``/fleet/origin``), and beside it
``OUT.gt.json`` (the ground truth, data/maps format) and ``OUT.sim.json`` (the simulator
config, seed and per-drive truth such as the true lateral bias). The map is a synthetic highway
name (``motorway``, ``motorway_ramps``, ``lane_drop``), a shipped real map (``esmini_e6mini``, found
in ``$HDMAP_MAPS_DIR`` or the repository's ``data/maps``) or a ``.gt.json`` path.
Simulator parameters: defaults of ``SimConfig`` (docs/simulator.md), overridden by ``--config``
(JSON or YAML mapping) and then by ``--set key=value`` (repeatable).
``--change KIND:FROM_M-TO_M[:SIZE][:ROUTE]@AFTER_DRIVE`` (repeatable; ``hdmap_core.simulation.changes``)
changes the road from drive AFTER_DRIVE on, a day later; then ``OUT.gt.json`` is the road as of
the last drive, ``OUT.gt_before.json`` the road before every change and ``OUT.changes.json`` the
changes with their times and zones (docs/updates.md). Exit status: 0 done,
1 an error (bad map, bad config, unwritable output), 2 usage.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from hdmap_core.errors import ConfigError
from hdmap_core.groundtruth import save_ground_truth

__all__ = ["NAME", "HELP", "add_arguments", "run", "load_overrides", "parse_set", "write_changes_json"]

NAME = "simulate"
HELP = "simulate a vehicle fleet over a ground-truth map and write a fleet bag (+ .gt.json, .sim.json)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--map",
        metavar="NAME_OR_PATH",
        default="motorway_ramps",
        help="synthetic name (motorway, motorway_ramps, lane_drop), shared map name (e.g. esmini_e6mini) "
        "or .gt.json path (default: %(default)s)",
    )
    parser.add_argument("-o", "--output", metavar="OUT", required=True, help="fleet bag directory to write")
    parser.add_argument(
        "--drives", type=int, metavar="N", help="number of drive snippets (default: SimConfig.n_drives)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulation (default: %(default)s)")
    parser.add_argument("--config", metavar="FILE", help="JSON or YAML mapping of SimConfig overrides")
    parser.add_argument(
        "--set",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        dest="overrides",
        help="override one SimConfig parameter (repeatable), e.g. --set bias_lateral_sigma_m=0.5",
    )
    parser.add_argument("--length-m", type=float, help="length of a synthetic highway [m] (default: 3000)")
    parser.add_argument("--map-seed", type=int, default=0, help="seed of a synthetic highway's shape (default: 0)")
    parser.add_argument(
        "--change",
        metavar="KIND:FROM_M-TO_M[:SIZE][:ROUTE]@AFTER_DRIVE",
        action="append",
        default=[],
        dest="changes",
        help="a road change seen by the drives from AFTER_DRIVE on (repeatable); kinds: shift (SIZE m to the right, "
        "default 1.5), restripe, remove (SIZE = k-th marking from the left, default every dashed one), add "
        "(SIZE m right of the route), close (the rightmost lane), open (the shoulder, SIZE m); "
        "e.g. shift:1000-2000:1.5@40",
    )
    parser.add_argument("--trajectories", action="store_true", help="also store true trajectories in OUT.sim.json")
    parser.add_argument(
        "--batch-drives",
        type=int,
        metavar="N",
        help="stream the fleet to the bag N drives at a time, never holding it (for fleets larger than memory; "
        "the same bag; OUT.sim.json without per-pose truth)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace OUT if it is an existing bag")


def load_overrides(path: str | Path) -> dict:
    """A mapping of SimConfig overrides from a JSON or YAML file.

    Raises:
        ConfigError: unreadable, not parseable, or not a mapping.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise ConfigError(f"cannot read config {path}: {err}") from err
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as json_err:
        try:
            from ruamel.yaml import YAML, YAMLError
        except ImportError:
            raise ConfigError(f"config {path} is not JSON ({json_err}) and no YAML parser is installed") from None
        try:
            doc = YAML(typ="safe").load(text)
        except YAMLError as err:
            raise ConfigError(f"config {path} is neither JSON nor YAML: {err}") from err
    if not isinstance(doc, dict):
        raise ConfigError(f"config {path} must hold a mapping of SimConfig parameters, got {type(doc).__name__}")
    return dict(doc)


def parse_set(items: list[str]) -> dict:
    """``["key=value", ...]`` -> dict; values stay strings (SimConfig parses them)."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        out[key.strip()] = value.strip()
    return out


def write_changes_json(fleet, path: Path, *, before: str) -> None:  # noqa: ANN001 (Fleet: imported late)
    """``OUT.changes.json``: the base ground truth's file name and every change with its time
    and zone (``hdmap evaluate --changes`` reads it back)."""
    from hdmap_core.simulation.changes import change_zone  # noqa: PLC0415

    gt = fleet.extra["gt_before"]
    doc = {
        "gt_before": before,
        "changes": [{**c.to_dict(), "zone": change_zone(gt, c).to_dict()} for c in fleet.extra["changes"]],
    }
    path.write_text(json.dumps(doc, indent=1))


def _batches(drives: Iterator, n: int) -> Iterator:
    """The drives, simulated ``n`` at a time ahead of the writer."""
    while batch := list(itertools.islice(drives, n)):
        yield from batch


def _sidecar(out: Path, suffix: str) -> Path:
    return out.with_name(out.name + suffix)


def run(args: argparse.Namespace) -> int:
    out = Path(str(args.output).rstrip("/\\"))
    overrides: dict = {}
    if args.config:
        overrides.update(load_overrides(args.config))
    overrides.update(parse_set(args.overrides))
    if args.drives is not None:
        overrides["n_drives"] = args.drives
    # Imported here, not at module level: the simulator pulls in scipy.signal, which made every
    # `hdmap` call (even --help) pay for it.
    from hdmap_core.simulation.changes import parse_change  # noqa: PLC0415
    from hdmap_core.simulation.fleet import SimConfig, load_map, simulate_fleet, write_sim_json  # noqa: PLC0415

    config = SimConfig.from_dict(overrides)
    changes = [parse_change(text) for text in args.changes]
    gt = load_map(args.map, length_m=args.length_m, map_seed=args.map_seed)
    from hdmap_ros.io.bagio import write_fleet_bag  # here: needs rosbags, the core part does not

    t0 = time.perf_counter()
    if args.batch_drives is not None:
        if args.batch_drives < 1:
            raise ConfigError(f"--batch-drives must be >= 1, got {args.batch_drives}")
        if args.trajectories:
            raise ConfigError("--trajectories keeps every drive's true trajectory: not with --batch-drives")
        from hdmap_core.simulation.fleet import FleetStream  # noqa: PLC0415

        stream = FleetStream(gt, config=config, seed=args.seed, changes=changes)
        write_fleet_bag(
            out,
            _batches(iter(stream), args.batch_drives),
            stream.origin,
            overwrite=args.overwrite,
            start_ns=int(config.start_time_ns),
        )
        fleet = stream.fleet()
        t_sim = time.perf_counter() - t0  # simulation and writing, interleaved
    else:
        fleet = simulate_fleet(gt, config=config, seed=args.seed, changes=changes)
        t_sim = time.perf_counter() - t0
        write_fleet_bag(out, fleet.drives, fleet.origin, overwrite=args.overwrite)
    if changes:
        save_ground_truth(fleet.extra["gt_after"], _sidecar(out, ".gt.json"))
        save_ground_truth(gt, _sidecar(out, ".gt_before.json"))
        write_changes_json(fleet, _sidecar(out, ".changes.json"), before=_sidecar(out, ".gt_before.json").name)
    else:
        save_ground_truth(gt, _sidecar(out, ".gt.json"))
    write_sim_json(fleet, _sidecar(out, ".sim.json"), include_trajectories=args.trajectories)
    s = fleet.summary()
    print(
        f"hdmap simulate: {s['drives']} drives, {s['km']:.1f} km, {s['detections']} detections "
        f"({s['false_positives']} false positives) on {gt.name!r} (seed {args.seed}) in {t_sim:.1f} s\n"
        f"  wrote {out}/, {_sidecar(out, '.gt.json').name}, {_sidecar(out, '.sim.json').name}"
        + (f", {_sidecar(out, '.gt_before.json').name}, {_sidecar(out, '.changes.json').name}" if changes else ""),
        file=sys.stdout,
    )
    for c in fleet.extra.get("changes", ()):
        print(f"  change {c.text()} at {c.time_ns} ns", file=sys.stdout)
    return 0
