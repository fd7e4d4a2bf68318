"""One hostile drive in a good fleet bag: bag2map's time and map against the map without it.

Usage: .venv/bin/python scripts/bench_hostile.py [BAG] [--workers N]

The hostile drives are copies of the bag's first drive under a new id with one defect each (issue
32: a pose or detection point far away, a zigzag). Prints per case: wall time of read + build,
its ratio to the clean bag's, the rejection, and the map against the clean map (mean distance of
feature points to the nearest same-type feature of the other map, both ways [m]; recall: share of
the clean map's points within 0.5 m of the other map).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.model import Detection
from hdmap_core.pipeline.driver import build_map
from hdmap_ros.io.bagio import read_fleet_bag, write_fleet_bag

ROOT = Path(__file__).resolve().parents[1]


def _pose(value):
    def spoil(d):
        xy = np.array(d.xy, dtype=float)
        xy[len(xy) // 2, 1] = value
        return replace(d, xy=xy)

    return spoil


def _detection(value):
    def spoil(d):
        pts = np.array(d.detections[0].points, dtype=float)
        pts[len(pts) // 2, 0] = value
        return replace(d, detections=(Detection(d.detections[0].type, pts), *d.detections[1:]))

    return spoil


def _zigzag(d):
    xy = np.array(d.xy, dtype=float)
    xy[1::2, 1] += 50.0
    return replace(d, xy=xy)


CASES = {
    "pose 1e6 m": _pose(1e6),
    "pose 1e9 m": _pose(1e9),
    "pose 1e12 m": _pose(1e12),
    "pose 1e200 m": _pose(1e200),
    "detection 1e12 m": _detection(1e12),
    "detection 1e60 m": _detection(1e60),
    "zigzag +50 m": _zigzag,
}


def _points(hdmap):
    return {t: np.vstack([f.points for f in hdmap.features if f.type == t]) for t in {f.type for f in hdmap.features}}


def compare(a, b) -> tuple[float, float]:
    """(mean distance both ways [m], recall of a's points within 0.5 m of b)."""
    pa, pb = _points(a), _points(b)
    dists, near = [], []
    for t, pts in pa.items():
        d = cKDTree(pb[t]).query(pts)[0] if t in pb else np.full(len(pts), np.inf)
        dists.append(d)
        near.append(d <= 0.5)
    for t, pts in pb.items():
        dists.append(cKDTree(pa[t]).query(pts)[0] if t in pa else np.full(len(pts), np.inf))
    return float(np.mean(np.concatenate(dists))), float(np.mean(np.concatenate(near)))


def _run(bag: Path, workers: int):
    t0 = time.perf_counter()
    fleet = read_fleet_bag(bag)
    res = build_map(fleet.drives, workers=workers)
    return res, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("bag", nargs="?", default=str(ROOT / "bags" / "e6mini_20"))
    ap.add_argument("--workers", type=int, default=1)
    args = ap.parse_args()
    fleet = read_fleet_bag(args.bag)
    clean, t_clean = _run(Path(args.bag), args.workers)
    print(f"clean {args.bag}: {len(fleet.drives)} drives, {len(clean.map.features)} features, {t_clean:.2f} s")
    with tempfile.TemporaryDirectory() as tmp:
        for name, spoil in CASES.items():
            bad = spoil(replace(fleet.drives[0], drive_id="hostile"))
            bag = write_fleet_bag(Path(tmp) / name.replace(" ", "_"), [*fleet.drives, bad], fleet.origin)
            res, secs = _run(bag, args.workers)
            mean_m, recall = compare(clean.map, res.map)
            why = "; ".join(r for d, r in res.report.rejected if d == "hostile") or "accepted"
            print(
                f"{name:18s} {secs:6.2f} s  x{secs / t_clean:4.2f}  "
                f"mean {mean_m:.4f} m  recall {100 * recall:5.1f} %  {why}"
            )


if __name__ == "__main__":
    main()
