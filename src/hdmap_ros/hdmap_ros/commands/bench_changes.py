"""Benchmark of map updating (issue 28): drives needed to follow a change, the changed zone then,
and false changes on fleets without a change.

Two sections, both simulated in memory (the pipeline's ``default`` preset, one worker):

**changes**: for each kind and size of change (``CASES``: shift 0.5 / 1.0 / 1.5 / 3 m of one
carriageway's lanes and lines over 1 km toward the shoulder, barrier staying; every dashed line
painted solid (re-striping); every dashed line removed; the right lane closed over 700 m; the
shoulder opened as a lane, 2 m and 2.5 m wide) on the synthetic ``motorway_ramps`` (3 km, both directions, an exit
and an entry per carriageway) and on the real map ``esmini_soderleden`` (the shift and re-striping;
the simulator applies changes along any route of a map): 40 drives on the road as it was, then
drives on the changed road. Of those, only the ones through the changed zone's middle are kept
(the others carry no evidence of it; the issue counts "drives through the changed place"), up to
10. With the first ``j`` of them (j = 2, 3, ...: a change point needs 2 drives after it,
``ChangeConfig.min_after``, so one never suffices) the map is built and followed as
``hdmap bag2map`` does (``updates.follow.follow_changes``):

* ``needed``: the fewest drives through the zone from which on a change on the zone's places is
  confirmed, so the map is rebuilt there, at every count after it that was run (the scan runs
  every count until a change is confirmed, then 3, 5 and 10, and every count again after one
  that lost it; ">10": not within 10); ``first``: the fewest after which one was confirmed at all
  (a change confirmed after 2 drives can be lost after the third, when it disagrees);
* after 3, 5 and 10 such drives: the zone against the road as it is now (``evaluation/zone.py``:
  recall, precision, mean error, type accuracy, ghost share = the map's points there matching only
  the old road) for the followed map and the ghost share of the map of every drive (plain
  consensus, ``--no-follow-changes``), the whole road's recall and mean error, changes confirmed on
  the zone / elsewhere; for ``close`` / ``open`` the share of zone cuts with the road's lane count
  and the road's lane links in the zone the map's lane graph has (``evaluate_zone_lanes``).

**nochange**: the bench fleets of ``make bench`` without any change (``paper_like`` 134 drives,
``esmini_e6mini`` 40, ``esmini_soderleden`` 40, ``carla_town04`` 100, ``carla_town06`` 100, seed 1),
the 40 drives before the change of the changes section (``motorway_ramps``, seed 0) and the sample
bags ``bags/e6mini_20`` and ``bags/ramps_20``, each built with the presets ``default``, ``paper``
and ``naive`` and followed: changes confirmed (all false), per 1000 drive-km, and the evaluator's
mean error, recall and coverage of the followed map against the map without following. With no
change confirmed, ``follow_changes`` returns the first build itself (the same object: "same map").

Time: the full run (both sections, seed 0 for the changes: 10 cases x 4-10 follows of 42-50
drives, 8 fleets x 3 presets) takes ~15 min of CPU on one core (6.6 min changes, 8.6 min no
change; measured 2026-12-06 on the 2-core development machine, whose load of 6-19 stretched it to
23 + 27 min wall with the sections side by side; docs/updates.md "Measured"); most of it is
``paper`` on the 100-134-drive fleets (the evidence pass of paper_like was a large part before
it indexed the map's lines once per fleet, about 3.5x cheaper; the full run not re-timed since). ``--smoke`` (the 1.5 m
shift up to 3 drives, the sample bags with ``default`` and ``naive``) ~1 min. More seeds:
``--seeds 0,1,2`` (each adds the changes section's time again). Prints Markdown tables;
``--markdown`` / ``--json`` write them::

    hdmap bench --changes                                          # full
    hdmap bench --changes --change-smoke                           # CI-sized
    hdmap bench --changes --change-section changes --change-cases shift1.5,restripe --change-seeds 0,1

(``scripts/bench_changes.py`` runs it from the repository with the options unprefixed.)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hdmap_core.errors import ConfigError

if TYPE_CHECKING:
    from collections.abc import Sequence

#: The sample bags of the no-change section (``bags/`` of the repository, from its root).
SAMPLE_BAGS = Path("bags")

N_BEFORE = 40  # drives on the road as it was
MAX_THROUGH = 10  # drives through the zone after the change, at most
AT = (3, 5, 10)  # zone figures after this many drives through
# label -> (map, change text without @AFTER)
CASES: dict[str, tuple[str, str]] = {
    "shift0.5": ("motorway_ramps", "shift:1000-2000:0.5:fwd_lane1"),
    "shift1.0": ("motorway_ramps", "shift:1000-2000:1.0:fwd_lane1"),
    "shift1.5": ("motorway_ramps", "shift:1000-2000:1.5:fwd_lane1"),
    "shift3.0": ("motorway_ramps", "shift:1000-2000:3.0:fwd_lane1"),
    "restripe": ("motorway_ramps", "restripe:1000-2000:fwd_lane1"),
    "remove": ("motorway_ramps", "remove:1000-2000:fwd_lane1"),
    "close": ("motorway_ramps", "close:2250-2950:fwd_lane1"),
    "open": ("motorway_ramps", "open:2250-2950:2.0:fwd_lane1"),
    # a lane a planner would use: temporary lanes are at least 2.5 m wide (German RSA: 2.5 m left
    # lanes in works zones, hard-shoulder running 3.0-3.5 m); the widest the 2.5 m shoulder there
    # allows (the simulator refuses an edge moved beyond the road border); the 2.0 m one stays as
    # the hard case
    "open2.5": ("motorway_ramps", "open:2250-2950:2.5:fwd_lane1"),
    "soderleden_shift1.5": ("esmini_soderleden", "shift:600-1400:1.5"),
    "soderleden_restripe": ("esmini_soderleden", "restripe:600-1400"),
}
LANE_KINDS = ("close", "open")
SMOKE_CASES = ("shift1.5",)
# (label, map or named scenario, drives, seed) of the no-change fleets; a label of a sample bag
# reads bags/<label>
NOCHANGE: tuple[tuple[str, str, int, int], ...] = (
    ("paper_like_134_s1", "paper_like", 134, 1),
    ("esmini_e6mini_40_s1", "esmini_e6mini", 40, 1),
    ("esmini_soderleden_40_s1", "esmini_soderleden", 40, 1),
    ("carla_town04_100_s1", "carla_town04", 100, 1),
    ("carla_town06_100_s1", "carla_town06", 100, 1),
    ("motorway_ramps_40_s0", "motorway_ramps", 40, 0),
    ("e6mini_20", "bag", 20, 1),
    ("ramps_20", "bag", 20, 1),
)
SMOKE_NOCHANGE = ("e6mini_20", "ramps_20")
PRESETS = ("default", "paper", "naive")
SMOKE_PRESETS = ("default", "naive")


def _pct(x: float) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.1f}"


def _m(x: float) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.3f}"


def drive_km(drives) -> float:
    import numpy as np

    return sum(float(np.linalg.norm(np.diff(np.asarray(d.xy), axis=0), axis=1).sum()) for d in drives) / 1000.0


def _builder(preset: str):
    """drives -> (map, report), the preset's pipeline on one worker; each drive set built once."""
    from hdmap_core.pipeline.driver import build_map
    from hdmap_core.pipeline.presets import preset as make_preset

    config = make_preset(preset)
    cache: dict[tuple, tuple] = {}

    def build(drives):
        key = tuple(d.drive_id for d in drives)
        if key not in cache:
            cache.clear()  # only the last set is asked again
            r = build_map(list(drives), config=config, seed=0, workers=1)
            cache[key] = (r.map, r.report)
        return cache[key]

    return build


# ------------------------------------------------------------------------------ changes


@dataclass
class Step:
    """The map after ``j`` drives through the zone."""

    j: int
    on_zone: int
    elsewhere: int
    zone: Any = None  # ZoneReport of the followed map
    first_ghost: float = math.nan  # ghost share of the map of every drive
    first_recall: float = math.nan
    road_recall: float = math.nan
    road_mean_m: float = math.nan
    lanes: Any = None
    seconds: dict = field(default_factory=dict)


def _zone_keys(zone, places) -> set:
    """The places the zone's route piece runs through, in its direction, and their neighbours."""
    import numpy as np

    pts = zone.piece(step_m=2.0)
    t = np.gradient(pts, axis=0)
    keys = set(places.keys(pts, np.arctan2(t[:, 1], t[:, 0])))
    return keys | {nb for k in keys for nb in places.neighbours(k)}


@dataclass
class CaseFleet:
    """A change case's fleet: ``before`` (on the road as it was), ``through`` (after the change,
    through the zone's middle, in time order), the change, its zone, the road ``now`` and ``old``."""

    change: Any
    zone: Any
    before: list
    through: list
    now: Any
    old: Any
    after_simulated: int


def case_fleet(label: str, seed: int, need: int, n_before: int = N_BEFORE) -> CaseFleet:
    """``n_before`` drives on the road as it was, then drives after the change, simulated until
    ``need`` of them pass the zone's middle (or 120 simulated)."""
    import numpy as np

    from hdmap_core.simulation.changes import change_zone, parse_change, zone_mask
    from hdmap_core.simulation.config import SimConfig
    from hdmap_core.simulation.fleet import load_map, simulate_fleet

    map_name, text = CASES[label]
    change = parse_change(f"{text}@{n_before}")
    gt = load_map(map_name)
    zone = change_zone(gt, change)
    mid = zone.line[np.argmin(np.abs(zone.s - 0.5 * (zone.from_m + zone.to_m)))]
    through: list = []
    n_after = 0
    for extra in (30, 60, 120):  # more drives after the change until enough pass the zone
        n_after = extra
        fleet = simulate_fleet(gt, config=SimConfig(n_drives=n_before + extra), seed=seed, changes=[change])
        through = []
        for d in fleet.drives[n_before:]:
            near = np.linalg.norm(d.xy - mid, axis=1) < 10.0
            tang = np.stack([np.cos(d.yaw), np.sin(d.yaw)], axis=1)
            if near.any() and zone_mask(zone, d.xy[near], tang[near]).any():
                through.append(d)
        if len(through) >= need:
            break
    return CaseFleet(
        change,
        zone,
        list(fleet.drives[:n_before]),
        through,
        fleet.extra["gt_after"],
        fleet.extra["gt_before"],
        n_after,
    )


def run_case(label: str, seed: int, js: list[int], preset: str = "default") -> dict:
    from hdmap_core.evaluation.evaluate import evaluate_map
    from hdmap_core.evaluation.zone import evaluate_zone, evaluate_zone_lanes
    from hdmap_core.lanes.derive import derive_lanes
    from hdmap_core.updates.config import ChangeConfig
    from hdmap_core.updates.follow import follow_changes
    from hdmap_core.updates.places import places_of

    map_name, _ = CASES[label]
    t0 = time.perf_counter()
    cf = case_fleet(label, seed, max(js))
    change, zone, before, through = cf.change, cf.zone, cf.before, cf.through
    now, old, n_after = cf.now, cf.old, cf.after_simulated
    sim_s = time.perf_counter() - t0
    build = _builder(preset)
    steps: list[Step] = []
    needed = first_seen = None
    for j in js:
        if j > len(through):
            break
        if needed is not None and j not in AT:
            continue  # confirmed: only the figures after 3 / 5 / 10 are left, unless it is lost
        drives = before + through[:j]
        res = follow_changes(drives, build=build)
        places = places_of(drives, cell_m=ChangeConfig().cell_m)
        zkeys = _zone_keys(zone, places)
        on = [c for c in res.changes if c.keys & zkeys]
        step = Step(j, len(on), len(res.changes) - len(on), seconds=dict(res.seconds))
        if on and needed is None:
            needed = j
        first_seen = j if first_seen is None and on else first_seen
        if not on:
            needed = None  # lost again: scan on
        if j in AT:
            step.zone = evaluate_zone(res.map, now, old, [zone])
            first = evaluate_zone(res.first_map, now, old, [zone])
            step.first_ghost, step.first_recall = first.ghost_share, first.recall
            whole = evaluate_map(res.map, now)
            step.road_recall, step.road_mean_m = whole.overall.recall, whole.overall.mean_m
            if change.kind in LANE_KINDS:
                step.lanes = evaluate_zone_lanes(derive_lanes(res.map), now, [zone])
        steps.append(step)
        print(
            f"  {label} seed {seed}: j={j} on zone {step.on_zone}, elsewhere {step.elsewhere}"
            + (f", zone recall {_pct(step.zone.recall)} ghost {_pct(step.zone.ghost_share)}" if step.zone else ""),
            file=sys.stderr,
            flush=True,
        )
    return {
        "case": label if preset == "default" else f"{label} ({preset})",
        "map": map_name,
        "change": change.text(),
        "seed": seed,
        "after_simulated": n_after,
        "through": len(through),
        "needed": needed,
        "first": first_seen,
        "steps": steps,
        "sim_s": sim_s,
        "total_s": time.perf_counter() - t0,
    }


def changes_tables(rows: list[dict]) -> str:
    out = [
        "| case | map | seed | through | needed | first | drives | zone recall % | precision % | mean m | type % "
        "| ghost % | ghost % plain | road recall % | road mean m | changes zone/else | lanes ok % |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        needed = str(r["needed"]) if r["needed"] is not None else f">{min(r['through'], MAX_THROUGH)}"
        needed += f" | {r['first'] if r['first'] is not None else '-'}"
        first = True
        for s in r["steps"]:
            if s.zone is None:
                continue
            z = s.zone
            head = f"| {r['case']} | {r['map']} | {r['seed']} | {r['through']} | {needed} " if first else "| | | | | | "
            first = False
            lanes = "-"
            if s.lanes is not None:
                lanes = _pct(s.lanes.count_accuracy) + (
                    f" ({s.lanes.links_ok}/{s.lanes.n_links} links)" if s.lanes.n_links else ""
                )
            out.append(
                head + f"| {s.j} | {_pct(z.recall)} | {_pct(z.precision)} | {_m(z.mean_m)} | {_pct(z.type_accuracy)} "
                f"| {_pct(z.ghost_share)} | {_pct(s.first_ghost)} | {_pct(s.road_recall)} | {_m(s.road_mean_m)} "
                f"| {s.on_zone}/{s.elsewhere} | {lanes} |"
            )
        if first:
            out.append(f"| {r['case']} | {r['map']} | {r['seed']} | {r['through']} | {needed} | - |" + " |" * 10)
    return "\n".join(out)


# ------------------------------------------------------------------------------ no change


def _fleet(label: str, name: str, n: int, seed: int, bags: Path = SAMPLE_BAGS):
    from hdmap_core.groundtruth import load_ground_truth
    from hdmap_core.simulation.config import SimConfig
    from hdmap_core.simulation.fleet import load_map, simulate_fleet
    from hdmap_core.simulation.scenarios import NAMED_SCENARIOS

    if name == "bag":
        from hdmap_ros.io.bagio import read_fleet_bag

        bag = Path(bags) / label
        if not bag.exists():
            raise ConfigError(f"sample bag {bag} not found (run from the repository's root, or --bags DIR)")
        return read_fleet_bag(bag).drives, load_ground_truth(bag.with_name(label + ".gt.json"))
    named = NAMED_SCENARIOS.get(name)
    if named is not None:
        gt = load_map(named["map"], length_m=named["length_m"])
        config = SimConfig.from_dict({**named["sim"], "n_drives": n})
    else:
        gt = load_map(name)
        config = SimConfig(n_drives=n)
    return simulate_fleet(gt, config=config, seed=seed).drives, gt


def run_nochange(
    label: str, name: str, n: int, seed: int, presets: tuple[str, ...], bags: Path = SAMPLE_BAGS
) -> list[dict]:
    from hdmap_core.evaluation.evaluate import evaluate_map
    from hdmap_core.updates.follow import follow_changes

    drives, gt = _fleet(label, name, n, seed, bags)
    km = drive_km(drives)
    rows = []
    for preset in presets:
        t0 = time.perf_counter()
        res = follow_changes(drives, build=_builder(preset))
        wall = time.perf_counter() - t0
        plain = evaluate_map(res.first_map, gt)
        same = res.map is res.first_map
        followed = plain if same else evaluate_map(res.map, gt)
        row = {
            "fleet": label,
            "preset": preset,
            "drives": len(drives),
            "drive_km": km,
            "changes": len(res.changes),
            "places": sum(len(c.places) for c in res.changes),
            "same_map": same,
            "plain": {"mean_m": plain.overall.mean_m, "recall": plain.overall.recall, "coverage": plain.coverage},
            "follow": {
                "mean_m": followed.overall.mean_m,
                "recall": followed.overall.recall,
                "coverage": followed.coverage,
            },
            "build_s": res.seconds.get("build", math.nan),
            "detect_s": res.seconds.get("detect", math.nan),
            "wall_s": wall,
        }
        print(
            f"  {label} {preset}: {row['changes']} change(s), build {row['build_s']:.1f} s, "
            f"detect {row['detect_s']:.1f} s",
            file=sys.stderr,
            flush=True,
        )
        rows.append(row)
    return rows


def nochange_tables(rows: list[dict]) -> str:
    out = [
        "| fleet | preset | drives | drive km | changes | map | mean m plain / follow | recall % plain / follow "
        "| coverage % plain / follow | build s | detect s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        p, f = r["plain"], r["follow"]
        out.append(
            f"| {r['fleet']} | {r['preset']} | {r['drives']} | {r['drive_km']:.1f} | {r['changes']} "
            f"| {'same map' if r['same_map'] else 'followed'} | {_m(p['mean_m'])} / {_m(f['mean_m'])} "
            f"| {_pct(p['recall'])} / {_pct(f['recall'])} | {_pct(p['coverage'])} / {_pct(f['coverage'])} "
            f"| {r['build_s']:.1f} | {r['detect_s']:.1f} |"
        )
    out += ["", "| preset | fleets | drive km | changes confirmed | per 1000 drive-km |", "|---|---|---|---|---|"]
    for preset in dict.fromkeys(r["preset"] for r in rows):
        sel = [r for r in rows if r["preset"] == preset]
        km = sum(r["drive_km"] for r in sel)
        n = sum(r["changes"] for r in sel)
        out.append(f"| {preset} | {len(sel)} | {km:.0f} | {n} | {1000.0 * n / km:.2f} |")
    return "\n".join(out)


def _jsonable(x: Any) -> Any:
    from dataclasses import asdict, is_dataclass

    if is_dataclass(x) and not isinstance(x, type):
        return _jsonable(asdict(x))
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, float) and math.isnan(x):
        return None
    return x


def add_arguments(ap: argparse.ArgumentParser, *, prefix: str = "") -> None:
    """The benchmark's options; ``prefix`` names them apart inside ``hdmap bench`` (``--change-``)."""
    p = prefix
    ap.add_argument(f"--{p}section", dest="section", choices=("changes", "nochange", "all"), default="all")
    ap.add_argument(
        f"--{p}smoke", dest="smoke", action="store_true", help="CI-sized: one case up to 3 drives, the sample bags"
    )
    ap.add_argument(f"--{p}cases", dest="cases", help=f"comma-separated cases (default: all of {', '.join(CASES)})")
    ap.add_argument(f"--{p}fleets", dest="fleets", help="comma-separated no-change fleets by label (default: all)")
    ap.add_argument(
        f"--{p}seeds", dest="seeds", default="0", help="comma-separated seeds of the changes section (default: 0)"
    )
    ap.add_argument(
        f"--{p}bags", dest="bags", default=str(SAMPLE_BAGS), help="the sample bags' directory (default: %(default)s)"
    )


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(ap)
    ap.add_argument("--presets", help="comma-separated presets of the no-change section (default: all three)")
    ap.add_argument("--preset", default="default", help="preset of the changes section (default: %(default)s)")
    ap.add_argument("--markdown", metavar="FILE", help="write the tables as Markdown")
    ap.add_argument("--json", metavar="FILE", help="write every figure as JSON")
    return run(ap.parse_args(argv))


def run(args: argparse.Namespace) -> int:
    """The benchmark (module docstring) with ``add_arguments``' options and ``presets`` (no-change
    section), ``preset`` (changes section), ``markdown``, ``json``."""
    t_start = time.perf_counter()
    cases = args.cases.split(",") if args.cases else list(SMOKE_CASES if args.smoke else CASES)
    fleets = args.fleets.split(",") if args.fleets else list(SMOKE_NOCHANGE if args.smoke else (f[0] for f in NOCHANGE))
    presets = tuple(args.presets.split(",")) if args.presets else (SMOKE_PRESETS if args.smoke else PRESETS)
    unknown = [c for c in cases if c not in CASES] + [f for f in fleets if f not in {x[0] for x in NOCHANGE}]
    if unknown:
        raise ConfigError(f"unknown change case / fleet: {', '.join(unknown)}")
    js = [2, 3] if args.smoke else list(range(2, MAX_THROUGH + 1))
    doc: dict[str, Any] = {"changes": [], "nochange": []}
    md = []
    if args.section in ("changes", "all"):
        for seed in (int(s) for s in args.seeds.split(",")):
            for c in cases:
                doc["changes"].append(run_case(c, seed, js, args.preset))
        md += [
            "## Changes: drives through the zone needed, the zone after 3 / 5 / 10",
            "",
            changes_tables(doc["changes"]),
        ]
    if args.section in ("nochange", "all"):
        for label, name, n, seed in NOCHANGE:
            if label in fleets:
                doc["nochange"] += run_nochange(label, name, n, seed, presets, Path(args.bags))
        md += ["", "## No change: false changes and the figures with following vs without", ""]
        md += [nochange_tables(doc["nochange"])]
    md += [
        "",
        "through: drives after the change through the zone's middle (kept, up to 10); needed: the fewest of them "
        "from which on a change on the zone is confirmed (the map rebuilt there); first: after which one was "
        "confirmed at all; drives: the zone figures after that "
        "many; zone: the changed stretch with its tapers against the road as of the last drive; ghost: share of the "
        "map's points there matching only the old road (plain: the map of every drive, no following); changes "
        "zone/else: confirmed on the zone's places / elsewhere (false); lanes ok: zone cuts with the road's lane "
        "count (its lane centerlines), and of its lane links in the zone those the map's lane graph has. "
        "No change: 'same map' = no change confirmed, the followed map is the first build itself.",
        f"Wall time {time.perf_counter() - t_start:.0f} s.",
    ]
    text = "\n".join(md)
    print(text)
    if args.markdown:
        Path(args.markdown).parent.mkdir(parents=True, exist_ok=True)
        Path(args.markdown).write_text(text + "\n")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(_jsonable(doc), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
