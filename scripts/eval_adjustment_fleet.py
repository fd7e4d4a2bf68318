#!/usr/bin/env python3
"""Measure the offset adjustment on observations of the real pipeline, against simulator truth.

Simulates a fleet (``hdmap_core.simulation.fleet``), runs the pipeline's first pass (sampling + per-step EM
of the "default" preset) to collect the per-step observations, adjusts the offsets jointly
(``hdmap_core.pipeline.adjustment``), and compares, step by step, the common error of the drives crossing
the step (mean of estimated minus true lateral correction: what shifts the fused lines):
- adjusted: the joint offset curves;
- per-step: what the per-step EM leaves (its offsets are zero-mean over the step's drives, so the
  mean true correction of those drives stays in the map).

With ``--build`` it also builds complete maps with the "default" preset, with and without the
adjustment, and prints the evaluator's summary (``hdmap_core.evaluation.evaluate``) of each.

Usage (from the repository root):
    .venv/bin/python scripts/eval_adjustment_fleet.py --map motorway --length-m 6000 --drives 134 --build
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src" / "hdmap_core"))

from hdmap_core.pipeline.adjustment import AdjustConfig, adjust_offsets  # noqa: E402
from hdmap_core.pipeline.driver import map_stretches  # noqa: E402
from hdmap_core.pipeline.overrides import config_from  # noqa: E402
from hdmap_core.simulation.fleet import SimConfig, load_map, simulate_fleet  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--map", default="motorway")
    parser.add_argument("--length-m", type=float, default=5000.0)
    parser.add_argument("--drives", type=int, default=134)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--knot-spacing-m", type=float, default=AdjustConfig().knot_spacing_m)
    parser.add_argument("--loss", default=AdjustConfig().loss)
    parser.add_argument(
        "--build",
        action="store_true",
        help="also build complete maps (default preset with and without the adjustment) and "
        "print the evaluator's summary of each",
    )
    args = parser.parse_args()

    gt = load_map(args.map, length_m=args.length_m)
    fleet = simulate_fleet(gt, config=SimConfig(n_drives=args.drives), seed=args.seed)
    t0 = time.perf_counter()
    cfg = config_from("default", {"final_pass": None})
    res = map_stretches(fleet.drives, config=cfg, seed=args.seed, collect_observations=True)
    t_pass = time.perf_counter() - t0
    obs = res.observations
    t0 = time.perf_counter()
    model = adjust_offsets(obs, config=AdjustConfig(knot_spacing_m=args.knot_spacing_m, loss=args.loss))
    t_adj = time.perf_counter() - t0
    st = model.stats
    print(
        f"{args.map} {args.length_m:.0f} m, {args.drives} drives, seed {args.seed}: first pass {t_pass:.1f} s, "
        f"{len(obs)} steps, {st['n_samples']} samples ({st['n_samples_used']} used), adjustment {t_adj:.2f} s, "
        f"{st['n_unknowns']} unknowns, {st['iterations']} iterations, downweighted {st['downweighted_fraction']:.3f}, "
        f"inlier rms {st['inlier_rms_m']:.3f} m"
    )

    # true correction (to add) of each drive as a function of its travelled distance
    truth = {}
    for d in fleet.drives:
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(d.xy, axis=0), axis=1))])
        truth[d.drive_id] = (s, -np.asarray(fleet.truth[d.drive_id]["lateral_error_m"]))
    ours, local, n_local, rel, z = [], [], [], [], []
    for o in obs:
        ids, first = np.unique(np.asarray(o.drive_ids), return_index=True)
        if ids.size < 2:
            continue
        s = np.asarray(o.drive_s_m)[first]
        true = np.array([np.interp(x, *truth[d]) for d, x in zip(ids, s)])
        est = np.array([model.offset(d, np.array([x]))[0] for d, x in zip(ids, s)])
        ours.append(np.mean(est - true))
        local.append(np.mean(true))
        n_local.append(ids.size)
        rel.append((est - true) - np.mean(est - true))
        sd = model.std(ids[0], s[:1])[0]
        z.append((est[0] - true[0]) / sd)
    ours, local, n_local = np.abs(ours), np.abs(local), np.asarray(n_local)
    floor = np.mean(np.hypot(1.0, 0.3) / np.sqrt(n_local)) * np.sqrt(2 / np.pi)
    rel = np.concatenate(rel)
    print(f"steps with >= 2 drives: {ours.size}, drives per step: mean {n_local.mean():.1f}")
    print(
        f"mean |common error| per step: adjusted {ours.mean():.3f} m, per-step {local.mean():.3f} m, "
        f"expected local floor {floor:.3f} m; 95th pct adjusted {np.percentile(ours, 95):.3f} m, "
        f"per-step {np.percentile(local, 95):.3f} m"
    )
    print(
        f"relative (per-drive) error rms {np.sqrt(np.mean(rel**2)):.3f} m; "
        f"error / posterior std: rms {np.sqrt(np.mean(np.square(z))):.2f}"
    )
    if args.build:
        _build_and_evaluate(fleet, gt, args.seed)
    return 0


def _build_and_evaluate(fleet, gt, seed: int) -> None:
    """Whole maps with the "default" preset, with and without the adjustment, scored (Sec. VII)."""
    from hdmap_core.evaluation.evaluate import evaluate_map
    from hdmap_core.evaluation.summary import format_summary
    from hdmap_core.pipeline.driver import build_map

    sigma = float(np.hypot(fleet.config.bias_lateral_sigma_m, fleet.config.drift_sigma_m))
    base = config_from("default")
    for name, cfg in (("with adjustment", base), ("without adjustment", config_from(base, {"final_pass": None}))):
        t0 = time.perf_counter()
        res = build_map(fleet.drives, config=cfg, seed=seed)
        print(f"=== default preset {name}: build {time.perf_counter() - t0:.1f} s")
        print(format_summary(evaluate_map(res.map, gt, drives=fleet.drives, sigma_loc_m=sigma)))


if __name__ == "__main__":
    raise SystemExit(main())
