#!/usr/bin/env bash
# Benchmarks: presets side by side (default, paper, naive) on the same simulated fleets, with the
# evaluator's figures, the floor, wall time and peak RSS per run, then the adjustment solver alone.
#
#   make bench                    # full: paper-like scenario at 0.25x, 1x, 4x drive-km
#   BENCH_SMOKE=1 make bench      # smoke run (CI-sized): small scenario, one scale, one switch,
#                                 # one road change
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-43}"
OUT="${BENCH_OUT:-out/bench}"
mkdir -p "$OUT"
HDMAP=.venv/bin/hdmap

if [[ -n "${BENCH_SMOKE:-}" ]]; then
    "$HDMAP" bench esmini_e6mini:20:1 --work-dir "$OUT/fleets" --markdown "$OUT/smoke.md" --json "$OUT/smoke.json"
    .venv/bin/python scripts/bench_incremental.py --drives 12 --road-km 2 --long-km 2 --replay-drives 6
    .venv/bin/python scripts/ablation.py --smoke --work-dir "$OUT/fleets" --out "$OUT/ablation"
    # Map updating: a 1.5 m shift followed after 2-3 drives, no false change on the sample bags.
    "$HDMAP" bench --changes --change-smoke --markdown "$OUT/changes_smoke.md" --json "$OUT/changes_smoke.json"
    .venv/bin/python scripts/bench_update_cost.py --smoke > "$OUT/update_cost_smoke.md"
    exit 0
fi
"$HDMAP" bench paper_like:134:1 esmini_e6mini:40:1 esmini_soderleden:40:1 carla_town04:100:1 carla_town06:100:1 \
    --work-dir "$OUT/fleets" --markdown "$OUT/presets.md" --json "$OUT/presets.json"
# One fleet can be unlucky (its drives' errors need not average out): the esmini maps over 8 seeds,
# with the means over the seeds; the CARLA maps with 100 drives and with a sparse fleet of 30 drives,
# over 3 seeds each.
"$HDMAP" bench esmini_soderleden:40:1-8 esmini_e6mini:40:1-8 \
    --work-dir "$OUT/fleets" --markdown "$OUT/seeds.md" --json "$OUT/seeds.json"
# The esmini maps with 100 drives: every place seen by ~40-95 drives.
"$HDMAP" bench esmini_e6mini:100:1-8 esmini_soderleden:100:1-8 --presets default,naive \
    --work-dir "$OUT/fleets" --markdown "$OUT/esmini100.md" --json "$OUT/esmini100.json"
"$HDMAP" bench carla_town04:100:1-3 carla_town06:100:1-3 --presets default \
    --work-dir "$OUT/fleets" --markdown "$OUT/carla100.md" --json "$OUT/carla100.json"
"$HDMAP" bench carla_town04:30:1-3 carla_town06:30:1-3 --presets default,naive \
    --work-dir "$OUT/fleets" --markdown "$OUT/sparse.md" --json "$OUT/sparse.json"
# Between the two: 50 drives, where the paper's density (5-25 drives per place) begins to hold.
"$HDMAP" bench carla_town04:50:1-3 carla_town06:50:1-3 --presets default \
    --work-dir "$OUT/fleets" --markdown "$OUT/carla50.md" --json "$OUT/carla50.json"
"$HDMAP" bench paper_like:134:1 --presets default --scale 0.25 --scale 1 --scale 4 \
    --work-dir "$OUT/fleets" --markdown "$OUT/scaling.md" --json "$OUT/scaling.json"
.venv/bin/python scripts/bench_incremental.py --drives 100
# Each switch of the default preset turned back, against the default on the same bags.
.venv/bin/python scripts/ablation.py --work-dir "$OUT/fleets" --out "$OUT/ablation"
# Map updating (issue 28): drives needed to follow each kind and size of change, the changed zone
# after 3 / 5 / 10 drives through it, and false changes on the fleets above without a change.
"$HDMAP" bench --changes --markdown "$OUT/changes.md" --json "$OUT/changes.json"
# What following a change costs (confirm, rebuild, apply) against mapping the places it touches.
.venv/bin/python scripts/bench_update_cost.py > "$OUT/update_cost.md"
if [[ -f scripts/bench_adjustment.py ]]; then .venv/bin/python scripts/bench_adjustment.py; fi
