#!/usr/bin/env python3
"""Each switch of the default preset measured against the default itself, on the same bags.

The mapping issue asks for the default's improvements to be switchable and measured. This runs
`hdmap bench --presets default` on a few fleets, then once more per switch with that switch
turned back (`--set KEY=VALUE`, rows `default+`), and prints one table: every evaluator figure
of every variant on every fleet, side by side with the plain default of the same run.

Usage (from the repository root, after ``make setup``):
    .venv/bin/python scripts/ablation.py                     # the fleets of make bench, ~10 min
    .venv/bin/python scripts/ablation.py --smoke             # one small fleet, one switch (CI)
    .venv/bin/python scripts/ablation.py carla_town06:30:1 --out out/abl6
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

# (what is turned back, the --set changes). Each undoes one idea of the default preset
# (docs/pipeline.md "Presets"); the paper's choice where the paper makes one.
SWITCHES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("no network-wide adjustment: offsets of the per-step EM only", ("final_pass=null",)),
    ("adjustment: one constant offset per drive (no drift along it)", ("adjustment.drift_sigma_m=0",)),
    ("adjustment: plain least squares (no robust loss)", ('adjustment.loss="linear"',)),
    ("per-step M-step: no robust (Huber) loss", ("alignment.robust_loss=false",)),
    ("per-step: no offset prior from the drive's previous step", ("alignment.prior_weight=0",)),
    ("E-step: silhouette k-means at every step (paper), no tracking", ('alignment.clustering="silhouette"',)),
    ("M-step: Levenberg-Marquardt on the full cost (paper), not closed form", ('alignment.solver="lm"',)),
    ("KDE bandwidth 6 x the cluster std (paper), not 1 x", ("aggregation.kde_bandwidth_factor=6",)),
)
FLEETS = ("paper_like:134:1", "carla_town04:100:1", "carla_town06:30:1", "esmini_e6mini:40:1", "esmini_soderleden:40:1")
SMOKE_FLEETS = ("esmini_e6mini:20:1",)
# the figures of hdmap bench's table that a switch can move (its formats), build time last
FIGURES = (
    "mean_m",
    "corrected_mean_m",
    "p95_m",
    "coverage",
    "recall",
    "precision",
    "type_accuracy",
    "fragmentation",
    "splits_merges",
    "road_splits_merges",
    "long_links",
    "build_s",
)


def table(base: list[dict], variants: list[tuple[str, list[dict]]]) -> str:
    """One Markdown table: per fleet, the default's row, then each variant's row."""
    from hdmap_ros.commands.bench import COLUMNS, format_table  # noqa: PLC0415 (needs the workspace)

    formats = {key: (header, fmt) for key, header, fmt in COLUMNS}
    columns = (("scenario", "fleet", "{}"), ("variant", "variant", "{}"), *((k, *formats[k]) for k in FIGURES))
    rows = []
    for run in base:
        rows.append({**run, "variant": "default"})
        rows += [{**r, "variant": label} for label, runs in variants for r in runs if r["scenario"] == run["scenario"]]
    return format_table(rows, markdown=True, columns=columns)


def _bench(fleets: tuple[str, ...], sets: tuple[str, ...], json_path: Path, work_dir: Path) -> list[dict]:
    cmd = [
        str(Path(sys.executable).with_name("hdmap")),
        "bench",
        *fleets,
        "--presets",
        "default",
        "--work-dir",
        str(work_dir),
        "--json",
        str(json_path),
    ]
    for s in sets:
        cmd += ["--set", s]
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return json.loads(json_path.read_text())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fleets", nargs="*", help=f"bench scenarios (default: {' '.join(FLEETS)})")
    parser.add_argument("--out", type=Path, default=Path("out/ablation"), help="JSON and table go here")
    parser.add_argument(
        "--work-dir", type=Path, default=Path("out/bench/fleets"), help="simulated bags (shared with make bench)"
    )
    parser.add_argument("--smoke", action="store_true", help="one small fleet and the first switch only")
    args = parser.parse_args(argv)
    fleets = tuple(args.fleets) or (SMOKE_FLEETS if args.smoke else FLEETS)
    switches = SWITCHES[:1] if args.smoke else SWITCHES
    args.out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    base = _bench(fleets, (), args.out / "default.json", args.work_dir)
    variants = [
        (label, _bench(fleets, sets, args.out / f"switch{i}.json", args.work_dir))
        for i, (label, sets) in enumerate(switches, 1)
    ]
    text = table(base, variants)
    (args.out / "ablation.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
