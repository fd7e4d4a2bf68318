"""Health counters of a node and their diagnostic_msgs form (/diagnostics).

:class:`Health` is plain Python (tested without rclpy); :func:`health_to_msg` builds a
``diagnostic_msgs/msg/DiagnosticArray`` with one ``DiagnosticStatus`` per node, whose key/values are
the counters (drives accepted / rejected per reason / duplicates, backlog, updates, last update time).
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

__all__ = ["Health", "health_to_msg", "OK", "WARN", "ERROR", "STALE"]

# diagnostic_msgs/DiagnosticStatus levels (byte constants of the message).
OK, WARN, ERROR, STALE = 0, 1, 2, 3


@dataclass
class Health:
    """Thread-safe counters of one node.

    Attributes:
        name: status name, e.g. ``"hdmap: drive_ingestor"``.
        hardware_id: what the status is about (the node's fully qualified name).
        backlog_warn: backlog at or above which the level is WARN.
        item: what the node counts, the prefix of its keys: ``drives`` (ingestor, mapper, player),
            ``tile_estimates`` (stitcher), ``maps`` (publisher).
    """

    name: str
    hardware_id: str = ""
    item: str = "drives"
    backlog_warn: int = 20
    accepted: int = 0
    rejected: Counter = field(default_factory=Counter)
    duplicates: int = 0
    backlog: int = 0
    updates: int = 0
    errors: int = 0
    last_update_ns: int = 0
    last_error: str = ""
    extra: dict = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def accept(self) -> None:
        with self._lock:
            self.accepted += 1

    def reject(self, reason: str, detail: str = "") -> None:
        with self._lock:
            self.rejected[reason] += 1
            self.last_error = f"{reason}: {detail}" if detail else reason

    def duplicate(self) -> None:
        with self._lock:
            self.duplicates += 1

    def error(self, text: str) -> None:
        """An update failed (the node went on)."""
        with self._lock:
            self.errors += 1
            self.last_error = text

    def updated(self, stamp_ns: int | None = None) -> None:
        with self._lock:
            self.updates += 1
            self.last_update_ns = int(stamp_ns if stamp_ns is not None else time.time_ns())

    def set(self, key: str, value: Any) -> None:
        """A node-specific figure (e.g. ``tiles``, ``map_version``)."""
        with self._lock:
            self.extra[key] = value

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def level(self) -> int:
        """OK; WARN when something was rejected or failed recently or the backlog is high."""
        if self.errors or self.backlog >= self.backlog_warn:
            return WARN
        return OK

    def message(self) -> str:
        parts = [f"{self.accepted} accepted", f"{self.rejected_total} rejected", f"backlog {self.backlog}"]
        if self.errors:
            parts.append(f"{self.errors} failed update(s)")
        return ", ".join(parts)

    def key_values(self) -> list[tuple[str, str]]:
        """(key, value) pairs, stable keys first, then rejections per reason, then extras."""
        with self._lock:
            kv = [
                (f"{self.item}_accepted", str(self.accepted)),
                (f"{self.item}_rejected", str(self.rejected_total)),
                (f"{self.item}_duplicate", str(self.duplicates)),
                ("backlog", str(self.backlog)),
                ("updates", str(self.updates)),
                ("failed_updates", str(self.errors)),
                ("last_update_time", f"{self.last_update_ns / 1e9:.3f}" if self.last_update_ns else "never"),
                ("last_error", self.last_error),
            ]
            kv += [(f"rejected.{r}", str(n)) for r, n in sorted(self.rejected.items())]
            kv += [(str(k), str(v)) for k, v in sorted(self.extra.items())]
        return kv


def health_to_msg(healths: list[Health], *, stamp: Any = None) -> Any:
    """diagnostic_msgs/DiagnosticArray with one status per :class:`Health` (needs rclpy msgs)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue  # noqa: PLC0415

    arr = DiagnosticArray()
    if stamp is not None:
        arr.header.stamp = stamp
    for h in healths:
        st = DiagnosticStatus()
        st.level = bytes([h.level()])
        st.name = h.name
        st.hardware_id = h.hardware_id
        st.message = h.message()
        st.values = [KeyValue(key=k, value=v) for k, v in h.key_values()]
        arr.status.append(st)
    return arr
