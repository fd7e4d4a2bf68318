#!/usr/bin/env python3
"""Benchmark of the live suite against the offline build, seen as a subscriber sees it.

1. simulates a fleet (``hdmap simulate``; default the 30-drive ``motorway_ramps`` fleet, seed 1)
   and times ``hdmap bag2map`` on it (wall time of the command);
2. runs ``hdmap run BAG --rate R -o LIVE`` in a subprocess while a probe node in this process
   (its own rclpy context, the same ROS_DOMAIN_ID) records, with receive times, every drive ack
   (``/hdmap/drive_acks``), every map version (``/hdmap/map``) and status (``/hdmap/status``);
3. prints: the settle time of ``hdmap run`` against the ``bag2map`` wall time, and the CPU time of
   the two (every process, user + system: less bent by other load on the machine than wall
   times); the settled live map and the offline map scored against the ground truth
   (``evaluate_map``, as ``hdmap evaluate``);
   the moment ``drive_ids`` first holds every drive and that map's score; and the latency from a
   drive's acknowledgement to the first map listing it.

4. with ``--rates R1,R2,...``: one live run per rate (``--rate`` is then ignored) and a table of
   the offered drive rate (drives per hour of wall time while the bag plays), the backlog slope
   while it plays (least-squares slope of ``MapStatus.tiles_pending`` over time [tiles/min]; > 0:
   the suite falls behind), the time from the last ack to the settled (last) map, and the ack -> listed latency.
   The highest offered rate whose slope stays <= 0 is what the suite absorbs on this machine.

5. with ``--latency``: the arrival-to-listed latency of single drives on a settled map (issue 29:
   <= 1 s for a 10 km drive on mapped road, <= 2 s per km on new road). The fleet (default: 16
   drives of 9.5-10 km on 10.5 km of ``motorway``, seed 1; or ``--fleet``) without its longest
   drive is played by ``hdmap run --keep-alive`` until settled; then the probe publishes that
   drive (on mapped road: the fast path) and, once settled again, the same drive moved 40 km away
   (new road); each once the machine is at rest (the map settled and the stitcher's following of
   road changes on it done). Per drive: publish -> ack -> first map listing it, and for the mapped-road drive
   that map scored against the ground truth beside ``bag2map`` of the whole fleet (the batch map
   of the same drives).

``BENCH_SMOKE=1``: a small fleet (8 drives on 2 km of ``motorway_ramps``), one run: a check
that the benchmark works, in about a minute.

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
from typing import Any

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
    ap.add_argument(
        "--fleet", default="", help="an existing fleet bag (its ground truth BAG.gt.json) instead of simulating one"
    )
    ap.add_argument(
        "--params-file", default="", help="node parameters (YAML) for hdmap run, e.g. the mapper's region_max_drives"
    )
    ap.add_argument("--rates", default="", help="comma-separated replay rates: one live run each, a backlog table")
    ap.add_argument("--latency", action="store_true", help="latency of one drive on mapped and on new road (5.)")
    args = ap.parse_args()
    if os.environ.get("BENCH_SMOKE") == "1":
        args.drives, args.length_m = 8, 2000.0
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if "ROS_DOMAIN_ID" not in os.environ:
        print("set ROS_DOMAIN_ID (your own domain) first", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="hdmap-bench-live-"))
    out.mkdir(parents=True, exist_ok=True)
    fleet = Path(args.fleet) if args.fleet else out / "fleet"
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
    if args.latency and not args.fleet:
        if "--drives" not in sys.argv:
            sim[sim.index("--drives") + 1] = "16"
        if args.map == "motorway_ramps" and "--map" not in sys.argv:
            sim[sim.index("--map") + 1] = "motorway"
        args.length_m = args.length_m or 10500.0
        sim += ["--set", "snippet_length_min_m=9500", "--set", "snippet_length_max_m=10000"]
    if args.length_m:
        sim += ["--length-m", str(args.length_m)]
    if not args.fleet:
        subprocess.run(sim, check=True, stdout=subprocess.DEVNULL)

    t0, c0 = time.monotonic(), _children_cpu()
    subprocess.run(
        [HDMAP, "bag2map", str(fleet), "-o", str(out / "offline"), "--overwrite", "--no-progress"],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    offline_s = time.monotonic() - t0
    args.offline_cpu = _children_cpu() - c0

    if args.latency:
        return _latency(args, fleet, out, offline_s)
    if args.rates:
        rows = []
        for rate in (float(r) for r in args.rates.split(",") if r.strip()):
            args.rate = rate
            probe = _Probe()
            try:
                live_s, settle_line = _run_live(args, fleet, out / f"live_{rate:g}", probe)
            finally:
                probe.close()
            rows.append(_backlog_row(args, fleet, rate, live_s, settle_line, probe))
            print(f"rate {rate:g} done", file=sys.stderr)
        print(
            f"fleet: {args.fleet or args.map} ({args.drives} drives, seed {args.seed} if simulated); "
            f"offline bag2map wall time {offline_s:.1f} s"
        )
        print(
            "rate  | drives/h offered | bag played [s] | backlog slope [tiles/min] | max backlog | "
            "settled map after bag [s] | latency median / p90 / max [s] (n)"
        )
        for r in rows:
            print(r)
        return 0
    probe = _Probe()
    try:
        live_s, settle_line = _run_live(args, fleet, out / "live", probe)
    finally:
        probe.close()
    _report(args, fleet, out, offline_s, live_s, settle_line, probe)
    return 0


def _children_cpu() -> float:
    """CPU time (user + system) of every child process waited for so far, with theirs [s]."""
    import resource

    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _latencies(probe: _Probe) -> list[float]:
    """Per drive whose ack the probe saw: time from the ack to the first map listing it [s]."""
    lat = []
    for did, t_ack in probe.acks.items():
        t_in = next((t for t, msg in probe.maps if did in set(msg.drive_ids)), None)
        if t_in is not None:
            lat.append(t_in - t_ack)
    return lat


def _backlog_row(args, fleet: Path, rate: float, live_s: float, settle_line: str, probe: _Probe) -> str:
    """One line of the rate table (see the module docstring, 4.)."""
    import numpy as np

    if not probe.acks:
        return f"{rate:5g} | no ack seen"
    t_first, t_last = min(probe.acks.values()), max(probe.acks.values())
    played = max(t_last - t_first, 1e-9)
    offered = (len(probe.acks) - 1) / played * 3600.0 if len(probe.acks) > 1 else float("nan")
    pts = np.array([(t, st.tiles_pending) for t, st in probe.status if t_first <= t <= t_last], dtype=np.float64)
    slope = float(np.polyfit(pts[:, 0], pts[:, 1], 1)[0] * 60.0) if len(pts) >= 3 else float("nan")
    peak = int(max((st.tiles_pending for _, st in probe.status), default=0))
    _ = settle_line
    settled_at = probe.maps[-1][0] if probe.maps else probe.t0 + live_s  # the settled map is the last one
    lat = np.array(_latencies(probe))
    lat_s = (
        f"{np.median(lat):.1f} / {np.percentile(lat, 90):.1f} / {lat.max():.1f} ({lat.size})"
        if lat.size
        else "none listed"
    )
    return (
        f"{rate:5g} | {offered:16.0f} | {played:14.1f} | {slope:25.1f} | {peak:11d} | "
        f"{settled_at - t_last:25.1f} | {lat_s}"
    )


class _Probe:
    """A subscriber of the live suite's topics, recording receive times (monotonic)."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from std_msgs.msg import String

        from hdmap_ros.convert.messages import rclpy_status_class, rclpy_types
        from hdmap_ros.nodes import qos

        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
        self.node = rclpy.create_node("bench_live_probe", context=self.context)
        self.acks: dict[str, float] = {}
        self.maps: list[tuple[float, Any]] = []
        self.status: list[tuple[float, Any]] = []
        self.t0 = time.monotonic()  # when the suite was started (set by _run_live)
        self.node.create_subscription(String, "/hdmap/drive_acks", self._ack, qos.ACKS)
        self.node.create_subscription(
            rclpy_types().Map, "/hdmap/map", lambda m: self.maps.append((time.monotonic(), m)), qos.LATCHED
        )
        self.node.create_subscription(
            rclpy_status_class(), "/hdmap/status", lambda m: self.status.append((time.monotonic(), m)), qos.LATCHED
        )
        self.diags: dict[str, dict[str, str]] = {}  # node -> its latest /diagnostics key-values
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._diag, qos.DIAGNOSTICS)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _diag(self, arr) -> None:
        for st in arr.status:
            self.diags[st.name.removeprefix("hdmap: ")] = {kv.key: kv.value for kv in st.values}

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
    probe.t0, c0 = time.monotonic(), _children_cpu()
    cmd = [HDMAP, "run", str(fleet), "--rate", str(args.rate), "-o", str(live), "--timeout", str(args.timeout)]
    if args.params_file:
        cmd += ["--params-file", args.params_file]
    proc = subprocess.run(
        cmd,
        capture_output=True,
        text=True,
    )
    live_s = time.monotonic() - probe.t0
    args.live_cpu = _children_cpu() - c0
    if proc.returncode != 0:
        print(proc.stderr[-3000:], file=sys.stderr)
        raise SystemExit(f"hdmap run failed ({proc.returncode})")
    settle = [ln for ln in proc.stderr.splitlines() if "settled:" in ln]
    time.sleep(0.5)
    return live_s, settle[-1] if settle else ""


def _on_mapped_road(drives):
    """The longest drive that drove no new road against the others (no tile with ``NEW_ROAD_CELLS``
    road cells they did not pass): on mapped road once they are mapped."""
    from hdmap_core.live.scheduler import NEW_ROAD_CELLS
    from hdmap_core.live.tiles import TileConfig, road_cells

    tc = TileConfig()
    cells = {d.drive_id: road_cells(d, config=tc) for d in drives}
    for d in sorted(drives, key=lambda d: -d.length_m):
        seen: dict = {}
        for o in drives:
            if o is not d:
                for k, c in cells[o.drive_id].items():
                    seen.setdefault(k, set()).update(c)
        if all(len(set(c) - seen.get(k, set())) < NEW_ROAD_CELLS for k, c in cells[d.drive_id].items()):
            return d
    raise SystemExit("no drive of the fleet lies on road the others drove")


def _latency(args, fleet: Path, out: Path, offline_s: float) -> int:
    """Latency of single drives on a settled map (module docstring, 5.)."""
    import signal
    from dataclasses import replace

    import numpy as np

    from hdmap_core.evaluation.evaluate import evaluate_map
    from hdmap_core.groundtruth import load_ground_truth
    from hdmap_core.model import Detection
    from hdmap_ros.convert.messages import drive_to_msg, msg_to_map, rclpy_types
    from hdmap_ros.io.bagio import read_fleet_bag, read_map_bag, write_fleet_bag
    from hdmap_ros.nodes import qos

    bag = read_fleet_bag(fleet)
    drives = sorted(bag.drives, key=lambda d: d.drive_id)
    mapped = _on_mapped_road(drives)
    base = [d for d in drives if d is not mapped]
    write_fleet_bag(out / "base", base, bag.origin, overwrite=True)
    far = np.array([40000.0, 0.0])
    new_road = replace(
        mapped,
        drive_id=mapped.drive_id + "_far",
        xy=np.asarray(mapped.xy) + far,
        detections=tuple(Detection(d.type, np.asarray(d.points) + far) for d in mapped.detections),
    )
    gt = load_ground_truth(str(fleet) + ".gt.json")
    batch = evaluate_map(read_map_bag(out / "offline"), gt)
    probe = _Probe()
    pub = probe.node.create_publisher(rclpy_types().Drive, "/fleet/drives", qos.DRIVES)
    cmd = [HDMAP, "run", str(out / "base"), "--rate", "0", "--keep-alive", "--state", str(out / "state")]
    if args.params_file:
        cmd += ["--params-file", args.params_file]
    import shutil

    shutil.rmtree(out / "state", ignore_errors=True)
    time.sleep(1.0)
    probe.t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=open(out / "run.log", "w"))  # noqa: SIM115

    def wait(cond, timeout: float, what: str) -> float:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if cond():
                return time.monotonic()
            if proc.poll() is not None:
                raise SystemExit(f"hdmap run ended ({proc.returncode}) waiting for {what}; see {out / 'run.log'}")
            time.sleep(0.01)
        raise SystemExit(f"timeout waiting for {what}")

    def settled(n: int) -> bool:
        return bool(probe.status) and probe.status[-1][1].settled and probe.status[-1][1].drives_integrated == n

    def followed(n: int) -> bool:
        """Settled and the stitcher followed the road changes on that map (the machine at rest)."""
        kv = probe.diags.get("map_stitcher", {})
        version = probe.status[-1][1].map_version if probe.status else -1
        return settled(n) and kv.get("changes_followed") == "True" and kv.get("map_version") == str(version)

    rows = []
    try:
        t_base = wait(lambda: settled(len(base)), args.timeout, "the base fleet settled")
        print(f"base fleet ({len(base)} drives) settled after {t_base - probe.t0:.1f} s", file=sys.stderr)
        wait(lambda: pub.get_subscription_count() > 0, 30, "the ingestor")
        n = len(base)
        for label, drive in (("mapped road", mapped), ("new road", new_road)):
            t_rest = wait(lambda n=n: followed(n), args.timeout, "the road changes followed")
            print(f"{label}: the road changes followed {t_rest - probe.t0:.1f} s after the start", file=sys.stderr)
            n_maps = len(probe.maps)
            msg = drive_to_msg(drive, types=rclpy_types())  # made first: not the suite's time (0.3 s for 10 km)
            t_pub = time.monotonic()
            pub.publish(msg)
            did = drive.drive_id
            t_in = wait(lambda did=did: any(did in set(m.drive_ids) for _, m in probe.maps[n_maps:]), args.timeout, did)
            msg = next(m for _, m in probe.maps[n_maps:] if did in set(m.drive_ids))
            t_ack = probe.acks.get(did, float("nan"))
            wall = time.time() - time.monotonic()  # the nodes' log stamps are wall clock
            print(f"{did}: ack at {t_ack + wall:.3f}, listed at {t_in + wall:.3f} (epoch s)", file=sys.stderr)
            n += 1
            t_set = wait(lambda n=n: settled(n), args.timeout, "settled again")
            rows.append((label, drive.length_m / 1000.0, t_ack - t_pub, t_in - t_ack, t_set - t_ack, msg))
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
        probe.close()
    print(f"fleet: {args.fleet or args.map} ({len(drives)} drives); bag2map of the whole fleet {offline_s:.1f} s wall")
    print(
        f"batch map (bag2map, every drive): mean error {batch.overall.mean_m:.4f} m, "
        f"coverage {100 * batch.overall.coverage:.2f} %"
    )
    print(
        "drive | km | publish -> ack [s] | ack -> listed [s] | per km [s] | ack -> settled again [s] | "
        "listed map vs truth"
    )
    for label, km, pa, al, ast, msg in rows:
        hd = msg_to_map(msg)
        score = ""
        if label == "mapped road":
            rep = evaluate_map(hd, gt)
            score = (
                f"mean {rep.overall.mean_m:.4f} m ({rep.overall.mean_m - batch.overall.mean_m:+.4f}), coverage "
                f"{100 * rep.overall.coverage:.2f} % ({100 * (rep.overall.coverage - batch.overall.coverage):+.2f} pt)"
            )
        print(f"{label} | {km:.2f} | {pa:.2f} | {al:.2f} | {al / km:.2f} | {ast:.2f} | {score}")
    return 0


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

    name = args.fleet or f"{args.map} (seed {args.seed})"
    print(f"fleet: {name}, {len(drives)} drives, hdmap run --rate {args.rate:g}")
    print(f"offline bag2map wall time                 {offline_s:7.1f} s")
    print(
        f"hdmap run: settled after                  {run_settle:7.1f} s  (suite up to settled; "
        f"process wall time {live_s:.1f} s)  = {run_settle / offline_s:.1f} x bag2map"
    )
    print(
        f"CPU time (user + system, every process): bag2map {args.offline_cpu:.1f} s, hdmap run {args.live_cpu:.1f} s"
        f" = {args.live_cpu / args.offline_cpu:.1f} x (holds on a loaded machine; wall times do not)"
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
    lat = _latencies(probe)
    if lat:
        a = np.array(lat)
        print(
            f"ack -> listed in drive_ids latency over {len(a)} drives (acks the probe saw): "
            f"min {a.min():.1f} s, p10 {np.percentile(a, 10):.1f} s, median {np.median(a):.1f} s, "
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
