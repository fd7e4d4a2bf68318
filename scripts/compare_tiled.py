#!/usr/bin/env python3
"""The tiled build against the whole-fleet build on one fleet bag: accuracy, identity, time, memory.

    scripts/compare_tiled.py BAG [--workers 1,2] [--block-tiles 0,4] [--no-whole] [--tile-size-m M] [--margin-m M]
                             [--out DIR]

Runs ``hdmap bag2map BAG`` (the whole fleet in memory, ``--workers 1``) and ``hdmap bag2map BAG
--tiled --workers N`` for each N, each in its own process, scores every map against
``BAG.gt.json`` (the paper's metric, ``hdmap_core.evaluation``) and prints one Markdown row per
build: mean and offset-corrected lateral error, coverage, recall, precision, wall time, peak RSS
(whole build: the process and its forked children, as ``wait4`` reports; tiled: the largest of
main, scheduler and each worker, from the build report) and CPU time of all its processes (what
the build cost on a machine shared with other work, where wall time says little). Then whether
the tiled maps are the same (feature and topology ids, points, links) and how far the tiled map's
feature points lie from the whole-fleet map's lines of the same type, both ways.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
HDMAP = [sys.executable, "-m", "hdmap_ros.cli"]


def _run(cmd: list[str]) -> tuple[float, float, float]:
    """Run a command; (wall s, peak RSS MB of it and its waited-for children, their CPU s)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode() if proc.stderr else ""
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"failed ({proc.returncode}): {' '.join(cmd)}\n{err}")
    return wall, usage.ru_maxrss / 1024.0, usage.ru_utime + usage.ru_stime


def _points(hdmap, spacing_m: float | None = None) -> dict[int, np.ndarray]:
    """Feature points per type (each polyline resampled every ``spacing_m`` when given)."""
    from hdmap_core.geometry import resample_evenly

    out: dict[int, list] = {}
    for f in hdmap.features:
        pts = np.asarray(f.points, dtype=float).reshape(-1, 2)
        if spacing_m and len(pts) >= 2:
            pts = resample_evenly(pts, spacing_m)
        out.setdefault(int(f.type), []).append(pts)
    return {t: np.vstack(v) for t, v in out.items()}


def _distances(a, b) -> np.ndarray:
    """Distance of every feature point of ``a`` to the nearest same-type polyline of ``b`` [m]
    (``b`` resampled every 0.05 m: at most 0.025 m too far)."""
    from scipy.spatial import cKDTree

    pa, pb = _points(a), _points(b, 0.05)
    out = [cKDTree(pb[t]).query(p)[0] if t in pb else np.full(len(p), np.inf) for t, p in pa.items()]
    return np.concatenate(out) if out else np.zeros(0)


def _same(a, b) -> bool:
    if len(a.features) != len(b.features) or len(a.topology) != len(b.topology):
        return False
    for f, g in zip(a.features, b.features):
        if (f.id, int(f.type), tuple(f.successors), tuple(f.predecessors)) != (
            g.id,
            int(g.type),
            tuple(g.successors),
            tuple(g.predecessors),
        ):
            return False
        if not np.array_equal(np.asarray(f.points), np.asarray(g.points)):
            return False
    return all(t.id == u.id and tuple(t.features) == tuple(u.features) for t, u in zip(a.topology, b.topology))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag")
    ap.add_argument("--workers", default="1,2", help="tiled worker counts, comma-separated (default: %(default)s)")
    ap.add_argument("--no-whole", action="store_true", help="skip the whole-fleet build")
    ap.add_argument("--tile-size-m", type=float)
    ap.add_argument("--margin-m", type=float)
    ap.add_argument(
        "--block-tiles",
        default="0",
        help="adjustments to build with, comma-separated: 0 one network-wide solve, N block-wise over N x N tiles "
        "(default: %(default)s)",
    )
    ap.add_argument("--out", help="keep maps and reports here (default: a temporary dir)")
    args = ap.parse_args(argv)

    from hdmap_core.evaluation.evaluate import evaluate_map
    from hdmap_core.groundtruth import load_ground_truth
    from hdmap_ros.io.bagio import read_map_bag

    bag = Path(args.bag)
    gt = load_ground_truth(bag.with_name(bag.name + ".gt.json"))
    tmp = tempfile.TemporaryDirectory(prefix="hdmap-cmp-")
    out = Path(args.out) if args.out else Path(tmp.name)
    out.mkdir(parents=True, exist_ok=True)
    runs: list[tuple[str, Path, float, float, float, dict]] = []
    if not args.no_whole:
        m, rep = out / "whole", out / "whole.json"
        wall, rss, cpu = _run(
            [
                *HDMAP,
                "bag2map",
                str(bag),
                "-o",
                str(m),
                "--overwrite",
                "--workers",
                "1",
                "--report",
                str(rep),
                "--no-progress",
            ]
        )
        doc = json.loads(rep.read_text())
        runs.append(("whole fleet, 1 process", m, doc["build"]["seconds"], rss, cpu, doc))
    variants = [
        (n, b)
        for b in [int(v) for v in args.block_tiles.split(",") if v]
        for n in [int(v) for v in args.workers.split(",") if v]
    ]
    for n, b in variants:
        tag = f"{n}" + (f"b{b}" if b else "")
        m, rep = out / f"tiled{tag}", out / f"tiled{tag}.json"
        cmd = [
            *HDMAP,
            "bag2map",
            str(bag),
            "-o",
            str(m),
            "--overwrite",
            "--tiled",
            "--workers",
            str(n),
            "--report",
            str(rep),
            "--no-progress",
        ]
        if args.tile_size_m:
            cmd += ["--tile-size-m", str(args.tile_size_m)]
        if args.margin_m:
            cmd += ["--margin-m", str(args.margin_m)]
        if b:
            cmd += ["--block-tiles", str(b)]
        wall, rss, cpu = _run(cmd)
        doc = json.loads(rep.read_text())
        peaks = doc["build"]["peak_rss_mb"]
        runs.append(
            (
                f"tiled, {n} worker(s)" + (f", adjustment in {b}x{b}-tile blocks" if b else ""),
                m,
                doc["build"]["seconds"] + doc["index_s"],
                max(peaks.values()),
                cpu,
                doc,
            )
        )

    print(f"{bag.name}: {runs[0][5]['drives']} drives, {runs[0][5]['drive_km']:.1f} drive-km\n")
    print(
        "| build | mean m | offset-corr. m | coverage | recall | precision | features | build s "
        "| drive-km/s per worker | peak RSS MB (largest process) | CPU s (all processes) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    maps = {}
    for name, m, secs, rss, cpu, doc in runs:
        hd = read_map_bag(m)
        maps[name] = hd
        o = evaluate_map(hd, gt)
        w = int(doc["build"].get("workers", 1))
        print(
            f"| {name} | {o.overall.mean_m:.4f} | {o.overall.corrected_mean_m:.4f} | {o.coverage:.1%} | "
            f"{o.overall.recall:.1%} | {o.overall.precision:.1%} | {len(hd.features)} | {secs:.1f} | "
            f"{doc['drive_km'] / secs / w:.2f} | {rss:.0f} | {cpu:.0f} |"
        )
    tiled = [k for k in maps if k.startswith("tiled")]
    for k in tiled:
        adj = k.partition(" worker(s)")[2]
        first = next(t for t in tiled if t.partition(" worker(s)")[2] == adj)  # same adjustment, other workers
        if k != first:
            print(
                f"\n{k} vs {first}: "
                + ("the same map (ids, points, links)" if _same(maps[k], maps[first]) else "DIFFERENT maps")
            )
    if not args.no_whole and tiled:
        whole, t = maps["whole fleet, 1 process"], maps[tiled[0]]
        for label, d in (("tiled -> whole", _distances(t, whole)), ("whole -> tiled", _distances(whole, t))):
            print(
                f"{label}: nearest same-type line median {np.median(d):.3f} m, p95 {np.percentile(d, 95):.3f} m, "
                f"share within 0.5 m {np.mean(d <= 0.5):.1%}"
            )
    for name, _, _, _, _, doc in runs:
        if "peak_rss_mb" in doc["build"]:
            print(
                f"{name}: stages "
                + ", ".join(f"{k} {v:.1f} s" for k, v in doc["build"]["stage_seconds"].items())
                + f", index {doc['index_s']:.1f} s; peak RSS MB "
                + ", ".join(f"{k} {v:.0f}" for k, v in doc["build"]["peak_rss_mb"].items())
                + "; CPU s "
                + ", ".join(f"{k} {v:.1f}" for k, v in doc["build"].get("cpu_seconds", {}).items())
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
