"""bag_player: replays a fleet bag onto its topics (rosbag2 is not on wheel installs).

Reads a rosbag2 directory or bare ``.mcap`` file (``hdmap_ros.io.bagio.iter_bag``) and publishes the
raw CDR bytes of ``/fleet/drives`` (and ``/fleet/origin``, latched) on publishers of the recorded
type, at the bag's log times scaled by ``rate`` (0 = as fast as possible), starting
``start_offset_s`` into the bag, optionally in a loop. On stock Jazzy ``ros2 bag play`` does the same.

A drive message no hdmap_msgs subscriber could read is not sent but counted as skipped with its
reason (``skipped``; warnings in the log and on /diagnostics): bytes that do not deserialize
(``undecodable``), or a message recorded with another Drive definition that does not convert
(``definition_mismatch``); one with another definition that converts is sent re-encoded. A
damaged chunk of the bag is skipped with a warning and the rest played. ``played`` counts every
drive message taken from the bag (sent or skipped).
"""

from __future__ import annotations

import importlib
import time
from collections import Counter
from collections.abc import Iterator

from rclpy.duration import Duration
from rclpy.node import Node

from hdmap_core.errors import HdmapError, InvalidDriveError
from hdmap_ros.convert.messages import drive_to_msg, rclpy_types
from hdmap_ros.io.bagio import (
    DRIVES_TOPIC,
    ORIGIN_TOPIC,
    ORIGIN_TYPE,
    BagMessage,
    Rejection,
    drive_of_message,
    has_contract_definition,
    iter_bag,
)
from hdmap_ros.io.cdr import decode_drive
from hdmap_ros.nodes import qos
from hdmap_ros.nodes._common import HealthMixin, declare, run_node

__all__ = ["BagPlayer", "main", "message_class"]


def message_class(type_name: str):
    """``"pkg/msg/Name"`` -> the rclpy message class."""
    pkg, _, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def _reads_vectorised(data: bytes) -> bool:
    """The bytes read as a Drive in the common layout (``io.cdr.decode_drive``, as the ingestor
    and the mapper read them): checked without a Python object per pose and point, which
    ``deserialize_message`` made (2 s of CPU for 8 drives of the 30-drive ramps fleet)."""
    try:
        return decode_drive(data) is not None
    except InvalidDriveError:  # decodes; its content is the ingestor's to judge
        return True


class BagPlayer(HealthMixin, Node):
    """Replays a bag; ``done`` becomes True at its end (never when looping)."""

    def __init__(self, **kwargs) -> None:
        super().__init__("bag_player", **kwargs)
        self.bag = declare(self, "bag", "", "The fleet bag to replay (rosbag2 directory or .mcap file).")
        self.rate = declare(
            self,
            "rate",
            1.0,
            "Replay speed factor; 0 = as fast as possible.",
            lo=0.0,
            hi=10000.0,
            dynamic="rate",
        )
        self.loop = declare(self, "loop", False, "Start again at the end.", dynamic="loop")
        self.start_offset_s = declare(self, "start_offset_s", 0.0, "Skip this much of the bag [s].", lo=0.0, hi=1e7)
        self.wait_for_subscribers_s = declare(
            self,
            "wait_for_subscribers_s",
            5.0,
            "Wait up to this long for a /fleet/drives subscriber [s].",
            lo=0.0,
            hi=600.0,
        )
        self.exit_when_done = declare(self, "exit_when_done", True, "Standalone: exit when the bag is done.")
        self.linger_s = declare(
            self,
            "linger_s",
            2.0,
            "Standalone: stay this long after the bag is done (and until every reader acknowledged), so "
            "readers that match late still get the latched origin [s].",
            lo=0.0,
            hi=3600.0,
        )
        self._init_health("bag_player")
        self.done = False
        self._done_at = 0.0
        self.published = 0
        self.skipped: Counter = Counter()  # drive messages not sent, by reason
        self._pubs: dict[str, object] = {}
        self._it: Iterator[BagMessage] | None = None
        self._next: BagMessage | None = None
        self._t0_bag: int | None = None
        self._t0_wall = 0.0
        self._started = time.monotonic()
        self._origin_sent = False
        if not self.bag:
            self.get_logger().error("parameter 'bag' is empty: nothing to play")
            self.done = True
            return
        # The origin's latched publisher exists from the start: readers in other processes match it
        # while the bag plays, not only after its first (and only) message.
        self._publisher_for(ORIGIN_TOPIC, ORIGIN_TYPE)
        self._timer = self.create_timer(0.01, self.tick)

    def _publisher(self, bm: BagMessage):
        return self._publisher_for(bm.topic, bm.msgtype)

    def _publisher_for(self, topic: str, msgtype: str):
        pub = self._pubs.get(topic)
        if pub is None:
            profile = qos.LATCHED if topic == ORIGIN_TOPIC else qos.DRIVES
            # the bag's absolute names become relative: a namespace (-r __ns:=/ns2) moves them
            pub = self.create_publisher(message_class(msgtype), topic.lstrip("/"), profile)
            self._pubs[topic] = pub
        return pub

    @property
    def played(self) -> int:
        """Drive messages taken from the bag: sent or skipped."""
        return self.published + sum(self.skipped.values())

    def _warn(self, text: str) -> None:
        self.health.error(text)
        self.get_logger().warning(text)

    def _skip(self, reason: str, detail: str) -> None:
        self.skipped[reason] += 1
        self.health.reject(reason, detail)
        self.get_logger().warning(f"drive message skipped: {reason} ({detail})")

    def _payload(self, bm: BagMessage) -> bytes | None:
        """The bytes to send for a drive message, or None when no subscriber could read it (counted)."""
        from rclpy.serialization import deserialize_message, serialize_message  # noqa: PLC0415

        if has_contract_definition(bm):
            if _reads_vectorised(bm.data):
                return bm.data  # raw CDR as recorded (invalid content is the ingestor's to judge)
            try:
                deserialize_message(bm.data, message_class(bm.msgtype))
            except Exception as err:  # noqa: BLE001 - rclpy raises plain exceptions of the C layer; named, counted
                self._skip("undecodable", f"log time {bm.log_time_ns}: {type(err).__name__}: {err}")
                return None
            return bm.data
        got = drive_of_message(bm, expected_frame=None)
        if isinstance(got, Rejection):
            self._skip(got.reason, f"log time {bm.log_time_ns}: {got.detail}")
            return None
        return serialize_message(drive_to_msg(got, types=rclpy_types()))

    def _restart(self) -> None:
        self._it = iter_bag(self.bag, topics=[DRIVES_TOPIC, ORIGIN_TOPIC], on_warning=self._warn)
        self._next = None
        self._t0_bag = None

    def _pull(self) -> BagMessage | None:
        if self._next is None and self._it is not None:
            try:
                self._next = next(self._it)
            except StopIteration:
                self._it = None
            except HdmapError as err:  # damaged bag: what was intact has been played
                self.health.error(str(err))
                self.get_logger().error(f"bag {self.bag}: {err}")
                self._it = None
        return self._next

    def tick(self) -> None:
        if self.done:
            return
        if self._it is None and self._next is None:
            if self._t0_bag is not None and not self.loop:
                self._finish()
                return
            if not self._wait_ready():
                return
            self._restart()
        now = time.monotonic()
        while (bm := self._pull()) is not None:
            if self._t0_bag is None:
                self._t0_bag = bm.log_time_ns + int(self.start_offset_s * 1e9)
                self._t0_wall = now
            if bm.topic == ORIGIN_TOPIC:
                if bm.msgtype != ORIGIN_TYPE:
                    self._warn(f"{ORIGIN_TOPIC} carries {bm.msgtype}, want {ORIGIN_TYPE}: not sent")
                elif not self._origin_sent:  # latched: once is enough, also across loops
                    self._publisher(bm).publish(bm.data)
                    self._origin_sent = True
                self._next = None
                continue
            if bm.log_time_ns < self._t0_bag:  # before the start offset
                self._next = None
                continue
            if self.rate > 0 and now < self._t0_wall + (bm.log_time_ns - self._t0_bag) / 1e9 / self.rate:
                return  # not due yet
            self._next = None
            payload = self._payload(bm)
            if payload is None:
                continue
            self._publisher(bm).publish(payload)
            self.published += 1
            self.health.accept()
            self.health.updated()
            if self.rate == 0:
                return  # one per tick as fast as possible: the executor stays responsive
        if self._it is None and not self.loop:
            self._finish()

    def _wait_ready(self) -> bool:
        """True when a /fleet/drives subscriber is there or the wait is over."""
        if self.count_subscribers(DRIVES_TOPIC.lstrip("/")) > 0:
            return True
        return time.monotonic() - self._started >= self.wait_for_subscribers_s

    def _finish(self) -> None:
        self.done = True
        self._done_at = time.monotonic()
        # a 100 Hz timer that only returns woke the executor of every node in the process (hdmap
        # run) ~100 times a second for the rest of the run: most of its wake-ups while settling
        self._timer.cancel()
        skipped = sum(self.skipped.values())
        self.get_logger().info(
            f"bag {self.bag} done: {self.published} drive message(s) published"
            + (f", {skipped} skipped ({dict(self.skipped)})" if skipped else "")
        )

    def finished(self) -> bool:
        """Standalone: the bag is done, ``linger_s`` has passed since (readers that match late still
        get the latched origin) and the node should exit (``exit_when_done``)."""
        return self.done and self.exit_when_done and time.monotonic() - self._done_at >= self.linger_s

    def destroy_node(self) -> None:
        if self.done and self.published and self.context.ok():
            for pub in self._pubs.values():  # let reliable readers take the tail before we go
                pub.wait_for_all_acked(Duration(seconds=10))
        super().destroy_node()


def main(args=None) -> None:
    run_node(BagPlayer, args, until=BagPlayer.finished)


if __name__ == "__main__":
    main()
