#!/usr/bin/env bash
# Fingerprints of the sample bags' maps: bag2map of bags/e6mini_20 and bags/ramps_20 with each
# preset into OUTDIR, then a hash of each map bag's /fleet/origin and /hdmap/map messages (raw CDR).
# Two checkouts that print the same lines build byte-identical maps. Usage:
#   scripts/maps_hash.sh OUTDIR
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
OUT=${1:?usage: scripts/maps_hash.sh OUTDIR}
mkdir -p "$OUT"
for bag in e6mini_20 ramps_20; do
  for preset in default naive paper; do
    "$ROOT/.venv/bin/hdmap" bag2map "$ROOT/bags/$bag" -o "$OUT/${bag}_$preset" --preset "$preset" \
      --overwrite --no-progress >/dev/null
  done
done
"$ROOT/.venv/bin/python" - "$OUT" <<'PY'
import hashlib, sys
from pathlib import Path
from rosbags.rosbag2 import Reader

for d in sorted(p for p in Path(sys.argv[1]).iterdir() if p.is_dir()):
    h = hashlib.sha256()
    with Reader(d) as reader:
        conns = [c for c in reader.connections if c.topic in ("/fleet/origin", "/hdmap/map")]
        for c, _, raw in reader.messages(connections=conns):
            h.update(c.topic.encode())
            h.update(raw)
    print(d.name, h.hexdigest()[:16])
PY
