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
    .venv/bin/python scripts/compare_fleets.py bags/ramps_20 --set stitching.track_rejoin_m=0
    .venv/bin/python scripts/compare_fleets.py carla_town04:30:1-3 --work-dir out/fleets --save out/maps
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import sys
from pathlib import Path

from hdmap_core import pipeline
from hdmap_core.errors import ConfigError, HdmapError
from hdmap_ros.commands.bench import build_and_evaluate, prepare_scenarios

COLUMNS = "scenario mean cor cov rec obs recobs prec frag roadsm long build"


def override(config: object, key: str, value: object, *, full: str | None = None) -> object:
    """``config`` with the dotted ``key`` (e.g. ``stitching.track_rejoin_m``) set to ``value``.

    Raises:
        ConfigError: a part of the key names no field, or a stage that is off (None) in the preset.
    """
    full = full or key
    head, _, rest = key.partition(".")
    if not dataclasses.is_dataclass(config) or head not in {f.name for f in dataclasses.fields(config)}:
        raise ConfigError(f"--set {full}: {type(config).__name__} has no field {head!r}")
    if not rest:
        try:
            return dataclasses.replace(config, **{head: value})
        except ConfigError as err:
            raise ConfigError(f"--set {full}: {err}") from err
        except (TypeError, ValueError) as err:  # a value of the wrong kind fails the field's check
            raise ConfigError(f"--set {full}={value!r}: not a valid value ({err})") from err
    inner = getattr(config, head)
    if inner is None:
        raise ConfigError(f"--set {full}: {head} is off (None) in this preset")
    return dataclasses.replace(config, **{head: override(inner, rest, value, full=full)})


def parse_set(item: str) -> tuple[str, object]:
    """``KEY=VALUE``: the value as JSON (numbers, true/false, null, lists), else as a string."""
    key, sep, raw = item.partition("=")
    if not sep or not key:
        raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
    try:
        return key, json.loads(raw)
    except json.JSONDecodeError:
        return key, raw


def score_line(name: str, report: object, build_s: float) -> str:
    """One line of ``COLUMNS`` for an ``EvalReport``."""
    o = report.overall
    return (
        f"{name} {o.mean_m:.4f} {o.corrected_mean_m:.4f} {100 * report.coverage:.2f} {100 * o.recall:.2f} "
        f"{100 * report.observed_share:.2f} {100 * report.recall_observed:.2f} {100 * o.precision:.2f} "
        f"{report.fragmentation_mean:.3f} {report.found_road_splits}/{report.gt_road_splits},"
        f"{report.found_road_merges}/{report.gt_road_merges} "
        f"{report.n_long_links_supported}/{report.n_long_links_evaluable} {build_s:.1f}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenarios", nargs="+", metavar="SCENARIO")
    parser.add_argument("--preset", default="default", help="pipeline preset (default: default)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a preset parameter, dotted into PipelineConfig (repeatable)")
    parser.add_argument("--seed", type=int, default=0, help="pipeline seed (default: 0)")
    parser.add_argument("--workers", type=int, default=None, help="processes per build (default: the CPUs)")
    parser.add_argument("--work-dir", type=Path, default=Path("out/fleets"), help="simulated bags go here")
    parser.add_argument("--save", type=Path, default=None, help="pickle each map and report to DIR/NAME.pkl")
    args = parser.parse_args(argv)
    try:
        config = pipeline.PipelineConfig.preset(args.preset)
        for item in args.set:
            config = override(config, *parse_set(item))
        scenarios = prepare_scenarios(args.scenarios, scales=[1.0], work_dir=args.work_dir)
    except ConfigError as err:
        print(f"compare_fleets: {err}", file=sys.stderr)
        return 2
    print(COLUMNS, flush=True)
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
    """Build and score one scenario (as ``hdmap bench`` does): its ``COLUMNS`` line (and the
    pickle with ``--save``)."""
    _fleet, result, report, build_s, _workers = build_and_evaluate(sc, config, args.seed, args.workers)
    if args.save is not None:
        args.save.mkdir(parents=True, exist_ok=True)
        with open(args.save / f"{sc.name}.pkl", "wb") as f:
            pickle.dump({"map": result.map, "rep": report}, f)
    return score_line(sc.name, report, build_s)


if __name__ == "__main__":
    sys.exit(main())
