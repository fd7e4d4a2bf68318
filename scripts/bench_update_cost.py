#!/usr/bin/env python3
"""Benchmark of what following a road change costs against what mapping costs (issue 28: "confirming
and applying a change costs no more than mapping the places it touches").

One process, the ``default`` preset, CPU seconds of this process (``time.process_time``), per fleet:

* ``build``: the first map (every drive, every place), as ``hdmap bag2map`` makes it;
* ``confirm``: ``follow_map`` up to its decision (every drive compared with the map, the change
  tests, the map as it was where the consensus took the new road; ``detect_cpu``);
* ``rebuild`` / ``apply``: the changed places mapped again from the drives after the change, then
  aligned and spliced (``rebuild_cpu`` / ``apply_cpu``);
* ``places``: mapping the places the change touches (the rebuilt places grown by the follow's
  margin, ``MARGIN_PLACES``) from every drive through them: the fleet's drives clipped to those places
  (``updates.follow.clip_to_places``) and built, what mapping those places costs.

Ratios: ``follow / places`` = (confirm + rebuild + apply) / places, and ``confirm / build``.

Fleets: change cases of ``bench_changes.py`` after 3 drives through the zone (seed 0) with
``--before`` drives on the road as it was (default 40 and 160: the same road and change, a fleet
four times larger), and the no-change fleets ``--nochange`` (confirm only: nothing is applied).

Prints a Markdown table; no assertions::

    .venv/bin/python scripts/bench_update_cost.py                    # ~6 min on one core
    .venv/bin/python scripts/bench_update_cost.py --smoke            # CI-sized, ~15 s
    .venv/bin/python scripts/bench_update_cost.py --cases shift1.5 --before 40 --nochange ''
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "src/hdmap_core"), str(ROOT / "src/hdmap_ros")]

from hdmap_ros.commands import bench_changes  # noqa: E402

DEFAULT_CASES = ("shift1.5", "restripe", "close", "open2.5", "soderleden_shift1.5")
DEFAULT_NOCHANGE = ("paper_like_134_s1", "carla_town04_100_s1")


MARGIN_PLACES = 2  # the follow's margin of places around the rebuilt ones (``follow_map``'s default)


def _timed_build():
    """drives -> (map, report) with ``default``, one worker, and the CPU seconds of each call."""
    from hdmap_core.pipeline.driver import build_map
    from hdmap_core.pipeline.presets import preset

    config = preset("default")
    cpu: list[float] = []

    def build(drives):
        c = time.process_time()
        r = build_map(list(drives), config=config, seed=0, workers=1)
        cpu.append(time.process_time() - c)
        return r.map, r.report

    return build, cpu


def measure(label: str, drives) -> dict:
    """The first build and the follow of ``drives``, and the map of the places a change touched."""
    from hdmap_core.updates.follow import clip_to_places, follow_changes
    from hdmap_core.updates.splice import grow

    build, cpu = _timed_build()
    res = follow_changes(drives, build=build, margin_places=MARGIN_PLACES)
    s = res.seconds
    row = {
        "fleet": label,
        "drives": len(drives),
        "changes": len(res.changes),
        "build": cpu[0],
        "confirm": s["detect_cpu"],
        "rebuild": s.get("rebuild_cpu", math.nan),
        "apply": s.get("apply_cpu", math.nan),
        "places_n": 0,
        "pieces": 0,
        "places": math.nan,
    }
    if res.changes and res.places is not None:
        region = grow(res.places, set(res.rebuilt), MARGIN_PLACES)
        pieces = clip_to_places(drives, res.places, region)
        mapped, mapped_cpu = _timed_build()
        mapped(pieces)
        row.update(places_n=len(region), pieces=len(pieces), places=mapped_cpu[0])
    return row


def table(rows: list[dict]) -> str:
    def f(x: float) -> str:
        return "-" if math.isnan(x) else f"{x:.2f}"

    out = [
        "| fleet | drives | changes | build | confirm | rebuild | apply | places (pieces) | mapping them | "
        "follow / mapping | confirm / build |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        follow = r["confirm"] + (0.0 if math.isnan(r["rebuild"]) else r["rebuild"] + r["apply"])
        ratio = follow / r["places"] if r["places"] > 0 else math.nan
        out.append(
            f"| {r['fleet']} | {r['drives']} | {r['changes']} | {f(r['build'])} | {f(r['confirm'])} | "
            f"{f(r['rebuild'])} | {f(r['apply'])} | "
            + (f"{r['places_n']} ({r['pieces']})" if r["places_n"] else "-")
            + f" | {f(r['places'])} | {f(ratio)} | {f(r['confirm'] / r['build'])} |"
        )
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(DEFAULT_CASES), help="change cases of bench_changes.py")
    ap.add_argument("--before", default="40,160", help="drives on the road as it was, per run")
    ap.add_argument("--after", type=int, default=3, help="drives through the zone after the change")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--nochange", default=",".join(DEFAULT_NOCHANGE), help="no-change fleets of bench_changes.py")
    ap.add_argument("--smoke", action="store_true", help="CI-sized: the 1.5 m shift after 40 drives, no other fleet")
    args = ap.parse_args()
    if args.smoke:
        args.cases, args.before, args.nochange = "shift1.5", "40", ""
    rows = []
    for n_before in [int(x) for x in args.before.split(",") if x]:
        for label in [c for c in args.cases.split(",") if c]:
            cf = bench_changes.case_fleet(label, args.seed, args.after, n_before)
            if len(cf.through) < args.after:
                print(f"{label}: only {len(cf.through)} drives through the zone", file=sys.stderr)
                continue
            rows.append(measure(f"{label}, {n_before} + {args.after}", cf.before + cf.through[: args.after]))
            print(rows[-1], file=sys.stderr, flush=True)
    fleets = {f[0]: f for f in bench_changes.NOCHANGE}
    for label in [c for c in args.nochange.split(",") if c]:
        _, name, n, seed = fleets[label]
        drives, _ = bench_changes._fleet(label, name, n, seed, ROOT / "bags")
        rows.append(measure(f"{label} (no change)", list(drives)))
        print(rows[-1], file=sys.stderr, flush=True)
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
