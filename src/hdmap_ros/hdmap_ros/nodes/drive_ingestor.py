"""drive_ingestor: /fleet/drives -> validated, cleaned, de-duplicated drives for the mapper.

Subscribes ``/fleet/drives`` (hdmap_msgs/Drive). Every drive is validated (the bad-input classes of
``hdmap_core.model.validate_drive``: NaN/inf, too few points, empty trajectory, unknown type, wrong
frame) and physically plausible (``hdmap_core.plausibility``, default bounds), its detections
cleaned as in Sec. III (length filter, RDP; ``pipeline.preprocess.clean_drive``),
duplicates dropped by drive id, and the rest published on ``/hdmap/drives_accepted``. Every
rejection is logged with the drive id and the reason and counted on ``/diagnostics``; the id of a
drive refused as invalid goes out on ``/hdmap/drives_rejected`` (std_msgs/String; the mapper counts
them in the map's status).
"""

from __future__ import annotations

import time

from rclpy.node import Node
from std_msgs.msg import String

from hdmap_core.errors import HdmapError, InvalidDriveError
from hdmap_core.pipeline.preprocess import PreprocessConfig, clean_drive
from hdmap_core.plausibility import check_plausible
from hdmap_ros.convert.messages import rclpy_types
from hdmap_ros.nodes import qos
from hdmap_ros.nodes._common import HealthMixin, declare, drive_from_wire, drive_to_wire, run_node

__all__ = ["DriveIngestor", "main"]

DRIVES_TOPIC = "fleet/drives"  # relative: a namespace (-r __ns:=/ns2) moves every topic
ACCEPTED_TOPIC = "hdmap/drives_accepted"
REJECTED_TOPIC = "hdmap/drives_rejected"


class DriveIngestor(HealthMixin, Node):
    """Validates and cleans incoming drives; see the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__("drive_ingestor", **kwargs)
        self.expected_frame = declare(
            self,
            "expected_frame",
            "map",
            "Frame every drive must be in ('' = any).",
            dynamic="expected_frame",
        )
        self.min_length_m = declare(
            self,
            "min_detection_length_m",
            3.0,
            "Detection polylines shorter than this are dropped [m] (paper: 3).",
            lo=0.0,
            hi=100.0,
            dynamic="min_length_m",
        )
        self.rdp_epsilon_m = declare(
            self,
            "rdp_epsilon_m",
            0.05,
            "Ramer-Douglas-Peucker tolerance for detections [m].",
            lo=0.001,
            hi=2.0,
            dynamic="rdp_epsilon_m",
        )
        depth = declare(
            self,
            "accepted_history_depth",
            100,
            "Accepted drives kept (TRANSIENT_LOCAL) for a mapper that restarts.",
            lo=1,
            hi=100000,
        )
        self.clean_config = PreprocessConfig(min_length_m=self.min_length_m, rdp_epsilon_m=self.rdp_epsilon_m)
        self._init_health("drive_ingestor")
        self._types = rclpy_types()
        self._seen: set[str] = set()
        self.published = 0
        self.received = 0
        self._pub = self.create_publisher(self._types.Drive, ACCEPTED_TOPIC, qos.replay(depth))
        self._rej_pub = self.create_publisher(String, REJECTED_TOPIC, qos.ACKS)
        # raw: CDR bytes in and out (``drive_from_wire``), no Python object per point
        self._sub = self.create_subscription(self._types.Drive, DRIVES_TOPIC, self.on_drive, qos.DRIVES, raw=True)

    def on_drive(self, msg) -> None:
        """Validate, de-duplicate, clean and forward one drive; never raises on bad input."""
        try:
            self._handle(msg)
        finally:
            self.received += 1  # counted once handled: "received" means "forwarded or refused"

    def _handle(self, msg) -> None:
        did = str(getattr(msg, "drive_id", ""))
        try:
            drive = check_plausible(drive_from_wire(msg, self._types.Drive, expected_frame=self.expected_frame or None))
        except InvalidDriveError as err:
            did = did or err.drive_id
            self.health.reject(err.reason, f"{did!r} {err.detail}")
            self.get_logger().warning(f"drive {did!r} rejected: {err.reason} ({err.detail})")
            self._rej_pub.publish(String(data=did))
            return
        except HdmapError as err:
            self.health.reject("invalid_message", f"{did!r} {err}")
            self.get_logger().warning(f"drive {did!r} rejected: invalid_message ({err})")
            self._rej_pub.publish(String(data=did))
            return
        if drive.drive_id in self._seen:
            self.health.duplicate()
            self.health.reject("duplicate_drive_id", drive.drive_id)
            self.get_logger().warning(f"drive {did!r} rejected: duplicate_drive_id")
            return
        self._seen.add(drive.drive_id)
        drive = clean_drive(drive, config=self.clean_config)
        self._pub.publish(drive_to_wire(drive))
        self.published += 1
        self.health.accept()
        self.health.updated(time.time_ns())


def main(args=None) -> None:
    run_node(DriveIngestor, args)


if __name__ == "__main__":
    main()
