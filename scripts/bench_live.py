#!/usr/bin/env python3
"""Benchmark of the live suite against the offline build, seen as a subscriber sees it.

1. simulates a fleet (``hdmap simulate``; default the 30-drive ``motorway_ramps`` fleet, seed 1)
   and times ``hdmap bag2map`` on it (wall time of the command);
2. runs ``hdmap run BAG --rate R -o LIVE`` in a subprocess while a probe node in this process
   (its own rclpy context, the same ROS_DOMAIN_ID) records, with receive times, every drive ack
   (``/hdmap/drive_acks``), every map version (``/hdmap/map``) and status (``/hdmap/status``);
3. prints: the settle time of ``hdmap run`` against the ``bag2map`` wall time; the settled live
   map and the offline map scored against the ground truth (``evaluate_map``, as ``hdmap evaluate``);
   the moment ``drive_ids`` first holds every drive and that map's score; and the latency from a
   drive's acknowledgement to the first map listing it.

Prints figures only; no assertions. Keep discovery local and the domain your own:

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_DOMAIN_ID=63 .venv/bin/python scripts/bench_live.py
    ... scripts/bench_live.py --map motorway_ramps --drives 10 --length-m 1500   # a small run
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HDMAP = str(ROOT / ".venv" / "bin" / "hdmap")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", default="motorway_ramps")
    ap.add_argument("--drives", type=int, default=30)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--length-m", type=float, default=None, help="length of a synthetic highway [m]")
    ap.add_argument("--rate", type=float, default=0.0, help="hdmap run --rate (0: as fast as possible)")
    ap.add_argument("--out", default=None, help="keep the bags here (default: a temporary folder)")
    ap.add_argument("--timeout", type=float, default=900.0)
    args = ap.parse_args()
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if "ROS_DOMAIN_ID" not in os.environ:
        print("set ROS_DOMAIN_ID (your own domain) first", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="hdmap-bench-live-"))
    out.mkdir(parents=True, exist_ok=True)
    fleet = out / "fleet"
    sim = [
        HDMAP,
        "simulate",
        "--map",
        args.map,
        "--drives",
        str(args.drives),
        "--seed",
        str(args.seed),
        "-o",
        str(fleet),
        "--overwrite",
    ]
    if args.length_m:
        sim += ["--length-m", str(args.length_m)]
    subprocess.run(sim, check=True, stdout=subprocess.DEVNULL)

    t0 = time.monotonic()
    subprocess.run(
        [HDMAP, "bag2map", str(fleet), "-o", str(out / "offline"), "--overwrite", "--no-progress"],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    offline_s = time.monotonic() - t0

    probe = _Probe()
    try:
        live_s, settle_line = _run_live(args, fleet, out / "live", probe)
    finally:
        probe.close()
    _report(args, fleet, out, offline_s, live_s, settle_line, probe)
    return 0


class _Probe:
    """A subscriber of the live suite's topics, recording receive times (monotonic)."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from std_msgs.msg import String

        from hdmap_ros.convert.messages import rclpy_status_class, rclpy_types
        from hdmap_ros.nodes import qos

        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
        self.node = rclpy.create_node("bench_live_probe", context=self.context)
        self.acks: dict[str, float] = {}
        self.maps: list[tuple[float, object]] = []
        self.status: list[tuple[float, object]] = []
        self.t0 = time.monotonic()  # when the suite was started (set by _run_live)
        self.node.create_subscription(String, "/hdmap/drive_acks", self._ack, qos.ACKS)
        self.node.create_subscription(
            rclpy_types().Map, "/hdmap/map", lambda m: self.maps.append((time.monotonic(), m)), qos.LATCHED
        )
        self.node.create_subscription(
            rclpy_status_class(), "/hdmap/status", lambda m: self.status.append((time.monotonic(), m)), qos.LATCHED
        )
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _ack(self, msg) -> None:
        self.acks.setdefault(str(msg.data), time.monotonic())

    def _spin(self) -> None:
        while not self._stop and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        import rclpy

        self._stop = True
        self._thread.join(timeout=5)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def _run_live(args, fleet: Path, live: Path, probe: _Probe) -> tuple[float, str]:
    time.sleep(1.0)  # the probe discovered before the suite starts
    probe.t0 = time.monotonic()
    proc = subprocess.run(
        [HDMAP, "run", str(fleet), "--rate", str(args.rate), "-o", str(live), "--timeout", str(args.timeout)],
        capture_output=True,
        text=True,
    )
    live_s = time.monotonic() - probe.t0
    if proc.returncode != 0:
        print(proc.stderr[-3000:], file=sys.stderr)
        raise SystemExit(f"hdmap run failed ({proc.returncode})")
    settle = [ln for ln in proc.stderr.splitlines() if "settled:" in ln]
    time.sleep(0.5)
    return live_s, settle[-1] if settle else ""


def _report(args, fleet: Path, out: Path, offline_s: float, live_s: float, settle_line: str, probe: _Probe) -> None:
    import numpy as np

    from hdmap_core.evaluation.evaluate import evaluate_map
    from hdmap_core.groundtruth import load_ground_truth
    from hdmap_ros.convert.messages import msg_to_map
    from hdmap_ros.io.bagio import read_fleet_bag, read_map_bag

    gt = load_ground_truth(str(fleet) + ".gt.json")
    drives = {d.drive_id for d in read_fleet_bag(fleet).drives}
    offline = evaluate_map(read_map_bag(out / "offline"), gt)
    settled = evaluate_map(read_map_bag(out / "live"), gt)
    m = re.search(r"\[\s*([\d.]+) s\] settled", settle_line)
    run_settle = float(m.group(1)) if m else float("nan")
    t0 = probe.t0

    print(f"fleet: {args.map}, {len(drives)} drives (seed {args.seed}), hdmap run --rate {args.rate:g}")
    print(f"offline bag2map wall time                 {offline_s:7.1f} s")
    print(
        f"hdmap run: settled after                  {run_settle:7.1f} s  (suite up to settled; "
        f"process wall time {live_s:.1f} s)  = {run_settle / offline_s:.1f} x bag2map"
    )
    print(
        f"settled live map: mean error {settled.overall.mean_m:.3f} m, coverage {100 * settled.overall.coverage:.1f} %"
        f"  | offline: {offline.overall.mean_m:.3f} m, {100 * offline.overall.coverage:.1f} %"
    )

    first_all = next(((t, msg) for t, msg in probe.maps if drives <= set(msg.drive_ids)), None)
    if first_all is None:
        print("no map version listed every drive")
    else:
        t, msg = first_all
        hd = msg_to_map(msg)
        rep = evaluate_map(hd, gt)
        print(
            f"drive_ids first held all {len(drives)} drives at {t - t0:6.1f} s (map version {hd.version}): "
            f"mean error {rep.overall.mean_m:.3f} m, coverage {100 * rep.overall.coverage:.1f} %"
        )
    # coverage while the fleet arrives: the map at the moment half of the drives were acknowledged
    if probe.acks:
        t_acks = sorted(probe.acks.values())
        print(f"drives acknowledged from {t_acks[0] - t0:.1f} s to {t_acks[-1] - t0:.1f} s")
    lat = []
    for did, t_ack in probe.acks.items():
        t_in = next((t for t, msg in probe.maps if did in set(msg.drive_ids)), None)
        if t_in is not None:
            lat.append(t_in - t_ack)
    if lat:
        a = np.array(lat)
        print(
            f"ack -> listed in drive_ids latency over {len(a)} drives (acks the probe saw): "
            f"median {np.median(a):.1f} s, "
            f"p90 {np.percentile(a, 90):.1f} s, max {a.max():.1f} s"
        )
    if probe.maps:  # coverage while the fleet is mapped: the latest map at quarters of the run
        end = probe.maps[-1][0]
        row = []
        for q in (0.25, 0.5, 0.75):
            at = t0 + q * (end - t0)
            seen = [(t, msg) for t, msg in probe.maps if t <= at]
            if seen:
                rep = evaluate_map(msg_to_map(seen[-1][1]), gt)
                row.append(f"{at - t0:.0f} s: {100 * rep.overall.coverage:.1f} % ({rep.overall.mean_m:.3f} m)")
        print(
            "coverage (mean error) of the latest map at a quarter, half, three quarters of the run: " + ", ".join(row)
        )
    versions = [(t - t0, len(msg.drive_ids)) for t, msg in probe.maps]
    if versions:
        print("map versions (s, drives listed): " + ", ".join(f"{t:.0f}:{n}" for t, n in versions))
    if probe.status:
        st = probe.status[-1][1]
        print(
            f"last status: map version {st.map_version}, received {st.drives_received}, integrated "
            f"{st.drives_integrated}, rejected {st.drives_rejected}, pending tiles {st.tiles_pending}, "
            f"settled {st.settled}"
        )


if __name__ == "__main__":
    sys.exit(main())
