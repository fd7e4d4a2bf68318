#!/usr/bin/env python3
"""The local offset update (new drives solved against a fixed fleet) against the global re-solve.

Simulates a fleet, runs the pipeline's first pass once to collect every step's observations, solves
the global adjustment on the first N - k drives (their samples only), then adds the last k drives
one at a time with ``update_offsets`` (each new drive free, every other drive fixed: what the live
mapper does on arrival) and compares the result with the global adjustment of all N drives:

- map shift: per step, |mean over the step's drives of (local - global offset)|, what moves the
  fused lines of the map between the two models (mean, 95th percentile, max);
- the new drives' own offset difference (rms over their samples);
- both models' common error against the simulator's truth (as scripts/eval_adjustment_fleet.py);
- wall time of each local update against the global solve.

Usage (from the repository root):
    .venv/bin/python scripts/bench_adjustment_local.py --map motorway_ramps --drives 30 --new 5
BENCH_SMOKE=1 runs a small fleet (12 drives on 1.5 km) in a few seconds.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src" / "hdmap_core"))

from hdmap_core.pipeline.adjustment import adjust_offsets  # noqa: E402
from hdmap_core.pipeline.adjustment_local import update_offsets  # noqa: E402
from hdmap_core.pipeline.driver import map_stretches  # noqa: E402
from hdmap_core.pipeline.overrides import config_from  # noqa: E402
from hdmap_core.simulation.fleet import SimConfig, load_map, simulate_fleet  # noqa: E402


def _without(obs, drop: set[str]):
    """The observations with the samples of ``drop`` removed (as if those drives had not come)."""
    out = []
    for o in obs:
        ids = np.asarray(o.drive_ids)
        keep = ~np.isin(ids, list(drop))
        if not keep.any():
            continue
        off = np.asarray(o.offsets_m)
        out.append(
            replace(
                o,
                drive_ids=tuple(ids[keep].tolist()),
                drive_s_m=np.asarray(o.drive_s_m)[keep],
                lateral_m=np.asarray(o.lateral_m)[keep],
                types=np.asarray(o.types)[keep],
                cluster=np.asarray(o.cluster)[keep],
                offsets_m=off[keep] if off.size == ids.size else off,
            )
        )
    return out


def _step_points(obs):
    """Per step with >= 2 drives: (drive ids, their travelled distance at the step)."""
    pts = []
    for o in obs:
        ids, first = np.unique(np.asarray(o.drive_ids), return_index=True)
        if ids.size >= 2:
            pts.append((ids, np.asarray(o.drive_s_m, dtype=float)[first]))
    return pts


def _common(model, pts, truth=None):
    """Per step: mean over its drives of the model's offset (minus the truth when given)."""
    out = []
    for ids, s in pts:
        est = np.array([model.offset(d, np.array([x]))[0] for d, x in zip(ids, s)])
        if truth is not None:
            est = est - np.array([np.interp(x, *truth[d]) for d, x in zip(ids, s)])
        out.append(est.mean())
    return np.asarray(out)


def main() -> int:
    smoke = os.environ.get("BENCH_SMOKE") == "1"
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", default="motorway")
    ap.add_argument("--length-m", type=float, default=1500.0 if smoke else 4000.0)
    ap.add_argument("--drives", type=int, default=12 if smoke else 30)
    ap.add_argument("--new", type=int, default=2 if smoke else 5, help="drives added one at a time")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--free",
        choices=("new", "neighbours", "all"),
        default="new",
        help="free drives of each update: the new drive only, it and every drive sharing a step with it, "
        "or every drive (a warm-started global solve)",
    )
    args = ap.parse_args()

    gt = load_map(args.map, length_m=args.length_m)
    fleet = simulate_fleet(gt, config=SimConfig(n_drives=args.drives), seed=args.seed)
    cfg = config_from("default", {"final_pass": None})
    t0 = time.perf_counter()
    obs = map_stretches(fleet.drives, config=cfg, seed=args.seed, collect_observations=True).observations
    print(
        f"{args.map} {args.length_m:.0f} m, {args.drives} drives: first pass {time.perf_counter() - t0:.1f} s, "
        f"{len(obs)} steps"
    )
    acfg = replace(config_from("default").adjustment, compute_std=False)
    ids = [d.drive_id for d in fleet.drives]
    new = ids[-args.new :]

    t0 = time.perf_counter()
    glob = adjust_offsets(obs, config=acfg)
    t_glob = time.perf_counter() - t0
    model = adjust_offsets(_without(obs, set(new)), config=acfg)
    times = []
    for k, d in enumerate(new):
        seen = _without(obs, set(new[k + 1 :]))
        t0 = time.perf_counter()
        free = {d}
        if args.free == "all":
            free.update(x for o in seen for x in o.drive_ids)
        elif args.free == "neighbours":
            free.update(x for o in seen if d in o.drive_ids for x in o.drive_ids)
        model = update_offsets(seen, model=model, free=free, config=acfg)
        times.append(time.perf_counter() - t0)

    pts = _step_points(obs)
    signed = _common(model, pts) - _common(glob, pts)
    shift = np.abs(signed)
    diff_new = []
    for o in obs:
        for d, s in zip(o.drive_ids, np.asarray(o.drive_s_m, dtype=float)):
            if d in new:
                diff_new.append(model.offset(d, np.array([s]))[0] - glob.offset(d, np.array([s]))[0])
    truth = {}
    for drv in fleet.drives:
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(drv.xy, axis=0), axis=1))])
        truth[drv.drive_id] = (s, -np.asarray(fleet.truth[drv.drive_id]["lateral_error_m"]))
    err_local = np.abs(_common(model, pts, truth))
    err_glob = np.abs(_common(glob, pts, truth))
    print(
        f"global solve of {args.drives} drives: {t_glob:.2f} s; local update per new drive: "
        f"median {np.median(times):.2f} s, max {max(times):.2f} s ({len(new)} drives added one at a time)"
    )
    print(
        f"map shift local vs global (per step, mean over its drives): mean {shift.mean():.4f} m, "
        f"95th pct {np.percentile(shift, 95):.4f} m, max {shift.max():.4f} m over {shift.size} steps "
        f"(signed mean {signed.mean():+.4f} m: the part common to all steps, the gauge)"
    )
    print(f"new drives' offset, local - global: rms {np.sqrt(np.mean(np.square(diff_new))):.4f} m")
    print(
        f"common error against truth: local {err_local.mean():.4f} m, global {err_glob.mean():.4f} m "
        f"(95th pct {np.percentile(err_local, 95):.4f} / {np.percentile(err_glob, 95):.4f} m)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
