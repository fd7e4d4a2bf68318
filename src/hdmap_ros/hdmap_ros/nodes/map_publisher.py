"""map_publisher: the map for RViz / Foxglove, and a service that saves it.

Subscribes ``/hdmap/map`` and ``/fleet/origin`` (both latched). Publishes
``/hdmap/markers`` (visualization_msgs/MarkerArray, latched): one LINE_STRIP per feature coloured
by type, plus the topology graph and the lanes (``hdmap_core.lanes``), and the road changes the map
followed (``hdmap/changes``, hdmap_msgs/MapChange: each zone's polygon and the pieces it retired, in
namespaces ``changes/zone`` and ``changes/retired``; the saved GeoJSON has the retired pieces,
``kind`` "retired"). The markers are made only while ``/hdmap/markers`` has a reader; a reader
that comes later gets them made then (latched). Offers ``/hdmap/save_map``
(hdmap_msgs/srv/SaveMap): writes the current map as a rosbag2 MCAP directory at ``path`` and, when
the WGS84 origin is known, as GeoJSON (features and lanes) at ``path + ".geojson"`` and as a
Lanelet2 / Autoware map directory at ``path + ".lanelet2"``.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from sensor_msgs.msg import NavSatFix
from std_msgs.msg import Header

from hdmap_core.errors import HdmapError
from hdmap_core.lanes.derive import derive_lanes
from hdmap_core.lanes.model import LaneMap
from hdmap_core.model import GeoOrigin, HDMap
from hdmap_core.updates.follow import RetiredFeature
from hdmap_ros.convert.markers import map_to_markers, rclpy_marker_types
from hdmap_ros.convert.messages import msg_to_map, msg_to_origin, rclpy_change_class, rclpy_types
from hdmap_ros.io.bagio import write_map_bag
from hdmap_ros.io.geojson import write_geojson
from hdmap_ros.io.lanelet2 import write_lanelet2
from hdmap_ros.nodes import qos
from hdmap_ros.nodes._common import HealthMixin, declare, run_node

__all__ = ["MapPublisher", "main"]

MAP_TOPIC = "hdmap/map"  # relative: a namespace (-r __ns:=/ns2) moves every topic
ORIGIN_TOPIC = "fleet/origin"
MARKERS_TOPIC = "hdmap/markers"
SAVE_SERVICE = "hdmap/save_map"
CHANGES_TOPIC = "hdmap/changes"


class MapPublisher(HealthMixin, Node):
    """Markers and the save service; see the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__("map_publisher", **kwargs)
        self.line_width_m = declare(
            self,
            "line_width_m",
            0.2,
            "Width of the feature LINE_STRIPs [m].",
            lo=0.01,
            hi=5.0,
            dynamic="line_width_m",
        )
        self.show_topology = declare(
            self,
            "show_topology",
            True,
            "Also draw the topology graph.",
            dynamic="show_topology",
        )
        self.show_lanes = declare(
            self,
            "show_lanes",
            True,
            "Also draw the lanes derived from the map.",
            dynamic="show_lanes",
        )
        self.overwrite = declare(
            self,
            "overwrite",
            True,
            "The save service replaces an existing map bag at the path.",
            dynamic="overwrite",
        )
        self._init_health("map_publisher", item="maps")
        from hdmap_msgs.srv import SaveMap  # noqa: PLC0415

        self.map: HDMap | None = None
        self.lanes: LaneMap | None = None
        self.origin: GeoOrigin | None = None
        self._marker_types = rclpy_marker_types()
        t = rclpy_types()
        self._drawn = True  # the latched markers show the current map and changes (or there is none)
        self._markers_pub = self.create_publisher(
            self._marker_types.MarkerArray,
            MARKERS_TOPIC,
            qos.LATCHED,
            event_callbacks=PublisherEventCallbacks(matched=self._on_matched),
        )
        self._map_sub = self.create_subscription(t.Map, MAP_TOPIC, self.on_map, qos.LATCHED)
        self._origin_sub = self.create_subscription(NavSatFix, ORIGIN_TOPIC, self.on_origin, qos.LATCHED)
        self._origin_live = self.create_subscription(NavSatFix, ORIGIN_TOPIC, self.on_origin, qos.ORIGIN_LIVE)
        self._srv = self.create_service(SaveMap, SAVE_SERVICE, self.on_save)
        # road changes by id: (polygon, retired pieces as RetiredFeature)
        self.changes: dict[int, tuple[np.ndarray, list[RetiredFeature]]] = {}
        self._changes_sub = self.create_subscription(rclpy_change_class(), CHANGES_TOPIC, self.on_change, qos.CHANGES)

    def on_change(self, msg) -> None:
        """Keep a road change (its zone and retired pieces) and draw the map again with it."""
        try:
            poly = np.array([[p.x, p.y] for p in msg.polygon.points], dtype=float).reshape(-1, 2)
            retired = [
                RetiredFeature(
                    int(f.id),
                    int(f.type),
                    np.array([[p.x, p.y] for p in f.points], dtype=float).reshape(-1, 2),
                    int(msg.id),
                    int(msg.retired_valid_from_ns),
                    int(msg.retired_valid_to_ns),
                )
                for f in msg.retired
            ]
        except (TypeError, ValueError, AttributeError) as err:
            self.health.reject("invalid_change", str(err))
            return
        if not (np.isfinite(poly).all() and all(np.isfinite(r.points).all() for r in retired)):
            self.health.reject("invalid_change", f"change {msg.id}: coordinates not finite")
            return
        self.changes[int(msg.id)] = (poly, retired)
        self.health.set("changes", len(self.changes))
        self._redraw()

    def on_map(self, msg) -> None:
        try:
            self.map = msg_to_map(msg)
        except HdmapError as err:
            self.health.reject("invalid_map", str(err))
            self.get_logger().warning(f"map rejected: {err}")
            return
        self.lanes = None
        self._redraw()
        self.health.accept()
        self.health.updated(time.time_ns())
        self.health.set("map_version", self.map.version)

    def _redraw(self) -> None:
        """The map or its changes changed: draw them for the readers of ``/hdmap/markers``.

        RULE: the markers (with the lanes derived from each map version: ~2.5 s of CPU for the
        134-drive ``paper_like`` map, in the process of every node under ``hdmap run``) are made
        only while someone reads them; with no reader they are made when one matches
        (:meth:`_on_matched`), so a late reader still gets the current ones (latched)."""
        self._drawn = False
        if self._markers_pub.get_subscription_count() > 0:
            self._draw()

    def _on_matched(self, status) -> None:
        """A reader of ``/hdmap/markers`` came (or went): draw what it has not been shown yet."""
        if status.current_count > 0 and not self._drawn:
            self._draw()

    def _draw(self) -> None:
        if self.map is None:
            return
        self._drawn = True
        header = Header(frame_id=self.map.frame_id, stamp=self.get_clock().now().to_msg())
        self._markers_pub.publish(
            map_to_markers(
                self.map,
                types=self._marker_types,
                header=header,
                line_width_m=self.line_width_m,
                topology=self.show_topology,
                lanes=self._lanes() if self.show_lanes else None,
                changes=[(poly, [r.points for r in retired]) for poly, retired in self.changes.values()],
            )
        )

    def _lanes(self) -> LaneMap:
        """The lanes of the current map, derived once per map version."""
        if self.lanes is None and self.map is not None:
            self.lanes = derive_lanes(self.map)
        return self.lanes if self.lanes is not None else LaneMap((), (), {})

    def on_origin(self, msg) -> None:
        try:
            self.origin = msg_to_origin(msg)
        except HdmapError as err:
            self.health.reject("invalid_origin", str(err))
            self.get_logger().warning(f"origin rejected: {err}")

    def on_save(self, request, response):
        """Write the current map to ``request.path`` (MCAP), ``request.path + '.geojson'`` and the
        Lanelet2 directory ``request.path + '.lanelet2'``."""
        path = Path(request.path).expanduser()
        if not request.path:
            response.success, response.message = False, "empty path"
            return response
        if self.map is None:
            response.success, response.message = False, "no map received yet"
            return response
        try:
            write_map_bag(path, self.map, self.origin, overwrite=self.overwrite)
            written = [str(path)]
            if self.origin is not None:
                lanes = self._lanes()
                retired = [r for _, pieces in self.changes.values() for r in pieces]
                shown = replace(self.map, extra={**self.map.extra, "retired": retired}) if retired else self.map
                written.append(str(write_geojson(shown, self.origin, Path(f"{path}.geojson"), lanes=lanes)))
                written.append(str(write_lanelet2(lanes, self.origin, Path(f"{path}.lanelet2"))))
                note = ""
            else:
                note = " (no /fleet/origin received: GeoJSON and Lanelet2 not written)"
        except (HdmapError, OSError) as err:
            response.success, response.message = False, f"cannot save map version {self.map.version}: {err}"
            self.get_logger().error(response.message)
            return response
        response.success = True
        response.message = f"map version {self.map.version} written to {', '.join(written)}{note}"
        self.get_logger().info(response.message)
        return response


def main(args=None) -> None:
    run_node(MapPublisher, args)


if __name__ == "__main__":
    main()
