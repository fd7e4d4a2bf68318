#!/usr/bin/env bash
# The main job on an embedded default: simulate a fleet over a real map (esmini E6, from
# the shared map set), build the HD map, score it against the ground truth, and show the result.
#
#   make demo                        # defaults below
#   DEMO_MAP=carla_town06 DEMO_DRIVES=60 make demo
#
# Outputs go to out/demo/: fleet bag, map bag, GeoJSON, evaluation JSON and PNG.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

MAP="${DEMO_MAP:-esmini_e6mini}"
DRIVES="${DEMO_DRIVES:-40}"
SEED="${DEMO_SEED:-1}"
OUT="${DEMO_OUT:-out/demo}"
HDMAP=.venv/bin/hdmap

mkdir -p "$OUT"
echo "== 1/3 simulate $DRIVES drives over $MAP (seed $SEED)"
"$HDMAP" simulate --map "$MAP" --drives "$DRIVES" --seed "$SEED" -o "$OUT/fleet" --overwrite
echo
echo "== 2/3 build the map (default preset)"
"$HDMAP" bag2map "$OUT/fleet" -o "$OUT/map" --geojson "$OUT/map.geojson" --overwrite
echo
echo "== 3/3 evaluate against the ground truth"
"$HDMAP" evaluate "$OUT/map" "$OUT/fleet.gt.json" --fleet "$OUT/fleet" \
    --json "$OUT/evaluation.json" --plot "$OUT/evaluation.png"
echo
echo "Results in $OUT/: map (rosbag2 MCAP, /hdmap/map), map.geojson, evaluation.json, evaluation.png"
