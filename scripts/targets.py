#!/usr/bin/env python3
"""Check the mapping issue's targets on `hdmap bench` results: one row per fleet, what is missed.

Reads the JSON files `hdmap bench --json` writes (``make bench``: out/bench/*.json) and, for every
fleet built with the default preset, checks the targets of the mapping issue:

- mean total lateral error <= 0.30 m and <= 1.15 x the floor; offset-corrected <= 0.12 m;
- coverage >= 97 %, recall >= 95 %, precision >= 97 %, fragmentation <= 1.5;
- every ground-truth split and merge connected: feature-level and road-level (the real maps'
  junction roads carry no markings, so their splits/merges are the lane graph's);
- the default beats every other preset run on the same bag on every figure (ties allowed).

A miss the fleet itself bounds is marked so: the error targets where the drives' own mean
localization error (``fleet err``, the realized floor) already exceeds them, recall where less
than 95 % of the ground truth was detected by any drive (``observed``), coverage where less than
97 % of it was driven at all. Such a miss counts as bound by the fleet only where the map meets
the target over what the fleet allows (``checked``): within 1.15 x the drives' own error, recall
>= 95 % over the observed part, coverage >= 97 % over the driven part. The last line counts the
fleets whose every miss is bound so. Means over seeds (rows without ``_sN``) are left out: each
fleet is judged on its own.

Usage (from the repository root, after ``make bench``):
    .venv/bin/python scripts/targets.py                 # out/bench/*.json but scaling/smoke
    .venv/bin/python scripts/targets.py out/bench/presets.json out/bench/sparse.json
    .venv/bin/python scripts/targets.py --misses-only     # only the fleets that miss a target
    # a change measured with `hdmap bench --presets default --set KEY=VALUE --json out/x.json`,
    # checked against the shipped presets (the plain default among them) on the same bags:
    .venv/bin/python scripts/targets.py out/bench/presets.json out/x.json --preset default+
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Iterable
from pathlib import Path

MEAN_MAX_M, MEAN_MAX_FLOOR, CORRECTED_MAX_M = 0.30, 1.15, 0.12
COVERAGE_MIN, RECALL_MIN, PRECISION_MIN, FRAGMENTATION_MAX = 0.97, 0.95, 0.97, 1.5
# (run key, label, higher is better) of the figures the default must not lose on
FIGURES = (
    ("mean_m", "mean", False),
    ("p95_m", "p95", False),
    ("corrected_mean_m", "corr. mean", False),
    ("coverage", "coverage", True),
    ("recall", "recall", True),
    ("precision", "precision", True),
    ("type_accuracy", "type acc.", True),
    ("fragmentation", "fragm.", False),
    ("found_splits_merges", "splits/merges", True),
    ("found_road_splits_merges", "road splits/merges", True),
    ("long_link_precision", "long-link prec.", True),
)
_SEEDED = re.compile(r"_s\d+$")
# make bench's files that are no target scenario: the 0.25x / 4x scaling runs (speed), the smoke run
NOT_TARGETS = ("scaling.json", "smoke.json")


def _fig(run: dict, key: str) -> float:
    if key == "found_splits_merges":
        return float(run["found_splits"] + run["found_merges"])
    if key == "found_road_splits_merges":
        return float(run["found_road_splits"] + run["found_road_merges"])
    value = run.get(key)
    return float(value) if value is not None else math.nan


def checked(run: dict) -> list[tuple[str, bool]]:
    """The targets one default-preset run misses, each as (what is missed, bound by the fleet).

    A miss is bound by the fleet when no map of these drives could meet the target and the map
    meets it over what the fleet allows: the error targets where the drives' own mean
    localization error (``fleet err``) already exceeds them and the map lies within 1.15 x that;
    recall where less than 95 % of the ground truth was detected by any drive and recall over
    the detected part is >= 95 %; coverage where less than 97 % was driven and coverage over the
    driven part is >= 97 %. Every other miss is the map's own.
    """
    out = []
    fleet_err, floor = run.get("fleet_floor_m"), run["floor_m"]
    mean = run["mean_m"]
    bounded = fleet_err is not None and (fleet_err > MEAN_MAX_M or fleet_err > MEAN_MAX_FLOOR * floor)
    note = f" (fleet's own error {fleet_err:.3f} m)" if bounded else ""
    follows = bounded and mean <= MEAN_MAX_FLOOR * fleet_err
    if mean > MEAN_MAX_M:
        out.append((f"mean {mean:.3f} m > {MEAN_MAX_M:.2f}{note}", follows and fleet_err > MEAN_MAX_M))
    if mean > MEAN_MAX_FLOOR * floor:
        out.append(
            (
                f"mean {mean / floor:.2f} x floor > {MEAN_MAX_FLOOR}{note}",
                follows and fleet_err > MEAN_MAX_FLOOR * floor,
            )
        )
    if run["corrected_mean_m"] > CORRECTED_MAX_M:
        out.append((f"corr. mean {run['corrected_mean_m']:.3f} m > {CORRECTED_MAX_M}", False))
    driven = run.get("driven_share")
    if run["coverage"] < COVERAGE_MIN:
        short = driven is not None and driven < COVERAGE_MIN
        why = f" (driven {100 * driven:.1f} %)" if short else ""
        over_driven = run.get("coverage_driven")
        out.append(
            (
                f"coverage {100 * run['coverage']:.1f} %{why}",
                short and over_driven is not None and over_driven >= COVERAGE_MIN,
            )
        )
    observed = run.get("observed_share")
    if run["recall"] < RECALL_MIN:
        short = observed is not None and math.isfinite(observed) and observed < RECALL_MIN
        why = f" (observed {100 * observed:.1f} %, recall obs. {100 * run['recall_observed']:.1f} %)" if short else ""
        out.append((f"recall {100 * run['recall']:.1f} %{why}", short and run["recall_observed"] >= RECALL_MIN))
    if run["precision"] < PRECISION_MIN:
        out.append((f"precision {100 * run['precision']:.1f} %", False))
    if run["fragmentation"] > FRAGMENTATION_MAX:
        out.append((f"fragm. {run['fragmentation']:.2f}", False))
    if run["found_splits"] + run["found_merges"] < run["gt_splits"] + run["gt_merges"]:
        out.append((f"splits/merges {run['splits_merges']}", False))
    if run["found_road_splits"] + run["found_road_merges"] < run["gt_road_splits"] + run["gt_road_merges"]:
        out.append((f"road splits/merges {run['road_splits_merges']}", False))
    return out


def misses(run: dict) -> list[str]:
    """The targets one default-preset run misses, each with its value and, where the fleet
    bounds it, why no map of these drives could meet it."""
    return [text for text, _ in checked(run)]


def own_misses(run: dict) -> list[str]:
    """The misses of ``run`` that its fleet does not bound (``checked``): the map's own."""
    return [text for text, bound in checked(run) if not bound]


def losses(run: dict, peers: Iterable[dict]) -> list[str]:
    """The figures on which the default run is worse than a peer preset's run on the same bag."""
    out = []
    for peer in peers:
        for key, label, higher in FIGURES:
            mine, theirs = _fig(run, key), _fig(peer, key)
            if not (math.isfinite(mine) and math.isfinite(theirs)):
                continue
            if (mine < theirs) if higher else (mine > theirs):
                extra = f" ({run['long_links']} vs {peer['long_links']})" if key == "long_link_precision" else ""
                out.append(f"{label} vs {peer['preset']}{extra}")
    return out


def load_runs(paths: Iterable[Path]) -> list[dict]:
    runs = []
    for path in paths:
        try:
            doc = json.loads(Path(path).read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise SystemExit(f"targets: {path}: not a readable hdmap bench JSON ({err})") from None
        if not isinstance(doc, list):
            raise SystemExit(f"targets: {path}: not a list of bench runs")
        runs += doc
    return runs


def table(runs: list[dict], *, misses_only: bool = False, preset: str = "default") -> tuple[str, int, int, int]:
    """The Markdown table (with ``misses_only`` only the fleets that miss something), the number
    of fleets, of fleets that meet every target, and of fleets whose every miss is bound by the
    fleet (``checked``), each losing no figure to a peer; ``preset``'s runs are checked, every
    other preset run on the same bag is a peer."""
    by_scenario: dict[str, list[dict]] = {}
    for run in runs:
        if _SEEDED.search(run["scenario"]):
            by_scenario.setdefault(run["scenario"], []).append(run)
    lines = ["| fleet | drives | targets missed | figures lost to a peer preset | peers |", "|---|---|---|---|---|"]
    n = n_ok = n_fleet_ok = 0
    for name in sorted(by_scenario):
        group = by_scenario[name]
        defaults = [r for r in group if r["preset"] == preset]
        if not defaults:
            continue
        run = defaults[0]
        peers = list({r["preset"]: r for r in reversed(group) if r["preset"] != preset}.values())  # first of each
        missed, lost = misses(run), losses(run, peers)
        n += 1
        n_ok += not missed and not lost
        n_fleet_ok += not own_misses(run) and not lost
        if misses_only and not missed and not lost:
            continue
        peer_names = ", ".join(sorted({p["preset"] for p in peers})) or "-"
        lines.append(
            f"| {name} | {run['drives']} | {'; '.join(missed) or 'none'} | {'; '.join(lost) or 'none'} | {peer_names} |"
        )
    return "\n".join(lines), n, n_ok, n_fleet_ok


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("json", nargs="*", type=Path, help="hdmap bench --json files (default: out/bench/*.json)")
    parser.add_argument(
        "--misses-only", action="store_true", help="list only the fleets that miss a target or lose a figure"
    )
    parser.add_argument(
        "--preset",
        default="default",
        help="the preset whose runs are checked, e.g. default+ of a bench --set run (default: default)",
    )
    args = parser.parse_args(argv)
    paths = args.json or sorted(p for p in Path("out/bench").glob("*.json") if p.name not in NOT_TARGETS)
    if not paths:
        print("targets: no bench JSON given and none in out/bench (run `make bench` first)", file=sys.stderr)
        return 2
    runs = load_runs(paths)
    if not any(r.get("preset") == args.preset for r in runs):
        have = ", ".join(sorted({str(r.get("preset")) for r in runs}))
        print(f"targets: no run of preset {args.preset!r} in the JSON (presets there: {have})", file=sys.stderr)
        return 2
    text, n, n_ok, n_fleet_ok = table(runs, misses_only=args.misses_only, preset=args.preset)
    print(text)
    print(f"\n{n_ok} of {n} fleets meet every target and lose no figure to a peer preset.")
    print(
        f"{n_fleet_ok} of {n} fleets meet every target their fleet allows (each miss bound by the fleet: "
        "the map within 1.15 x the drives' own error, recall over the observed >= 95 %, coverage over "
        "the driven >= 97 %) and lose no figure to a peer preset."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
