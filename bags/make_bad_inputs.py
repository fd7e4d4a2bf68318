"""Make the bad-input demo bags of this folder (see README.md).

    .venv/bin/python bags/make_bad_inputs.py [OUT_DIR]      # default: the folder of this script

Writes ``OUT_DIR/bad_inputs/`` (rosbag2 MCAP: 4 good drives, 11 malformed or undecodable
messages) and ``OUT_DIR/bad_inputs_truncated.mcap`` (the same bag's .mcap cut at 70 % of its size).
Deterministic: the good drives come from the simulator with a fixed seed.
"""

from __future__ import annotations

import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer

from hdmap_core.model import Detection, FeatureType
from hdmap_core.simulation.fleet import SimConfig, simulate_fleet
from hdmap_core.simulation.synthetic import synthetic_highway
from hdmap_ros.convert.messages import origin_to_msg
from hdmap_ros.io.bagio import DRIVE_TYPE, DRIVES_TOPIC, ORIGIN_TOPIC, ORIGIN_TYPE
from hdmap_ros.io.cdr import encode_drive
from hdmap_ros.io.msgdefs import default_typestore

SEED = 7
CONFIG = SimConfig(n_drives=4, snippet_length_min_m=150.0, snippet_length_max_m=250.0)
TRUNCATE_AT = 0.70


def _malformed(good: list) -> list[tuple[str, object]]:
    """(what, drive or raw bytes) for every bad-input class; ids say what is wrong."""
    a, b = good[0], good[1]

    def bad_xy(drive, i, value):
        xy = np.array(drive.xy, dtype=float)
        xy[i, 0] = value
        return xy

    det_inf = np.array(a.detections[0].points, dtype=float)
    det_inf[1, 1] = np.inf
    none = np.zeros(0)
    return [
        ("NaN in the trajectory", replace(a, drive_id="bad-nan-trajectory", xy=bad_xy(a, 5, np.nan))),
        (
            "inf in a detection",
            replace(
                a,
                drive_id="bad-inf-detection",
                detections=(Detection(a.detections[0].type, det_inf),) + a.detections[1:],
            ),
        ),
        (
            "a 1-point detection",
            replace(
                a, drive_id="bad-short-detection", detections=a.detections + (Detection(FeatureType.SOLID, a.xy[:1]),)
            ),
        ),
        (
            "no poses",
            replace(
                a,
                drive_id="bad-empty-trajectory",
                xy=np.zeros((0, 2)),
                yaw=none,
                stamps_ns=np.zeros(0, np.int64),
                detections=(),
            ),
        ),
        ("a single pose", replace(a, drive_id="bad-one-pose", xy=a.xy[:1], yaw=a.yaw[:1], stamps_ns=a.stamps_ns[:1])),
        (
            "detection type 7",
            replace(a, drive_id="bad-unknown-type", detections=a.detections + (Detection(7, a.xy[:5]),)),
        ),
        ("frame 'odom'", replace(a, drive_id="bad-wrong-frame", frame_id="odom")),
        (
            "NaN heading",
            replace(a, drive_id="bad-nan-heading", yaw=np.where(np.arange(len(a.yaw)) == 3, np.nan, a.yaw)),
        ),
        ("empty drive id", replace(a, drive_id="")),
        ("duplicate of a good drive's id", replace(b, vehicle_id="impostor")),
        ("bytes that are no Drive", b"\x00\x01\x00\x00this is not a CDR Drive message"),
    ]


def main(argv: list[str]) -> int:
    out_dir = Path(argv[1]) if len(argv) > 1 else Path(__file__).resolve().parent
    fleet = simulate_fleet(synthetic_highway("motorway", seed=0), config=CONFIG, seed=SEED)
    good = fleet.drives
    bad = _malformed(good)
    bag = out_dir / "bad_inputs"
    if bag.exists():
        shutil.rmtree(bag)
    store = default_typestore()
    t0 = min(d.start_ns for d in good)
    # good and bad interleaved; log times 1 s apart keep this order when read back
    order = [good[0], *[x for _, x in bad[:5]], good[1], *[x for _, x in bad[5:]], good[2], good[3]]
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        oc = writer.add_connection(ORIGIN_TOPIC, ORIGIN_TYPE, typestore=store)
        writer.write(oc, t0, store.serialize_cdr(origin_to_msg(fleet.origin, stamp_ns=t0), ORIGIN_TYPE))
        dc = writer.add_connection(DRIVES_TOPIC, DRIVE_TYPE, typestore=store)
        for i, item in enumerate(order):
            raw = item if isinstance(item, bytes) else encode_drive(item)
            writer.write(dc, t0 + (i + 1) * 1_000_000_000, raw)
    (mcap,) = bag.glob("*.mcap")
    data = mcap.read_bytes()
    (out_dir / "bad_inputs_truncated.mcap").write_bytes(data[: int(len(data) * TRUNCATE_AT)])
    print(f"wrote {bag} ({len(good)} good drives, {len(bad)} bad messages) and bad_inputs_truncated.mcap")
    for what, item in bad:
        print(f"  {item.drive_id if not isinstance(item, bytes) else '(undecodable)'!s:24s} {what}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
