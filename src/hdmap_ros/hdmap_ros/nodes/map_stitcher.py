"""map_stitcher: tile estimates -> the complete hierarchical map on /hdmap/map (Sec. V-VI).

Subscribes ``/hdmap/segments`` (hdmap_msgs/TileSegments). A tile estimate newer than the stored
one replaces it (committed in one transaction; older or repeated versions are ignored, so replays
after a restart are harmless). After a quiet ``debounce_s`` (or at the latest ``max_delay_s`` after
the first unstitched update, and no sooner after the last rebuild than that rebuild took) the map
is rebuilt: every tile's segments connected (Sec. V, cached
per tile version), all stitched into the complete graph (Sec. VI), and feature ids carried over
from the previous version where a feature persists (``incremental.carry_over_ids``). The map is
committed with a growing version and published on ``/hdmap/map`` (RELIABLE, TRANSIENT_LOCAL,
depth 1), so a late subscriber gets the latest map at once.

``Map.drive_ids`` lists exactly the drives every tile of which is in the map with them (each tile
estimate names how many tiles each of its drives covers; ``live.progress.integrated_drives``): a
subscriber that waits until its drives are listed gets them fully mapped. The map's progress
(hdmap_msgs/MapStatus: version, drives received / integrated / rejected, tiles pending, settled)
is published latched on ``/hdmap/status`` whenever it changes, from the mapper's part
(``/hdmap/mapper_status``) and the stitcher's own, and is on /diagnostics too.

A burst of final estimates that completes drives (every drive its estimates name is then in
the map with all its tiles: a drive fused on settled road by the mapper's fast path, the end of a
settle) is stitched at once, without waiting for ``debounce_s`` (still no sooner after the last
rebuild than ``REBUILD_SHARE`` allows): a subscriber waiting for its drives does not wait for the
debounce (``_completes_drives``).

Road changes: once the map has settled, their following (``nodes.change_following``) rebuilds
the changed places and publishes each change on ``hdmap/changes``.

Restart: the stored map is published again; if tiles changed after it was made it is rebuilt.
"""

from __future__ import annotations

import contextlib
import threading
import time
import traceback
from dataclasses import replace
from typing import NamedTuple

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node

from hdmap_core.errors import HdmapError
from hdmap_core.graph.map_graph import MapGraph
from hdmap_core.live.progress import LiveStatus, integrated_drives, map_status
from hdmap_core.live.restitch import moved_graphs, moved_map, raw_id_map, remap_ids, stitch_tiles
from hdmap_core.live.tiles import TileKey, carry_over_ids, connect_tile
from hdmap_core.segment_columns import SegmentColumns, columns_to_segments
from hdmap_ros.convert.messages import (
    msg_to_status,
    rclpy_status_class,
    rclpy_types,
    status_to_msg,
)
from hdmap_ros.convert.tiles import TileMessage, batch_to_tiles, msg_to_tile, rclpy_tile_types
from hdmap_ros.io.cdr import encode_map
from hdmap_ros.nodes import qos
from hdmap_ros.nodes._common import HealthMixin, declare, declare_pipeline_config, run_node, state_path
from hdmap_ros.nodes.change_following import ChangeFollowing
from hdmap_ros.persistence.store import MapStore, blob_to_columns, columns_to_blob, segments_to_blob

__all__ = ["MapStitcher", "main"]

SEGMENTS_TOPIC = "hdmap/segments"  # relative: a namespace (-r __ns:=/ns2) moves every topic
BATCHES_TOPIC = "hdmap/segment_batches"
MAP_TOPIC = "hdmap/map"
STATUS_TOPIC = "hdmap/status"
MAPPER_STATUS_TOPIC = "hdmap/mapper_status"
# RULE: while tile estimates keep coming (no quiet debounce_s), rebuilds take at most this share
# of the time: on a loaded machine a rebuild takes seconds, and back-to-back rebuilds every
# max_delay_s took the CPU the mapper needs to finish its tiles (a quiet debounce_s rebuilds at once)
REBUILD_SHARE = 0.5


class TileGraphs(NamedTuple):
    """A tile's segment graphs as the stitcher holds them."""

    version: int  # of the tile estimate they are of
    graphs: list  # its segment graphs (live.tiles.connect_tile)
    estimate: list | SegmentColumns  # its segments (or these in columns: what the fast update compares)
    connected: bool  # connected from them (False: moved there by a fast update; a rebuild connects again)


class MapStitcher(ChangeFollowing, HealthMixin, Node):
    """Integrates tile estimates into the map; see the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__("map_stitcher", **kwargs)
        db = declare(self, "db_path", "", "SQLite file of the map store ('' = $ROS_HOME/hdmap/map_stitcher.db).")
        pipeline_config = declare_pipeline_config(self)  # a bad preset or override fails here, named
        self.debounce_s = declare(
            self,
            "debounce_s",
            1.0,
            "Rebuild the map after this long without a new tile estimate [s].",
            lo=0.0,
            hi=600.0,
            dynamic="debounce_s",
        )
        self.max_delay_s = declare(
            self,
            "max_delay_s",
            5.0,
            "Rebuild at the latest this long after the first unstitched update [s].",
            lo=0.0,
            hi=3600.0,
            dynamic="max_delay_s",
        )
        self.id_distance_m = declare(
            self,
            "id_match_distance_m",
            0.75,
            "A new feature keeps an old id when this close to it [m].",
            lo=0.01,
            hi=10.0,
            dynamic="id_distance_m",
        )
        self.id_overlap = declare(
            self,
            "id_min_overlap",
            0.5,
            "... along at least this share of the shorter of the two.",
            lo=0.0,
            hi=1.0,
            dynamic="id_overlap",
        )
        depth = declare(
            self,
            "segments_history_depth",
            1000,
            "History depth of /hdmap/segments (match the mapper).",
            lo=1,
            hi=100000,
        )
        self._declare_change_following()
        self._init_health("map_stitcher", item="tile_estimates")
        self.pipeline_config = pipeline_config
        self.store = MapStore(state_path(db, "map_stitcher.db"))
        self.health.set("tile_versions", self.store.version_total())
        self._types = rclpy_types()
        self._graphs: dict[TileKey, TileGraphs] = {}
        # the stitched map graph of the current map (restitch.stitch_tiles / moved_map); None
        # while there is none: at the start, and once road changes were followed on the map
        self._mg: MapGraph | None = None
        self._raw_ids: dict[int, int] = {}  # its features' raw ids -> their ids in the current map
        # the estimates received since the last map (tile -> (version, its segments as received, or
        # these in columns: a batch's)): the fast update moves the map to them without decoding
        # the stored blobs again
        self._rx_segments: dict[TileKey, tuple[int, list | SegmentColumns]] = {}
        self._last_msg = b""  # the CDR bytes of the last map published
        self._first_dirty: float | None = None
        self._last_rx = 0.0
        self._rested_at = 0.0  # while estimates stream in, no rebuild before then (REBUILD_SHARE)
        # final estimates stored (tile -> its drives and their tile counts: the drives a map lists,
        # rebuild) and the tiles received since the last rebuild began: a burst that completes
        # drives is stitched at once
        self._final: dict[TileKey, tuple[list[str], list[int]]] = {}
        progress = self.store.tile_progress()
        for key, _, ids, _ in self.store.tiles():
            counts, final = progress.get(key, ([], True))
            if final:
                self._final[key] = (list(ids), list(counts))
        self._dirty: set[TileKey] = set()
        self.map, sig = self.store.map()
        self._map_sig = sig  # the tile versions the current map was made from
        self._failed_sig = ""
        self._map_pub = self.create_publisher(self._types.Map, MAP_TOPIC, qos.LATCHED)
        self._status_cls = rclpy_status_class()
        self._status_pub = self.create_publisher(self._status_cls, STATUS_TOPIC, qos.LATCHED)
        self._mapper_status = LiveStatus()
        self.status: LiveStatus | None = None
        self._rx_group = MutuallyExclusiveCallbackGroup()
        self._work_group = MutuallyExclusiveCallbackGroup()
        self._sub = self.create_subscription(
            rclpy_tile_types().TileSegments,
            SEGMENTS_TOPIC,
            self.on_tile,
            qos.replay(depth),
            callback_group=self._rx_group,
        )
        self._batch_sub = self.create_subscription(
            rclpy_tile_types().TileSegmentsBatch,
            BATCHES_TOPIC,
            self.on_batch,
            qos.BATCHES,
            callback_group=self._rx_group,
        )
        self._status_sub = self.create_subscription(
            self._status_cls, MAPPER_STATUS_TOPIC, self._on_mapper_status, qos.LATCHED, callback_group=self._work_group
        )
        self._work_lock = threading.Lock()  # work and the mapper's status; destroy_node takes both
        self._rx_lock = threading.Lock()  # on_tile
        self._destroyed = False
        self._timer = self.create_timer(0.1, self.work, callback_group=self._work_group)
        # a received burst that completes drives wakes the work at once, not at the next tick
        self._wake = self.create_guard_condition(self.work, callback_group=self._work_group)
        self._init_change_following(sig)
        if self.map is not None:
            self._publish()
            # the stored map is this node's map until a rebuild (none comes when no tile changed)
            self._map_health()
        if self.store.tiles_signature() != sig:
            self._first_dirty = time.monotonic()
        self.get_logger().info(
            f"map store {self.store.path}: {len(self.store.tiles())} tile(s), map version "
            f"{self.map.version if self.map else 0}"
        )

    def on_tile(self, msg) -> None:
        """Store a newer tile estimate; the rebuild happens in :meth:`work`."""
        try:
            tile = msg_to_tile(msg)
        except (HdmapError, ValueError, TypeError) as err:
            self.health.reject("invalid_tile", str(err))
            self.get_logger().warning(f"tile message rejected: {err}")
            return
        segments = list(tile.segments)
        self._store_tiles([(tile, segments_to_blob(segments), segments)])

    def on_batch(self, msg) -> None:
        """Store the newer of a batch's tile estimates in one transaction (each as :meth:`on_tile`
        would); the fast update takes their columns as they are (no segment objects made)."""
        t0 = time.perf_counter()
        try:
            entries = batch_to_tiles(msg)
        except (HdmapError, ValueError, TypeError, IndexError) as err:
            self.health.reject("invalid_tile", f"batch: {err}")
            self.get_logger().warning(f"tile batch rejected: {err}")
            return
        self._store_tiles([(e.tile, columns_to_blob(e.columns), e.columns) for e in entries])
        self.get_logger().info(f"a batch of {len(entries)} tile estimate(s) stored in {time.perf_counter() - t0:.3f} s")
        if self._completes_drives():
            # RULE: a burst that completes drives (a fused drive) is stitched at once: the work
            # timer's tick (0.1 s) was up to a tenth of the fast path's latency
            with contextlib.suppress(Exception):  # the node may be on its way down
                self._wake.trigger()

    def _store_tiles(self, tiles: list[tuple[TileMessage, bytes, list | SegmentColumns]]) -> None:
        """Store tile estimates newer than the stored ones in one transaction: (tile, its segments'
        blob, its segments or these in columns)."""
        with self._rx_lock:
            if self._destroyed:
                return
            stored = self.store.put_tiles(
                [(t.key, t.version, blob, t.drive_ids, t.drive_tile_counts, t.final) for t, blob, _ in tiles]
            )
            now = time.monotonic()
            for (tile, _, segments), ok in zip(tiles, stored, strict=True):
                if not ok:
                    self.health.duplicate()
                    continue
                self.health.accept()
                self._dirty.add(tile.key)
                self._rx_segments[tile.key] = (tile.version, segments)
                if tile.final:
                    self._final[tile.key] = (list(tile.drive_ids), list(tile.drive_tile_counts))
                else:
                    self._final.pop(tile.key, None)
                self._last_rx = now
                if self._first_dirty is None:
                    self._first_dirty = now
            self.health.backlog = int(self._first_dirty is not None)
            self.health.set("tile_versions", self.store.version_total())

    def work(self) -> None:
        with self._work_lock:  # destroy_node waits for a pass in flight (another thread may spin)
            if self._destroyed:
                return
            if self.follow_changes and self._first_dirty is not None:
                self._follow_pool()  # started with the first estimates: its imports are done when the map settles
            self._work()
            self._follow()
            self._update_status()
            self.health.set("changes_followed", self.changes_followed())

    def _work(self) -> None:
        if self._first_dirty is None:
            return
        now = time.monotonic()
        mapper = self._mapper_status
        in_flight = mapper.tile_versions > self.store.version_total()  # published, not here yet
        if mapper.settled and not in_flight:
            pass  # RULE: the mapper settled and every estimate it made is here: nothing more comes
        elif (
            now - self._last_rx < self.debounce_s
            and (now - self._first_dirty < self.max_delay_s or now < self._rested_at)
            and (now < self._rested_at or not self._completes_drives())
        ):
            return
        elif in_flight and now - self._last_rx < max(self.debounce_s, self.max_delay_s):
            # RULE: the rest of a burst (the region's tiles) is on its way: no map of a part of it
            # (an estimate lost for good, e.g. beyond the history depth, delays the map by max_delay_s)
            return
        with self._rx_lock:
            dirty = set(self._dirty)
            self._dirty.clear()
            received = dict(self._rx_segments)
            self._rx_segments.clear()
        self._first_dirty = None
        sig = self.store.tiles_signature()
        t0 = time.monotonic()
        try:
            if not (dirty and self._fast_update(dirty, received)):
                self.rebuild()
        except HdmapError as err:
            self._fail(sig, str(err))
        except Exception as err:  # noqa: BLE001 - a bug must not stop the live map; logged in full
            self._fail(sig, f"{type(err).__name__}: {err}\n{traceback.format_exc()}")
        end = time.monotonic()
        self._rested_at = end + (end - t0) * (1.0 - REBUILD_SHARE) / REBUILD_SHARE
        self.health.backlog = int(self._first_dirty is not None)

    def _completes_drives(self) -> bool:
        """RULE: every estimate received since the last rebuild is final and every drive they
        name is then in the map with all its tiles (a fused drive, a settle's last estimate)."""
        with self._rx_lock:
            if not self._dirty or any(k not in self._final for k in self._dirty):
                return False
            named = {d for k in self._dirty for d in self._final[k][0]}
            tiles = list(self._final.values())
        return named <= integrated_drives(tiles)

    def _fail(self, sig: str, text: str) -> None:
        self._failed_sig = sig  # these inputs cannot be stitched: nobody should wait for them
        self.health.error(text.splitlines()[0])
        self.get_logger().error(f"map rebuild failed, previous map kept: {text}")

    def rebuild(self) -> None:
        """Stitch every stored tile into a new map version, commit and publish it."""
        t0 = time.perf_counter()
        with self._rx_lock:  # the estimates and the drives they vouch for as of one moment (on_tile)
            sig = self.store.tiles_signature()
            tiles = self.store.tiles()
            final = list(self._final.values())  # an estimate vouches for its drives once final
        graphs = []
        for key, version, _, blob in tiles:
            cached = self._graphs.get(key)
            if cached is None or cached.version != version or not cached.connected:
                columns = blob_to_columns(blob)
                tile_graphs = connect_tile(columns_to_segments(columns), key, pipeline_config=self.pipeline_config)
                cached = TileGraphs(version, tile_graphs, columns, True)
                self._graphs[key] = cached
            graphs.extend(cached.graphs)
        drive_ids = integrated_drives(final)  # every tile of each is in this map with it, final
        t1 = time.perf_counter()
        raw, self._mg = stitch_tiles(graphs, pipeline_config=self.pipeline_config, drive_ids=drive_ids)
        t2 = time.perf_counter()
        new = carry_over_ids(raw, self.map, max_distance_m=self.id_distance_m, min_overlap=self.id_overlap)
        new = replace(new, version=(self.map.version if self.map else 0) + 1, stamp_ns=time.time_ns())
        self._raw_ids = raw_id_map(raw, new)
        t3 = time.perf_counter()
        self.store.put_map(new, sig)
        self.map = new
        self._consensus = new
        self._map_sig = sig
        t4 = time.perf_counter()
        self._publish()
        self.health.set(
            "last_rebuild_parts_s",
            f"connect {t1 - t0:.3f}, stitch {t2 - t1:.3f}, ids {t3 - t2:.3f}, commit {t4 - t3:.3f}, "
            f"publish {time.perf_counter() - t4:.3f}",
        )
        self.health.updated()
        self._map_health()
        self.health.set("last_rebuild_s", f"{time.perf_counter() - t0:.3f}")

    def _fast_update(self, dirty: set[TileKey], received: dict[TileKey, tuple[int, list | SegmentColumns]]) -> bool:
        """RULE fast update: when every tile received since the last map is final and its estimate
        only moved the maxima of the one the map holds (a drive fused into it, ``live.fuse``), the
        map's stitch decisions are kept and only its geometry moves (``live.restitch``): a new
        version at once, listing the drives that completes. The full rebuild of the same tiles
        follows as the next version (``_first_dirty`` stays set), so the map is again a function of the
        tiles before it counts as settled. False (nothing done): rebuild in full. ``received``:
        the estimates as received (tile -> (version, their segments or these in columns))."""
        if self._mg is None or self.map is None:
            return False  # RULE: not on a map with road changes followed (the rebuild, then the follow)
        t0, c0 = time.perf_counter(), time.thread_time()
        with self._rx_lock:  # the estimates and the drives they vouch for as of one moment (as rebuild)
            sig = self.store.tiles_signature()
            final = dict(self._final)  # the final estimates stored: their drives
            versions = {key: self.store.tile_version(key) for key in dirty}
        moved, updates = [], {}
        for key in sorted(dirty):
            cached = self._graphs.get(key)
            got = received.get(key)
            version = versions[key]
            if cached is None or key not in final or got is None or got[0] != version:
                return False
            estimate = got[1]
            graphs = moved_graphs(cached.graphs, cached.estimate, estimate)
            if graphs is None:
                return False
            moved.extend(graphs)
            updates[key] = TileGraphs(version, graphs, estimate, False)
        parts = list(final.values())
        drive_ids = integrated_drives(parts)
        t1 = time.perf_counter()
        try:
            raw, mg = moved_map(self._mg, moved, drive_ids=drive_ids)
        except HdmapError:
            return False  # a graph not in the map as it is: rebuild in full
        t2 = time.perf_counter()
        new = remap_ids(raw, self._raw_ids)
        if new is None:
            new = carry_over_ids(raw, self.map, max_distance_m=self.id_distance_m, min_overlap=self.id_overlap)
        new = replace(new, version=(self.map.version if self.map else 0) + 1, stamp_ns=time.time_ns())
        t3 = time.perf_counter()
        self._graphs.update(updates)
        self._mg = mg
        self._raw_ids = raw_id_map(raw, new)
        self._first_dirty = time.monotonic()  # the full rebuild of these tiles follows
        self.map = new
        self._map_sig = sig
        self._publish()
        t4 = time.perf_counter()
        # RULE: published first, then stored (the commit, map blob and fsync, was a fifth of the
        # fast update's wall time), with a signature no tile set has: a restart rebuilds it in full.
        # A crash between the two: the restart publishes the version before and rebuilds, as it does
        # from the stored moved map; the moved map is that rebuild's approximation anyway
        self.store.put_map(new, sig + ";moved")
        text = (
            f"{time.perf_counter() - t0:.3f} s (move {t1 - t0:.3f}, export {t2 - t1:.3f}, ids {t3 - t2:.3f}, "
            f"publish {t4 - t3:.3f}, then commit {time.perf_counter() - t4:.3f}; {len(dirty)} tiles; "
            f"CPU of this thread {time.thread_time() - c0:.3f} s)"
        )
        self.health.set("last_fast_update_s", text)
        self.get_logger().info(f"map version {new.version} moved in place (a fused burst) in {text}")
        self.health.updated()
        self._map_health()
        return True

    def _map_health(self) -> None:
        """The current map's version and size on /diagnostics (after each new map)."""
        self.health.set("map_version", self.map.version)
        self.health.set("features", len(self.map.features))

    def _publish(self) -> None:
        """Publish the map as CDR bytes (``io.cdr.encode_map``: no message object per point and
        topology node; the bytes rosbags gives for ``map_to_msg``, read by rclpy as its own)."""
        self._last_msg = encode_map(self.map)
        self._map_pub.publish(self._last_msg)

    def _on_mapper_status(self, msg) -> None:
        with self._work_lock:
            if self._destroyed:
                return
            self._mapper_status = msg_to_status(msg)
            self._update_status()

    def _update_status(self) -> None:
        """Publish the map's status when it changed (and put it on /diagnostics)."""
        in_map = set(self._map_sig.split(";")) if self._map_sig else set()
        sig = self.store.tiles_signature()
        unstitched = sum(1 for part in (sig.split(";") if sig else []) if part not in in_map)
        status = map_status(
            self._mapper_status,
            map_version=self.map.version if self.map else 0,
            drives_integrated=len(self.map.drive_ids) if self.map else 0,
            tile_versions=self.store.version_total(),
            tiles_unstitched=unstitched,
            stitched=self.is_settled(),
        )
        if status.same(self.status):
            return
        status = replace(status, stamp_ns=time.time_ns())
        self.status = status
        self._status_pub.publish(status_to_msg(status, cls=self._status_cls, types=self._types))
        for name in ("drives_received", "drives_integrated", "drives_rejected", "tiles_pending", "settled"):
            self.health.set(name, getattr(status, name))

    def is_settled(self) -> bool:
        """Nothing waits to be stitched: the map was made from every stored tile estimate."""
        sig = self.store.tiles_signature()
        return self._first_dirty is None and sig in (self._map_sig, self._failed_sig)

    def destroy_node(self) -> None:
        # An executor spinning in another thread may be inside work() or about to start it:
        # close the store only after that pass, and let no pass start after it.
        self._timer.cancel()
        with self._work_lock, self._rx_lock:
            self._destroyed = True
            self.store.close()
            self._close_change_following()
        super().destroy_node()


def main(args=None) -> None:
    run_node(MapStitcher, args)


if __name__ == "__main__":
    main()
