#!/usr/bin/env python3
"""Benchmark and accuracy check of the network-wide offset adjustment on synthetic chains.

Usage (from the repository root):
    .venv/bin/python scripts/bench_adjustment.py                 # ~100k samples
    .venv/bin/python scripts/bench_adjustment.py --samples 600k  # the full-map size

Prints the adjustment's wall and CPU time (CPU time is the steadier figure on a shared machine;
with and without the posterior std), the problem size, and the mean absolute error of the
common offset per step (what stays in the map) next to the local per-step floor (the mean
offset of the drives crossing the step, which the per-step EM keeps).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src" / "hdmap_core"))

from hdmap_core.pipeline.adjustment import AdjustConfig, adjust_offsets  # noqa: E402
from hdmap_core.simulation.chains import ChainSimConfig, simulate_step_observations  # noqa: E402

SIZES = {
    # name: (road length, drives, step spacing, detection probability)
    "100k": (20000.0, 90, 4.0, 0.3),
    "600k": (30000.0, 134, 1.0, 0.25),
}


def _common_error(obs, truth, model) -> tuple[float, float, float]:
    """Mean |common offset error| per step: adjusted, per-step (paper) and mean drives per step."""
    ours, local, n_local = [], [], []
    for o in obs[:: max(1, len(obs) // 2000)]:
        ids, first = np.unique(np.asarray(o.drive_ids), return_index=True)
        if ids.size < 2:
            continue
        s = o.drive_s_m[first]
        true = np.array([truth.true_correction(d, x) for d, x in zip(ids, s)])
        est = np.array([model.offset(d, np.array([x]))[0] for d, x in zip(ids, s)])
        ours.append(np.mean(est - true))
        local.append(np.mean(true))
        n_local.append(ids.size)
    return float(np.mean(np.abs(ours))), float(np.mean(np.abs(local))), float(np.mean(n_local))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", choices=sorted(SIZES), default="100k")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--knot-spacing-m", type=float, default=AdjustConfig().knot_spacing_m)
    parser.add_argument("--wrong-label-fraction", type=float, default=0.05)
    args = parser.parse_args()
    road, drives, spacing, detect = SIZES[args.samples]
    sim = ChainSimConfig(
        road_length_m=road,
        n_drives=drives,
        step_spacing_m=spacing,
        detect_prob=detect,
        wrong_label_fraction=args.wrong_label_fraction,
        wrong_label_burst_m=100.0,
    )
    t0 = time.perf_counter()
    obs, truth = simulate_step_observations(config=sim, seed=args.seed)
    t_sim = time.perf_counter() - t0
    n = sum(len(o.drive_ids) for o in obs)
    print(f"simulated {len(obs)} steps, {n} samples, {drives} drives in {t_sim:.1f} s")
    for std in (False, True):
        cfg = AdjustConfig(knot_spacing_m=args.knot_spacing_m, compute_std=std)
        t0, c0 = time.perf_counter(), time.process_time()
        model = adjust_offsets(obs, config=cfg)
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        st = model.stats
        print(
            f"adjust_offsets(compute_std={std}): wall {dt:.2f} s, cpu {dc:.2f} s  unknowns {st['n_unknowns']}  "
            f"clusters {st['n_clusters']}  iterations {st['iterations']}  "
            f"downweighted {st['downweighted_fraction']:.3f}  relabelled {st['relabelled_fraction']:.3f}  "
            f"lane shifts {st['lane_shifts']}  inlier rms {st['inlier_rms_m']:.3f} m"
        )
    ours, local, n_local = _common_error(obs, truth, model)
    print(
        f"mean |common offset error| per step: adjusted {ours:.3f} m, per-step (local) {local:.3f} m, "
        f"drives per step {n_local:.1f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
